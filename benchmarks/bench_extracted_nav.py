"""Navigation and map settings judged on a dozen extracted dives, not three (issue 27).

    python benchmarks/bench_extracted_nav.py [--modes good,drift,depth-only] [--seeds 1,2,3,5] [--ways smoothed]
        [--variant NAME=KEY=VALUE[,KEY=VALUE...] ...] [--order-seeds 1,2] [--max-range-m 3] [--dives DIR]
        [--cache FILE] [--out benchmarks/results/extracted_nav.md]

The acceptance check replays clouds extracted from rendered 640x360 images, and a map made of them moves by
several faces with any small change (one draw per dive). So a setting is judged here on every mode x seed: each
dive rendered once (:func:`benchmarks.fleet_dives.write_fleet` caches it under ``DIR``), its clouds cut at
``--max-range-m`` and mapped as :mod:`benchmarks.diag_extracted_poses` maps them (``smoothed``: the base's
``--nav on``; ``true``: the true poses, no navigation), each robot's clouds with its calibration's range error.

``--variant NAME=KEY=VALUE,...``: a named setting, its keys those of ``diag_extracted_poses --set``
(``nav.`` / ``smoother.`` / ``graph.`` / ``map.``; ``order=SEED``: with each tick's robots shuffled by SEED).
``--order-seeds``: the default again with the robots' order within each tick (clouds of one capture time)
shuffled by that seed, which is what the map's result moves by from the order alone. Each (dive, way, variant)
is mapped once and kept in ``--cache`` (JSON lines), so a rerun
with another variant maps only that one (the key holds the settings, not the code: remove the file after a
change to the navigation or the map).

Per dive: faces within the bar (2 deg, 5 cm) / seen, duplicates, spurious planes. Per variant: the sums per mode
and overall, and its wins / losses against the default, dive by dive: more faces in the bar wins, equal faces
fewer duplicates plus spurious planes. Prints markdown, and writes it to ``--out``; progress on stderr.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: python benchmarks/bench_extracted_nav.py
    sys.path.insert(0, str(ROOT))

from mapping.synth import DiveFrame  # noqa: E402

DEFAULT = "default"
RESULTS = ROOT / "benchmarks" / "results" / "extracted_nav.md"


@dataclass(frozen=True)
class Variant:
    """A named setting: ``sets`` as ``diag_extracted_poses --set`` takes them; ``order_seed`` > 0 shuffles the
    robots' order within each tick by that seed."""

    name: str
    sets: tuple[str, ...] = ()
    order_seed: int = 0


@dataclass(frozen=True)
class Row:
    """One dive mapped one way with one variant: faces within the bar, faces seen, duplicate faces, spurious
    planes, the served poses' mean horizontal error at the end (m, over every robot's clouds; nan for ``true``)
    and the mapping's CPU time (s)."""

    mode: str
    seed: int
    way: str
    variant: str
    faces: int
    seen: int
    dup: int
    spurious: int
    end_error_m: float
    cpu_s: float


def parse_variant(text: str) -> Variant:
    """``NAME=KEY=VALUE[,KEY=VALUE...]`` as a :class:`Variant` (a bare ``NAME=`` is the default's settings;
    ``order=SEED`` among them shuffles each tick's robots by that seed)."""
    name, _, sets = text.partition("=")
    if not name or name == DEFAULT or "." in name:
        msg = f"a variant needs a name other than {DEFAULT!r} before '=': {text!r}"
        raise ValueError(msg)
    keys = tuple(s for s in sets.split(",") if s)
    order = [s for s in keys if s.startswith("order=")]
    keys = tuple(s for s in keys if s not in order)
    bad = [s for s in keys if "=" not in s or "." not in s.split("=", 1)[0]]
    if bad or len(order) > 1:
        msg = f"variant {name!r}: settings are PART.KEY=VALUE and at most one order=SEED, got {sets}"
        raise ValueError(msg)
    return Variant(name, keys, int(order[0].split("=", 1)[1]) if order else 0)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--modes", default="good,drift,depth-only")
    ap.add_argument("--seeds", default="1,2,3,5")
    ap.add_argument("--ways", default="smoothed", help="smoothed and/or true")
    ap.add_argument("--variant", action="append", default=[], type=parse_variant, metavar="NAME=KEY=VALUE,...")
    ap.add_argument("--order-seeds", default="", help="the default with each tick's robots shuffled by these seeds")
    ap.add_argument("--seconds", type=float, default=90.0)
    ap.add_argument("--max-range-m", type=float, default=3.0)
    ap.add_argument("--dives", type=Path, default=Path("/tmp/nav23/dives"))
    ap.add_argument("--cache", type=Path, default=Path("/tmp/nav23/extracted_nav.jsonl"))
    ap.add_argument("--out", type=Path, default=RESULTS)
    a = ap.parse_args(argv)
    a.modes = [m for m in a.modes.split(",") if m]
    a.seeds = [int(s) for s in a.seeds.split(",") if s]
    a.ways = [w for w in a.ways.split(",") if w]
    if set(a.ways) - {"smoothed", "true"}:
        ap.error(f"--ways takes smoothed and true, got {','.join(a.ways)}")
    a.variants = [Variant(DEFAULT), *a.variant]
    a.variants += [Variant(f"order {k}", order_seed=k) for k in (int(s) for s in a.order_seeds.split(",") if s)]
    return a


