"""Crash-safe file writes: a temporary file in the target's folder, fsync, then a rename.

A reader sees either the old file or the new one, never a torn one. Every package that persists state
(calibration files, PLY exports, the base station's state, the ROV's outbox, the map) writes through here.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def atomic_write(path: str | os.PathLike[str], data: bytes | str, *, fsync: bool = True, mode: int = 0o644) -> Path:
    """Write ``data`` to ``path`` atomically and return the path.

    Args:
        path: target file; its folder is created when missing.
        data: bytes, or text (written as UTF-8).
        fsync: flush the file and the folder entry to disk before returning (survives a power cut);
            without it the write still survives a crash of the process.
        mode: permission bits of the new file (``mkstemp`` alone would leave 0600).
    """
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    payload = data.encode("utf-8") if isinstance(data, str) else data
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())
        Path(tmp).chmod(mode)
        Path(tmp).replace(target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if fsync:
        _fsync_dir(target.parent)
    return target


def _fsync_dir(folder: Path) -> None:
    """Flush a folder's entries (the rename) to disk; a no-op where folders cannot be opened."""
    try:
        dfd = os.open(folder, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(dfd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(dfd)
