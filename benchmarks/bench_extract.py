"""Benchmark of the stripe extractors on the simulator's named scenes: accuracy and speed.

    python benchmarks/bench_extract.py [--seeds 1] [--repeats 15] [--out benchmarks/results/extract.md]
    python benchmarks/bench_extract.py --cold-after FRAME [--repeats 15]
    python benchmarks/bench_extract.py --copies [--repeats 15]
    python benchmarks/bench_extract.py --stages FRAME [--seeds 1] [--repeats 15]
    python benchmarks/bench_extract.py --flank-gate [--seeds 1]
    python benchmarks/bench_extract.py --against WORKTREE [WORKTREE ...] [--rounds 3] [--seeds 4]

Accuracy (both methods, every named body-frame scene, 1920x1080, f = 554 px, b = 0.1 m):
- relative range error per point ``|r_est - r_true| / r_true`` with ``r`` the distance from the camera centre and
  ``r_true`` the simulator's true hit point of the same laser at the same image column;
- median and 95th percentile (%), outliers (% of points more than 5 % off);
- coverage: share of the *visible* stripe columns that got a point (visible: the true stripe peak is at least
  three times the image noise, measured on the frame; the paper's method gives one point per ROI by design);
- points per frame.

Speed (ms per 1920x1080 frame, one thread: ``cv2.setNumThreads(1)``, per-thread CPU time, medians, in three
cache states: everything cold, a stream of new frames, and the same frame back to back; on 14 renders of each
frame that differ in their noise, as a camera's frames do): ``Sensor.process``
with each method (extraction and triangulation) and, measured in the same run, a plain per-column arg-max of
the green channel with a parabolic fit over the full frame (numpy on uint8 and on float32, and compiled loops).

``--copies``: only the speed table, timed on copies of one render of each frame instead of renders that differ
(what replaying the same frame gives the branch predictors).

``--stages FRAME``: only the time of each compiled stage on one speed frame, a column per render (``--seeds``).

``--flank-gate``: only the effect of the neighbour refits' flank threshold (a neighbour's tail in a point's
background flanks triggers a refit from ``NEIGHBOUR_FLANK_TAIL`` of its amplitude, against 1 % as in the rows its
centroid reads) on walls at 3.5-6 m and the tank: refitted columns, accuracy, and how far the centres move. The
thresholds are compiled into the kernels, so both are run in the numpy reference, which reads them at each call.

``--against WORKTREE [WORKTREE ...]``: ``Sensor.process`` on wall_5.0 (the ``--stages`` figure, ``--seeds`` renders)
and every speed frame's warm ``subpixel`` column of ``--copies``, of this tree and of other worktrees of the
repository (earlier commits, each with its kernels compiled into its own ``.numba-cache``; its ``bench_extract.py``
run with the same options), all alternately ``--rounds`` times on the same machine: the medians per frame and their
ratios to the first worktree.

``--cold-after FRAME``: only cold calls of ``Sensor.process`` and the uint8 reference on one speed frame, by the
function called just before the cache flush (the flush leaves the branch predictors as that function left them).
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from lrsensor import Sensor
from lrsensor.atomic import atomic_write
from lrsensor.extract import frame as frame_module
from lrsensor.extract import frame_locate, reference_finish, refit, subpixel
from lrsensor.extract.compile import HAVE_NUMBA, warm_up
from lrsensor.extract.refit import NEIGHBOUR_FLANK_TAIL, NEIGHBOUR_TAIL
from lrsensor.extract.settings import frame_settings
from lrsensor.scan import Scan
from lrsensor.sim import named_scene
from lrsensor.sim import scenes as sim_scenes
from lrsensor.sim.render import Render
from lrsensor.sim.score import score_scan

SCENES = (
    "paper_box",
    "wall_0.3",
    "wall_0.5",
    "wall_0.8",
    "wall_1.0",
    "wall_1.5",
    "wall_2.0",
    "wall_2.5",
    "wall_3.0",
    "tilted_wall",
    "corner",
    "pipe",
    "occluder",
    "tilted_lasers",
    "distorted",
    "turbid",
    "cluttered",
)
#: The speed frames: named scenes, and a wall at 5 m (``wall_5.0``, the deepest row of the default range limits,
#: where the two lasers' stripes lie 11 rows apart and the columns the neighbour reaches are refitted with it
#: subtracted).
SPEED_SCENES = ("paper_box", "wall_0.3", "wall_0.5", "wall_1.0", "turbid", "cluttered", "tank", "wall_5.0")
METHODS = ("subpixel", "paper")


def argmax_parabola(image: np.ndarray) -> np.ndarray:
    """The reference: per column the brightest green pixel of the full frame, refined by a parabola; (W,)."""
    g = image[:, :, 1]
    h, w = g.shape
    r = np.clip(np.argmax(g, axis=0), 1, h - 2)
    cols = np.arange(w)
    a = g[r - 1, cols].astype(np.float64)
    b = g[r, cols].astype(np.float64)
    c = g[r + 1, cols].astype(np.float64)
    den = a - 2.0 * b + c
    off = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    return r + off


def argmax_parabola_float(image: np.ndarray) -> np.ndarray:
    """The same reference on a float32 copy of the green channel (how it is often written); (W,)."""
    g = image[:, :, 1].astype(np.float32)
    h, w = g.shape
    r = np.clip(np.argmax(g, axis=0), 1, h - 2)
    cols = np.arange(w)
    a, b, c = g[r - 1, cols], g[r, cols], g[r + 1, cols]
    den = a - 2.0 * b + c
    off = np.where(den < 0, 0.5 * (a - c) / np.where(den < 0, den, -1.0), 0.0)
    return r + off


def _argmax_parabola_loops(image: np.ndarray) -> np.ndarray:
    """The same reference as plain loops (compiled with numba below): one pass over the rows keeping each column's
    brightest green pixel (the first of equal ones, as ``np.argmax``), then the parabola; (W,)."""
    h, w = image.shape[0], image.shape[1]
    best = np.zeros(w, np.uint8)
    arg = np.zeros(w, np.int64)
    for y in range(h):
        row = image[y]
        for x in range(w):
            g = row[x, 1]
            if g > best[x]:
                best[x] = g
                arg[x] = y
    out = np.empty(w)
    for x in range(w):
        r = min(max(arg[x], 1), h - 2)
        a = float(image[r - 1, x, 1])
        b = float(image[r, x, 1])
        c = float(image[r + 1, x, 1])
        den = a - 2.0 * b + c
        out[x] = r + (0.5 * (a - c) / den if den < 0 else 0.0)
    return out


if HAVE_NUMBA:
    import numba

    #: The reference compiled (numba): what a per-column arg-max costs when written as tight loops.
    argmax_parabola_compiled: Callable[[np.ndarray], np.ndarray] | None = numba.njit(cache=True)(_argmax_parabola_loops)
else:  # pragma: no cover - depends on the platform
    argmax_parabola_compiled = None


def accuracy(name: str, seed: int) -> list[dict[str, float | str]]:
    """Accuracy rows (one per method) of one render of scene ``name``."""
    r = named_scene(name).render(seed=seed)
    sensor = Sensor(r.calibration)
    rows: list[dict[str, float | str]] = []
    for method in METHODS:
        scan = sensor.process(r.image, method=method)
        rows.append({"scene": name, "method": method, **score_scan(r, scan)})
    return rows


def speed_frame(name: str, seed: int = 0) -> Render:
    """The render (noise ``seed``) of speed frame ``name``: a named scene, or ``wall_<metres>`` at any distance."""
    if name in sim_scenes.SCENES:
        return named_scene(name).render(seed=seed)
    return sim_scenes.wall_scene(float(name.removeprefix("wall_")), width=1920, height=1080).render(seed=seed)


def speed_frames(name: str, n: int) -> list[Render]:
    """Renders of speed frame ``name`` with noise seeds ``0 ... n - 1``: the same scene and calibration, frames that
    differ as a camera's successive frames do (in their noise, so in the candidates, chains and refits)."""
    return [speed_frame(name, seed) for seed in range(n)]


