"""PLY point clouds: binary little-endian, float32 x, y, z plus optional per-point properties.

Written by ``lrsensor process`` (properties ``x y z laser quality u v``) and read back by tests and by the
mapping export. Files are written atomically (temporary file in the same directory, then rename).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .atomic import atomic_write
from .errors import LrsensorError
from .scan import Scan


class PlyError(LrsensorError):
    """A PLY file could not be written or read (bad header, unsupported format, truncated data)."""


#: PLY type name -> numpy little-endian dtype.
_PLY_TYPES: dict[str, str] = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}  # fmt: skip
_NUMPY_TO_PLY = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
                 "f4": "float", "f8": "double"}  # fmt: skip


def write_ply(
    path: str | os.PathLike[str],
    points: ArrayLike,
    properties: Mapping[str, ArrayLike] | None = None,
    comments: tuple[str, ...] = (),
) -> Path:
    """Write points (N, 3) as a binary little-endian PLY with float32 x, y, z and extra vertex properties.

    Args:
        path: output file; its directory is created when missing.
        points: (N, 3) coordinates (metres); written as float32.
        properties: name -> (N,) array; dtype kept (uint8, int32, float32, ... ; float64 becomes float32).
        comments: header comment lines.

    Returns:
        The path written.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        msg = f"{path}: points must have shape (N, 3), got {p.shape}"
        raise PlyError(msg)
    n = p.shape[0]
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    cols: dict[str, NDArray[np.generic]] = {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}
    for name, values in (properties or {}).items():
        a = np.asarray(values)
        if a.shape != (n,):
            msg = f"{path}: property {name!r} must have shape ({n},), got {a.shape}"
            raise PlyError(msg)
        if not name.isidentifier() or name in cols:
            msg = f"{path}: bad or duplicate property name {name!r}"
            raise PlyError(msg)
        kind = a.dtype.str[1:]
        if kind == "f8" or a.dtype.kind == "b":
            kind = "f4" if a.dtype.kind == "f" else "u1"
        if kind not in _NUMPY_TO_PLY:
            kind = "i4" if a.dtype.kind in "iu" else "f4"
        fields.append((name, "<" + kind))
        cols[name] = a
    rec = np.empty(n, dtype=np.dtype(fields))
    for name, _ in fields:
        rec[name] = cols[name]
    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments), f"element vertex {n}"]
    header += [f"property {_NUMPY_TO_PLY[np.dtype(dt).str[1:]]} {name}" for name, dt in fields]
    header.append("end_header")
    data = ("\n".join(header) + "\n").encode("ascii") + rec.tobytes()
    return atomic_write(path, data)


def write_scan_ply(path: str | os.PathLike[str], scan: Scan, comments: tuple[str, ...] = ()) -> Path:
    """Write a :class:`Scan` as PLY: x, y, z (body frame, metres), laser (uchar), quality, u, v (float)."""
    return write_ply(
        path,
        scan.points,
        {
            "laser": scan.laser.astype(np.uint8),
            "quality": scan.quality.astype(np.float32),
            "u": scan.uv[:, 0].astype(np.float32),
            "v": scan.uv[:, 1].astype(np.float32),
        },
        comments=(f"lrsensor scan, body frame, metres, method {scan.method}", *comments),
    )


def read_ply(path: str | os.PathLike[str]) -> dict[str, NDArray[np.generic]]:
    """Read the vertex element of a PLY file (binary little-endian or ASCII) into name -> (N,) arrays."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as err:
        msg = f"{p}: cannot read PLY file: {err.strerror or err}"
        raise PlyError(msg) from err
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        msg = f"{p}: not a PLY file (missing 'ply' magic or 'end_header')"
        raise PlyError(msg)
    body_start = raw.index(b"\n", end) + 1
    lines = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = ""
    n = -1
    fields: list[tuple[str, str]] = []
    element = ""
    for line in lines:
        tok = line.split()
        if not tok:
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            element = tok[1]
            if element == "vertex":
                n = int(tok[2])
        elif tok[0] == "property" and element == "vertex":
            if tok[1] == "list":
                msg = f"{p}: list properties in the vertex element are not supported"
                raise PlyError(msg)
            if tok[1] not in _PLY_TYPES:
                msg = f"{p}: unknown PLY type {tok[1]!r}"
                raise PlyError(msg)
            fields.append((tok[2], _PLY_TYPES[tok[1]]))
    if n < 0 or not fields:
        msg = f"{p}: no vertex element in the header"
        raise PlyError(msg)
    if fmt == "binary_little_endian":
        dt = np.dtype(fields)
        need = n * dt.itemsize
        if len(raw) - body_start < need:
            msg = f"{p}: truncated: {len(raw) - body_start} bytes of vertex data, {need} expected"
            raise PlyError(msg)
        rec = np.frombuffer(raw, dtype=dt, count=n, offset=body_start)
        return {name: rec[name].copy() for name, _ in fields}
    if fmt == "ascii":
        text = raw[body_start:].decode("ascii").split()
        vals = np.asarray(text[: n * len(fields)], dtype=np.float64).reshape(n, len(fields))
        return {name: vals[:, i].astype(dt) for i, (name, dt) in enumerate(fields)}
    msg = f"{p}: unsupported PLY format {fmt!r} (binary_little_endian and ascii are read)"
    raise PlyError(msg)


def read_ply_points(path: str | os.PathLike[str]) -> NDArray[np.float64]:
    """The x, y, z of a PLY file as (N, 3) float64."""
    d = read_ply(path)
    try:
        return np.stack([d["x"], d["y"], d["z"]], axis=1).astype(np.float64)
    except KeyError as err:
        msg = f"{path}: PLY vertex element lacks property {err}"
        raise PlyError(msg) from None
