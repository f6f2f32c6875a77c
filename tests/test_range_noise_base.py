"""The base station gives each cloud the range noise of the calibration it was measured with (schema 2), none to
a cloud without one (schema 1), in its own map and through the plane workers' jobs."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_wire_stripe import stripe_scan

from lrsensor.calibration import Calibration
from lrsensor.frames import Pose
from lrsensor.range_theory import range_error_per_px
from mapping import MapConfig
from mapping.range_noise import STRIPE_SIGMA_PX
from services.base import BaseStation
from services.calibbook import CalibrationBook
from services.errors import WireError
from services.keys import FleetKeys
from services.map_worker import MapWorker
from services.map_worker_wire import MapJob, decode_work
from services.wire import CloudMsg, StripeMsg, calibration_fingerprint

CAL = Calibration.paper(0.1, 640, 360)


def test_the_base_gives_a_schema_2_cloud_its_calibrations_k_and_a_schema_1_cloud_none(tmp_path: Path) -> None:
    base = BaseStation(None, FleetKeys("t"), tmp_path / "state", map_mode="on", navigation=False)
    base.calibrations = CalibrationBook(base.calibration_path, lambda robot: CAL)
    assert base.map is not None
    base.map.cfg = replace(base.map.cfg, stripe_sigma_px=STRIPE_SIGMA_PX)  # the default, said explicitly
    base.feed.start(None)
    try:
        pose = Pose(1.0, 2.0, 3.0, 0.0, 0.0, 0.5)
        stripe = StripeMsg.from_scan("rov1", 1, 1_000_000_000, pose, stripe_scan(), calibration_fingerprint(CAL))
        base._ingest(base.keys.cloud("rov1"), stripe.to_bytes(), 0)
        base.feed.flush()
        assert base.map.range_noise("rov1") == pytest.approx(STRIPE_SIGMA_PX * range_error_per_px(CAL))  # 0.0020 / m
        k = base.status()["robots"]["rov1"]["range_noise_per_m"]  # what the status says of it
        assert k == pytest.approx(STRIPE_SIGMA_PX * range_error_per_px(CAL))
        cloud = CloudMsg.from_scan("rov1", 2, 1_100_000_000, pose, stripe_scan(1))
        base._ingest(base.keys.cloud("rov1"), cloud.to_bytes(), 0)
        base.feed.flush()
        assert base.map.range_noise("rov1") == 0.0  # measured with a calibration the base cannot name
        assert base.status()["robots"]["rov1"]["range_noise_per_m"] == 0.0
        assert base.records["rov1"].rejected == 0
    finally:
        base.feed.close(save=False)


def test_a_job_carries_its_clouds_calibration_to_the_worker() -> None:
    pts = np.zeros((3, 3), np.float32)
    pts[:, 0] = 2.0
    job = MapJob("rov1", 1, 10, 0, Pose.identity(), pts, range_error_per_px=range_error_per_px(CAL))
    back = decode_work(job.to_bytes())
    assert isinstance(back, MapJob)
    assert back.range_error_per_px == job.range_error_per_px
    plain = decode_work(MapJob("rov1", 1, 10, 0, Pose.identity(), pts).to_bytes())
    assert isinstance(plain, MapJob)
    assert plain.range_error_per_px == 0.0  # absent on the wire
    worker = MapWorker(None, FleetKeys("t"), "w1", MapConfig(stripe_sigma_px=STRIPE_SIGMA_PX))
    worker.handle(back)
    assert worker.builder.range_noise("rov1") == pytest.approx(STRIPE_SIGMA_PX * range_error_per_px(CAL))
    worker.handle(MapJob("rov1", 2, 20, 0, Pose.identity(), pts))
    assert worker.builder.range_noise("rov1") == 0.0


def test_a_job_with_an_impossible_calibration_factor_is_refused() -> None:
    import msgpack

    d = msgpack.unpackb(MapJob("rov1", 1, 10, 0, Pose.identity(), np.zeros((1, 3), np.float32)).to_bytes())
    for bad in (-1.0, float("nan"), "x"):
        with pytest.raises(WireError, match="malformed"):
            decode_work(msgpack.packb(d | {"perpx": bad}))
