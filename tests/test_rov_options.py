"""Range limits reach the ROV's extractor; the demo's range limit follows the camera's resolution."""

from __future__ import annotations

import numpy as np
import pytest

from lrsensor import Calibration
from lrsensor.sim import named_scene
from services.demo import MIN_STRIPE_OFFSET_PX, useful_range_m
from services.rov import RovService


def test_useful_range_follows_resolution() -> None:
    full = Calibration.paper()
    assert useful_range_m(full) == 5.0
    low = named_scene("wall_1.0", width=640, height=360).calibration
    r = useful_range_m(low)
    # at that range the stripe sits MIN_STRIPE_OFFSET_PX from the principal row
    assert low.camera.fy * 0.05 / r == pytest.approx(MIN_STRIPE_OFFSET_PX)
    assert 2.0 < r < 2.6


def test_process_options_reach_the_extractor() -> None:
    setup = named_scene("wall_2.0", width=640, height=360)
    image = setup.render(seed=0).image
    cal = setup.calibration

    class Probe(RovService):
        def __init__(self, **kw: object) -> None:  # no Zenoh needed to check the processing options
            super().__init__(None, None, "rov1", None, None, cal, **kw)  # type: ignore[arg-type]

    near = Probe(process_options={"max_range_m": 1.0})
    far = Probe(process_options={"max_range_m": 3.0})
    assert len(near.sensor.process(image, **near.process_options)) == 0
    scan = far.sensor.process(image, **far.process_options)
    assert len(scan) > 100
    assert np.median(scan.points[:, 0]) == pytest.approx(2.0, rel=0.02)


def test_range_limits_hold_for_the_output() -> None:
    from lrsensor import Sensor
    from lrsensor.extract import subpixel
    from lrsensor.sensor import range_limits

    assert range_limits("subpixel", {"max_range_m": 2.0}) == (0.2, 2.0)
    assert range_limits("paper", {}) == (0.2, 5.0)
    setup = named_scene("wall_2.0", width=640, height=360)
    image = setup.render(seed=0).image
    sensor = Sensor(setup.calibration)
    for hi in (1.9, 2.5):
        for reference in (False, True):  # the compiled road gates in the kernel, the reference in numpy
            with pytest.MonkeyPatch.context() as mp:
                mp.setattr(subpixel, "USE_REFERENCE", reference)
                scan = sensor.process(image, max_range_m=hi)
            depth = setup.calibration.body_to_cam(scan.points)[:, 2]
            assert np.all(depth <= hi)
        paper = sensor.process(image, method="paper", max_range_m=hi)  # gated by Sensor.process
        assert np.all(setup.calibration.body_to_cam(paper.points)[:, 2] <= hi)
    assert len(sensor.process(image, max_range_m=1.9)) < len(sensor.process(image, max_range_m=2.5)) / 10


def test_demo_imu_follows_the_flown_trajectory() -> None:
    # regression: the demo changed the vehicles' speed after making their IMU, so frames and poses disagreed
    from services.demo import DemoConfig, simulated_robot

    dive, imu, _ = simulated_robot("rov2", DemoConfig(speed_m_s=0.6), 40)
    for t in dive.times[::8]:
        true, measured = dive.true_pose(int(t)), imu.track.pose_at(int(t))
        assert measured is not None
        assert np.hypot(true.north_m - measured.north_m, true.east_m - measured.east_m) < 0.1
        assert abs(np.rad2deg(true.yaw_rad - measured.yaw_rad)) < 1.5


def test_rov_channel_flag_is_checked_before_the_network(capsys: pytest.CaptureFixture[str]) -> None:
    """``lrsensor rov --channel luma --method paper`` stops at once, naming the flag (no Zenoh session is opened);
    ``--channel`` parses to the extractor option."""
    from lrsensor.cli import build_parser, main

    code = main(["rov", "--fleet", "x", "--robot", "rov1", "--source", "sim", "--channel", "luma", "--method", "paper"])
    assert code == 2
    assert "--channel is an option of the subpixel extractor" in capsys.readouterr().err
    args = build_parser().parse_args(["rov", "--fleet", "x", "--robot", "rov1", "--source", "sim", "--channel", "luma"])
    assert args.channel == "luma"


def test_luma_channel_reaches_the_rov_extractor() -> None:
    setup = named_scene("wall_1.0", width=640, height=360)
    image = setup.render(seed=0).image
    cal = setup.calibration

    class Probe(RovService):
        def __init__(self, **kw: object) -> None:
            super().__init__(None, None, "rov1", None, None, cal, **kw)  # type: ignore[arg-type]

    rov = Probe(process_options={"channel": "luma"})
    scan = rov.sensor.process(image, **rov.process_options)
    assert len(scan) > 0.95 * 2 * 640
    assert np.median(scan.points[:, 0]) == pytest.approx(1.0, rel=0.002)
    with pytest.raises(Exception, match="channel must be one of"):
        Probe(process_options={"channel": "red"}).sensor.process(image, channel="red")
