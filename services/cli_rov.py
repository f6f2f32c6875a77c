"""``lrsensor rov``: run one ROV (camera + IMU -> pose-tagged point clouds over Zenoh)."""

from __future__ import annotations

import argparse
import logging

from .zconfig import add_network_args

log = logging.getLogger(__name__)


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of ``lrsensor rov``."""
    parser.add_argument("--fleet", required=True, help="fleet name")
    parser.add_argument("--robot", required=True, help="this robot's name")
    parser.add_argument("--prefix", default="lrs", help="key prefix (default: lrs)")
    parser.add_argument(
        "--source",
        required=True,
        help="frames: 'sim' (simulated tank dive), a folder of <t_ns>.png, a video file, or a camera index",
    )
    parser.add_argument(
        "--imu",
        default=None,
        help="poses: 'sim', 'csv:FILE' or 'serial:PORT[@BAUD]' (default: sim for --source sim, "
        "else csv:<folder>/imu.csv when the folder has one)",
    )
    parser.add_argument(
        "--calib", default=None, help="calibration JSON (default: the simulator's, or fetched from the base station)"
    )
    parser.add_argument("--rate", type=float, default=None, metavar="HZ", help="process at most HZ frames per second")
    parser.add_argument("--method", default=None, help="stripe extractor (default: the best one)")
    parser.add_argument(
        "--calib-timeout-s", type=float, default=15.0, help="how long to ask the base station for a calibration"
    )
    parser.add_argument(
        "--ack-timeout-s",
        type=float,
        default=15.0,
        help="at the end of a finite source, wait this long for the base station to acknowledge every cloud",
    )
    parser.add_argument("--seq-start", type=int, default=0, help="first sequence number (continue after a restart)")
    parser.add_argument("--video-t0-ns", type=int, default=None, help="capture time of a video's first frame")
    parser.add_argument("--sim-frames", type=int, default=60, help="frames of the simulated dive (--source sim)")
    parser.add_argument("--sim-size", default="640x360", help="image size of the simulated camera (WxH)")
    parser.add_argument("--sim-seed", type=int, default=0, help="seed of the simulated dive")
    add_network_args(parser, default_mode="client")
    parser.epilog = "Defaults to client mode connecting to tcp/127.0.0.1:7447 when no endpoint is given."


def run(args: argparse.Namespace) -> int:
    """Run until the source ends (0), SIGINT/SIGTERM (0) or an error."""
    from pathlib import Path

    from lrsensor.calibration import Calibration

    from .errors import CalibrationUnavailableError
    from .imu import open_imu
    from .keys import FleetKeys, check_robot_name
    from .rov import RovService, fetch_calibration
    from .signals import stop_on_signals
    from .sources import FolderSource, open_source
    from .zconfig import NetworkOptions, open_session, options_from_args

    keys = FleetKeys(args.fleet, args.prefix)
    robot = check_robot_name(args.robot)
    options = options_from_args(args)
    mode = args.mode or "client"
    if not (options.connect or options.listen or options.config_file):
        options = NetworkOptions(mode=options.mode, connect=("tcp/127.0.0.1:7447",))
    if mode == "client" and not options.config_file:
        # wait for the router instead of failing at once (a ROV is often started before the shore side)
        options = NetworkOptions(
            mode=options.mode,
            connect=options.connect,
            listen=options.listen,
            config_file=options.config_file,
            connect_timeout_ms=int(max(args.calib_timeout_s, 5.0) * 1000),
        )
    calibration = Calibration.load(args.calib) if args.calib else None
    dive_calib: Path | None = None
    if args.source == "sim":
        from .simsource import open_sim

        w, _, h = args.sim_size.partition("x")
        source, sim_imu, sim_calib = open_sim(
            n_frames=args.sim_frames, width=int(w), height=int(h), seed=args.sim_seed, robot=robot
        )
        imu = sim_imu if args.imu in (None, "sim") else open_imu(args.imu)
        calibration = calibration or sim_calib
    else:
        source = open_source(args.source, args.video_t0_ns)
        imu_spec = args.imu
        if imu_spec is None and isinstance(source, FolderSource) and (source.folder / "imu.csv").is_file():
            imu_spec = f"csv:{source.folder / 'imu.csv'}"
        if imu_spec is None or imu_spec == "sim":
            log.error("--imu sim needs --source sim; give --imu csv:FILE or serial:PORT")
            return 2
        imu = open_imu(imu_spec)
        if isinstance(source, FolderSource) and (source.folder / "calib.json").is_file():
            dive_calib = Path(source.folder / "calib.json")
    with stop_on_signals() as stop, open_session(options, default_mode="client") as session:
        if calibration is None:
            try:
                calibration = fetch_calibration(session, keys, robot, args.calib_timeout_s, stop)
            except CalibrationUnavailableError as err:
                if dive_calib is None:
                    raise
                log.warning("%s; using the dive's own calibration %s", err, dive_calib)
                calibration = Calibration.load(dive_calib)
        service = RovService(
            session,
            keys,
            robot,
            source,
            imu,
            calibration,
            rate_hz=args.rate,
            method=args.method,
            ack_timeout_s=args.ack_timeout_s,
            seq_start=args.seq_start,
        )
        counters = service.run(stop)
    print(counters.summary(robot), flush=True)
    return 0
