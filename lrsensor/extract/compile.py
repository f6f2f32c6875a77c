"""Compiling the extractor's kernels once: ahead with ``lrsensor setup``, or at first use with a message.

The compiled road (:func:`lrsensor.extract.frame.extract_frame`) is the extractor; numba compiles it once and
keeps the machine code in its on-disk cache (``cache=True``), from which any later process loads it in about a
second. This module decides when that compile happens and where:

- **In a child process, never in a thread of the caller.** A compile still running when its process ends (a
  background thread at interpreter shutdown) crashes inside LLVM (SIGSEGV or SIGABRT), and a compile interrupted
  in the caller's own thread leaves LLVM's state half built. A child (:func:`child_command`) and its helper
  compile and write the cache; they can be ended at any moment (numba writes each cache file by an atomic
  rename, so an unfinished compile leaves nothing half written), each dies with its parent (``PR_SET_PDEATHSIG``
  on Linux; at a normal exit :func:`atexit` ends the child), and the caller only ever *loads* finished kernels.
- **Compile time.** Numba compiles each kernel into a library of its own, callees first, and optimises and
  generates machine code again for a caller's whole call tree each time it links one; the rest is numba's own
  typing and lowering, which does not run in parallel within a process. So the frame is six compiled calls
  (:mod:`lrsensor.extract.frame`) in two parts of about equal compile time (:data:`PARTS`), and the child
  compiles the first while a helper process of its own compiles the second, on two cores about half the time
  of one: the first part is the detection, chains, the fit and the neighbour refits (the one column-parallel fit
  of :mod:`lrsensor.extract.fit` compiles in this part only), the width limits the fit needs, the pinhole
  triangulation and the placing of the points, the second the glow, gates and smoothing; the turbid-water fits
  are the largest call tree, a call of its own from Python (:func:`~lrsensor.extract.glow.glow_refit`, which a
  kernel around it would link in and optimise and compile again). The second part
  links the port's central view, the gate's pooled median and the smoothing late, after the glow's whole call
  tree: the first part compiles those first, and the second loads them from the cache (were it there first, it
  would compile them itself, the same kernels). The
  triangulations are calls of their own from Python (:func:`~lrsensor.extract.geometry.triangulate_geo`, for the
  width limits and for the points), so no other kernel but the smoothing's central view (the port's) links them
  in and compiles them again; and the thin stages that mostly call kernels
  (:func:`~lrsensor.extract.refit.refit_columns`, :func:`~lrsensor.extract.smooth.smooth_runs`, ...) are inlined
  into their callers (:data:`~lrsensor.extract._jit.inline`), one library less each, and the kernels only other
  kernels call have no wrappers for Python (:data:`~lrsensor.extract._jit.callee`). The larger stages stay
  kernels of their own (inlined, they make their callers' functions so large that LLVM takes longer over them
  than over the libraries they would save). The child and its
  helper compile at LLVM's optimisation level 1 (``NUMBA_OPT=1``, unless the caller set ``NUMBA_OPT``). The
  kernels avoid numpy conveniences that compile far more code than they run (array-to-array assignments, which
  bring numpy's broadcasting and its messages; fancy indexing, whose one-dimensional case is a loop,
  :func:`~lrsensor.extract.columns.take`; a sort where a selection gives the order statistic; numba's array
  constructors, a library per spelling of shape and dtype in each process: the kernels build their arrays in
  place, :func:`~lrsensor.extract._jit.empty` and its kin), and a kernel
  called with a constant argument compiles once for each constant (numba types a constant as a literal of its
  value: the glow's rounds compiled twice, for ``False`` and ``True``; a count started at the literal 0 typed
  the water's retelling twice), so flags reach kernels as values. Numba's typing and lowering allocate millions
  of small objects in reference cycles (its IR), and Python's cyclic garbage collector, at its default thresholds,
  walked all of them again in each full collection, about a sixth of the compile's time: the child and its
  helper collect less often (:data:`COMPILE_GC_THRESHOLDS`; their memory grows by about a tenth and is given back
  when they end). ``python -m benchmarks.bench_compile`` measures the compile and what its level costs a frame
  (docs/performance.md).
- **Three ways in.** :func:`ensure` (the default of :class:`lrsensor.Sensor`, and any first use): loaded from
  the cache, or compiled now in the foreground with a warning that says so and how long it takes. :func:`begin`
  (the ROV, which must not stall its camera): the compile runs in the background and the extractor runs its
  numpy reference until :func:`usable` finds the kernels built (both said in the log). ``lrsensor setup``
  compiles ahead, after ``pip install``.

Without numba (:data:`HAVE_NUMBA` False) nothing compiles and the extractor runs its numpy reference, with a
warning once per process.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import hashlib
import logging
import os
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..atomic import atomic_write
from ..errors import ExtractionError
from ._jit import HAVE_NUMBA

__all__ = [
    "HAVE_NUMBA",
    "CompileError",
    "CompileJob",
    "begin",
    "cache_dir",
    "cached",
    "ensure",
    "ready",
    "source_fingerprint",
    "start",
    "usable",
    "warm_up",
]

log = logging.getLogger(__name__)

#: What the one-time compile takes on a 2-core machine, for the messages (docs/performance.md has the figure).
COMPILE_TIME_HINT = "about 30 s"
#: LLVM's optimisation level of the child's compile (see the module documentation).
CHILD_OPT_LEVEL = "1"
#: The cyclic garbage collector's thresholds in the child and its helper (:func:`gc.set_threshold`; Python's are
#: 700, 10, 10): the youngest objects collected every 20 000 allocations less deallocations, and the oldest
#: generation, which holds the compiled kernels' IR, in effect never (see the module documentation).
COMPILE_GC_THRESHOLDS = (20_000, 20, 1_000)


class CompileError(ExtractionError):
    """The kernels could not be compiled (the child's error output is in the message)."""


def entry_points() -> tuple[object, ...]:
    """The kernels the Python side calls (each loaded from the cache on its own): the seven calls of the frame
    and the triangulation that :mod:`lrsensor.triangulation` uses for detections it gets from elsewhere."""
    from .frame import finish_located, fit_points, glow_starts, locate_candidates, place_points, pool_ends
    from .geometry import fwhm_from_points, triangulate_points, triangulate_points_port
    from .glow import glow_refit

    return (
        locate_candidates, fwhm_from_points, fit_points, glow_starts, glow_refit, finish_located, pool_ends,
        place_points, triangulate_points, triangulate_points_port,
    )  # fmt: skip


#: The parts of the compile that run side by side, in the child and in its helper (see the module documentation):
#: the frame's detection, fits, width limits and the placing of the points, and its glow stage and finish, of about
#: equal compile time.
PARTS = ("locate", "finish")


def child_command(part: str | None = None) -> list[str]:
    """The command line of the compiling child (this interpreter; ``main(["--child"])``), or of its helper that
    compiles one ``part`` of :data:`PARTS`."""
    args = ["--child"] if part is None else ["--child", "--part", part]
    return [sys.executable, "-c", f"from lrsensor.extract.compile import main; raise SystemExit(main({args!r}))"]


def _build(part: str | None = None) -> None:
    """Load the entry points from the cache, or compile them here (by the child and its helper, a ``part``
    each; in the caller only where a finished child left no cache behind), by calling each with arguments of the
    exact types of a real call: the records :func:`~lrsensor.extract.settings.frame_settings` builds, for a
    small calibration, and the :class:`~lrsensor.extract.frame.Located` points of a frame without stripes."""
    import numpy as np

    from ..calibration import Calibration
    from .config import SubpixelConfig
    from .finish import pooled_median
    from .frame import (
        finish_located,
        fit_points,
        glow_starts,
        locate_candidates,
        no_points,
        place_points,
        pool_ends,
        refine_points,
    )
    from .geometry import central_view, fwhm_from_points, triangulate_points, triangulate_points_port
    from .glow import new_water
    from .settings import frame_settings
    from .smooth import smooth_runs_at

    bands, settings, g = frame_settings(Calibration.paper(0.1, 64, 48), SubpixelConfig())
    image = np.zeros((48, 64, 3), np.uint8)
    f64 = np.zeros(4)
    i64 = np.zeros(4, np.int64)
    if part in (None, "locate"):
        # (first: the finish part links the port's central view, the gate's pooled median and the smoothing late in
        # its compile and loads them from the cache when this part has written them there by then, else compiles
        # them itself)
        central_view(f64, f64, i64, g)
        i32 = np.zeros(4, np.int32)
        pooled_median(i32, np.zeros(4, np.float32), i32, 1, 4)
        smooth_runs_at(f64, f64, i64, i64)
        picked = locate_candidates(image, bands, settings)  # (none on a blank frame: of a real frame's types)
        fit_points(image, picked, np.zeros(0), settings)
        fwhm_from_points(np.zeros((4, 3)), 1.0, 1.0, g)
        place_points(f64, f64, i64, f64, np.zeros((4, 3)), settings, g, True)
        # (the pooled dim ends: called on glowing frames only; compiled in this part, the shorter one)
        pool_ends(
            image, f64, f64, i64, f64, bands.glow_side, i64, np.zeros(4, np.bool_), f64, g.glow_vanish, g.glow_path,
            new_water(),
        )  # fmt: skip
        triangulate_points(
            f64, f64, i64, g.camera, g.distortion, g.R_cam_body, g.origin_body, g.normals_body,
            g.points_body,
        )  # fmt: skip
    if part in (None, "finish"):  # (the Located record built in Python: no compile of its own)
        located = no_points.py_func(np.ones(bands.rows.shape[0]), settings.window_half_px)
        # (the glow stage's two kernels: SubpixelConfig's glow_fit is on; the starts called here too, which a sharp
        # frame does not call)
        glow_starts(located)
        glow = refine_points(image, located, bands.glow_side, settings, g, new_water())
        finish_located(located, glow, image.shape[1], settings, g)
        # (the central view's callee: compiled in this part either way)
        triangulate_points_port(
            f64, f64, i64, g.camera, g.distortion, g.R_cam_body, g.origin_body, g.normals_body,
            g.points_body, g.port,
        )  # fmt: skip


@dataclass
class CompileJob:
    """A compile running in a child process (see the module documentation)."""

    process: subprocess.Popen[bytes]
    log_path: Path
    started_s: float = field(default_factory=time.monotonic)

    def done(self) -> bool:
        """Whether the child has ended (successfully or not)."""
        return self.process.poll() is not None

    def wait(self, timeout_s: float | None = None) -> bool:
        """Wait for the child to end (polling, so that a signal handler of the caller runs); True when it did."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while self.process.poll() is None:
            if deadline is not None and time.monotonic() >= deadline:
                return False
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(0.1)
        return True

    def check(self) -> None:
        """Raise :class:`CompileError` if the child ended with an error (with the end of its output)."""
        code = self.process.poll()
        if code not in (0, None):
            try:
                tail = self.log_path.read_text(errors="replace")[-2000:]
            except OSError:
                tail = ""
            msg = f"compiling the extractor's kernels failed (exit code {code}):\n{tail}"
            raise CompileError(msg)

    def cancel(self) -> None:
        """End the child if it still runs (nothing is left half written) and wait for it."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(5.0)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.discard_log()

    def discard_log(self) -> None:
        """Remove the child's output file (kept only while it can explain a failure)."""
        with contextlib.suppress(OSError):
            self.log_path.unlink()

    @property
    def elapsed_s(self) -> float:
        return time.monotonic() - self.started_s


class _State:
    """This process's kernels: loaded or not, and the compile job it started (one per process: the kernels
    are process-wide, as numba's dispatchers are)."""

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.loaded = threading.Event()
        self.job: CompileJob | None = None
        self.failed: str | None = None
        self.warned_missing = False


_STATE = _State()


def ready() -> bool:
    """True when this process has the compiled kernels loaded (calling them compiles nothing). Never waits."""
    return _STATE.loaded.is_set()


def cached() -> bool:
    """Whether numba's on-disk cache holds every entry point for the sources as they are now (then loading
    takes about a second): numba's own index for each entry point, and the stamp of every kernel module's
    source beside it (:func:`source_fingerprint`)."""
    if not HAVE_NUMBA or not _stamp_current():
        return False
    try:
        for kernel in entry_points():
            index = kernel._cache._cache_file._load_index()  # type: ignore[attr-defined]
            if not index:
                return False
    except Exception:  # numba's cache internals moved: assume nothing is cached, compile in a child
        return False
    return True


def source_fingerprint() -> str:
    """A hash of every module of this package (the kernels and what they call), hex.

    Numba checks a cached kernel only against its own source file; a frame call cached with the stages it
    linked in would outlive a change to one of those stages' files (after an upgrade or a ``git pull``). The
    cache therefore holds this fingerprint beside it (:data:`STAMP_NAME`), and a cache stamped with another one
    is cleared before the next compile."""
    digest = hashlib.sha256()
    for path in sorted(Path(__file__).parent.glob("*.py")):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:32]


