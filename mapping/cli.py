"""``lrsensor map``: export or view the base station's shared map from its state directory.

lrsensor map export --state DIR --out map.ply [--json map.json] [--png top.png]
lrsensor map view --state DIR --png top.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of ``lrsensor map``."""
    sub = parser.add_subparsers(dest="map_command", metavar="ACTION")
    sub.required = True
    exp = sub.add_parser("export", help="write the map as PLY (points + plane patches), JSON and/or PNG")
    exp.add_argument("--state", type=Path, required=True, help="the base station's --state directory")
    exp.add_argument("--out", type=Path, help="PLY file to write (NED metres)")
    exp.add_argument("--json", type=Path, help="JSON file to write (planes and tracks)")
    exp.add_argument("--png", type=Path, help="PNG top view to write")
    view = sub.add_parser("view", help="draw a PNG top view of the map (planes as segments, robot tracks)")
    view.add_argument("--state", type=Path, required=True, help="the base station's --state directory")
    view.add_argument("--png", "--out", dest="png", type=Path, required=True, help="PNG file to write")
    view.add_argument("--no-tracks", action="store_true", help="leave the robots' tracks out")


def run(args: argparse.Namespace) -> int:
    """Run ``lrsensor map export|view``; returns the exit code (1 when there is no map)."""
    from .builder import MapBuilder
    from .export import export_map
    from .store import STATE_FILE
    from .view import plot_top_view

    state: Path = args.state
    if not (state / STATE_FILE).exists():
        print(f"lrsensor map: no map in {state} (expected {state / STATE_FILE})", file=sys.stderr)
        return 1
    builder = MapBuilder(None, state)
    if args.map_command == "export":
        if args.out is None and args.json is None and args.png is None:
            print("lrsensor map export: give at least one of --out, --json, --png", file=sys.stderr)
            return 2
        doc = export_map(builder, args.out, args.json)
        if args.png is not None:
            plot_top_view(args.png, doc["planes"], doc.get("tracks"))
        written = [str(p) for p in (args.out, args.json, args.png) if p is not None]
        print(f"map: {len(doc['planes'])} planes, {len(doc.get('tracks', {}))} robots -> {', '.join(written)}")
        return 0
    doc = builder.map_json(include_tracks=not args.no_tracks)
    plot_top_view(args.png, doc["planes"], doc.get("tracks"))
    print(f"map: {len(doc['planes'])} planes -> {args.png}")
    return 0
