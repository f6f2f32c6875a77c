"""Atomic persistence of the map under a state directory (no pickle).

Files:
    ``map_state.npz``: the whole builder state: a JSON header (exact integer plane statistics, configuration,
        per-robot window counters) stored as a unicode array, and numeric arrays (plane voxels, tracks, the
        clouds still waiting in the windows). Loaded with ``allow_pickle=False``.
    ``map.json``: the serving form of the map (planes and tracks) for people and tools; derived, never read back.

Every file is written to a temporary name in the same directory, flushed, fsynced, renamed over the old one
(``os.replace`` is atomic on POSIX), and the directory is fsynced: a crash leaves the old or the new file.
"""

from __future__ import annotations

import io
import json
import logging
import os
import threading
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import MappingError, MapStoreError
from .types import MapConfig

log = logging.getLogger(__name__)

STATE_FILE = "map_state.npz"
JSON_FILE = "map.json"
FORMAT = "lrsensor-map-state"
VERSION = 1


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (tmp + fsync + rename + directory fsync)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{threading.get_ident()}")
    try:
        with tmp.open("wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        tmp.replace(path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        msg = f"cannot write {path}: {err}"
        raise MapStoreError(msg) from err
    try:
        dir_fd = os.open(path.parent, os.O_RDONLY)
    except OSError:  # pragma: no cover - platforms without directory fds
        return
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def save_state(state_dir: Path, header: dict[str, Any], arrays: dict[str, NDArray[Any]]) -> Path:
    """Write the state file atomically; returns its path. ``header`` must be JSON-serializable."""
    body = dict(header)
    body["format"] = FORMAT
    body["version"] = VERSION
    buf = io.BytesIO()
    np.savez(buf, header=np.array(json.dumps(body, sort_keys=True)), **arrays)  # type: ignore[arg-type]
    path = state_dir / STATE_FILE
    atomic_write_bytes(path, buf.getvalue())
    return path


def load_state(state_dir: Path) -> tuple[dict[str, Any], dict[str, NDArray[Any]]] | None:
    """Read the state file, or ``None`` when the directory holds none. Raises :class:`MapStoreError` if bad."""
    path = state_dir / STATE_FILE
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        msg = f"cannot read the map state {path}: {err}"
        raise MapStoreError(msg) from err
    if "header" not in arrays:
        msg = f"{path}: no header array (not a map state file)"
        raise MapStoreError(msg)
    try:
        header = json.loads(str(arrays.pop("header")))
    except json.JSONDecodeError as err:
        msg = f"{path}: header is not JSON: {err}"
        raise MapStoreError(msg) from err
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        msg = f"{path}: format is not {FORMAT!r}"
        raise MapStoreError(msg)
    if header.get("version") != VERSION:
        msg = f"{path}: unsupported map state version {header.get('version')!r} (this build reads {VERSION})"
        raise MapStoreError(msg)
    return header, arrays


def save_json(path: Path, data: dict[str, Any]) -> None:
    """Write a JSON document atomically."""
    atomic_write_bytes(path, (json.dumps(data, indent=1) + "\n").encode())


def six_ints(values: list[int]) -> tuple[int, int, int, int, int, int]:
    """Six integers from a JSON list (a plane's ``within`` counters); ValueError otherwise."""
    v = [int(x) for x in values]
    if len(v) != 6:
        msg = f"expected 6 integers, got {values!r}"
        raise ValueError(msg)
    return (v[0], v[1], v[2], v[3], v[4], v[5])


def saved_config(header: dict[str, Any]) -> MapConfig:
    """The configuration a state was saved with (keys this version does not know are ignored)."""
    saved = header.get("config")
    if not isinstance(saved, dict):
        return MapConfig()
    known = set(MapConfig().to_dict())
    try:
        return MapConfig.from_dict({k: v for k, v in saved.items() if k in known})
    except MappingError as err:
        log.warning("saved map configuration refused (%s); using defaults", err)
        return MapConfig()