#: The file beside numba's cache files that holds the :func:`source_fingerprint` they were compiled from.
STAMP_NAME = "lrsensor-kernels.stamp"


def _stamp_current() -> bool:
    directory = cache_dir()
    if directory is None:
        return False
    try:
        return (directory / STAMP_NAME).read_text().strip() == source_fingerprint()
    except OSError:
        return False


def _clear_stale() -> None:
    """Remove numba's cache files of this package's kernels (index ``.nbi`` and data ``.nbc``), so that nothing
    compiled from other sources is loaded."""
    directory = cache_dir()
    if directory is None or not directory.is_dir():
        return
    stems = {path.stem for path in Path(__file__).parent.glob("*.py")}
    for path in directory.iterdir():
        if path.suffix in (".nbi", ".nbc") and path.name.split(".", 1)[0] in stems:
            with contextlib.suppress(OSError):
                path.unlink()


def _write_stamp() -> None:
    directory = cache_dir()
    if directory is not None and directory.is_dir():
        with contextlib.suppress(OSError):
            atomic_write(directory / STAMP_NAME, source_fingerprint() + "\n", fsync=False)


def cache_dir() -> Path | None:
    """Where numba keeps the extractor's compiled kernels (None without numba)."""
    if not HAVE_NUMBA:
        return None
    try:
        return Path(entry_points()[0]._cache._cache_path)  # type: ignore[attr-defined]
    except Exception:
        return None


