"""The chaos soak (issue 30, item 5): random kills and restarts of the base station, the router and the robots,
link flaps; then every cloud produced is held by the base station once, acknowledged, and the outboxes are empty.

The soak is ``benchmarks/bench_chaos.py`` (its docstring defines what is produced and counted). Over the netns
tether where the harness can run (root, ``iptables``), on loopback otherwise (no impairments, no flaps: the
output says so). The short version (about 75 s) covers every kind of fault at least once and runs in CI; the
10-minute one is ``long`` (``pytest -m long``); ``python -m benchmarks.bench_chaos --minutes 30`` gives the
table in docs/reliability.md.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("zenoh")

from benchmarks.bench_chaos import KINDS, ChaosConfig, ChaosResult, Loopback, run_chaos


def _check(res: ChaosResult) -> None:
    why = res.explain()
    assert res.healed, why  # every robot finished a dive with every cloud acknowledged
    assert res.total_produced > 0, why
    assert not any(res.missing.values()), why  # every cloud produced is held by the base station ...
    assert not any(res.extra.values()), why  # ... and nothing it did not produce
    assert not any(res.unacked.values()), why  # ... acknowledged
    assert not any(res.pending.values()), why  # outboxes empty
    assert not any(res.dropped.values()), why  # nothing dropped by the budget
    assert not res.crashes, why  # no process died or hung unasked (SIGSEGV at exit included)
    assert res.base_exit == 0, why
    assert res.ok, why


@pytest.mark.slow
def test_short_chaos_soak_delivers_every_cloud_once(tmp_path: Path) -> None:
    cfg = ChaosConfig(fault_s=50, dive_frames=60, fault_every_s=6, flap_s=(10, 15), heal_s=120, ack_timeout_s=30)
    res = run_chaos(cfg, tmp_path, echo=False)
    _check(res)
    kinds = [k for k in KINDS if not (k == "link flap" and res.network.startswith("loopback"))]
    assert all(res.faults[k] >= 1 for k in kinds), res.explain()  # every kind of fault at least once
    assert sum(sum(c.values()) for c in res.robot_runs.values()) >= 2 * cfg.robots, res.explain()  # restarts


@pytest.mark.slow
@pytest.mark.long  # 10 minutes of faults: pytest -m long
@pytest.mark.timeout(1800)
def test_ten_minute_chaos_soak_delivers_every_cloud_once_in_bounded_memory(tmp_path: Path) -> None:
    cfg = ChaosConfig(fault_s=600, dive_frames=300, fault_every_s=30, heal_s=600, seed=2)
    res = run_chaos(cfg, tmp_path, echo=False)
    _check(res)
    assert sum(res.faults.values()) >= 10, res.explain()
    for kind in ("base", "router"):
        first, second = res.rss_peaks(kind)
        assert second - first < 64 * 1024, (kind, first, second)  # KiB: no growth beyond noise


def test_loopback_stands_in_without_namespaces(tmp_path: Path) -> None:
    import sys

    net = Loopback(tmp_path / "net")  # its folder is made (the soak's first loopback run failed without it)
    try:
        p = net.start("hello", net.ns_base, [sys.executable, "-c", "print('hello')"])
        assert p.wait(30) == 0
        assert net.log("hello").strip() == "hello"
        assert net.rov_endpoint().startswith("tcp/127.0.0.1:")
        net.set_up(False)  # no link to flap: a no-op
        assert net.link_bytes()["up_bytes"] == 0
    finally:
        net.close()


def test_a_number_given_twice_is_dropped_but_counted_and_said(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A re-sent cloud (same number, same capture time) is a plain duplicate; a robot that gives a number to
    another cloud (restarted without its outbox: its numbering starts again at 0) cannot be told from it by
    the number alone: the base station drops it too, but counts it as ``reused`` and says so."""
    from lrsensor.frames import Pose
    from services.ledger import Ledger
    from services.wire import CloudMsg

    def cloud(seq: int, t_ns: int) -> CloudMsg:
        pts = np.ones((3, 3), np.float32)
        return CloudMsg("rov1", seq, t_ns, Pose(0, 0, 1, 0, 0, 0), pts, np.zeros(3, np.uint8), np.ones(3, np.float32))

    ledger = Ledger(tmp_path / "state")
    assert ledger.accept(cloud(0, 1_000))
    assert not ledger.accept(cloud(0, 1_000))  # re-sent
    with caplog.at_level(logging.WARNING, logger="services.ledger"):
        assert not ledger.accept(cloud(0, 2_000))  # the same number, another cloud
    st = ledger.robots_json()["rov1"]
    assert (st["received"], st["duplicates"], st["reused"]) == (1, 2, 1)
    assert "gives numbers twice" in caplog.text
    ledger.save_state()
    assert Ledger(tmp_path / "state").robots_json()["rov1"]["reused"] == 1  # kept across a restart


def test_bench_chaos_exports_the_same_objects_as_its_parts() -> None:
    """``benchmarks.bench_chaos`` keeps every name it had (this test and the docs import them from there)."""
    import benchmarks.bench_chaos as bench_chaos
    import benchmarks.chaos_accounting as accounting
    import benchmarks.chaos_setup as setup
    import benchmarks.chaos_soak as soak

    own = {"RESULTS", "ROOT", "main", "report", "tables"}
    parts = (setup, soak, accounting)
    moved = {n: getattr(p, n) for p in parts for n in vars(p) if n in bench_chaos.__all__ and n not in own}
    assert {*moved, *own} == set(bench_chaos.__all__)
    for name, obj in moved.items():
        assert getattr(bench_chaos, name) is obj, name
