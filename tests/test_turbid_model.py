"""The independent turbid-water stripe model (``benchmarks/turbid_model.py``) is what its docstring claims, checked
on its rendered layers without the extractor; and ``benchmarks/bench_turbid.py --quick`` writes its tables."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from benchmarks import bench_turbid
from benchmarks.turbid_model import Turbid, TurbidFrame, render

#: No veil, particles or noise: the laser's layers alone.
QUIET = {"veil_dn": 0.0, "particles_per_mpx": 0.0, "read_noise_dn": 0.0}
#: Columns checked: the centre, both halves and near both edges.
COLUMNS = (60, 400, 959, 1500, 1860)


def _edge_row(glow: np.ndarray, u: int, v_true: float, outward: int) -> float:
    """Where the unblurred glow of column ``u`` ends, measured from the pixels: the glow divided by its own
    smooth level is the share of each pixel row that the glow covers, and their sum over a window that starts
    fully covered places the edge. The smooth level is fitted 8-30 px outward of the true row and extrapolated:
    the log of the glow is smooth in the sheet's range ``x ~ 1 / |v - cy|``, so the fit is a quadratic in that."""
    col = glow[:, u].astype(float)
    r0 = round(v_true)
    cy = (glow.shape[0] - 1) / 2.0

    def basis(rows: np.ndarray) -> np.ndarray:
        w = 10.0 / np.abs(rows - cy)
        return np.stack([np.ones_like(w), w, w * w], axis=1)

    fit_rows = r0 + outward * np.arange(8, 31)
    coef, *_ = np.linalg.lstsq(basis(fit_rows), np.log(col[fit_rows]), rcond=None)
    window = r0 + np.arange(-8, 9)
    share = col[window] / np.exp(basis(window) @ coef)
    assert share[0 if outward < 0 else -1] == pytest.approx(1.0, abs=2e-3)  # fully covered at the far end
    assert share[-1 if outward < 0 else 0] < 1e-3  # nothing on the inner side
    if outward < 0:  # the glow covers [.., v_edge]: rows from window[0] - 0.5 up to the edge
        return float(window[0] - 0.5 + share.sum())
    return float(window[-1] + 0.5 - share.sum())


@pytest.mark.parametrize(
    "turbid",
    [
        Turbid(distance_m=0.5, glow_step=0.3, blur_px=0.0, **QUIET),
        Turbid(distance_m=1.0, glow_step=0.5, blur_px=0.0, **QUIET),
        Turbid(distance_m=1.0, tilt_deg=30.0, glow_step=0.1, blur_px=0.0, **QUIET),
    ],
    ids=["0.5m", "1m", "1m-tilt30"],
)
def test_the_glow_ends_at_the_true_stripe_row_before_blurring(turbid: Turbid) -> None:
    frame = render(turbid)
    for li, outward in ((0, -1), (1, 1)):
        for u in COLUMNS:
            v_true = float(frame.rows[li, u])
            if not np.isfinite(v_true) or frame.range_m[li, u] > 3.0:
                continue
            assert _edge_row(frame.layers["glow"], u, v_true, outward) == pytest.approx(v_true, abs=0.1)


@pytest.mark.parametrize("blur_px", [0.0, 4.0])
def test_the_glow_lies_outward_of_each_stripe(blur_px: float) -> None:
    """Above the top stripe and below the bottom one, nothing on the inner side; its level next to the edge is
    the asked share of the blurred stripe's peak (without attenuation the glow is nearly flat along v)."""
    step = 0.3
    t = Turbid(distance_m=1.0, glow_step=step, blur_px=blur_px, attenuation_per_m=0.0, **QUIET)
    frame = render(t)
    glow, stripe = frame.layers["glow"], frame.layers["stripe"]
    clear = round(6 * max(blur_px, 1.0) + 4)  # px beyond which the blur and the sheet's thickness have faded
    for li, outward in ((0, -1), (1, 1)):
        for u in COLUMNS:
            v0 = round(float(frame.rows[li, u]))
            outer, inner = glow[v0 + outward * clear, u], glow[v0 - outward * clear, u]
            # the blurred Gaussian's peak (continuous) from its area: sigma_sheet fy / x_w and the blur in quadrature
            sigma = np.hypot(t.sheet_sigma_m * frame.calibration.camera.fy / frame.range_m[li, u], blur_px)
            peak = stripe[v0 - 25 : v0 + 26, u].sum() / (np.sqrt(2 * np.pi) * sigma)
            assert outer == pytest.approx(step * peak, rel=0.01)
            assert inner < 1e-3 * outer


def test_the_stripe_is_centred_on_the_true_row() -> None:
    frame = render(Turbid(distance_m=2.0, tilt_deg=30.0, glow_step=0.0, blur_px=1.5, **QUIET))
    stripe = frame.layers["stripe"].astype(float)
    rows = np.arange(stripe.shape[0], dtype=float)[:, None]
    for li in (0, 1):
        half = (rows < 539.5) if li == 0 else (rows > 539.5)
        s = stripe * half
        vis = frame.visible[li]
        centroid = (s * rows).sum(axis=0)[vis] / s.sum(axis=0)[vis]
        assert np.abs(centroid - frame.rows[li, vis]).max() < 0.01


