"""``lrsensor setup``: compile the sub-pixel extractor's kernels once, after installing.

    lrsensor setup            # compile (about 30 s on 2 cores) or confirm they are compiled
    lrsensor setup --check    # exit 0 if they are compiled, 1 if not; compiles nothing

Without this step the first use of the extractor compiles them (with a message); every later process loads them
from numba's on-disk cache in about a second. Exit codes: 0 compiled (or already), 1 not compiled (``--check``,
or numba missing: the numpy reference then runs), 2 the compile failed, 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of this sub-command."""
    parser.add_argument("--check", action="store_true", help="only say whether the kernels are compiled (exit 0/1)")


def run(args: argparse.Namespace) -> int:
    """Compile or check the kernels; returns the exit code."""
    from ..extract import compile as kernels

    if not kernels.HAVE_NUMBA:
        print(
            "lrsensor setup: numba is not installed here; the extractor runs its numpy reference (tens of ms a "
            "frame). Install numba (pip install numba) for the compiled extractor.",
            file=sys.stderr,
        )
        return 1
    if kernels.cached():
        if args.check:
            print(f"the extractor's kernels are compiled (cache: {kernels.cache_dir()})")
            return 0
        seconds = kernels.warm_up()
        print(f"the extractor's kernels are compiled already; loaded in {seconds:.1f} s (cache: {kernels.cache_dir()})")
        return 0
    if args.check:
        print("the extractor's kernels are not compiled: run `lrsensor setup`")
        return 1
    print(f"compiling the extractor's kernels once ({kernels.COMPILE_TIME_HINT}) ...", flush=True)
    job = kernels.start()
    if job is not None:
        try:
            job.wait()
        except BaseException:
            job.cancel()
            raise
        try:
            job.check()
        except kernels.CompileError as err:
            print(f"lrsensor setup: {err}", file=sys.stderr)
            return 2
        job.discard_log()
    compiled_s = job.elapsed_s if job is not None else 0.0
    load_s = kernels.warm_up()
    print(f"compiled in {compiled_s:.1f} s, loaded in {load_s:.1f} s (cache: {kernels.cache_dir()})")
    return 0
