"""``lrsensor rov``: run one ROV (camera + IMU -> pose-tagged point clouds over Zenoh)."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import faulthandler
import io
import logging
import shutil
import signal
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from lrsensor.extract import CHANNELS, command_line_options

from .ros2 import add_ros2_arg
from .zconfig import add_network_args

log = logging.getLogger(__name__)

#: Exit code of a finite run that ended with clouds the base station has not acknowledged.
EXIT_UNDELIVERED = 3
#: The ROV's TCP send buffer, KiB (Linux doubles it): a kernel queue of about a second for three robots sharing
#: 2 Mbit/s, so that keep-alives stay well inside Zenoh's 10 s lease (a longer queue got links declared dead
#: and re-opened, benchmarks/results/link.md); it caps one TCP connection at about 5 Mbit/s over a 400 ms round
#: trip, so raise it for a fast link with a long round trip.
DEFAULT_TCP_SEND_BUFFER_KIB = 128.0


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of ``lrsensor rov``."""
    parser.add_argument("--fleet", required=True, help="fleet name")
    parser.add_argument("--robot", required=True, help="this robot's name")
    parser.add_argument("--prefix", default="lrs", help="key prefix (default: lrs)")
    parser.add_argument(
        "--source",
        required=True,
        help="frames: 'sim' (simulated tank dive), a folder of <t_ns>.png, a video file, a camera index, or a "
        "camera stream: udp://HOST:PORT (H.264 in MPEG-TS), rtsp://..., or FILE.sdp (RTP, e.g. a BlueROV2's "
        "H.264 on port 5600); video files and streams are read on the luma channel unless --channel is given",
    )
    parser.add_argument(
        "--stream-timeout-s",
        type=float,
        default=10.0,
        metavar="S",
        help="stream: fail when it sends nothing for S seconds at start; later, reopen it (with a backoff) "
        "after S seconds without a frame (default 10)",
    )
    parser.add_argument(
        "--imu",
        default=None,
        help="poses: 'sim', 'csv:FILE', 'serial:PORT[@BAUD]' (OpenROV) or 'mavlink:CONNECTION' (ArduSub, e.g. "
        "mavlink:udpin:127.0.0.1:14551) (default: sim for --source sim, else csv:<folder>/imu.csv when the "
        "folder has one)",
    )
    parser.add_argument(
        "--imu-stale-s",
        type=float,
        default=None,
        metavar="S",
        help="mavlink: samples further apart than S seconds are not interpolated between, so frames in a silent "
        "link's gap get no pose (default 1.0)",
    )
    parser.add_argument(
        "--calib", default=None, help="calibration JSON (default: the simulator's, or fetched from the base station)"
    )
    parser.add_argument("--rate", type=float, default=None, metavar="HZ", help="process at most HZ frames per second")
    parser.add_argument("--method", default=None, help="stripe extractor (default: the best one)")
    parser.add_argument(
        "--min-range-m", type=float, default=None, help="nearest range searched, metres along the optical axis"
    )
    parser.add_argument(
        "--max-range-m",
        type=float,
        default=None,
        help="farthest range searched, metres (default: the extractor's; lower it for low-resolution cameras)",
    )
    parser.add_argument(
        "--channel",
        choices=CHANNELS,
        default=None,
        help="subpixel extractor: 'luma' for a JPEG/MJPEG/H.264 camera (colour stored at half resolution); "
        "default green",
    )
    parser.add_argument(
        "--calib-timeout-s", type=float, default=15.0, help="how long to ask the base station for a calibration"
    )
    parser.add_argument(
        "--ack-timeout-s",
        type=float,
        default=15.0,
        help="at the end of a finite source, wait for the base station to acknowledge every cloud, giving up after "
        "S seconds without an acknowledgement moving on; clouds still unacknowledged then make the exit code "
        f"{EXIT_UNDELIVERED} and stay in the outbox, whose folder is printed (default 15)",
        metavar="S",
    )
    parser.add_argument(
        "--cloud-schema",
        type=int,
        choices=(1, 2),
        default=2,
        help="cloud payload: 2 = the stripe's pixels, triangulated at the base with this robot's calibration "
        "(about 8x smaller, the default); 1 = float32 points (docs/conventions.md)",
    )
    add_ros2_arg(parser, "each scan (PointCloud2 in <robot>/base_link)")
    parser.add_argument("--seq-start", type=int, default=0, help="first sequence number (continue after a restart)")
    g = parser.add_argument_group("store-and-forward outbox (every cloud is kept until the base acknowledges it)")
    g.add_argument(
        "--outbox",
        metavar="DIR",
        default=None,
        help="outbox folder: unacknowledged clouds survive a ROV restart and the numbering continues; one "
        "process per folder (default: $XDG_STATE_HOME/lrsensor/outbox/<fleet>/<robot>, i.e. "
        "~/.local/state/lrsensor/outbox/<fleet>/<robot>; a temporary folder, with a warning, where that is "
        "not writable)",
    )
    g.add_argument(
        "--outbox-max-mb",
        type=float,
        default=1024.0,
        help="the outbox's disk budget, MiB: every cloud not yet acknowledged is kept within it; when full the "
        "oldest are dropped, logged and counted (dropped_budget) (default 1024)",
    )
    g.add_argument("--outbox-max-messages", type=int, default=20_000, help="outbox bound, clouds")
    g.add_argument("--outbox-no-fsync", action="store_true", help="do not fsync each cloud (faster, not power-safe)")
    g.add_argument("--no-outbox", action="store_true", help="publish only (clouds sent during an outage are lost)")
    parser.add_argument("--video-t0-ns", type=int, default=None, help="capture time of a video's first frame")
    parser.add_argument("--sim-frames", type=int, default=60, help="frames of the simulated dive (--source sim)")
    parser.add_argument("--sim-size", default="640x360", help="image size of the simulated camera (WxH)")
    parser.add_argument("--sim-seed", type=int, default=0, help="seed of the simulated dive")
    parser.add_argument(
        "--tcp-send-buffer-kib",
        type=float,
        default=DEFAULT_TCP_SEND_BUFFER_KIB,
        metavar="KIB",
        help="kernel send buffer of the ROV's TCP links, KiB (0: the system's; ignored when --config sets "
        "so_sndbuf): short, so that acknowledgement queries and keep-alives do not wait behind seconds of "
        f"clouds already handed to the kernel on a slow link (default {DEFAULT_TCP_SEND_BUFFER_KIB:g}; Linux "
        "doubles it)",
    )
    add_network_args(parser, default_mode="client")
    parser.epilog = "Defaults to client mode connecting to tcp/127.0.0.1:7447 when no endpoint is given."


