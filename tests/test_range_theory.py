"""Range theory (eq. 33-34) against the paper's own numbers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lrsensor.cli import main
from lrsensor.range_theory import (
    RangeCamera,
    depth_resolution,
    max_range,
    pixel_change,
    pixel_from_range,
    range_from_pixel,
)


def test_focal_length_in_pixels() -> None:
    assert RangeCamera().focal_px == pytest.approx(554.28, abs=0.01)


def test_eq33_34_hand_value() -> None:
    # v = 100 px -> y_c = 100 * 0.018/1080 m; x = 0.1 * 0.009238 / y_c
    assert float(range_from_pixel(100, 0.1)) == pytest.approx(0.1 * 0.009238 / (100 * 0.018 / 1080))
    np.testing.assert_allclose(range_from_pixel(pixel_from_range([0.5, 2.0], 0.2), 0.2), [0.5, 2.0])


def test_paper_pixel_value_below_50_under_2m() -> None:
    # paper 5.1: "the pixel value is < 50 for distances < 2 m" - i.e. at 2 m it is well below 50
    assert float(pixel_from_range(2.0, 0.1)) < 50
    assert float(pixel_from_range(1.2, 0.1)) < 50


def test_paper_sub_pixel_change_beyond_2_5m() -> None:
    x = np.linspace(2.5, 8.0, 100)
    assert np.all(pixel_change(x, 0.1, 0.1) < 1.0)
    assert float(pixel_change(2.0, 0.1, 0.1)) > 1.0
    assert 2.0 < max_range(0.1) < 2.5


def test_larger_baseline_extends_range() -> None:
    # paper Fig. 10: b = 0.5 m gives an effective range of 5-8 m
    assert 4.5 < max_range(0.5) < 8.0
    assert depth_resolution(1.0, 0.1) == pytest.approx(1.0 / (0.1 * 554.28), rel=1e-3)


def test_cli_table_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    png = tmp_path / "fig.png"
    assert main(["range", "--baseline-m", "0.1", "0.5", "--distance-m", "2.5", "--plot", str(png)]) == 0
    out = capsys.readouterr().out
    assert "0.10   2.50    22.17          0.853" in out
    assert png.stat().st_size > 10_000