#: Where the tables are written.
RESULTS = Path(__file__).parent / "results"
#: Bytes written before each cold call: twice the last-level cache of common CPUs, so that the frame, the
#: kernels' code and their work arrays all come from memory, as for a new camera frame.
FLUSH_BYTES = 64 << 20
_flush_buf: np.ndarray | None = None


def flush_caches() -> None:
    """Write one byte of every cache line of a :data:`FLUSH_BYTES` buffer (evicts whatever the caches held)."""
    global _flush_buf
    if _flush_buf is None:
        _flush_buf = np.zeros(FLUSH_BYTES, np.uint8)
    _flush_buf[::64] += 1


#: Frames a stream of new frames cycles through: 14 renders of a scene (noise seeds 0-13; 87 MB at 1920x1080)
#: exceed the last-level cache, so each call reads a frame that is not cached, while the code and the work arrays
#: stay warm; and each frame differs from the one before, as a camera's do, so the branch predictors cannot replay
#: the last call (on copies of one frame the extractor ran up to 13 % faster than on such a stream: `--copies`).
STREAM_FRAMES = 14
#: Rounds of the stream and warm timings: each round calls every function back to back, in turn.
ROUNDS = 5
#: Untimed calls that start each function's calls in a round of the stream and warm timings: after another
#: function ran, the first few calls still refill the caches and the branch history (the compiled extractor's
#: call settles within about five).
SETTLE_CALLS = 5
CACHE_STATES = ("cold", "stream", "warm")


