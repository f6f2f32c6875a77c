"""What the one-time compile of the extractor's kernels costs, and what its optimisation level costs a frame.

    python -m benchmarks.bench_compile [--repeats 2] [--out benchmarks/results/compile.md]

For each LLVM optimisation level (1, the child's default, and 3, numba's default), into a fresh numba cache:
- **compile**: wall time of the compiling child process (``compile.child_command()``: what ``lrsensor setup``
  and a first use run; it compiles one part of the frame's calls while its helper process compiles the other),
  seconds, median of ``--repeats`` runs, each into an empty cache directory; the child's own part (as it
  reports it); and the CPU seconds of the child and its helper together (user + system; what one core alone
  would take, about);
- **load**: wall time of a new process loading the compiled kernels from that cache (``compile.warm_up``);
- **frame**: CPU time of ``Sensor.process`` per 1920x1080 frame with the kernels of that level, warm, median of
  60 calls on each of three named scenes, ms.

The compile keeps both cores busy; run it on a quiet machine (other work on the two cores stretches it: the
table gives the highest 1-minute load average seen after a compile, 2.0 being two busy cores, this one's own).
"""

from __future__ import annotations

import argparse
import math
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from lrsensor.atomic import atomic_write
from lrsensor.extract import compile as kernels

SPEED_SCENES = ("paper_box", "wall_1.0", "tank")

_SPEED = """
import json, time, numpy as np
from lrsensor import Sensor
from lrsensor.extract import compile as kc
from lrsensor.sim import named_scene
t0 = time.monotonic(); kc.warm_up(); load_s = time.monotonic() - t0
out = {"load_s": load_s}
for name in %r:
    setup = named_scene(name); image = setup.render(0).image; sensor = Sensor(setup.calibration)
    for _ in range(5): sensor.process(image)
    ts = []
    for _ in range(60):
        t = time.thread_time(); sensor.process(image); ts.append(time.thread_time() - t)
    out[name] = 1e3 * float(np.median(ts))
print(json.dumps(out))
"""


def _env(cache: str, opt: str) -> dict[str, str]:
    env = dict(os.environ)
    env["NUMBA_CACHE_DIR"] = cache
    env["NUMBA_OPT"] = opt
    return env


def measure(opt: str, repeats: int) -> dict[str, float]:
    """Compile time (median), load time and frame times at LLVM level ``opt``."""
    import json

    compiles: list[float] = []
    firsts: list[float] = []
    cpus: list[float] = []
    loads: list[float] = []
    with tempfile.TemporaryDirectory(prefix="lrsensor-bench-compile-") as top:
        cache = ""
        for i in range(repeats):
            cache = str(Path(top) / f"cache{i}")
            t0 = time.monotonic()
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            child = subprocess.run(
                kernels.child_command(),
                env=_env(cache, opt),
                check=True,
                capture_output=True,
                text=True,
            )
            compiles.append(time.monotonic() - t0)
            found = re.search(r"compiled in [0-9.]+ s \(\w+ ([0-9.]+) s", child.stderr)
            firsts.append(float(found.group(1)) if found else math.nan)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)  # the child and its helper, both waited for
            cpus.append(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
            loads.append(os.getloadavg()[0])
            print(
                f"level {opt}: compile {compiles[-1]:.1f} s (first part {firsts[-1]:.1f} s), CPU {cpus[-1]:.1f} s "
                f"(load average {loads[-1]:.1f})",
                file=sys.stderr,
            )
        done = subprocess.run(
            [sys.executable, "-c", _SPEED % (SPEED_SCENES,)],
            env=_env(cache, "3"),
            check=True,
            capture_output=True,
            text=True,
        )
    speeds = json.loads(done.stdout.strip().splitlines()[-1])
    return {
        "compile_s": statistics.median(compiles),
        "first_s": statistics.median(firsts),
        "cpu_s": statistics.median(cpus),
        "load_avg": max(loads),
        **speeds,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--repeats", type=int, default=2, help="compiles per level (default 2)")
    parser.add_argument("--levels", default="1,3", help="LLVM optimisation levels (default 1,3)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/compile.md"), help="results file")
    args = parser.parse_args(argv)
    rows = [
        "# The one-time compile of the extractor's kernels",
        "",
        f"`python -m benchmarks.bench_compile --repeats {args.repeats}`: wall seconds of a compile into an empty "
        f"cache (median of {args.repeats}; the two parts of the frame's calls side by side, in the child and its "
        "helper), the child's own part of it (detection and fits: when it is shorter, the helper's part set the "
        "wall time), the CPU seconds of both processes together, the 1-minute load average after it (2.0: two "
        "busy cores), wall seconds of a new process loading the kernels from the cache, and CPU ms per 1920x1080 "
        "frame with those kernels (warm, median of 60). `lrsensor setup` and a first use compile at level 1.",
        "",
        "| LLVM level | compile s | first part s | CPU s | machine load | load s | "
        + " | ".join(f"{s} ms" for s in SPEED_SCENES)
        + " |",
        "|---:|---:|---:|---:|---:|---:|" + "---:|" * len(SPEED_SCENES),
    ]
    for opt in args.levels.split(","):
        m = measure(opt.strip(), args.repeats)
        frame = " | ".join(f"{m[s]:.2f}" for s in SPEED_SCENES)
        rows.append(
            f"| {opt} | {m['compile_s']:.1f} | {m['first_s']:.1f} | {m['cpu_s']:.1f} | {m['load_avg']:.1f} | "
            f"{m['load_s']:.2f} | {frame} |"
        )
    text = "\n".join(rows) + "\n"
    print(text)
    atomic_write(args.out, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
