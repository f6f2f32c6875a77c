"""``lrsensor base --smoother wait`` (issue 27): the map thread waits for each smoother run and takes it over at
once, so the base's map is the one the in-process replays make (``mapping.synth.replay_dive`` with
``background="wait"``), whatever the machine's speed; by default (``thread``) a run is handed over at the first
cloud after it finished, which depends on how long it took."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mapping.smoother import SMOOTHED_NAV, SmootherConfig
from mapping.synth import replay_dive, simulate_dive, tank, three_rov_plans
from services import cli_base
from services.mapfeed import MapFeed, load_map_builder
from services.wire import CloudMsg


def _parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    cli_base.configure(parser)
    return parser.parse_args(["--fleet", "f", *argv])


def test_the_flag_parses_and_defaults_to_a_thread(capsys: pytest.CaptureFixture[str]) -> None:
    assert _parse().smoother == "thread"
    assert _parse("--smoother", "wait").smoother == "wait"
    with pytest.raises(SystemExit):
        _parse("--smoother", "later")
    assert "invalid choice: 'later'" in capsys.readouterr().err


def test_a_waiting_base_maps_as_the_in_process_replay(tmp_path: Path) -> None:
    frames = simulate_dive(
        tank(), three_rov_plans(), duration_s=24.0, rate_hz=10.0, n_rays=300, seed=2, navigation="drift"
    )
    # the points as the wire carries them (float32), for both roads
    frames = [replace(f, points_body=f.points_body.astype(np.float32).astype(np.float64)) for f in frames]
    ref = replay_dive(frames, navigate=True, nav_cfg=SMOOTHED_NAV, smoother=SmootherConfig(), background="wait")
    feed = MapFeed(load_map_builder(tmp_path, "on"), lambda robot, seq: None, navigation=True, queue_size=1 << 14)
    feed.set_smoothing(True, wait=True)
    assert feed.fleet is not None
    assert feed.fleet.background == "wait"
    feed.start(None)
    seqs: dict[str, int] = {}
    for f in frames:
        n = len(f.points_body)
        seq = seqs[f.robot] = seqs.get(f.robot, -1) + 1
        msg = CloudMsg(f.robot, seq, f.t_ns, f.pose_est, f.points_body.astype(np.float32), np.zeros(n, np.uint8),
                       np.ones(n, np.float32))  # fmt: skip
        feed.take(msg, f.t_ns)
    feed.flush()
    got = feed.map_json()["planes"]
    want = ref.planes()
    feed.close(save=False)
    assert len(feed.fleet.holds_s) >= 2  # runs during the dive, each handed over at once
    assert len(got) == len(want)
    for a, b in zip(sorted(got, key=lambda p: p["d"]), sorted(want, key=lambda p: p["d"]), strict=True):
        assert np.allclose(a["normal"], b["normal"], atol=1e-6)
        assert a["d"] == pytest.approx(b["d"], abs=1e-6)
