"""The lrsensor command: every sub-command is listed and has --help."""

from __future__ import annotations

import subprocess
import sys

import pytest

from lrsensor.cli import COMMANDS, main

ALL = ["setup", "process", "calibrate", "simulate", "range", "base", "rov", "demo", "map"]


def test_help_lists_every_subcommand(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for name in ALL:
        assert name in out
    assert set(ALL) <= set(COMMANDS)


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_each_subcommand_has_help(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main([name, "--help"])
    assert exc.value.code == 0
    assert "usage: lrsensor" in capsys.readouterr().out


def test_console_entry_point_runs() -> None:
    out = subprocess.run([sys.executable, "-m", "lrsensor", "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0
    assert "demo" in out.stdout