def shuffle_ticks(frames: list[DiveFrame], seed: int) -> list[DiveFrame]:
    """``frames`` (capture order) with the frames of each capture time in an order drawn by ``seed``."""
    rng = np.random.default_rng(seed)
    out: list[DiveFrame] = []
    i = 0
    while i < len(frames):
        j = i
        while j < len(frames) and frames[j].t_ns == frames[i].t_ns:
            j += 1
        out += [frames[i + k] for k in rng.permutation(j - i)]
        i = j
    return out


def map_dive(frames: list[DiveFrame], way: str, v: Variant, per_px: dict[str, float]) -> dict[str, float]:
    """``frames`` mapped ``way`` under ``v``: faces, seen, dup, spurious, end_error_m, cpu_s."""
    from benchmarks.diag_extracted_poses import _tuning, run_way
    from mapping.synth import hit_faces, score_map, tank

    kw = _tuning(list(v.sets))
    kw["range_error_per_px"] = per_px
    c0 = time.process_time()
    planes, run = run_way(way, shuffle_ticks(frames, v.order_seed) if v.order_seed else frames, kw)
    cpu = time.process_time() - c0
    scene = tank()
    score = score_map(planes, scene, hit_faces(scene, frames))
    seen = sum(f.hit for f in score.faces)
    ends = [e for errs in (run.final_error_m.values() if run is not None else ()) for e in errs]
    return {"faces": seen - len(score.missing()), "seen": seen, "dup": len(score.duplicates()),
            "spurious": len(score.spurious), "end_error_m": float(np.mean(ends)) if ends else float("nan"),
            "cpu_s": cpu}  # fmt: skip


def _cache_key(mode: str, seed: int, way: str, v: Variant, a: argparse.Namespace) -> str:
    return json.dumps([mode, seed, a.seconds, a.max_range_m, way, sorted(v.sets), v.order_seed])


def load_dive(a: argparse.Namespace, mode: str, seed: int) -> tuple[list[DiveFrame], dict[str, float]]:
    """``mode``/``seed``'s extracted frames cut at ``a.max_range_m`` (rendered into ``a.dives`` unless there), and
    robot -> its calibration's range error per pixel."""
    from benchmarks.fleet_dives import dive_frames, extracted_frames, write_fleet
    from lrsensor.calibration import Calibration
    from lrsensor.range_theory import range_error_per_px

    print(f"{mode} seed {seed}: the dive (rendered and extracted once, in {a.dives})", file=sys.stderr)
    folders = write_fleet(a.dives, mode, seed, a.seconds, "640x360")
    frames = extracted_frames(dive_frames(mode, seed, a.seconds), folders)
    frames = [replace(f, points_body=f.points_body[f.points_body[:, 0] <= a.max_range_m]) for f in frames]
    return frames, {r: range_error_per_px(Calibration.load(d / "calib.json")) for r, d in folders.items()}


