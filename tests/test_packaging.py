"""Packaging contracts: the ROV install has no Open3D, CI runs the README's test command."""

from __future__ import annotations

import re
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]


def _pyproject() -> dict:  # type: ignore[type-arg]
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_rov_install_does_not_pull_open3d() -> None:
    deps = _pyproject()["project"]["dependencies"]
    assert not [d for d in deps if d.lower().startswith("open3d")]
    for needed in ("numpy", "opencv-python-headless", "eclipse-zenoh", "pyserial", "msgpack"):
        assert any(d.startswith(needed) for d in deps), needed


def test_all_extra_has_the_base_station() -> None:
    extras = _pyproject()["project"]["optional-dependencies"]
    assert any(d.startswith("open3d") for d in extras["all"])


def test_ci_runs_the_readme_test_command() -> None:
    readme = (ROOT / "README.md").read_text()
    block = re.search(r"## Quick start.*?```bash\n(.*?)```", readme, re.S)
    assert block is not None
    commands = [line.split("#")[0].strip() for line in block.group(1).splitlines() if line.strip()]
    assert commands == ["./run demo", "./run test"]
    ci = (ROOT / ".ci" / "run").read_text()
    assert "./run test" in ci
    assert 'lrsensor = "lrsensor.cli:main"' in (ROOT / "pyproject.toml").read_text()
