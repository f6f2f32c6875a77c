"""Simulated dives: trajectories, IMU noise, recorded dive files, truth clouds, and the CLI."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from lrsensor.calibration import Calibration
from lrsensor.cli import main
from lrsensor.errors import SimulationError
from lrsensor.frames import body_to_ned
from lrsensor.sim import SCENES, tank_scene
from lrsensor.sim.dive import (
    IMU_CSV_HEADER,
    ImuLog,
    ImuNoise,
    clearance_m,
    frame_times_ns,
    in_range_fraction,
    min_separation_m,
    record_dive,
    simulate_imu,
    tank_trajectories,
    trace_dive_clouds,
)


def test_tank_trajectories_are_distinct_safe_and_look_at_structure() -> None:
    trajs = tank_trajectories(5)
    assert len({t.name for t in trajs}) == 5
    assert min_separation_m(trajs, 240.0) > 0.5
    for tr in trajs:
        assert clearance_m(tr, 240.0) > 0.4, tr.name
        assert in_range_fraction(tr, 240.0, step_s=2.0) > 0.8, tr.name
    # trajectory k does not depend on how many were asked for; a big fleet does not collide either
    big = tank_trajectories(20)
    assert big[3].pose_at(big[3].t0_ns + 5_000_000_000) == trajs[3].pose_at(trajs[3].t0_ns + 5_000_000_000)
    assert min_separation_m(big, 120.0, step_s=1.0) > 0.5
    p0 = trajs[0].pose_at(trajs[0].t0_ns)
    p1 = trajs[1].pose_at(trajs[1].t0_ns)
    assert np.linalg.norm(p0.p_ned - p1.p_ned) > 1.0


def test_trajectory_is_smooth() -> None:
    tr = tank_trajectories(2)[1]
    ts = tr.t0_ns + (np.arange(0, 60, 0.05) * 1e9).astype(np.int64)
    a = tr.arrays(ts)
    step = np.hypot(np.diff(a["north_m"]), np.diff(a["east_m"]))
    assert step.max() < abs(tr.speed_m_s) * 0.05 * 1.01
    dyaw = np.angle(np.exp(1j * np.diff(a["yaw_rad"])))
    assert np.abs(dyaw).max() < math.radians(3.0)  # < 60 deg/s
    assert np.abs(a["roll_rad"]).max() < math.radians(3)


def test_imu_noise_is_realistic_and_seeded() -> None:
    tr = tank_trajectories(1)[0]
    t0 = tr.t0_ns
    imu = simulate_imu(tr, t0, t0 + 60_000_000_000, rate_hz=100.0, seed=3)
    again = simulate_imu(tr, t0, t0 + 60_000_000_000, rate_hz=100.0, seed=3)
    np.testing.assert_array_equal(imu.roll_rad, again.roll_rad)
    assert len(imu) == 6001
    assert np.all(np.diff(imu.t_ns) == 10_000_000)
    a = tr.arrays(imu.t_ns)
    droll = np.degrees(imu.roll_rad - a["roll_rad"])
    assert 0.1 < droll.std() < 0.3
    dyaw = np.degrees(np.angle(np.exp(1j * (imu.yaw_rad - a["yaw_rad"]))))
    assert 0.1 < abs(dyaw.mean()) < 1.0  # a small bias
    dn = imu.north_m - a["north_m"]
    assert 0.005 < dn.std() < 0.05
    perfect = simulate_imu(tr, t0, t0 + 1_000_000_000, noise=ImuNoise.none())
    b = tr.arrays(perfect.t_ns)
    np.testing.assert_allclose(perfect.yaw_rad, b["yaw_rad"])


def test_drift_navigation_dead_reckons_with_growing_error_and_a_compass_bias() -> None:
    tr = tank_trajectories(1)[0]
    t0 = tr.t0_ns
    imu = simulate_imu(tr, t0, t0 + 120_000_000_000, rate_hz=50.0, seed=4, navigation="drift")
    again = simulate_imu(tr, t0, t0 + 120_000_000_000, rate_hz=50.0, seed=4, navigation="drift")
    np.testing.assert_array_equal(imu.north_m, again.north_m)
    a = tr.arrays(imu.t_ns)
    err = np.hypot(imu.north_m - a["north_m"], imu.east_m - a["east_m"])
    assert err[0] < 0.02  # the launch point is known
    assert err[:500].max() < 0.3  # smooth growth, not noise
    assert err.max() > 0.5  # dead reckoning drifts past half a metre in two minutes
    dyaw = np.degrees(np.angle(np.exp(1j * (imu.yaw_rad - a["yaw_rad"]))))
    assert 0.5 < abs(np.median(dyaw)) < 2.5  # the compass is biased by 1-2 deg
    assert 0.1 < np.ptp(np.convolve(dyaw, np.ones(500) / 500, mode="valid")) < 3.0  # and the bias wanders
    ddown = imu.down_m - a["down_m"]
    assert ddown.std() < 0.02


def test_depth_only_navigation_has_a_launch_fix_only_and_round_trips_the_csv(tmp_path: Path) -> None:
    tr = tank_trajectories(2)[1]
    t0 = tr.t0_ns
    imu = simulate_imu(tr, t0, t0 + 10_000_000_000, rate_hz=20.0, seed=2, navigation="depth-only")
    assert np.isfinite(imu.north_m[0])
    assert np.isfinite(imu.east_m[0])
    assert np.all(np.isnan(imu.north_m[1:]))
    assert np.all(np.isnan(imu.east_m[1:]))
    assert np.all(np.isfinite(imu.yaw_rad))
    assert np.all(np.isfinite(imu.down_m))
    path = tmp_path / "imu.csv"
    imu.write_csv(path)
    rows = list(csv.reader(path.open()))
    i_n, i_e = IMU_CSV_HEADER.index("north_m"), IMU_CSV_HEADER.index("east_m")
    assert rows[1][i_n] != ""
    assert rows[2][i_n] == ""
    assert rows[2][i_e] == ""
    back = ImuLog.read_csv(path)
    assert np.isnan(back.north_m[5])
    assert back.north_m[0] == pytest.approx(imu.north_m[0], abs=1e-5)
    with pytest.raises(SimulationError, match="navigation"):
        simulate_imu(tr, t0, t0 + 1_000_000_000, navigation="dvl")


def test_trace_dive_clouds_are_true_points() -> None:
    tr = tank_trajectories(3)[1]
    clouds = list(trace_dive_clouds(tr, frame_times_ns(0.6, 5.0, tr.t0_ns)))
    assert len(clouds) == 3
    scene = tank_scene()
    for c in clouds:
        assert c.points_body.shape[0] > 500
        assert set(np.unique(c.laser)) <= {0, 1}
        pts_ned = body_to_ned(c.points_body, c.pose)
        assert scene.distance_to_surface(pts_ned).max() < 1e-6
        assert c.pose == tr.pose_at(c.t_ns)


def test_record_dive_writes_the_recorded_dive_format(tmp_path: Path) -> None:
    rec = record_dive(
        tmp_path / "d",
        robot="rov2",
        robot_index=1,
        n_robots=2,
        duration_s=1.0,
        rate_hz=4.0,
        width=320,
        height=180,
        seed=5,
    )
    files = sorted(p.name for p in (tmp_path / "d").iterdir())
    pngs = [f for f in files if f.endswith(".png")]
    assert len(pngs) == 4
    assert {"imu.csv", "calib.json", "truth.json"} <= set(files)
    t_frames = sorted(int(f[:-4]) for f in pngs)
    assert t_frames == [int(t) for t in rec.t_ns]
    assert np.all(np.diff(t_frames) == 250_000_000)
    img = cv2.imread(str(rec.frames[0]))
    assert img.shape == (180, 320, 3)
    with rec.imu_csv.open() as fh:
        rows = list(csv.reader(fh))
    assert tuple(rows[0]) == IMU_CSV_HEADER
    imu = ImuLog.read_csv(rec.imu_csv)
    assert imu.t_ns[0] < t_frames[0]
    assert imu.t_ns[-1] > t_frames[-1]
    assert np.all(np.diff(imu.t_ns) > 0)
    calib = Calibration.load(rec.calib_json)
    assert (calib.camera.width, calib.camera.height) == (320, 180)
    truth = json.loads(rec.truth_json.read_text())
    assert truth["robot"] == "rov2"
    assert truth["navigation"] == "good"
    assert [f["t_ns"] for f in truth["frames"]] == t_frames
    p = truth["frames"][2]["pose"]
    exp = rec.trajectory.pose_at(t_frames[2])
    assert p["north_m"] == pytest.approx(exp.north_m)
    assert p["yaw_rad"] == pytest.approx(exp.yaw_rad)
    assert any(s["name"] == "pillar1+x" for s in truth["surfaces_ned"])
    # the IMU agrees with the truth within its noise
    k = int(np.argmin(np.abs(imu.t_ns - t_frames[2])))
    assert abs(imu.north_m[k] - exp.north_m) < 0.1


def test_cli_simulate_list_scene_wall_dive(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", "list"]) == 0
    out = capsys.readouterr().out
    for name in SCENES:
        assert name in out
    assert (
        main(
            [
                "simulate",
                "scene",
                "occluder",
                "--out",
                str(tmp_path / "s"),
                "--width",
                "480",
                "--height",
                "270",
                "--seed",
                "3",
            ]
        )
        == 0
    )
    truth = json.loads((tmp_path / "s" / "truth.json").read_text())
    assert truth["scene"] == "occluder"
    assert len(truth["lasers"]) == 2
    assert len(truth["lasers"][0]["columns"]["u"]) > 400
    assert Calibration.load(tmp_path / "s" / "calib.json").camera.width == 480
    ply = (tmp_path / "s" / "truth_points.ply").read_bytes()
    assert ply.startswith(b"ply\nformat binary_little_endian 1.0\n")
    assert cv2.imread(str(tmp_path / "s" / "image.png")).shape == (270, 480, 3)
    assert (
        main(
            [
                "simulate",
                "wall",
                "--distance-m",
                "0.5",
                "--tilted",
                "--out",
                str(tmp_path / "w"),
                "--width",
                "480",
                "--height",
                "270",
            ]
        )
        == 0
    )
    w = json.loads((tmp_path / "w" / "truth.json").read_text())
    assert w["wall"]["distance_m"] == 0.5
    tilted = Calibration.load(tmp_path / "w" / "calib.json")
    assert abs(tilted.lasers[0].normal[0]) > 0.01
    assert (
        main(
            [
                "simulate",
                "dive",
                "--out",
                str(tmp_path / "d"),
                "--robot",
                "rov3",
                "--duration-s",
                "0.5",
                "--rate-hz",
                "4",
                "--width",
                "160",
                "--height",
                "90",
                "--no-progress",
            ]
        )
        == 0
    )
    assert len(list((tmp_path / "d").glob("*.png"))) == 2
    pose = "6,1.5,2,0,0,90"
    assert (
        main(
            [
                "simulate",
                "scene",
                "tank",
                "--out",
                str(tmp_path / "t"),
                "--width",
                "320",
                "--height",
                "180",
                "--pose",
                pose,
            ]
        )
        == 0
    )
    tank = json.loads((tmp_path / "t" / "truth.json").read_text())
    assert tank["pose_ned"]["yaw_rad"] == pytest.approx(math.pi / 2)
    assert main(["simulate", "scene", "tank", "--out", str(tmp_path / "t"), "--pose", "1,2"]) == 2
    assert main(["simulate", "scene", "nope", "--out", str(tmp_path / "x")]) == 2
    assert "unknown scene" in capsys.readouterr().err
