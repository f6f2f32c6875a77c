"""Shared fixtures."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from procs import Proc


@pytest.fixture(autouse=True)
def _state_home(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test gets its own ``XDG_STATE_HOME`` (beside, not inside, its ``tmp_path``): ``lrsensor rov``
    keeps a robot's outbox there by default, so without this the ROVs of different tests (same fleet and
    robot names) would continue each other's numbering, forward each other's leftovers, refuse to start
    beside each other, and leave files in the home folder. Child processes inherit it through ``os.environ``
    (``tests/procs.py`` and ``tests/netlink.py`` pass the environment on)."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path_factory.mktemp("xdg-state")))


@pytest.fixture
def procs() -> Iterator[list[Proc]]:
    """Processes a test started; each is killed at the end whatever happened."""
    started: list[Proc] = []
    yield started
    for p in started:
        p.kill()