def measure(a: argparse.Namespace) -> list[Row]:
    """Every mode x seed x way x variant of ``a``, from ``a.cache`` where mapped before."""
    cache: dict[str, dict[str, float]] = {}
    if a.cache.exists():
        for line in a.cache.read_text().splitlines():
            if line.strip():
                d = json.loads(line)
                cache[d["key"]] = d["row"]
    rows: list[Row] = []
    for mode in a.modes:
        for seed in a.seeds:
            dive: tuple[list[DiveFrame], dict[str, float]] | None = None
            for way in a.ways:
                for v in a.variants:
                    key = _cache_key(mode, seed, way, v, a)
                    if key not in cache:
                        dive = dive or load_dive(a, mode, seed)
                        c = cache[key] = map_dive(dive[0], way, v, dive[1])
                        a.cache.parent.mkdir(parents=True, exist_ok=True)
                        with a.cache.open("a") as fh:
                            fh.write(json.dumps({"key": key, "row": c}) + "\n")
                        print(f"{mode} seed {seed} {way} {v.name}: {c['faces']:.0f} / {c['seen']:.0f}, {c['dup']:.0f}, "
                              f"{c['spurious']:.0f} ({c['cpu_s']:.0f} s CPU)", file=sys.stderr)  # fmt: skip
                    c = cache[key]
                    rows.append(Row(mode, seed, way, v.name, int(c["faces"]), int(c["seen"]), int(c["dup"]),
                                    int(c["spurious"]), float(c["end_error_m"]), float(c["cpu_s"])))  # fmt: skip
    return rows


def _better(x: Row, y: Row) -> int:
    """+1 when ``x`` beats ``y`` (more faces in the bar; equal faces, fewer duplicates plus spurious), -1, 0."""
    kx, ky = (x.faces, -(x.dup + x.spurious)), (y.faces, -(y.dup + y.spurious))
    return (kx > ky) - (kx < ky)


def table(rows: Sequence[Row], variants: Sequence[Variant]) -> str:
    """Markdown: per way, the dives x variants (faces / seen, dup, spurious), the sums per mode and overall, and
    each variant's wins / ties / losses against the default (dive by dive)."""
    names = [v.name for v in variants]
    out: list[str] = []
    for way in dict.fromkeys(r.way for r in rows):
        mine = [r for r in rows if r.way == way]
        by = {(r.mode, r.seed, r.variant): r for r in mine}
        dives = list(dict.fromkeys((r.mode, r.seed) for r in mine))
        modes = list(dict.fromkeys(m for m, _ in dives))
        out += [f"`{way}`: faces in the bar / seen, duplicates, spurious planes (the poses' mean error at the end, "
                "cm)\n", "| dive | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]  # fmt: skip
        for m, s in dives:
            cells = []
            for n in names:
                r = by.get((m, s, n))
                err = f" ({100 * r.end_error_m:.0f})" if r is not None and np.isfinite(r.end_error_m) else ""
                cells.append(f"{r.faces} / {r.seen}, {r.dup}, {r.spurious}{err}" if r is not None else "")
            out.append(f"| {m} seed {s} | " + " | ".join(cells) + " |")
        for group in [*modes, "all"]:
            cells = []
            for n in names:
                rs = [r for r in mine if r.variant == n and group in ("all", r.mode)]
                cells.append(f"**{sum(r.faces for r in rs)} / {sum(r.seen for r in rs)}, {sum(r.dup for r in rs)}, "
                             f"{sum(r.spurious for r in rs)}**")  # fmt: skip
            out.append(f"| sum, {group} | " + " | ".join(cells) + " |")
        cells = []
        for n in names:
            pairs = [(by[(m, s, n)], by[(m, s, DEFAULT)]) for m, s in dives
                     if (m, s, n) in by and (m, s, DEFAULT) in by]  # fmt: skip
            wins = sum(_better(x, y) > 0 for x, y in pairs)
            losses = sum(_better(x, y) < 0 for x, y in pairs)
            cells.append("-" if n == DEFAULT else f"{wins} / {len(pairs) - wins - losses} / {losses}")
        out += ["| wins / ties / losses against the default | " + " | ".join(cells) + " |", ""]
    return "\n".join(out)


def main(argv: Sequence[str] | None = None) -> int:
    a = parse_args(argv)
    rows = measure(a)
    legend = "\n".join(f"- {v.name}: " + (", ".join(f"`{s}`" for s in v.sets) or "the base's `--nav on`")
                        + (f", each tick's robots shuffled by seed {v.order_seed}" if v.order_seed else "")
                        for v in a.variants)  # fmt: skip
    cmd = "python benchmarks/bench_extracted_nav.py " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )  # fmt: skip
    n = len(a.modes) * len(a.seeds)
    text = (f"# Settings on the extracted dives\n\n`{cmd}`\n\n{n} dives ({', '.join(a.modes)} "
            f"x seeds {', '.join(map(str, a.seeds))}; {a.seconds:g} s, 3 robots, clouds extracted from 640x360 "
            f"renders, cut at {a.max_range_m:g} m). Variants:\n\n{legend}\n\n{table(rows, a.variants)}")  # fmt: skip
    print(text)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