def run(args: argparse.Namespace) -> int:
    """Run until the source ends (0), SIGINT/SIGTERM (0) or an error (2: among them an outbox in use).

    SIGUSR1 writes the stack of every thread to stderr and the ROV runs on (a stop that does not end shows
    where it waits)."""
    from .keys import FleetKeys, check_robot_name

    _dump_threads_on_sigusr1()

    # (--channel with another method is refused here, before the network)
    process_options = command_line_options(args.method, args.channel, args.min_range_m, args.max_range_m)
    keys = FleetKeys(args.fleet, args.prefix)
    robot = check_robot_name(args.robot)
    # The outbox (its lock) comes first: a second ROV of the same robot stops here, before it opens the
    # camera, the IMU's serial port or a session that would disturb the first one.
    with _open_outbox(args, keys.fleet, robot) as (outbox, temporary):
        return _run(args, process_options, keys, robot, outbox, temporary)


def _dump_threads_on_sigusr1() -> None:
    """Make SIGUSR1 write every thread's stack to stderr, where stderr is a real file (not under a test's capture,
    whose stream has no descriptor for the signal handler to write to)."""
    if not hasattr(signal, "SIGUSR1"):
        return
    try:
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    except (io.UnsupportedOperation, ValueError, AttributeError):
        log.debug("stderr has no file descriptor: no thread dump on SIGUSR1")