def warm_up() -> float:
    """Load the kernels in this process, from the cache or, where it misses, by compiling them here (the
    child's job; tests and benchmarks call it too); blocks; returns the seconds it took (0 without numba)."""
    if not HAVE_NUMBA:
        return 0.0
    t0 = time.monotonic()
    with _STATE.lock:
        if not _STATE.loaded.is_set():
            current = _stamp_current()
            if not current:
                _clear_stale()  # compiled from other sources (see source_fingerprint)
            _build()
            if not current:
                _write_stamp()
            _STATE.loaded.set()
            log.info("extractor: compiled kernels loaded in %.1f s", time.monotonic() - t0)
    return time.monotonic() - t0


def start() -> CompileJob | None:
    """Start compiling in a child process unless the kernels are loaded, cached or already compiling; returns
    the running job (None when there is nothing to compile). Does not wait: see :func:`usable`."""
    if not HAVE_NUMBA or ready():
        return None
    with _STATE.lock:
        if _STATE.job is not None and not _STATE.job.done():
            return _STATE.job
        if cached():
            return None
        env = dict(os.environ)
        env.setdefault("NUMBA_OPT", CHILD_OPT_LEVEL)
        fd, name = tempfile.mkstemp(prefix="lrsensor-compile-", suffix=".log")
        with os.fdopen(fd, "wb") as out:
            process = subprocess.Popen(
                child_command(),
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                env=env,
            )
        _STATE.job = CompileJob(process, Path(name))
        return _STATE.job


