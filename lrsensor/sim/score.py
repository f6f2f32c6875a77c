"""Scoring a scan against a render's ground truth (used by the extraction tests and benchmark)."""

from __future__ import annotations

import numpy as np

from ..extract.reference_detect import _noise_dn
from ..scan import Scan
from .render import Render

#: A point more than this relative range error off is an outlier.
OUTLIER_REL = 0.05


def score_scan(render: Render, scan: Scan) -> dict[str, float]:
    """Accuracy of ``scan`` (made from ``render.image``) against the render's truth.

    Per point, the relative range error ``|r_est - r_true| / r_true`` from the camera centre, with ``r_true`` the
    true hit of the same laser at the same column. Returns percentages ``median``, ``p95``, ``outliers``
    (> 5 % off), ``coverage`` (visible columns, true peak >= 3x the image noise, that got a point) and the
    number of ``points``; NaN accuracy figures when no point could be scored.
    """
    C = render.calibration.camera_center_body
    noise = _noise_dn(np.ascontiguousarray(render.image[:, :, 1]))
    errs, covered, visible = [], 0, 0
    for lt in render.truth.lasers:
        sel = scan.laser == lt.index
        u = scan.uv[sel, 0]
        _, p_true, _ = lt.at_columns(u)
        r_true = np.linalg.norm(p_true - C, axis=1)
        r_est = np.linalg.norm(scan.points[sel] - C, axis=1)
        ok = np.isfinite(r_true)
        errs.append(np.abs(r_est[ok] - r_true[ok]) / r_true[ok])
        v, _, peak = lt.at_columns(np.arange(render.truth.width, dtype=float))
        vis = np.flatnonzero(np.isfinite(v) & (np.nan_to_num(peak) >= 3.0 * noise))
        visible += vis.size
        covered += int(np.isin(vis, np.rint(u).astype(int)).sum())
    e = np.concatenate(errs) if errs else np.zeros(0)
    nan = float("nan")
    return {
        "median": 100 * float(np.median(e)) if e.size else nan,
        "p95": 100 * float(np.percentile(e, 95)) if e.size else nan,
        "outliers": 100 * float(np.mean(e > OUTLIER_REL)) if e.size else nan,
        "coverage": 100 * covered / max(visible, 1),
        "points": float(len(scan)),
    }