def _run(args: argparse.Namespace, process_options: Any, keys: Any, robot: str, outbox: Any, temporary: bool) -> int:
    """:func:`run` once the outbox (None with ``--no-outbox``; ``temporary``: a folder of this run) is held."""
    from lrsensor.calibration import Calibration

    from .errors import CalibrationUnavailableError
    from .imu import ImuSource, open_imu
    from .rov import RovService, fetch_calibration
    from .signals import stop_on_signals
    from .sources import FolderSource, FrameSource, open_source
    from .zconfig import NetworkOptions, open_session, options_from_args

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
    if args.tcp_send_buffer_kib > 0:
        options = dataclasses.replace(options, tcp_send_buffer=int(args.tcp_send_buffer_kib * 1024))
    calibration = Calibration.load(args.calib) if args.calib else None
    stop = threading.Event()  # set by SIGINT/SIGTERM; a stream's wait for frames ends on it
    dive_calib: Path | None = None
    if args.source == "sim":
        from .simsource import open_sim

        w, _, h = args.sim_size.partition("x")
        source: FrameSource
        imu: ImuSource
        source, sim_imu, sim_calib = open_sim(
            n_frames=args.sim_frames, width=int(w), height=int(h), seed=args.sim_seed, robot=robot
        )
        imu = sim_imu if args.imu in (None, "sim") else open_imu(args.imu, args.imu_stale_s)
        calibration = calibration or sim_calib
    else:
        source = open_source(args.source, args.video_t0_ns, stream_timeout_s=args.stream_timeout_s, stop=stop)
        imu_spec = args.imu
        if imu_spec is None and isinstance(source, FolderSource) and (source.folder / "imu.csv").is_file():
            imu_spec = f"csv:{source.folder / 'imu.csv'}"
        if imu_spec is None or imu_spec == "sim":
            log.error("--imu sim needs --source sim; give --imu csv:FILE, serial:PORT or mavlink:CONNECTION")
            return 2
        imu = open_imu(imu_spec, args.imu_stale_s)
        if isinstance(source, FolderSource) and (source.folder / "calib.json").is_file():
            dive_calib = Path(source.folder / "calib.json")
    with (
        stop_on_signals(stop),
        open_session(options, default_mode="client") as session,
        _open_delivery(session, keys, robot, outbox) as sink,
    ):
        seq_start = args.seq_start if sink is None else max(args.seq_start, sink.outbox.next_seq)
        ros2_view = None
        if args.ros2 is not None:
            from .ros2_views import Ros2ScanView

            ros2_view = Ros2ScanView(session, keys.root, robot, args.ros2)
            print(f"rov {robot}: ROS 2 PointCloud2 on {ros2_view.publisher.topic} (domain {args.ros2})", flush=True)
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
            process_options=process_options,
            # only a finite source ends; a stream or camera stops on a signal, with nothing to wait for
            ack_timeout_s=args.ack_timeout_s if source.finite else 0.0,
            seq_start=seq_start,
            sink=sink,
            cloud_schema=args.cloud_schema,
            on_scan=ros2_view.on_scan if ros2_view is not None else None,
        )
        try:
            counters = service.run(stop)
        finally:
            if ros2_view is not None:
                ros2_view.close()
        undelivered = ""
        if sink is not None:
            if counters.delivered and len(sink.outbox):  # older clouds of a persistent outbox
                sink.wait_empty(args.ack_timeout_s, stop, idle=True)
            st = sink.stats()
            o = st["outbox"]
            print(
                f"rov {robot}: outbox {o['pending']} pending, {st['acked']} acknowledged, {st['resent']} re-sent "
                f"({st['resent_bytes']} bytes, {st['resent_unheard']} never heard before), {o['dropped']} dropped "
                f"(full), {st['unstored']} not stored, {st['held']} held while the link was down, "
                f"clouds {st['sent_bytes']} bytes",
                flush=True,
            )
            print(
                f"rov {robot}: link budget: published {st['sent']} + reloaded {st['reloaded']} = live {st['live']} "
                f"+ forwarded {st['forwarded']} + queued {st['queued']} + dropped by the budget "
                f"{st['dropped_budget']} ({st['released']} sent and released by the budget before their "
                f"acknowledgement, {st['thinned']} thinned from the live stream, {st['held']} held)",
                flush=True,
            )
            if service.state == "done" and o["pending"]:
                again = (
                    f"--outbox {sink.outbox.directory}"
                    if args.outbox is not None or temporary
                    else "the same --fleet and --robot (its default outbox)"
                )
                undelivered = (
                    f"rov {robot}: {o['pending']} clouds NOT acknowledged by the base station are kept in "
                    f"{sink.outbox.directory}; run again with {again} to deliver them"
                )
        elif service.state == "done" and counters.delivered is False:
            undelivered = f"rov {robot}: delivery NOT confirmed and --no-outbox keeps no copy"
    print(counters.summary(robot), flush=True)
    if undelivered:
        print(undelivered, file=sys.stderr, flush=True)
        return EXIT_UNDELIVERED
    return 0


