"""Whether a change to the extractor changes its points: every named scene, saved once and compared later.

    python -m benchmarks.compare_points save REF.npz [--seeds 2]
    python -m benchmarks.compare_points compare REF.npz [--out benchmarks/results/extract_reshape.md]

``save`` renders every named scene of the simulator (1920x1080, ``--seeds`` noise renders each) and keeps what
the default extractor gives for it through the public entry points: ``Sensor.process`` (pixels, laser, quality,
body-frame points) and the extractor alone (``get_extractor("subpixel")``: pixels, laser, quality).
``compare`` renders the same frames again and prints, per scene, whether the points are bit-identical and the
largest pixel and point differences (a changed point count is reported as such). A reshape of the extractor
must keep every scene bit-identical or within 0.001 px per point.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from lrsensor import Sensor
from lrsensor.atomic import atomic_write
from lrsensor.extract import get_extractor
from lrsensor.sim import named_scene
from lrsensor.sim.scenes import SCENES

#: Largest pixel difference a reshape may leave (issue 29).
TOLERANCE_PX = 1e-3


def _frames(seeds: int) -> Any:
    for name in SCENES:
        setup = named_scene(name)
        for seed in range(seeds):
            yield f"{name}/{seed}", setup.calibration, setup.render(seed).image


def _extract(calibration: Any, image: np.ndarray) -> dict[str, np.ndarray]:
    scan = Sensor(calibration).process(image)
    det = get_extractor("subpixel")(image, calibration)
    return {
        "uv": scan.uv,
        "laser": scan.laser,
        "quality": scan.quality,
        "points": scan.points,
        "det_uv": det.uv,
        "det_laser": det.laser,
        "det_quality": det.quality,
    }


def save(path: Path, seeds: int) -> None:
    """Save every named frame's outputs to ``path`` (npz, keys ``<scene>/<seed>/<field>``)."""
    out: dict[str, np.ndarray] = {"seeds": np.array(seeds)}
    for key, calibration, image in _frames(seeds):
        for field, value in _extract(calibration, image).items():
            out[f"{key}/{field}"] = value
        print(f"saved {key}: {out[key + '/uv'].shape[0]} points", file=sys.stderr)
    np.savez_compressed(path, **out)  # type: ignore[arg-type]


def _diff(ref: dict[str, np.ndarray], new: dict[str, np.ndarray]) -> tuple[str, float, float, float]:
    """(verdict, largest pixel difference of Sensor.process, of the extractor alone, largest point difference m)."""
    if ref["uv"].shape != new["uv"].shape or ref["det_uv"].shape != new["det_uv"].shape:
        return f"count {ref['uv'].shape[0]} -> {new['uv'].shape[0]}", np.inf, np.inf, np.inf
    same = all(np.array_equal(ref[k], new[k], equal_nan=True) for k in ref)
    if not np.array_equal(ref["laser"], new["laser"]) or not np.array_equal(ref["det_laser"], new["det_laser"]):
        return "lasers differ", np.inf, np.inf, np.inf
    d_px = float(np.max(np.abs(ref["uv"] - new["uv"]), initial=0.0))
    d_det = float(np.max(np.abs(ref["det_uv"] - new["det_uv"]), initial=0.0))
    d_m = float(np.max(np.abs(ref["points"] - new["points"]), initial=0.0))
    verdict = "identical" if same else ("within" if max(d_px, d_det) <= TOLERANCE_PX else "CHANGED")
    return verdict, d_px, d_det, d_m


def compare(path: Path, out: Path | None) -> int:
    """Compare the frames saved in ``path`` with what the extractor gives now; 0 when every frame is within
    :data:`TOLERANCE_PX`."""
    data = np.load(path)
    seeds = int(data["seeds"])
    rows = [
        "| frame | verdict | max px (Sensor.process) | max px (extractor) | max point diff (m) |",
        "|---|---|---:|---:|---:|",
    ]
    bad = 0
    for key, calibration, image in _frames(seeds):
        ref = {
            f: data[f"{key}/{f}"] for f in ("uv", "laser", "quality", "points", "det_uv", "det_laser", "det_quality")
        }
        verdict, d_px, d_det, d_m = _diff(ref, _extract(calibration, image))
        bad += verdict not in ("identical", "within")
        rows.append(f"| {key} | {verdict} | {d_px:.2e} | {d_det:.2e} | {d_m:.2e} |")
    text = "\n".join(rows) + "\n"
    print(text)
    if out is not None:
        atomic_write(out, text.encode())
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    p_save = sub.add_parser("save", help="render every named scene and save the extractor's outputs")
    p_save.add_argument("path", type=Path)
    p_save.add_argument("--seeds", type=int, default=2, help="noise renders per scene (default 2)")
    p_cmp = sub.add_parser("compare", help="compare today's outputs with a saved file")
    p_cmp.add_argument("path", type=Path)
    p_cmp.add_argument("--out", type=Path, default=None, help="also write the table to this file")
    args = parser.parse_args(argv)
    if args.cmd == "save":
        save(args.path, args.seeds)
        return 0
    return compare(args.path, args.out)


if __name__ == "__main__":
    raise SystemExit(main())
