"""Atomic writes: whole file or nothing, readable mode, no temporary files left behind."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from lrsensor.atomic import atomic_write


def test_writes_text_and_bytes_with_readable_mode(tmp_path: Path) -> None:
    p = atomic_write(tmp_path / "a" / "f.json", '{"x": 1}')
    assert p.read_text() == '{"x": 1}'
    assert stat.S_IMODE(p.stat().st_mode) == 0o644
    atomic_write(p, b"\x00\x01", fsync=False)
    assert p.read_bytes() == b"\x00\x01"
    assert sorted(x.name for x in p.parent.iterdir()) == ["f.json"]


def test_failed_write_keeps_the_old_file(tmp_path: Path) -> None:
    p = atomic_write(tmp_path / "f.bin", b"old")

    with pytest.raises(TypeError):
        atomic_write(p, 12345)  # type: ignore[arg-type]
    assert p.read_bytes() == b"old"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["f.bin"]