def timed(
    fns: dict[str, Callable[[np.ndarray], object]], frames: Sequence[np.ndarray], repeats: int, state: str
) -> dict[str, tuple[float, float]]:
    """Median per-thread CPU time and median wall time (ms) of each function called on ``frames``, renders of one
    scene that differ in their noise (:func:`speed_frames`; one frame is taken as it is).

    ``state`` (:data:`CACHE_STATES`): ``cold``, repetitions interleaved, each call right after
    :func:`flush_caches` (nothing of the frame, the code or the work arrays cached; the flush does not reset the
    branch predictors, which hold what the function before it in the interleave taught them: see
    :func:`cold_after`), repetition ``i`` on frame ``i mod n``; ``stream``, each function's calls back to back on
    the frames in turn, at least :data:`STREAM_FRAMES` of them (fewer are repeated as copies), a new frame from
    memory each call, as from a camera, code warm; ``warm``, each function's calls back to back on the same frame,
    frame ``r mod n`` in round ``r``. Stream and warm take the functions in turn in :data:`ROUNDS` rounds of
    back-to-back calls, each after :data:`SETTLE_CALLS` untimed ones, so that a slow spell of the machine (another
    tenant on the shared cache, say) lands on a few calls of every function rather than on all the calls of one.
    """
    if state not in CACHE_STATES:
        msg = f"unknown cache state {state!r}; expected one of {CACHE_STATES}"
        raise ValueError(msg)
    if len(frames) == 0:
        msg = "timed: no frames to time on"
        raise ValueError(msg)
    frame = frames[0]
    cpu: dict[str, list[float]] = {k: [] for k in fns}
    wall: dict[str, list[float]] = {k: [] for k in fns}

    def one(k: str, f: Callable[[np.ndarray], object], img: np.ndarray) -> None:
        t0, w0 = time.thread_time(), time.perf_counter()
        f(img)
        cpu[k].append(time.thread_time() - t0)
        wall[k].append(time.perf_counter() - w0)

    for f in fns.values():
        f(frame)
    n = len(frames)
    if state == "cold":
        for i in range(repeats):
            for k, f in fns.items():
                flush_caches()
                one(k, f, frames[i % n])
    elif state == "stream":
        ring = list(frames) if n >= STREAM_FRAMES else [frames[i % n].copy() for i in range(STREAM_FRAMES)]
        per_round = max(repeats, len(ring) * ROUNDS) // ROUNDS
        i = 0
        for _ in range(ROUNDS):
            for k, f in fns.items():
                for j in range(SETTLE_CALLS + per_round):
                    if j < SETTLE_CALLS:
                        f(ring[i % len(ring)])
                    else:
                        one(k, f, ring[i % len(ring)])
                    i += 1
    else:
        per_round = max(1, -(-repeats // ROUNDS))
        for r in range(ROUNDS):
            for k, f in fns.items():
                for _ in range(SETTLE_CALLS):
                    f(frames[r % n])
                for _ in range(per_round):
                    one(k, f, frames[r % n])
    return {k: (1e3 * float(np.median(cpu[k])), 1e3 * float(np.median(wall[k]))) for k in fns}


def cold_after(
    before: dict[str, Callable[[np.ndarray], object]],
    targets: dict[str, Callable[[np.ndarray], object]],
    frame: np.ndarray,
    repeats: int,
) -> dict[tuple[str, str], float]:
    """Median per-thread CPU time (ms) of each target called cold (right after :func:`flush_caches`) when the
    function called just before the flush was ``before[b]``: ``{(b, target): ms}``.

    The flush evicts the caches but not the branch predictors, so a cold call still runs with the branch history
    its predecessor left; this measures how much that predecessor moves the cold time. Pairs are interleaved.
    """
    times: dict[tuple[str, str], list[float]] = {(b, k): [] for b in before for k in targets}
    for f in (*before.values(), *targets.values()):
        f(frame)
    for _ in range(repeats):
        for b, fb in before.items():
            for k, f in targets.items():
                fb(frame)
                flush_caches()
                t0 = time.thread_time()
                f(frame)
                times[(b, k)].append(time.thread_time() - t0)
    return {key: 1e3 * float(np.median(v)) for key, v in times.items()}


#: The functions of the speed table, by key.
SPEED_LABELS = {
    "ref": "reference (uint8)",
    "ref32": "reference (float32)",
    "subpixel": "subpixel",
    "paper": "paper",
    "refc": "reference (compiled)",
}


def speed_functions(sensor: Sensor) -> dict[str, Callable[[np.ndarray], object]]:
    """The functions the speed table times, keyed as :data:`SPEED_LABELS`, in the order the cold calls interleave
    them: the references (uint8, float32), ``sensor.process`` with each method, and the compiled reference where
    numba is installed."""
    fns: dict[str, Callable[[np.ndarray], object]] = {
        "ref": argmax_parabola,
        "ref32": argmax_parabola_float,
        "subpixel": sensor.process,
        "paper": functools.partial(sensor.process, method="paper"),
    }
    if argmax_parabola_compiled is not None:
        fns["refc"] = argmax_parabola_compiled
    return fns


def cold_after_table(name: str, repeats: int) -> list[str]:
    """Markdown table of :func:`cold_after` on speed frame ``name``: ``Sensor.process`` and the uint8 reference,
    cold, after each function of the speed table (and after themselves), and their ratio per predecessor."""
    r = speed_frame(name)
    fns = speed_functions(Sensor(r.calibration))
    t = cold_after(fns, {"subpixel": fns["subpixel"], "ref": fns["ref"]}, r.image, repeats)
    lines = [
        f"### Cold calls by predecessor ({name}, ms, one thread)",
        "",
        f"Each call right after {FLUSH_BYTES >> 20} MB were written, the flush itself right after one call of the "
        "function in the first column (whose branch history the flush leaves in place). Medians of "
        f"{repeats} interleaved repetitions.",
        "",
        "| function called before the flush | subpixel | reference (uint8) | subpixel / reference (uint8) |",
        "|---|---:|---:|---:|",
    ]
    for b in fns:
        sub, ref = t[(b, "subpixel")], t[(b, "ref")]
        lines.append(f"| {SPEED_LABELS[b]} | {sub:.3f} | {ref:.3f} | {sub / ref:.3f} |")
    return lines


#: The stages of ``Sensor.process`` (default method): the compiled kernels that ``extract_frame`` and its
#: calls call.
STAGES = {
    "detection (noise, 2x2 average, response, local maxima)": ("detect_band",),
    "candidate chains": ("select_candidates", "expand_half"),
    "sub-pixel fits (frame statistics, width limits, the fit of every point)": (
        "max_fwhm_at",
        "frame_profile_stats",
        "fit_columns",
    ),
    "neighbour refits (stripes of two lasers close together: targets and fits)": ("refit_neighbours",),
    "turbid water (glow test, joint stripe-and-glow fits)": ("glow_refit",),
    "pooled gates, smoothing, quality": ("finish_points",),
    "triangulation": ("triangulate_geo",),
}


@contextmanager
def _stage_clock(totals: dict[str, float]) -> Iterator[Callable[..., object]]:
    """A Python twin of ``extract_frame`` that calls the same compiled stage kernels, each wrapped in a
    clock: the per-thread CPU time spent in each of :data:`STAGES` adds up in ``totals`` (s)."""
    # (the stages are called from the kernels of two modules, frame and frame_locate: each looks them up in its own
    # globals)
    spaces = (vars(frame_module), vars(frame_locate))
    saved = [{name: names[name] for stage in STAGES.values() for name in stage if name in names} for names in spaces]
    missing = {name for stage in STAGES.values() for name in stage} - {name for own in saved for name in own}
    if missing:
        msg = f"stages not called from the frame's modules: {sorted(missing)}"
        raise KeyError(msg)
    names = spaces[0]
    halves = {name: names[name] for name in ("locate_candidates", "fit_points", "finish_located", "place_points")}
    for space, own in zip(spaces, saved, strict=True):
        for stage, stage_names in STAGES.items():
            for name in stage_names:
                if name not in own:
                    continue
                f = own[name]

                def clocked(*a: object, _f: Callable[..., object] = f, _s: str = stage) -> object:
                    t0 = time.thread_time()
                    try:
                        return _f(*a)
                    finally:
                        totals[_s] = totals.get(_s, 0.0) + time.thread_time() - t0

                space[name] = functools.wraps(f)(clocked)
    for name, half in halves.items():
        names[name] = half.py_func  # their stage calls go through the clocks (their modules' globals)
    try:
        yield frame_module.extract_frame
    finally:
        for space, own in zip(spaces, saved, strict=True):
            space.update(own)
        names.update(halves)


def stage_times(image: np.ndarray, sensor: Sensor, repeats: int) -> list[tuple[str, float]]:
    """Mean per-thread CPU ms per frame of each compiled stage of ``sensor.process(image)`` and of the whole
    call (the stages timed one by one through a Python twin of the two-call frame, on the same frame)."""
    totals: dict[str, float] = {}
    args = (*frame_settings(sensor.calibration, subpixel.SubpixelConfig()), True)
    with _stage_clock(totals) as frame:
        frame(image, *args)
        totals.clear()
        for _ in range(repeats):
            frame(image, *args)
    sensor.process(image)
    whole = 0.0
    for _ in range(repeats):
        t0 = time.thread_time()
        sensor.process(image)
        whole += time.thread_time() - t0
    rows = [(stage, 1e3 * totals.get(stage, 0.0) / repeats) for stage in STAGES]
    rows.append(("sum of the stages, each timed as a separate call", sum(t for _, t in rows)))
    rows.append(("Sensor.process (six compiled calls for all of them)", 1e3 * whole / repeats))
    return rows


def _tree_run(tree: Path, cache: str, args: list[str]) -> str:
    """The markdown that ``tree``'s bench_extract.py writes with ``args`` (its own code and numba cache)."""
    env = dict(os.environ, PYTHONPATH=str(tree), NUMBA_CACHE_DIR=cache)
    with tempfile.TemporaryDirectory(prefix="bench-against-") as tmp:
        out = Path(tmp) / "out.md"
        cmd = [sys.executable, str(tree / "benchmarks" / "bench_extract.py"), *args, "--out", str(out)]
        subprocess.run(cmd, cwd=tree, env=env, check=True, capture_output=True)
        return out.read_text()


def _process_ms(stages_md: str) -> list[float]:
    """The ``Sensor.process`` row of a ``--stages`` table, ms per render."""
    row = next(line for line in stages_md.splitlines() if line.startswith("| Sensor.process"))
    return [float(x) for x in row.strip(" |").split("|")[1:]]


def _warm_ms(copies_md: str) -> dict[str, float]:
    """The warm ``subpixel`` column of a ``--copies`` table, ms per frame."""
    lines = copies_md.splitlines()
    head = next(line for line in lines if line.startswith("| frame |"))
    col = [c.strip() for c in head.strip(" |").split("|")].index("subpixel")
    out: dict[str, float] = {}
    for line in lines:
        cells = [c.strip() for c in line.strip(" |").split("|")]
        if len(cells) > col and cells[1:2] == ["warm"]:
            out[cells[0]] = float(cells[col])
    return out


def against_table(others: list[Path], rounds: int, seeds: int) -> list[str]:
    """``--against``: this tree and ``others`` alternately, ``rounds`` times; ratios to the first of ``others``
    (see the module documentation)."""
    here = Path(__file__).resolve().parent.parent
    trees = {"this": (here, os.environ.get("NUMBA_CACHE_DIR", str(here / ".numba-cache")))}
    for other in others:
        log = subprocess.run(["git", "-C", str(other), "log", "-1", "--format=%h"], capture_output=True, text=True)
        trees[log.stdout.strip() or other.name] = (other, str(other / ".numba-cache"))
    names = list(trees)
    ref = names[1]
    process: dict[str, list[list[float]]] = {k: [] for k in trees}
    warm: dict[str, list[dict[str, float]]] = {k: [] for k in trees}
    loads = []
    for _ in range(rounds):
        for key, (tree, cache) in trees.items():
            process[key].append(_process_ms(_tree_run(tree, cache, ["--stages", "wall_5.0", "--seeds", str(seeds)])))
            warm[key].append(_warm_ms(_tree_run(tree, cache, ["--copies"])))
            loads.append(os.getloadavg()[0])
    shown = [k for k in names if k != ref]
    lines = [
        f"### Against the code of {', '.join(names[1:])} (ms per frame, one thread)",
        "",
        f"`python benchmarks/bench_extract.py --against {' '.join(['WORKTREE'] * len(others))} --rounds {rounds} "
        f"--seeds {seeds}`: per-thread CPU ms of `Sensor.process`, this tree and the other trees' code (each its own "
        f"benchmark, its kernels from its own cache) alternately {rounds} times on the same machine (1-minute load "
        f"average {min(loads):.1f}-{max(loads):.1f}), medians of the rounds: wall_5.0 as `--stages` times it (a "
        f"column per render), and the warm `subpixel` column of `--copies` for every speed frame all trees time; "
        f"ratios to {ref}.",
        "",
        "| frame | " + " | ".join(f"{k} ms" for k in names) + " | " + " | ".join(f"{k} / {ref}" for k in shown) + " |",
        "|---|" + "---:|" * (len(names) + len(shown)),
    ]

    def row(label: str, ms: dict[str, float], digits: int) -> str:
        cells = [f"{ms[k]:.{digits}f}" for k in names] + [f"{ms[k] / ms[ref]:.2f}" for k in shown]
        return f"| {label} | " + " | ".join(cells) + " |"

    for i in range(seeds):
        lines.append(
            row(f"wall_5.0 seed {i} (stages)", {k: statistics.median(r[i] for r in process[k]) for k in names}, 3)
        )
    for scene in SPEED_SCENES:
        if all(scene in r for k in names for r in warm[k]):
            lines.append(
                row(f"{scene} (copies, warm)", {k: statistics.median(r[scene] for r in warm[k]) for k in names}, 2)
            )
    return lines


def main() -> int:
    """Run the benchmark, print the markdown tables and write them to ``--out``."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=1, help="renders per scene (seeds 0..n-1)")
    ap.add_argument("--repeats", type=int, default=15, help="timing repetitions per frame")
    ap.add_argument(
        "--out",
        help="markdown file written (default benchmarks/results/extract.md; extract_cold_after_FRAME.md, "
        "extract_stages_FRAME.md, extract_copies.md or extract_flank_gate.md with those options)",
    )
    ap.add_argument(
        "--cold-after",
        metavar="FRAME",
        help="only the cold calls of one speed frame (e.g. tank) by the function called before the flush",
    )
    ap.add_argument(
        "--copies",
        action="store_true",
        help="only the speed table, every frame timed on copies of one render (seed 0): how much replaying the "
        "same frame flatters the extractor against renders that differ (default out: extract_copies.md)",
    )
    ap.add_argument(
        "--stages",
        metavar="FRAME",
        help="only the time of each stage on one speed frame (e.g. wall_5.0), a column per render of --seeds "
        "(default out: extract_stages_FRAME.md)",
    )
    ap.add_argument(
        "--flank-gate",
        action="store_true",
        help="only the neighbour refits' flank threshold against 1 %% on walls at 3.5-6 m and the tank, --seeds "
        "renders each, in the numpy reference (default out: extract_flank_gate.md)",
    )
    ap.add_argument(
        "--against",
        metavar="WORKTREE",
        type=Path,
        nargs="+",
        help="only Sensor.process of this tree and of other worktrees, alternately, with ratios to the first "
        "(default out: extract_against.md; each tree's kernels compiled into WORKTREE/.numba-cache)",
    )
    ap.add_argument("--rounds", type=int, default=3, help="alternations of --against (default 3)")
    args = ap.parse_args()
    if args.against:
        _publish(
            against_table([p.resolve() for p in args.against], args.rounds, args.seeds), args.out, "extract_against.md"
        )
        return 0
    for flag, frame in (("--cold-after", args.cold_after), ("--stages", args.stages)):
        if frame and frame not in SPEED_SCENES:
            ap.error(f"{flag}: unknown speed frame {frame!r}; expected one of {SPEED_SCENES}")
    cv2.setNumThreads(1)
    warm_up()  # compile the kernels now, not during the first timed frames
    if args.cold_after:
        _publish(cold_after_table(args.cold_after, args.repeats), args.out, f"extract_cold_after_{args.cold_after}.md")
        return 0
    if args.stages:
        _publish(stages_table(args.stages, args.seeds, 10 * args.repeats), args.out, f"extract_stages_{args.stages}.md")
        return 0
    if args.flank_gate:
        _publish(flank_gate_table(args.seeds), args.out, "extract_flank_gate.md")
        return 0
    if args.copies:
        _publish([*speed_header(copies=True), *speed_rows(1, args.repeats)], args.out, "extract_copies.md")
        return 0

    rows: list[dict[str, float | str]] = []
    for name in SCENES:
        for seed in range(args.seeds):
            rows.extend(accuracy(name, seed))
    lines = [
        "### Accuracy on the simulator's named scenes (1920x1080, f = 554 px, b = 0.1 m)",
        "",
        "Relative range error |r_est - r_true| / r_true per point against the simulator's truth at the same column "
        f"and laser; outliers: > 5 % off; coverage: visible stripe columns (true peak >= 3x noise) with a point. "
        f"Seeds per scene: {args.seeds}.",
        "",
        "| scene | method | median % | p95 % | outliers % | coverage % | points/frame |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    agg: dict[tuple[str, str], list[dict[str, float | str]]] = {}
    for row in rows:
        agg.setdefault((str(row["scene"]), str(row["method"])), []).append(row)
    for (scene, method), rs in agg.items():
        m = {k: float(np.mean([float(r[k]) for r in rs])) for k in ("median", "p95", "outliers", "coverage", "points")}
        lines.append(
            f"| {scene} | {method} | {m['median']:.3f} | {m['p95']:.3f} | {m['outliers']:.2f} | {m['coverage']:.1f} "
            f"| {m['points']:.0f} |"
        )

    speed_lines = ["", *speed_header(copies=False)]
    speed_lines += speed_rows(STREAM_FRAMES, args.repeats)
    stage_lines = ["", *stages_table("wall_1.0", 1, 10 * args.repeats)]
    _publish(lines + speed_lines + stage_lines, args.out, "extract.md")
    return 0


def stages_table(name: str, seeds: int, repeats: int) -> list[str]:
    """Markdown table of :func:`stage_times` on speed frame ``name``: a column per render (noise seeds
    ``0 ... seeds - 1``), each the mean of ``repeats`` back-to-back repetitions (warm)."""
    frames = speed_frames(name, seeds)
    sensor = Sensor(frames[0].calibration)
    cols = [stage_times(r.image, sensor, repeats) for r in frames]
    which = "" if seeds == 1 else f", seeds 0-{seeds - 1}"
    lines = [
        f"### Where the time goes ({name}{which}, ms per frame, one thread)",
        "",
        "Per-thread CPU time of each compiled stage of `Sensor.process` (default method), mean over back-to-back "
        "repetitions on the same render (warm). The stages are timed one call at a time from Python (each call's "
        "argument passing included), so they add up to more than the six compiled calls that `Sensor.process` "
        "makes.",
        "",
        "| stage | " + " | ".join("ms" if seeds == 1 else f"seed {k}" for k in range(seeds)) + " |",
        "|---|" + "---:|" * seeds,
    ]
    for i, (stage, _) in enumerate(cols[0]):
        lines.append(f"| {stage} | " + " | ".join(f"{c[i][1]:.3f}" for c in cols) + " |")
    return lines


#: The frames of ``--flank-gate``: walls where the two lasers' stripes come close (beyond about 4 m) and the tank.
FLANK_GATE_FRAMES = ("wall_3.5", "wall_4.0", "wall_4.5", "wall_5.0", "wall_5.5", "wall_6.0", "tank")


@contextmanager
def _numpy_path(log_flank_tail: float) -> Iterator[list[int]]:
    """Run the sub-pixel extractor's reference with the flank threshold ``log(NEIGHBOUR_TAIL / flank)``; yields a
    list to which every refit round appends the number of points it finds a neighbour to subtract for."""
    neighbours = reference_finish.neighbours
    saved = (subpixel.USE_REFERENCE, refit.LOG_FLANK_TAIL)
    rounds: list[int] = []

    def counted(*a: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        out = neighbours(*a)
        rounds.append(int(np.isfinite(out[0]).sum()))
        return out

    subpixel.USE_REFERENCE, refit.LOG_FLANK_TAIL = True, log_flank_tail
    reference_finish.neighbours = counted  # type: ignore[assignment]
    try:
        yield rounds
    finally:
        subpixel.USE_REFERENCE, refit.LOG_FLANK_TAIL = saved
        reference_finish.neighbours = neighbours


def _row_moves(a: Scan, b: Scan) -> np.ndarray:
    """|row change| (px) of the points of two scans of one frame at the same laser and column."""

    def rows(s: Scan) -> dict[tuple[int, int], float]:
        return {(int(l), round(float(u))): float(v) for l, (u, v) in zip(s.laser, s.uv, strict=True)}

    rows_a, rows_b = rows(a), rows(b)
    return np.array([abs(rows_a[k] - rows_b[k]) for k in rows_a.keys() & rows_b.keys()])


def flank_gate_table(seeds: int) -> list[str]:
    """Markdown table: per frame of :data:`FLANK_GATE_FRAMES` (``seeds`` renders each), the neighbour refits with
    the flank threshold at 1 % (as the centroid's rows) and at ``NEIGHBOUR_FLANK_TAIL``: columns refitted in the
    first round, median and p95 range error, outliers, points; and how far the centres move between the two."""
    flank = NEIGHBOUR_FLANK_TAIL
    variants = {"1 %": 0.0, f"{100 * flank:g} %": refit.LOG_FLANK_TAIL}
    lines = [
        f"### Neighbour refits: a tail in the background flanks from 1 % against {100 * flank:g} % (numpy reference)",
        "",
        "A point is refitted with the other laser's stripe subtracted where that stripe's Gaussian reaches "
        f"{100 * NEIGHBOUR_TAIL:g} % of the point's amplitude in the rows its centroid reads, or the "
        "flank threshold in its background flanks. Columns: points refitted in the first round, then range error "
        "(%, median and p95), outliers (> 5 % off, %) and points per frame with the flanks at 1 % -> at "
        f"{100 * flank:g} %, means over seeds 0-{seeds - 1}; and the row change of the points both keep (px: mean "
        "over the points that move, 95th percentile and largest).",
        "",
        "| frame | refitted | median % | p95 % | outliers % | points | moved | mean px | p95 px | max px |",
        "|---|---|---|---|---|---|---:|---:|---:|---:|",
    ]
    for name in FLANK_GATE_FRAMES:
        per: dict[str, list[dict[str, float]]] = {k: [] for k in variants}
        refits: dict[str, list[int]] = {k: [] for k in variants}
        moves = []
        for seed in range(seeds):
            r = speed_frame(name, seed)
            sensor = Sensor(r.calibration)
            scans = {}
            for key, log_tail in variants.items():
                with _numpy_path(log_tail) as rounds:
                    scans[key] = sensor.process(r.image)
                refits[key].append(rounds[0] if rounds else 0)
                per[key].append(score_scan(r, scans[key]))
            moves.append(_row_moves(*scans.values()))
        d = np.concatenate(moves)
        moved = d[d > 1e-9]

        def pair(k: str, fmt: str, per: dict[str, list[dict[str, float]]] = per) -> str:
            a, b = (float(np.mean([m[k] for m in per[v]])) for v in variants)
            return f"{a:{fmt}} -> {b:{fmt}}"

        a, b = (float(np.mean(refits[v])) for v in variants)
        stats = (
            f"{moved.mean():.4f} | {np.percentile(moved, 95):.4f} | {moved.max():.3f}" if moved.size else "0 | 0 | 0"
        )
        lines.append(
            f"| {name} | {a:.0f} -> {b:.0f} | {pair('median', '.3f')} | {pair('p95', '.2f')} "
            f"| {pair('outliers', '.2f')} | {pair('points', '.0f')} | {moved.size} of {d.size} | {stats} |"
        )
    return lines


def speed_header(copies: bool) -> list[str]:
    """The title, the method and the column heads of the speed table: on renders that differ in their noise, or
    (``copies``) on copies of one render."""
    frames = (
        f"on {STREAM_FRAMES} copies of one render of each frame (seed 0; the stream cycles through the copies, and "
        "every call of a function sees the same frame: its branch predictors can replay the previous call), "
        if copies
        else f"on {STREAM_FRAMES} renders of each frame that differ in their noise (seeds 0-{STREAM_FRAMES - 1}, as "
        "a camera's successive frames differ), "
    )
    each = "" if copies else ", repetition i on render i"
    warm = "the frame" if copies else "one render, another in each round"
    return [
        "### Speed (ms per 1920x1080 frame, one thread)" + (": copies of one render" if copies else ""),
        "",
        f"Per-thread CPU time (ms), medians of repetitions in one run, {frames}in three cache states: **cold**, "
        f"every call right after {FLUSH_BYTES >> 20} MB were written (frame, code and work arrays all start from "
        "memory; calls interleaved, so each starts with the branch history of the function before it: "
        f"`--cold-after FRAME` measures that){each}; **stream**, each function's calls back to back on the frames "
        "in turn (a new frame from memory each call, with the code warm); and **warm**, each function's calls back "
        f"to back on {warm}. Stream and warm take the functions in turn in {ROUNDS} rounds of back-to-back calls, "
        f"each after {SETTLE_CALLS} untimed calls (a slow spell of the machine then lands on every function "
        "alike). `Sensor.process` = extraction + triangulation; reference = plain per-column arg-max + parabola "
        "over the full frame's green channel: numpy on the uint8 channel as stored and on a float32 copy, and the "
        "same written as loops and compiled (numba), which is what the arg-max itself costs. "
        f"Compiled kernels: {'numba' if HAVE_NUMBA else 'no (numpy fallback)'}.",
        "",
        "| frame | caches | reference (uint8) | reference (float32) | reference (compiled) | subpixel | paper "
        "| subpixel / reference (uint8) | subpixel / reference (float32) | subpixel / reference (compiled) "
        "| subpixel wall |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]


def speed_rows(renders: int, repeats: int) -> list[str]:
    """The rows of the speed table: every speed frame in every cache state, timed on ``renders`` renders of it
    (noise seeds ``0 ... renders - 1``; one render: the stream cycles through copies of it)."""
    rows: list[str] = []
    for name in SPEED_SCENES:
        frames = speed_frames(name, renders)
        fns = speed_functions(Sensor(frames[0].calibration))
        for state in CACHE_STATES:
            t = timed(fns, [r.image for r in frames], repeats, state)
            sub = t["subpixel"][0]
            refc, ratio_c = ("n/a", "n/a") if "refc" not in t else (f"{t['refc'][0]:.2f}", f"{sub / t['refc'][0]:.2f}")
            rows.append(
                f"| {name} | {state} | {t['ref'][0]:.2f} | {t['ref32'][0]:.2f} | {refc} "
                f"| {sub:.2f} | {t['paper'][0]:.2f} | {sub / t['ref'][0]:.3f} | {sub / t['ref32'][0]:.2f} "
                f"| {ratio_c} | {t['subpixel'][1]:.2f} |"
            )
    return rows


def _publish(lines: list[str], out: str | None, default: str) -> None:
    """Print the markdown ``lines`` and write them to ``out``, else to ``default`` in :data:`RESULTS`
    (:func:`lrsensor.atomic.atomic_write`: the folder created, no half-written table)."""
    text = "\n".join(lines) + "\n"
    print(text)
    atomic_write(Path(out) if out else RESULTS / default, text, fsync=False)


if __name__ == "__main__":
    raise SystemExit(main())