def _visible_rule(frame: TurbidFrame) -> np.ndarray:
    H = frame.image.shape[0]
    with np.errstate(invalid="ignore"):
        return (
            np.isfinite(frame.rows)
            & (frame.rows > 0)
            & (frame.rows < H - 1)
            & (frame.range_m >= 0.2)
            & (frame.range_m <= 5.0)
            & (frame.peak_dn >= 3.0 * np.nan_to_num(frame.noise_dn, nan=np.inf))
        )


def test_visible_columns_are_those_whose_peak_is_three_times_the_noise() -> None:
    # a dim far wall: the stripe fades towards the image's sides (oblique, further, attenuated)
    frame = render(Turbid(distance_m=3.0, glow_step=0.3, blur_px=4.0, peak_dn=40.0, attenuation_per_m=0.6))
    assert 0.2 < frame.visible.mean() < 0.9
    np.testing.assert_array_equal(frame.visible, _visible_rule(frame))
    # the centre column is visible, the outermost columns are not
    assert frame.visible[:, 959].all()
    assert not frame.visible[:, [0, 1919]].any()


def test_the_noise_is_what_the_visible_rule_assumes() -> None:
    """Read + shot noise and rounding, measured on the veil between the stripes (no glow there)."""
    t = Turbid(distance_m=0.5, glow_step=0.3, blur_px=1.5, particles_per_mpx=0.0, veil_dn=60.0)
    frame = render(t)
    green = frame.image[520:560, 100:1800, 1].astype(float)
    veil = frame.layers["veil"][520:560, 100:1800].astype(float)
    measured = float(np.std(green - veil))
    expected = float(np.sqrt(t.read_noise_dn**2 + veil.mean() / t.electrons_per_dn + 1.0 / 12.0))
    assert measured == pytest.approx(expected, rel=0.05)


def test_a_seed_gives_one_frame() -> None:
    t = Turbid(distance_m=1.0, tilt_deg=30.0, glow_step=0.3, blur_px=2.0, seed=7)
    a, b = render(t), render(t)
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.visible, b.visible)
    other = render(Turbid(distance_m=1.0, tilt_deg=30.0, glow_step=0.3, blur_px=2.0, seed=8))
    assert np.mean(a.image != other.image) > 0.5  # the noise differs nearly everywhere
    np.testing.assert_array_equal(a.rows, other.rows)  # the truth does not depend on the seed


def test_the_quick_bench_writes_one_table_per_method(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "turbid.md"
    assert bench_turbid.main(["--quick", "--out", str(out)]) == 0
    text = out.read_text(encoding="utf-8")
    assert text.startswith("<!-- python benchmarks/bench_turbid.py --quick")
    tables = text.split("#### ")[1:]
    assert len(tables) == len(bench_turbid.METHODS)
    n_cols = len(bench_turbid.HEADER[0].strip("|").split("|"))
    for table in tables:
        rows = [ln for ln in table.splitlines() if ln.startswith("| ") and not ln.startswith("| range")]
        assert len(rows) == len(bench_turbid.grid(quick=True))
        assert all(len(r.strip("|").split("|")) == n_cols for r in rows)
    assert capsys.readouterr().out.count("| 1.0 | 0 |") == len(bench_turbid.METHODS)


def test_the_bench_runs_a_few_cells_noise_free(capsys: pytest.CaptureFixture[str]) -> None:
    cells = bench_turbid.parse_cells("1:0.3:1.5, 3:0.5:4:30", noise_free=True)
    assert cells == [
        bench_turbid.Cell(1.0, 0.0, 0.3, 1.5, noise_free=True),
        bench_turbid.Cell(3.0, 30.0, 0.5, 4.0, noise_free=True),
    ]
    t = cells[0].turbid(2)
    assert (t.read_noise_dn, t.particles_per_mpx, t.seed) == (0.0, 0.0, 2)
    assert bench_turbid.Cell(1.0, 0.0, 0.3, 1.5).turbid(2) == Turbid(distance_m=1.0, glow_step=0.3, blur_px=1.5, seed=2)
    for bad in ("3:0.5", "3:x:4"):
        with pytest.raises(ValueError, match="--cells"):
            bench_turbid.parse_cells(bad)
    assert bench_turbid.main(["--cells", "1:0.3:1.5", "--seeds", "1", "--noise-free"]) == 0
    out = capsys.readouterr().out
    assert out.count("| 1.0 | 0 | 0.3 | 1.5 |") == 1  # the default extractor's row alone
    assert "wrote" not in out
    with pytest.raises(SystemExit):
        bench_turbid.main(["--noise-free"])