def _finish(job: CompileJob) -> bool:
    """After the child ended: load its kernels (True), or record and log its failure once (False)."""
    try:
        job.check()
    except CompileError as err:
        if _STATE.failed is None:
            _STATE.failed = str(err)
            log.error("extractor: %s\nthe numpy reference runs instead", err)
        return False
    job.discard_log()
    warm_up()
    return True


def ensure() -> bool:
    """Make the compiled kernels ready in this process, waiting for them if need be; False where they cannot be
    (no numba, or the compile failed: the reference runs, said once in the log).

    Loads them from the cache (about a second), or compiles them once in a child process with a warning (the
    first use after installing, unless ``lrsensor setup`` ran). Ending the process meanwhile ends the child."""
    if ready():
        return True
    if not HAVE_NUMBA:
        if not _STATE.warned_missing:
            _STATE.warned_missing = True
            log.warning("extractor: numba is not installed; the numpy reference runs (tens of ms a frame)")
        return False
    if _STATE.failed is not None:
        return False
    job = start()
    if job is None:
        warm_up()
        return True
    log.warning(
        "extractor: compiling the kernels once (%s; `lrsensor setup` does this ahead of the first use)",
        COMPILE_TIME_HINT,
    )
    try:
        job.wait()
    except BaseException:
        job.cancel()
        raise
    if job.process.returncode == 0:
        log.warning("extractor: kernels compiled in %.0f s and cached in %s", job.elapsed_s, cache_dir())
    return _finish(job)


