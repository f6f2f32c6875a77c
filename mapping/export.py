"""Export of the map: binary PLY (plane points and plane patches) and JSON.

The PLY writer is local because the map needs a face element (one quad per plane patch), which
``lrsensor.ply.write_ply`` (vertices only) does not write; ``lrsensor.ply.read_ply`` reads the vertices back.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .builder import MapBuilder
from .store import atomic_write_bytes, save_json


def map_points(builder: MapBuilder) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The map's down-sampled points: (K, 3) NED metres (voxel centroids) and (K,) plane id of each."""
    q = builder.cfg.quantum_m
    pts, ids = [], []
    for pid, rec in builder.planes_records().items():
        c = rec.voxels.centroids_m(q)
        pts.append(c)
        ids.append(np.full(c.shape[0], pid, np.int64))
    if not pts:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    return np.concatenate(pts), np.concatenate(ids)


def ply_bytes(points: NDArray[np.float64], point_plane: NDArray[np.int64], planes: list[dict[str, Any]]) -> bytes:
    """Binary little-endian PLY of points and plane patches.

    Vertices: the points, then the 4 extent corners of every plane; properties ``x y z`` (float32, NED metres),
    ``plane`` (int32 id) and ``corner`` (uchar: 0 for a point, 1 for a patch corner). Faces: one quad per plane
    (``vertex_indices`` and ``plane``).
    """
    corners = np.array([p["extent"]["corners"] for p in planes], dtype=np.float64).reshape(-1, 3)
    corner_ids = np.repeat(np.array([p["id"] for p in planes], dtype=np.int64), 4)
    xyz = np.concatenate([points, corners]).astype("<f4")
    pid = np.concatenate([point_plane, corner_ids]).astype("<i4")
    kind = np.concatenate([np.zeros(points.shape[0], np.uint8), np.ones(corners.shape[0], np.uint8)])
    vdt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("plane", "<i4"), ("corner", "u1")])
    verts = np.empty(xyz.shape[0], vdt)
    verts["x"], verts["y"], verts["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    verts["plane"], verts["corner"] = pid, kind
    fdt = np.dtype([("n", "u1"), ("idx", "<i4", (4,)), ("plane", "<i4")])
    faces = np.empty(len(planes), fdt)
    faces["n"] = 4
    base = points.shape[0] + 4 * np.arange(len(planes), dtype=np.int64)
    faces["idx"] = (base[:, None] + np.arange(4)[None, :]).astype("<i4")
    faces["plane"] = corner_ids[::4] if planes else np.zeros(0, np.int64)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment lrsensor shared map, NED frame, metres\n"
        f"element vertex {verts.shape[0]}\nproperty float x\nproperty float y\nproperty float z\n"
        "property int plane\nproperty uchar corner\n"
        f"element face {faces.shape[0]}\nproperty list uchar int vertex_indices\nproperty int plane\n"
        "end_header\n"
    )
    return header.encode("ascii") + verts.tobytes() + faces.tobytes()


def read_ply_vertices(path: Path) -> NDArray[Any]:
    """Read back the vertex table of a PLY written by :func:`ply_bytes` (structured array)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    n = next(int(line.split()[2]) for line in header if line.startswith("element vertex"))
    vdt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("plane", "<i4"), ("corner", "u1")])
    return np.frombuffer(data, dtype=vdt, count=n, offset=end)


def export_map(builder: MapBuilder, ply_path: Path | None = None, json_path: Path | None = None) -> dict[str, Any]:
    """Write the map as PLY and/or JSON (with tracks); returns the JSON document."""
    doc = builder.map_json(include_tracks=True)
    if ply_path is not None:
        pts, ids = map_points(builder)
        atomic_write_bytes(ply_path, ply_bytes(pts, ids, doc["planes"]))
    if json_path is not None:
        save_json(json_path, doc)
    return doc
