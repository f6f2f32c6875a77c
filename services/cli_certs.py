"""CLI wiring of `lrsensor certs`: not built yet."""

from __future__ import annotations

import argparse
import sys


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of this sub-command."""
    parser.add_argument("args", nargs="*")


def run(args: argparse.Namespace) -> int:
    """Run the sub-command."""
    print("lrsensor: this sub-command is not implemented yet", file=sys.stderr)
    return 4
