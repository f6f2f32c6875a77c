"""Fleet services in one process on the loopback test network: ingest, counters, calibration, liveliness,
rejection of bad payloads, persistence of the counters, and the small building blocks (keys, seqset, zconfig).
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from waiting import wait_until

from lrsensor.calibration import Calibration
from lrsensor.frames import Pose
from services.base import BaseStation
from services.errors import CalibrationUnavailableError, KeyNameError, NetworkConfigError
from services.imu import CsvImu, TrackImu
from services.keys import FleetKeys, check_robot_name
from services.posetrack import PoseTrack
from services.rov import fetch_calibration
from services.seqset import SeqSet
from services.simsource import open_sim, record_sim_dive
from services.sources import FolderSource, Frame, open_source
from services.testnet import TestNetwork
from services.wire import ENCODING, CalibMsg, CloudMsg, StripeMsg, calibration_fingerprint, decode_cloud
from services.zconfig import NetworkOptions, make_config

N_FRAMES = 6
WAIT_S = 10.0  # how long a test waits for a message or a state unless it says otherwise


@pytest.fixture(scope="module")
def dives(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("dives")
    return {r: record_sim_dive(root / r, r, n_frames=N_FRAMES, clean_water=True) for r in ("rov1", "rov2")}


class GatedSource:
    """Frames of a folder, then waits for ``release`` before ending (keeps a ROV alive in a test)."""

    finite = True
    live = False

    def __init__(self, folder: Path) -> None:
        self.inner = FolderSource(folder)
        self.name = "gated"
        self.release = threading.Event()
        self.delivered = threading.Event()

    def __enter__(self) -> GatedSource:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def __iter__(self) -> Iterator[Frame]:
        yield from self.inner
        self.delivered.set()
        self.release.wait(30)


def publisher(session: Any, key: str) -> Any:
    pub = session.declare_publisher(
        key, encoding=zenoh.Encoding(ENCODING), congestion_control=zenoh.CongestionControl.BLOCK
    )
    assert wait_until(lambda: pub.matching_status.matching, 10), f"no subscriber matched {key}"
    return pub


def get_json(session: Any, key: str) -> Any:
    for _ in range(50):
        for reply in session.get(key, timeout=2.0):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
        time.sleep(0.05)
    raise AssertionError(f"no reply on {key}")


def a_cloud(robot: str, seq: int, n: int = 10) -> CloudMsg:
    rng = np.random.default_rng(seq)
    return CloudMsg(
        robot,
        seq,
        1_700_000_000_000_000_000 + seq,
        Pose(1, 2, 3, 0, 0, 0.5),
        rng.normal(0, 1, (n, 3)).astype(np.float32),
        np.zeros(n, np.uint8),
        np.ones(n, np.float32),
    )


# ----------------------------------------------------------------------------- fleet on the test network


def test_two_rovs_every_cloud_arrives_and_membership_is_followed(dives: dict[str, Path], tmp_path: Path) -> None:
    with TestNetwork("t1") as net:
        base = net.start_base(tmp_path / "state", map_mode="off")
        handles = []
        for robot, folder in dives.items():
            src = FolderSource(folder)
            handles.append(
                net.start_rov(robot, src, CsvImu(folder / "imu.csv"), Calibration.load(folder / "calib.json"))
            )
        for h in handles:
            assert h.join(60), f"{h.robot} did not finish"
            assert h.error is None
            assert h.result is not None
            assert h.result.published == N_FRAMES
            assert h.result.delivered
        assert wait_until(lambda: not any(r.alive for r in base.records.values()), WAIT_S)
        status = get_json(net.session(), net.keys.base_status)
        for robot in dives:
            st = status["robots"][robot]
            assert (st["received"], st["missed"], st["rejected"], st["last_seq"]) == (N_FRAMES, 0, 0, N_FRAMES - 1)
            assert st["alive"] is False
            assert st["reported"]["published"] == N_FRAMES
            events = [e for r, e, _ in base.membership_events if r == robot]
            assert events[:1] == ["joined"]
            assert events[-1] == "left"
        tracks = base.tracks()
        assert tracks["rov1"].shape == (N_FRAMES, 4)
        assert status["map"]["planes"] == 0
        assert status["map"]["enabled"] is False


def test_calibration_queryables_and_fetch(dives: dict[str, Path], tmp_path: Path) -> None:
    folder = dives["rov1"]
    calib = Calibration.load(folder / "calib.json")
    with TestNetwork("t2") as net:
        base = net.start_base(tmp_path / "state", map_mode="off")
        base.store_calibration("rov1", calib)
        client = net.session()
        assert fetch_calibration(client, net.keys, "rov1", timeout_s=10) == calib
        with pytest.raises(CalibrationUnavailableError, match="no calibration stored for robot 'rov7'"):
            fetch_calibration(client, net.keys, "rov7", timeout_s=10)
        as_json = get_json(client, net.keys.base_calib("rov1") + "?format=json")
        assert Calibration.from_dict(as_json) == calib

        src = GatedSource(folder)
        h = net.start_rov("rov1", src, CsvImu(folder / "imu.csv"), calib)
        assert src.delivered.wait(30)
        replies = [r.ok for r in client.get(net.keys.calib("rov1"), timeout=5) if r.ok is not None]
        assert len(replies) == 1
        assert CalibMsg.from_bytes(replies[0].payload.to_bytes()).calibration == calib
        alive = [str(r.ok.key_expr) for r in client.liveliness().get(net.keys.all_alive, timeout=5) if r.ok]
        assert alive == ["lrs/t2/rov1/alive"]
        src.release.set()
        assert h.join(30)
        assert h.error is None


def test_fetch_without_base_fails_clearly() -> None:
    with TestNetwork("t3") as net, pytest.raises(CalibrationUnavailableError, match="give --calib"):
        fetch_calibration(net.session(), net.keys, "rov1", timeout_s=1.0)


def test_garbage_spoofing_and_duplicates_are_counted_and_never_stop_the_base(tmp_path: Path) -> None:
    with TestNetwork("t4") as net:
        base = net.start_base(tmp_path / "state", map_mode="off", robots=["rov1", "rov2"])
        s = net.session()
        rng = np.random.default_rng(0)
        pub9 = publisher(s, net.keys.cloud("rov9"))
        pub1 = publisher(s, net.keys.cloud("rov1"))
        pub2 = publisher(s, net.keys.cloud("rov2"))
        for _ in range(200):
            pub1.put(rng.integers(0, 256, int(rng.integers(0, 300)), dtype=np.uint8).tobytes())
        pub2.put(a_cloud("rov1", 0).to_bytes())  # rov1's cloud under rov2's key
        pub9.put(a_cloud("rov9", 0).to_bytes())  # not a fleet member
        good = a_cloud("rov1", 3).to_bytes()
        pub1.put(good)
        pub1.put(good)  # duplicate
        pub1.put(a_cloud("rov1", 0).to_bytes())
        assert wait_until(lambda: base.processed == 2 and base.records["rov1"].duplicates == 1, WAIT_S)
        assert base.drain(10)
        st = get_json(s, net.keys.base_status)["robots"]
        assert st["rov1"]["rejected"] == 200
        assert (st["rov1"]["received"], st["rov1"]["missed"], st["rov1"]["duplicates"]) == (2, 2, 1)
        assert st["rov2"]["rejected"] == 1
        assert st["rov2"]["received"] == 0
        assert st["rov9"]["rejected"] == 1
        acks = get_json(s, net.keys.base_acks("rov1"))
        assert acks["ranges"] == [[0, 0], [3, 3]]


def test_counters_survive_a_restart(tmp_path: Path) -> None:
    state = tmp_path / "state"
    with TestNetwork("t5") as net:
        base = net.start_base(state, map_mode="off")
        pub = publisher(net.session(), net.keys.cloud("rov1"))
        for seq in (0, 1, 2, 5):
            pub.put(a_cloud("rov1", seq).to_bytes())
        assert wait_until(lambda: base.processed == 4, WAIT_S)
    saved = json.loads((state / "fleet.json").read_text())
    assert saved["robots"]["rov1"]["ranges"] == [[0, 2], [5, 5]]
    with TestNetwork("t5") as net:
        base = net.start_base(state, map_mode="off")
        pub = publisher(net.session(), net.keys.cloud("rov1"))
        pub.put(a_cloud("rov1", 2).to_bytes())
        pub.put(a_cloud("rov1", 3).to_bytes())
        assert wait_until(lambda: base.processed == 1 and base.records["rov1"].duplicates == 1, WAIT_S)
        st = base.status()["robots"]["rov1"]
        assert (st["received"], st["missed"], st["last_seq"]) == (5, 1, 5)


def test_status_reports_transit_time_of_replayed_clouds(tmp_path: Path) -> None:
    # capture times from 2023 (a replayed recording): end-to-end latency is years, transit is milliseconds
    with TestNetwork("t5b") as net:
        base = net.start_base(tmp_path / "state", map_mode="off")
        pub = publisher(net.session(), net.keys.cloud("rov1"))
        pub.put(a_cloud("rov1", 0).with_sent_ns(time.time_ns()).to_bytes())
        assert wait_until(lambda: base.processed == 1, WAIT_S)
        ingest = base.status()["ingest"]
        assert ingest["latency_ms"]["p50"] > 1e9
        assert 0 <= ingest["transit_ms"]["p50"] < 5_000


def test_frames_outside_the_imu_span_are_skipped_not_guessed(dives: dict[str, Path], tmp_path: Path) -> None:
    folder = dives["rov2"]
    full = CsvImu(folder / "imu.csv").track
    times, poses = full.samples()
    frame_times = [t for t, _ in FolderSource(folder).files]
    keep = [(t, p) for t, p in zip(times, poses, strict=True) if frame_times[1] <= t <= frame_times[-2]]
    imu = TrackImu(PoseTrack.from_arrays([t for t, _ in keep], [p for _, p in keep]))
    with TestNetwork("t6") as net:
        base = net.start_base(None, map_mode="off")
        h = net.start_rov("rov2", FolderSource(folder), imu, Calibration.load(folder / "calib.json"))
        assert h.join(60)
        assert h.result is not None
        assert (h.result.frames, h.result.skipped, h.result.published) == (N_FRAMES, 2, N_FRAMES - 2)
        assert h.result.delivered
        assert base.status()["robots"]["rov2"]["received"] == N_FRAMES - 2


@pytest.mark.parametrize("schema", [1, 2])
def test_published_pose_is_the_interpolated_imu_pose(dives: dict[str, Path], schema: int) -> None:
    folder = dives["rov1"]
    imu = CsvImu(folder / "imu.csv")
    calib = Calibration.load(folder / "calib.json")
    got: list[CloudMsg | StripeMsg] = []
    with TestNetwork("t7") as net:
        s = net.session()
        sub = s.declare_subscriber(net.keys.cloud("rov1"), lambda smp: got.append(decode_cloud(smp.payload.to_bytes())))
        h = net.start_rov("rov1", FolderSource(folder), imu, calib, ack_timeout_s=0, cloud_schema=schema)
        assert h.join(60)
        assert wait_until(lambda: len(got) == N_FRAMES, WAIT_S)
        sub.undeclare()
    assert {type(m) for m in got} == {CloudMsg if schema == 1 else StripeMsg}
    for m in got:
        if isinstance(m, StripeMsg):
            assert m.calib_id == calibration_fingerprint(calib)
            assert np.isfinite(m.to_cloud(calib).points_body).all()
        expect = imu.track.pose_at(m.t_ns)
        assert expect is not None
        assert m.pose.north_m == pytest.approx(expect.north_m)
        assert m.pose.yaw_rad == pytest.approx(expect.yaw_rad)
        assert len(m) > 50  # the lasers hit the tank
    assert [m.seq for m in got] == list(range(N_FRAMES))


# ----------------------------------------------------------------------------- building blocks


def test_sim_source_frames_lie_inside_the_imu_span() -> None:
    src, imu, calib = open_sim(n_frames=3, width=320, height=180, robot="rov2", clean_water=True)
    frames = list(src)
    assert len(frames) == 3
    assert frames[0].image.shape == (180, 320, 3)
    assert calib.camera.width == 320
    assert all(imu.track.pose_at(f.t_ns) is not None for f in frames)


def test_open_source_dispatch(dives: dict[str, Path], tmp_path: Path) -> None:
    assert isinstance(open_source(str(dives["rov1"])), FolderSource)
    with pytest.raises(Exception, match="unknown frame source"):
        open_source(str(tmp_path / "nothing-here"))
    with pytest.raises(Exception, match="no image named"):
        FolderSource(tmp_path)


def test_keys_layout_and_name_checks() -> None:
    k = FleetKeys("reef")
    assert k.cloud("rov1") == "lrs/reef/rov1/cloud"
    assert k.base_status == "lrs/reef/base/status"
    assert k.map == "lrs/reef/map"
    assert k.base_calib("rov2") == "lrs/reef/base/calib/rov2"
    assert k.robot_of("lrs/reef/rov3/cloud") == "rov3"
    assert k.robot_of("lrs/other/rov3/cloud") is None
    assert k.robot_of("lrs/reef/base/status") is None
    assert k.robot_of_base_key("lrs/reef/base/calib/rov2", "calib") == "rov2"
    for bad in ("", "a/b", "x*", "base", "$1", "a" * 65):
        with pytest.raises(KeyNameError):
            check_robot_name(bad)
    with pytest.raises(KeyNameError):
        FleetKeys("fleet/**")


def test_seqset_counts() -> None:
    s = SeqSet()
    for x in (0, 1, 2, 5, 7, 6, 2):
        s.add(x)
    assert s.ranges() == [[0, 2], [5, 7]]
    assert len(s) == 6
    assert s.missed() == 2
    assert s.highest == 7
    assert s.covers(5, 7)
    assert not s.covers(1, 5)
    rng = np.random.default_rng(3)
    ref: set[int] = set()
    s = SeqSet()
    for x in rng.integers(0, 300, 2000):
        assert s.add(int(x)) == (int(x) not in ref)
        ref.add(int(x))
    assert len(s) == len(ref)
    assert s.missed() == max(ref) + 1 - len(ref)
    assert SeqSet(s.ranges()).ranges() == s.ranges()


def test_zconfig_flags_and_file(tmp_path: Path) -> None:
    def get(conf: Any, key: str) -> Any:
        return json.loads(conf.get_json(key))

    conf = make_config(NetworkOptions(mode="client", connect=("tcp/127.0.0.1:7447",)))
    assert get(conf, "mode") == "client"
    assert get(conf, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert get(conf, "scouting/multicast/enabled") is False
    f = tmp_path / "z.json5"
    f.write_text('{ mode: "router", listen: { endpoints: ["tcp/127.0.0.1:9999"] }, // comment\n }')
    conf = make_config(NetworkOptions(config_file=str(f)))
    assert get(conf, "mode") == "router"
    assert get(conf, "listen/endpoints") == ["tcp/127.0.0.1:9999"]
    with pytest.raises(NetworkConfigError, match="invalid Zenoh endpoint"):
        NetworkOptions(connect=("127.0.0.1:7447",))
    with pytest.raises(NetworkConfigError, match="does not exist"):
        make_config(NetworkOptions(config_file=str(tmp_path / "none.json5")))


def test_base_station_without_state_keeps_counters_in_memory() -> None:
    with TestNetwork("t8") as net:
        base: BaseStation = net.start_base(None, map_mode="off")
        assert base.state_dir is None
        assert base.status()["robots"] == {}


# ----------------------------------------------------------------------------- ROV side without Open3D, video, map


def test_rov_side_imports_without_open3d_or_mapping() -> None:
    import subprocess
    import sys

    code = (
        "import sys\n"
        "import services.rov, services.wire, services.imu, services.sources, services.cli_rov, services.simsource\n"
        "bad = [m for m in ('open3d', 'mapping', 'matplotlib') if m in sys.modules]\n"
        "assert not bad, bad\n"
        "from lrsensor.cli import build_parser; build_parser()\n"
        "assert 'open3d' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_video_source_stamps_frames_from_the_container(tmp_path: Path) -> None:
    import cv2

    from services.sources import VideoSource

    path = tmp_path / "dive.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    assert w.isOpened()
    for k in range(5):
        w.write(np.full((48, 64, 3), 40 * k, np.uint8))
    w.release()
    with VideoSource(path, t0_ns=1_000_000_000) as src:
        frames = list(src)
    assert len(frames) == 5
    dt = np.diff([f.t_ns for f in frames])
    assert np.allclose(dt, 100_000_000, atol=2_000_000)
    assert frames[0].t_ns == 1_000_000_000
    assert frames[0].image.shape == (48, 64, 3)


@pytest.mark.slow
def test_base_serves_the_map_and_publishes_its_updates(tmp_path: Path) -> None:
    pytest.importorskip("open3d")
    mapping = pytest.importorskip("mapping")
    if not hasattr(mapping, "MapBuilder"):
        pytest.skip("mapping.MapBuilder is not built yet")
    updates: list[dict[str, Any]] = []
    with TestNetwork("t9") as net:
        base = net.start_base(tmp_path / "state", map_mode="on")
        s = net.session()
        sub = s.declare_subscriber(net.keys.map_updates, lambda smp: updates.append(json.loads(smp.payload.to_bytes())))
        handles = []
        for robot in ("rov1", "rov3"):
            src, imu, calib = open_sim(n_frames=16, robot=robot, rate_hz=2, clean_water=True)
            handles.append(net.start_rov(robot, src, imu, calib))
        for h in handles:
            assert h.join(120)
            assert h.error is None
        base.flush_map()
        served = get_json(s, net.keys.map)
        assert served["planes"], "the map has no plane"
        for p in served["planes"]:
            assert abs(np.linalg.norm(p["normal"]) - 1.0) < 1e-6
            assert np.isfinite(p["d"])
        assert base.status()["map"]["planes"] == len(served["planes"])
        assert wait_until(lambda: len(updates) > 0, WAIT_S)
        assert all("planes" in u for u in updates)
        sub.undeclare()
    assert (tmp_path / "state" / "map").is_dir()


def test_rov_cli_without_a_router_fails_clearly(capsys: pytest.CaptureFixture[str], dives: dict[str, Path]) -> None:
    from lrsensor.cli import main
    from services.testnet import free_port

    folder = dives["rov1"]
    code = main(
        [
            "rov",
            "--fleet",
            "x",
            "--robot",
            "rov1",
            "--connect",
            f"tcp/127.0.0.1:{free_port()}",
            "--source",
            str(folder),
            "--calib-timeout-s",
            "1",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2
    assert "cannot open a Zenoh session" in err
