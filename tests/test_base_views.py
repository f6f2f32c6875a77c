"""``lrsensor base --record --foxglove --ros2 --http`` as a user runs it: one base process with every view, a ROV
process replaying a dive, then Ctrl-C: the recording is complete, the live view was served, the ROS 2 topics
were published, the status page answered (issue 28)."""

from __future__ import annotations

import json
import re
import signal
import urllib.request
from pathlib import Path

import pytest
from procs import Proc, client_session, lrsensor_cmd
from waiting import wait_until

from services.simsource import record_sim_dive
from services.testnet import free_port

pytest.importorskip("foxglove")
pytest.importorskip("rosbags")

FLEET = "views"
N_FRAMES = 8


def test_base_with_every_view(tmp_path: Path, procs: list[Proc]) -> None:
    from mcap.reader import make_reader

    dive = record_sim_dive(tmp_path / "rov1", "rov1", n_frames=N_FRAMES, seed=9, clean_water=True)
    port, mcap_path = free_port(), tmp_path / "dive.mcap"
    base = Proc(
        lrsensor_cmd(
            "base", "--fleet", FLEET, "--listen", f"tcp/127.0.0.1:{port}", "--map", "off",
            "--record", str(mcap_path), "--foxglove", "127.0.0.1:0", "--ros2", "--http", "127.0.0.1:0",
        ),
        tmp_path / "base.log",
    )  # fmt: skip
    procs.append(base)
    ros_keys: list[str] = []
    with client_session(port) as session:
        sub = session.declare_subscriber("0/**", lambda s: ros_keys.append(str(s.key_expr)))
        assert wait_until(lambda: "Foxglove live view on ws://127.0.0.1:" in base.output(), 30), base.output()
        rov = Proc(
            lrsensor_cmd(
                "rov", "--fleet", FLEET, "--robot", "rov1", "--connect", f"tcp/127.0.0.1:{port}",
                "--source", str(dive), "--imu", f"csv:{dive / 'imu.csv'}", "--calib", str(dive / "calib.json"),
                "--ros2",
            ),
            tmp_path / "rov.log",
        )  # fmt: skip
        procs.append(rov)
        assert rov.wait(120) == 0, rov.output()
        url = re.search(r"status page on (http://\S+)", base.output())
        assert url is not None, base.output()
        with urllib.request.urlopen(url.group(1) + "status.json", timeout=10) as r:
            assert json.loads(r.read())["robots"]["rov1"]["received"] == N_FRAMES
        assert wait_until(lambda: sum("points_map" in k for k in ros_keys) >= N_FRAMES, 20), ros_keys
        assert wait_until(lambda: sum("/rov1/points/" in k for k in ros_keys) >= N_FRAMES, 20), ros_keys
        sub.undeclare()
    assert base.stop(signal.SIGINT) == 0, base.output()
    out = base.output()
    assert f"recording the fleet into {mcap_path}" in out
    assert re.search(r"ROS 2 topics /lrs/views/\.\.\. on domain 0", out)
    with mcap_path.open("rb") as f:
        reader = make_reader(f)
        counts: dict[str, int] = {}
        for _, channel, _ in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    assert counts[f"/lrs/{FLEET}/rov1/points"] == N_FRAMES
    assert counts[f"lrs/{FLEET}/rov1/cloud"] == N_FRAMES
    assert {f"0/lrs/{FLEET}/rov1/points_map", f"0/lrs/{FLEET}/rov1/pose"} <= {k.rsplit("/", 2)[0] for k in ros_keys}
    # the ROV's own scans (lrsensor rov --ros2), in its base_link
    rov_scans = [
        k for k in ros_keys if k.startswith(f"0/lrs/{FLEET}/rov1/points/sensor_msgs::msg::dds_::PointCloud2_/")
    ]
    assert len(rov_scans) == N_FRAMES
    assert "ROS 2 PointCloud2 on /lrs/views/rov1/points (domain 0)" in rov.output()
