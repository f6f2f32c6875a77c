"""The one-time compile of the extractor's kernels, from outside: `lrsensor setup`, a first use, and processes
ended while they compile.

Each test gives its processes an empty numba cache of their own (``NUMBA_CACHE_DIR``), so that they start as
on a fresh install, whatever the repository's own cache holds.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import cv2
import pytest
from procs import lrsensor_cmd
from waiting import wait_until

from lrsensor.extract import compile as kernels
from lrsensor.sim import named_scene

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba is not installed")

#: What a crash at exit looks like (signals and LLVM's own messages).
CRASH_CODES = {-signal.SIGSEGV, -signal.SIGABRT, -signal.SIGBUS, 128 + signal.SIGSEGV, 128 + signal.SIGABRT}
CRASH_TEXT = ("LLVM ERROR", "Assertion", "Segmentation fault", "Fatal Python error", "core dumped")


@pytest.fixture(scope="module")
def frame(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A 1920x1080 image of a wall at 1 m and its calibration, as files."""
    d = tmp_path_factory.mktemp("frame")
    setup = named_scene("wall_1.0")
    image, calib = d / "wall.png", d / "calib.json"
    cv2.imwrite(str(image), setup.render(0).image)
    setup.calibration.save(calib)
    return image, calib


def _env(cache: Path) -> dict[str, str]:
    return dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONUNBUFFERED="1")


def _compiles_of_cache(cache: Path) -> list[int]:
    """The compiling child processes (:func:`lrsensor.extract.compile.child_command`) whose environment names
    ``cache``: the compiles of the processes a test started."""
    found = []
    needle = f"NUMBA_CACHE_DIR={cache}".encode()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if b"lrsensor.extract.compile" not in (entry / "cmdline").read_bytes():
                continue
            if needle in (entry / "environ").read_bytes().split(b"\0"):
                found.append(int(entry.name))
        except OSError:
            continue
    return found


