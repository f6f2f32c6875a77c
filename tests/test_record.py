"""Recording a fleet into MCAP and replaying it into a new base station (issue 28, item 3).

The recording is read back with the ``mcap`` reader and its protobuf decoder (mcap-protobuf-support), not
with our own code: one ``foxglove.PointCloud`` per distinct cloud, points equal to what the base station
triangulated, transforms for placed clouds, the map's planes as a scene. The replay feeds a fresh base
station, which rebuilds the same map.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from waiting import wait_until

from lrsensor.calibration import Calibration
from services.imu import CsvImu
from services.record import Recorder, RecordError
from services.replay import ReplayError, read_recording, replay
from services.simsource import record_sim_dive
from services.sources import FolderSource
from services.testnet import TestNetwork
from services.wire import decode_cloud

pytest.importorskip("foxglove")
pytest.importorskip("mcap_protobuf")

ROBOTS = ("rov1", "rov2")
N_FRAMES = 24
WAIT_S = 30.0


@pytest.fixture(scope="module")
def dives(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("record-dives")
    return {r: record_sim_dive(root / r, r, n_frames=N_FRAMES, seed=3, clean_water=True) for r in ROBOTS}


@pytest.fixture(scope="module")
def recorded(dives: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Two ROVs dive into a base station with the map on while a recorder listens; the file and the base's view."""
    out = tmp_path_factory.mktemp("recording") / "dive.mcap"
    raw: dict[str, list[bytes]] = {}
    with TestNetwork("rec") as net:
        base = net.start_base(None, map_mode="on", workers=1)  # one ingest thread: the map sees the send order
        rec = Recorder(net.session(), net.keys, out)
        sub = net.session().declare_subscriber(
            net.keys.all_clouds, lambda s: raw.setdefault(str(s.key_expr), []).append(s.payload.to_bytes())
        )
        handles = [
            net.start_rov(r, FolderSource(d), CsvImu(d / "imu.csv"), Calibration.load(d / "calib.json"))
            for r, d in dives.items()
        ]
        for h in handles:
            assert h.join(120)
            assert h.result is not None
        assert wait_until(
            lambda: all(base.status()["robots"].get(r, {}).get("received") == N_FRAMES for r in ROBOTS), WAIT_S
        )
        base.flush_map()
        assert wait_until(rec.idle, WAIT_S)
        stats = rec.close()
        status = base.status()
        map_json = base.map_json()
        sub.undeclare()
    return {"path": out, "stats": stats, "status": status, "map": map_json, "raw": raw}


def test_recording_has_one_point_cloud_per_distinct_cloud(recorded: dict[str, Any]) -> None:
    from mcap.reader import make_reader

    # the protobuf decoder refuses our raw msgpack channel; read foxglove topics with it, the rest raw
    with recorded["path"].open("rb") as f:
        channels = make_reader(f).get_summary().channels.values()
        topics = {c.topic for c in channels}
    for r in ROBOTS:
        assert {f"/lrs/rec/{r}/points", f"lrs/rec/{r}/cloud", f"lrs/rec/{r}/calib"} <= topics
    assert {"/tf", "/lrs/rec/map"} <= topics
    stats = recorded["stats"]
    assert stats["clouds"] == dict.fromkeys(ROBOTS, N_FRAMES)
    assert (stats["rejected"], stats["pending"], stats["duplicates"]) == (0, 0, 0)
    # the recording's clouds counted against the base's status
    for r in ROBOTS:
        assert recorded["status"]["robots"][r]["received"] == stats["clouds"][r]


def test_point_clouds_decode_with_foxglove_schemas_and_match_the_base(recorded: dict[str, Any], dives) -> None:
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    clouds: dict[str, list[Any]] = {r: [] for r in ROBOTS}
    tfs: list[Any] = []
    scenes: list[Any] = []
    with recorded["path"].open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        fox_topics = [f"/lrs/rec/{r}/points" for r in ROBOTS] + ["/tf", "/lrs/rec/map"]
        for schema, channel, _, decoded in reader.iter_decoded_messages(topics=fox_topics):
            if channel.topic == "/tf":
                assert schema.name == "foxglove.FrameTransform"
                tfs.append(decoded)
            elif channel.topic == "/lrs/rec/map":
                assert schema.name == "foxglove.SceneUpdate"
                scenes.append(decoded)
            else:
                assert schema.name == "foxglove.PointCloud"
                clouds[channel.topic.split("/")[3]].append(decoded)
    for r in ROBOTS:
        assert len(clouds[r]) == N_FRAMES
        calib = Calibration.load(dives[r] / "calib.json")
        first = decode_cloud(recorded["raw"][f"lrs/rec/{r}/cloud"][0])
        want = first.to_cloud(calib) if hasattr(first, "to_cloud") else first
        pc = next(c for c in clouds[r] if c.timestamp.ToNanoseconds() == want.t_ns)
        assert pc.frame_id == f"{r}/base_link"
        assert [fld.name for fld in pc.fields] == ["x", "y", "z", "laser"]
        rec = np.frombuffer(pc.data, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("laser", "u1")])
        got = np.stack([rec["x"], rec["y"], rec["z"]], axis=1)
        np.testing.assert_array_equal(got, want.points_body)
        np.testing.assert_array_equal(rec["laser"], want.laser)
    assert len(tfs) == len(ROBOTS) * N_FRAMES  # every cloud of a simulated dive has a position
    assert {t.parent_frame_id for t in tfs} == {"ned"}
    # the last scene state holds every plane of the base's map
    shown: set[str] = set()
    for s in scenes:
        shown -= {d.id for d in s.deletions}
        shown |= {e.id for e in s.entities}
    assert shown == {f"plane/{p['id']}" for p in recorded["map"]["planes"]}
    assert shown  # the dive sees walls