def _default_folder(fleet: str, robot: str) -> Path | None:
    """The robot's folder in the user's state directory, created; None when it cannot be written."""
    from .outbox import OutboxError, default_outbox_dir

    try:
        folder = default_outbox_dir(fleet, robot)
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):  # writable? (a read-only mount passes the mkdir)
            pass
    except (OSError, OutboxError) as err:
        log.warning(
            "rov %s: no writable state directory for the outbox (%s): using a temporary folder, so a restart "
            "of this ROV numbers its clouds from 0 again and the base station drops them as reused; set "
            "XDG_STATE_HOME or give --outbox DIR",
            robot,
            err,
        )
        return None
    return folder


@contextlib.contextmanager
def _open_outbox(args: argparse.Namespace, fleet: str, robot: str) -> Iterator[tuple[Any, bool]]:
    """The robot's :class:`~services.outbox.Outbox` (None with ``--no-outbox``), locked until the end, and
    whether its folder is a temporary one of this run.

    ``--outbox DIR``, else the robot's folder in the user's state directory (a restart continues the
    numbering and forwards what is pending), else a temporary folder, removed at the end when empty; when
    clouds are still pending it is kept and named, so that a later ``lrsensor rov --outbox DIR`` delivers them.

    Raises:
        OutboxError: the folder is held by another process (one process per outbox), or unusable.
    """
    if args.no_outbox:
        yield None, False
        return
    from .outbox import Outbox, OutboxError, OutboxInUseError

    folder = Path(args.outbox) if args.outbox is not None else _default_folder(fleet, robot)
    temporary = folder is None
    if folder is None:
        folder = Path(tempfile.mkdtemp(prefix=f"lrs-outbox-{robot}-"))
    try:
        outbox = Outbox(
            folder,
            max_messages=args.outbox_max_messages,
            max_bytes=int(args.outbox_max_mb * 1024 * 1024),
            fsync=not args.outbox_no_fsync,
        )
    except OutboxInUseError as err:
        who = "with this --outbox" if args.outbox is not None else f"of robot {robot!r} in fleet {fleet!r}"
        msg = f"{err} (another lrsensor rov {who} on this machine?); stop it first, or give this one another --outbox"
        raise OutboxError(msg) from err
    try:
        if len(outbox):
            log.warning("rov %s: %d clouds from an earlier run are pending in %s", robot, len(outbox), folder)
        else:
            log.info("rov %s: outbox %s, numbering from %d", robot, folder, outbox.next_seq)
        yield outbox, temporary
    finally:
        outbox.close()
        if len(outbox):
            log.warning("rov %s: %d clouds not acknowledged are kept in %s", robot, len(outbox), folder)
        elif temporary:
            shutil.rmtree(folder, ignore_errors=True)


@contextlib.contextmanager
def _open_delivery(session: Any, keys: Any, robot: str, outbox: Any) -> Iterator[Any]:
    """The robot's :class:`~services.delivery.OutboxSink` on ``outbox`` (None without one), closed at the end."""
    if outbox is None:
        yield None
        return
    from .delivery import OutboxSink

    sink = OutboxSink(session, keys, robot, outbox, forward_now=False)  # RovService.run starts forwarding
    try:
        yield sink
    finally:
        sink.close()