def begin() -> bool:
    """Make the compiled kernels ready without waiting for a compile: load them from the cache if it holds
    them (True), else start compiling in a child process and say that the numpy reference runs until
    :func:`usable` finds them built (False)."""
    if ready():
        return True
    if not HAVE_NUMBA or _STATE.failed is not None:
        return ensure()  # says why the reference runs
    job = start()
    if job is None:
        warm_up()
        return True
    log.warning(
        "extractor: the numpy reference runs (tens of ms a frame) while the kernels compile in a child process "
        "(%s; `lrsensor setup` does this ahead of the first use)",
        COMPILE_TIME_HINT,
    )
    return False


def usable() -> bool:
    """Whether the extractor's next frame runs on the compiled road: True when the kernels are loaded, or a
    background compile (:func:`begin`) has just finished (they are loaded now and take over, said in the log),
    or a first use compiles them now in the foreground (:func:`ensure`); False while a background compile runs
    or where the kernels cannot be had."""
    if ready():
        return True
    job = _STATE.job
    if job is not None and job.process.poll() is None:
        return False
    if job is not None and _STATE.failed is None:
        if not _finish(job):
            return False
        log.warning("extractor: the compiled kernels take over (compiled in %.0f s)", job.elapsed_s)
        return True
    return ensure()


def _end_child() -> None:
    job = _STATE.job
    if job is not None:
        job.cancel()


atexit.register(_end_child)


def _die_with_parent() -> None:
    """Ask Linux to end this process when its parent dies (elsewhere the parent's atexit ends it)."""
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGTERM)
        if os.getppid() == 1:  # the parent is already gone
            sys.exit(1)
    except (OSError, AttributeError):
        pass


def _compile_parts() -> int:
    """The compiling child's work: :data:`PARTS` side by side, the first here, the second in a helper process
    that dies with this one; then the stamp of the sources they were compiled from. Returns the exit code."""
    if not _stamp_current():
        _clear_stale()  # compiled from other sources (see source_fingerprint)
    t0 = time.monotonic()
    helper = subprocess.Popen(child_command(PARTS[1]), stdin=subprocess.DEVNULL)  # its output goes to ours
    try:
        _build(PARTS[0])
    except BaseException:
        helper.terminate()
        helper.wait()
        raise
    own_s = time.monotonic() - t0
    code = helper.wait()
    if code != 0:
        print(f"compiling the part {PARTS[1]!r} failed (exit code {code})", file=sys.stderr)
        return 1
    _write_stamp()
    # (benchmarks.bench_compile reads the parts' times)
    print(f"compiled in {time.monotonic() - t0:.1f} s ({PARTS[0]} {own_s:.1f} s)", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    """The compiling child (:func:`child_command`): compile every entry point into numba's cache, its
    :data:`PARTS` side by side; with ``--part`` the helper that compiles one of them."""
    args = sys.argv[1:] if argv is None else argv
    if "--child" in args:
        _die_with_parent()
        gc.set_threshold(*COMPILE_GC_THRESHOLDS)
    if not HAVE_NUMBA:
        print("numba is not installed: nothing to compile", file=sys.stderr)
        return 1
    if "--part" in args:
        t0 = time.monotonic()
        part = args[args.index("--part") + 1]
        _build(part)
        print(f"part {part} compiled in {time.monotonic() - t0:.1f} s", file=sys.stderr)
        return 0
    return _compile_parts()
