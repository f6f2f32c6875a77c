"""docs/water.md's pictures come from a command (benchmarks/plot_water.py) that still runs."""

from __future__ import annotations

from pathlib import Path

from benchmarks import plot_water


def test_plot_water_writes_both_pictures(tmp_path: Path) -> None:
    assert plot_water.main(["--out", str(tmp_path)]) == 0
    for name in ("turbid_profile.png", "port_error.png"):
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n", name
        assert len(data) > 20_000, name


def test_the_docs_show_the_pictures() -> None:
    text = (Path(__file__).resolve().parents[1] / "docs" / "water.md").read_text()
    for name in ("img/turbid_profile.png", "img/port_error.png"):
        assert name in text
        assert (Path(__file__).resolve().parents[1] / "docs" / name).is_file()