def test_replay_rebuilds_the_same_map(recorded: dict[str, Any], tmp_path: Path) -> None:
    rec = read_recording(recorded["path"])
    assert (rec.prefix, rec.fleet, rec.robots) == ("lrs", "rec", list(ROBOTS))
    assert len(rec.clouds) == N_FRAMES * len(ROBOTS)
    with TestNetwork("rep") as net:
        base = net.start_base(None, map_mode="on", workers=1)
        res = replay(net.session(), net.keys, rec, tmp_path / "outboxes", rate=0.0, ack_timeout_s=WAIT_S)
        assert res.delivered, res
        assert res.sent == dict.fromkeys(ROBOTS, N_FRAMES)
        assert wait_until(
            lambda: all(base.status()["robots"].get(r, {}).get("received") == N_FRAMES for r in ROBOTS), WAIT_S
        )
        base.flush_map()
        again = base.map_json()
        status = base.status()
    assert all(status["robots"][r]["rejected"] == 0 for r in ROBOTS)
    # the same planes from the same points; the fits may differ slightly because the base's ingest threads
    # hand the robots' clouds to the map in an order that varies from run to run (the merge is order-sensitive)
    before = sorted(recorded["map"]["planes"], key=lambda p: p["n_points"])
    after = sorted(again["planes"], key=lambda p: p["n_points"])
    assert len(after) == len(before) > 0
    for a, b in zip(before, after, strict=True):
        assert abs(a["n_points"] - b["n_points"]) <= 0.01 * a["n_points"], (a, b)
        angle = np.degrees(np.arccos(min(1.0, abs(float(np.dot(a["normal"], b["normal"]))))))
        assert angle < 0.5, (a, b)
        assert abs(a["d"] - b["d"]) < 0.01, (a, b)


def test_recorder_refuses_an_existing_file_and_replay_a_bad_one(tmp_path: Path) -> None:
    existing = tmp_path / "x.mcap"
    existing.write_bytes(b"not mcap")
    with TestNetwork("bad") as net:
        with pytest.raises(RecordError, match="exists"):
            Recorder(net.session(), net.keys, existing)
        with pytest.raises(RecordError, match="does not exist"):
            Recorder(net.session(), net.keys, tmp_path / "no" / "x.mcap")
    with pytest.raises(ReplayError, match="cannot be read"):
        read_recording(existing)
    with pytest.raises(ReplayError, match="does not exist"):
        read_recording(tmp_path / "missing.mcap")


def test_record_and_replay_cli_help() -> None:
    for cmd in ("record", "replay"):
        out = subprocess.run(
            [sys.executable, "-m", "lrsensor", cmd, "--help"], capture_output=True, text=True, check=True
        ).stdout
        assert "--connect" in out
        assert ("--out" if cmd == "record" else "--rate") in out


def test_replay_cli_exits_non_zero_and_names_the_outbox_without_a_base(recorded: dict[str, Any]) -> None:
    with TestNetwork("nobase") as net:  # a router, no base station: nothing is acknowledged
        proc = subprocess.run(
            [
                sys.executable, "-m", "lrsensor", "replay", str(recorded["path"]), "--rate", "0",
                "--ack-timeout-s", "2", "--connect", net.endpoint, "--fleet", "nobase",
            ],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    assert proc.returncode == 3, proc.stderr
    for r in ROBOTS:
        assert f"{r}: {N_FRAMES} clouds not acknowledged, kept in" in proc.stderr
    folder = proc.stderr.split("kept in ")[1].split()[0]
    assert Path(folder).is_dir()