def test_setup_then_process_runs_the_compiled_road(frame: tuple[Path, Path], tmp_path: Path) -> None:
    image, calib = frame
    env = _env(tmp_path / "cache")
    check = subprocess.run(lrsensor_cmd("setup", "--check"), env=env, capture_output=True, text=True, timeout=60)
    assert check.returncode == 1, check.stdout + check.stderr
    setup = subprocess.run(lrsensor_cmd("setup"), env=env, capture_output=True, text=True, timeout=600)
    assert setup.returncode == 0, setup.stdout + setup.stderr
    assert "compiled in" in setup.stdout
    # each kernel typed for one signature: a second (a literal argument, an array's other layout) compiles its whole
    # call tree again, into a second data file beside the first
    compiled_twice = sorted(path.name for path in (tmp_path / "cache").rglob("*.2.nbc"))
    assert not compiled_twice, compiled_twice
    again = subprocess.run(lrsensor_cmd("setup"), env=env, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stdout + again.stderr
    assert "compiled already" in again.stdout, again.stdout
    out = tmp_path / "wall.ply"
    done = subprocess.run(
        lrsensor_cmd("process", str(image), "--calib", str(calib), "--out", str(out), "--no-progress"),
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "compiled kernels loaded" in done.stderr, done.stderr
    assert "reference" not in done.stderr, done.stderr
    assert "compiling" not in done.stderr, done.stderr
    assert out.stat().st_size > 3000 * 12


def test_without_numba_setup_says_the_reference_runs(monkeypatch: pytest.MonkeyPatch, capsys) -> None:  # type: ignore[no-untyped-def]
    from lrsensor.cli import main

    monkeypatch.setattr(kernels, "HAVE_NUMBA", False)
    assert main(["setup"]) == 1
    assert "numpy reference" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("command", "sig", "after_s"),
    [
        ("process", signal.SIGINT, 1.0),
        ("process", signal.SIGTERM, 3.0),
        ("process", signal.SIGINT, 6.0),
        ("process", signal.SIGTERM, 10.0),
        ("rov", signal.SIGTERM, 2.0),
        ("rov", signal.SIGINT, 5.0),
        ("rov", signal.SIGTERM, 9.0),
    ],
)
def test_ending_a_first_use_at_any_moment_exits_cleanly(
    frame: tuple[Path, Path], tmp_path: Path, command: str, sig: int, after_s: float
) -> None:
    image, calib = frame
    cache = tmp_path / "cache"
    if command == "process":
        args = lrsensor_cmd("process", str(image), "--calib", str(calib), "--out", str(tmp_path / "o.ply"))
    else:
        port = _free_port()
        args = lrsensor_cmd(
            "rov", "--fleet", "cx", "--robot", "r1", "--mode", "peer", "--listen", f"tcp/127.0.0.1:{port}",
            "--source", "sim", "--sim-frames", "100000", "--sim-size", "320x180", "--rate", "5", "--no-outbox",
        )  # fmt: skip
    p = subprocess.Popen(args, env=_env(cache), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        # the moment is counted from the start of the compile (the process imports for a while before it)
        assert wait_until(lambda: bool(_compiles_of_cache(cache)) or p.poll() is not None, 120.0)
        time.sleep(after_s)
        p.send_signal(sig)
        try:
            out, _ = p.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            if command == "rov":  # the stacks of its threads (lrsensor rov dumps them on SIGUSR1)
                p.send_signal(signal.SIGUSR1)
                time.sleep(2.0)
            p.kill()
            out, _ = p.communicate()
            pytest.fail(f"no exit within 60 s of the signal:\n{out[-6000:]}")
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode not in CRASH_CODES, out
    assert p.returncode in (0, 130, -sig, 128 + sig), (p.returncode, out)
    assert not any(text in out for text in CRASH_TEXT), out
    assert "compiling the kernels once" in out or "numpy reference" in out, out
    assert wait_until(lambda: not _compiles_of_cache(cache), 10.0), "a compile outlived its process"


def test_a_rov_dumps_its_threads_on_sigusr1_and_runs_on(tmp_path: Path) -> None:
    """SIGUSR1 makes ``lrsensor rov`` write every thread's stack to stderr (what a stop that does not end waits
    for); it runs on and still stops cleanly on SIGTERM."""
    cache = tmp_path / "cache"
    args = lrsensor_cmd(
        "rov", "--fleet", "cx", "--robot", "r1", "--mode", "peer", "--listen", f"tcp/127.0.0.1:{_free_port()}",
        "--source", "sim", "--sim-frames", "100000", "--sim-size", "320x180", "--rate", "5", "--no-outbox",
    )  # fmt: skip
    p = subprocess.Popen(args, env=_env(cache), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert wait_until(lambda: bool(_compiles_of_cache(cache)) or p.poll() is not None, 120.0)
        time.sleep(1.0)
        p.send_signal(signal.SIGUSR1)
        time.sleep(1.0)
        assert p.poll() is None
        p.send_signal(signal.SIGTERM)
        out, _ = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 0, out
    assert "Current thread" in out, out  # faulthandler's dump
    assert "Thread 0x" in out, out


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_first_use_compiles_once_with_a_message(frame: tuple[Path, Path], tmp_path: Path) -> None:
    image, calib = frame
    env = _env(tmp_path / "cache")
    args = lrsensor_cmd("process", str(image), "--calib", str(calib), "--out", str(tmp_path / "o.ply"), "--no-progress")
    first = subprocess.run(args, env=env, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr
    assert "compiling the kernels once" in first.stderr, first.stderr
    assert "kernels compiled in" in first.stderr, first.stderr
    first_ply = (tmp_path / "o.ply").read_bytes()
    second = subprocess.run(args, env=env, capture_output=True, text=True, timeout=120)
    assert second.returncode == 0, second.stderr
    assert "compiling" not in second.stderr, second.stderr
    assert (tmp_path / "o.ply").read_bytes() == first_ply


def test_a_cache_compiled_from_other_sources_is_cleared_not_loaded(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Numba checks a cached kernel only against its own file: a frame call cached with the stages it linked in
    would outlive a change to a stage's file. The stamp beside the cache says which sources it was built from."""
    monkeypatch.setattr(kernels, "cache_dir", lambda: tmp_path)
    ours = [tmp_path / "frame.extract_frame-258.py311.nbi", tmp_path / "fit.fit_columns-30.py311.1.nbc"]
    theirs = tmp_path / "userlib.kernel-12.py311.nbi"  # another package's kernel in a shared NUMBA_CACHE_DIR
    for path in (*ours, theirs):
        path.write_bytes(b"cached")
    (tmp_path / kernels.STAMP_NAME).write_text("0123456789abcdef\n")  # built from other sources
    assert not kernels.cached()
    kernels._clear_stale()
    assert not any(path.exists() for path in ours)
    assert theirs.exists()
    kernels._write_stamp()
    assert (tmp_path / kernels.STAMP_NAME).read_text().strip() == kernels.source_fingerprint()
    assert kernels._stamp_current()


def test_the_kernels_constructors_give_numpys_arrays() -> None:
    """empty, zeros, full and arange, built in place in a kernel, give numpy's shapes, dtypes and values (the
    value of ``full`` converted as numpy converts it), and call numpy's from Python."""
    import numba
    import numpy as np

    from lrsensor.extract._jit import arange, empty, full, zeros

    @numba.njit(cache=False)
    def made(n):  # type: ignore[no-untyped-def]
        return (
            zeros(n, np.float64), zeros((n, 3), np.int64), zeros(n, np.bool_), full(n, np.nan, np.float32),
            full((2, n), -1, np.int32), full(n, True, np.bool_), full(n, 2.75, np.int64), full(n, 7, np.uint8),
            arange(n, np.float64), arange(n, np.int64), empty((n, 2), np.uint16).shape, empty(n, np.float64).dtype,
        )  # fmt: skip

    for n in (0, 1, 5):
        expected = (
            np.zeros(n), np.zeros((n, 3), np.int64), np.zeros(n, np.bool_), np.full(n, np.nan, np.float32),
            np.full((2, n), -1, np.int32), np.full(n, True), np.full(n, 2, np.int64), np.full(n, 7, np.uint8),
            np.arange(n, dtype=np.float64), np.arange(n), (n, 2), np.dtype(np.float64),
        )  # fmt: skip
        got = made(n)
        for value, want in zip(got[:10], expected[:10], strict=True):
            assert value.dtype == want.dtype
            assert value.shape == want.shape
            assert value.flags.c_contiguous
            np.testing.assert_array_equal(value, want)
        assert got[10:] == expected[10:]
        assert full(n, -1, np.int32).dtype == np.int32
        assert zeros((n, 2), np.uint8).shape == (n, 2)
        assert empty(n, np.int64).dtype == np.int64
        assert arange(n, np.float64).dtype == np.float64
