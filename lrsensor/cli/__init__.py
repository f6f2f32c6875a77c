"""The ``lrsensor`` command: one program, one sub-command per job.

Each sub-command lives in its own module with ``configure(parser)`` (flags only, cheap imports) and
``run(args) -> int`` (does the work; heavy imports happen here). Fleet commands live in ``services``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from ..errors import LrsensorError

#: name -> (module, one-line help). Order is the order ``--help`` lists them in.
COMMANDS: dict[str, tuple[str, str]] = {
    "setup": ("lrsensor.cli.setup", "compile the sensor's kernels once after installing (about 30 s)"),
    "process": (
        "lrsensor.cli.process",
        "extract and triangulate laser stripes of images into PLY point clouds",
    ),
    "calibrate": ("lrsensor.cli.calibrate", "calibrate the laser planes (wall images) or the camera (board)"),
    "simulate": ("lrsensor.cli.simulate", "render a simulated scene: image, calibration and ground truth"),
    "range": ("lrsensor.cli.range", "range theory of the paper (eq. 33-34): table and Fig. 9/10 plot"),
    "map": ("mapping.cli", "export or view the base station's shared map"),
    "base": ("services.cli_base", "run the base station (Zenoh router, fleet subscriber, map)"),
    "map-worker": (
        "services.cli_map_worker",
        "run a plane worker: extract planes of the robots a base station assigns it",
    ),
    "rov": ("services.cli_rov", "run one ROV: camera + IMU -> pose-tagged point clouds over Zenoh"),
    "record": ("services.cli_record", "record a fleet's clouds, poses and map into an MCAP file (Foxglove)"),
    "replay": ("services.cli_replay", "publish an MCAP recording back into a fleet (a base rebuilds the map)"),
    "demo": ("services.cli_demo", "run an in-process demo fleet of simulated ROVs and a base station"),
    "certs": (
        "services.cli_certs",
        "generate the secure profile: CA, base-station and per-robot TLS certificates",
    ),
}


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every sub-command."""
    parser = argparse.ArgumentParser(
        prog="lrsensor",
        description="Line-laser range sensor for underwater robots, distributed over Zenoh.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        module = importlib.import_module(module_name)
        module.configure(p)
        p.set_defaults(_module=module_name)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``lrsensor`` program; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    module = importlib.import_module(args._module)
    try:
        code: int = module.run(args)
    except LrsensorError as err:
        print(f"lrsensor {args.command}: error: {err}", file=sys.stderr)
        return 2
    except ImportError as err:
        print(f"lrsensor {args.command}: error: {err}", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        return 130
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
