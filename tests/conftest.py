"""Shared fixtures."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from procs import Proc


@pytest.fixture
def procs() -> Iterator[list[Proc]]:
    """Processes a test started; each is killed at the end whatever happened."""
    started: list[Proc] = []
    yield started
    for p in started:
        p.kill()
