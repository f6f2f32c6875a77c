"""How many plane workers ``lrsensor base`` starts when the operator does not say."""

from __future__ import annotations

import pytest

from services.map_worker_procs import default_map_workers


def test_no_workers_by_default_under_the_smoother() -> None:
    # Workers run no smoother: under --nav on the map thread must navigate, whatever the cores.
    assert default_map_workers(cores=16, nav="on") == 0
    assert default_map_workers(cores=16) == 0


@pytest.mark.parametrize(("cores", "want"), [(1, 0), (2, 0), (3, 1), (8, 6)])
def test_cores_minus_two_where_workers_map_as_one_process(cores: int, want: int) -> None:
    assert default_map_workers(cores=cores, nav="filter") == want
    assert default_map_workers(cores=cores, nav="off") == want
