"""Plane extraction from one window of NED points: local-normal regions, then Open3D RANSAC per region.

Why not RANSAC on the raw window: every hit of one laser lies in that laser's sheet, a plane through the vehicle;
when the vehicle holds depth and attitude, all frames of a window share that sheet, and ``segment_plane`` on the
whole window happily returns it (a horizontal "plane" made of the top stripe on every wall). Two coplanar but
separate faces (the fronts of two pillars in a row) would also be glued by one infinite RANSAC plane.

So extraction runs in four steps, all vectorized numpy except the Open3D call:

1. **Down-sample** the window on a voxel grid (``voxel_m``): RANSAC cost is linear in the points.
2. **Local normals** on a coarser cell grid (``cell_m``): each cell's normal is the smallest principal axis of
   its 3x3x3 block of cells. The block spans both laser lines (0.1 m apart), so a wall cell has a well-defined
   normal, while a laser sheet never shows up as a local plane. Cells that are line-like (one laser only),
   non-planar (corners, pipes) or nearly empty get no normal. Normals are oriented toward the vehicle.
3. **Regions**: adjacent cells whose normals agree within ``grow_angle_deg`` form one region (union-find over
   the cell adjacency graph). A region is one connected face; coplanar faces that do not touch stay apart.
4. **RANSAC per region** with Open3D ``segment_plane`` (re-seeded before every call, so the result depends only
   on the input), peeling up to ``max_planes_per_region`` planes. Each inlier set must pass: enough points, a
   second principal spread of at least ``min_width_m`` (a single stripe is a line and defines no plane), a
   spread along down of at least ``min_down_spread_m`` (the lasers are horizontal sheets a baseline apart: a
   true face holds both stripes; a tilted plane through one noisy stripe does not), both
   in-plane extents of at least ``min_extent_m``, an RMS below ``max_rms_m``, a quadratic residual model bending
   less than ``max_sagitta_m`` (pipes are curved), and the plane must not pass within ``min_sensor_distance_m``
   of the observing vehicle (that would be the laser sheet).

With a range noise k > 0 the thresholds follow the sensor's range noise, which grows as about ``r^2 / (f c)``
(focal length f, the laser's offset c) times the stripe's sub-pixel error: a point at range ``r`` is expected
``k r^2`` off. k is one number for the window (``MapConfig.range_noise_per_m``, or the window's clouds all from
one calibration) or one per point (clouds of several calibrations, or some without one: k 0,
:mod:`mapping.range_noise`). A cell's thickness has its points' mean expected error, squared, removed before the
``cell_planarity`` test, and a region's RANSAC and refit inlier distance is at least ``_NOISE_THRESHOLD_SIGMAS``
times its points' median expected error (the RMS limit stays): a region that mixes robots reads each point's own
k, and one of points without a calibration keeps the fixed thresholds. docs/mapping.md ("Range noise") has what
it gives on extracted clouds.

The accepted planes then claim the full-resolution points near them (within the RANSAC threshold, in the cells
of their inliers or the cells next to them); :mod:`mapping.builder` turns those into exact statistics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import Open3DMissingError
from .noisy_faces import YAW_SPREAD_SIGMAS, expected_error_m, horizontal_spread, prior_fit
from .types import MapConfig

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

_KEY_OFF = 1 << 20
_KEY_BASE = 1 << 21
_NEIGHBOURS_27 = np.array([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)], dtype=np.int64)
_NEIGHBOUR_KEYS = ((_NEIGHBOURS_27[:, 0] * _KEY_BASE + _NEIGHBOURS_27[:, 1]) * _KEY_BASE + _NEIGHBOURS_27[:, 2]).astype(
    np.int64
)
_FORWARD_13 = np.array([o for o in _NEIGHBOURS_27.tolist() if tuple(o) > (0, 0, 0)], dtype=np.int64)

_o3d: ModuleType | None = None

#: With a range noise (:mod:`mapping.range_noise`): a region's RANSAC / refit inlier distance is at least this many
#: of its points' expected range errors (their median). The inliers' RMS limit (``max_rms_m``) stays: a looser one
#: let near-horizontal planes through single noisy stripes in (docs/mapping.md, "Range noise").
_NOISE_THRESHOLD_SIGMAS = 2.0


def open3d() -> ModuleType:
    """The ``open3d`` module, imported on first use, or :class:`Open3DMissingError` with the fix."""
    global _o3d
    if _o3d is None:
        try:
            import open3d as o3d
        except ImportError as err:
            msg = (
                f"plane extraction needs Open3D, which the ROV-only install leaves out ({err}); "
                "install the base-station extra: pip install 'lrsensor[base]' "
                "(the open3d wheel also needs the system library libusb-1.0-0)"
            )
            raise Open3DMissingError(msg) from err
        _o3d = o3d
    return _o3d


def seeded_segment_plane(
    pcd: Any, cfg: MapConfig, seed: int, threshold_m: float | None = None
) -> tuple[Any, list[int]]:
    """Open3D ``segment_plane`` made reproducible: re-seeded, and on one thread. ``threshold_m``: the inlier
    distance (metres; ``cfg.distance_threshold_m`` by default).

    Seeding alone is not enough: with several OpenMP threads the RANSAC iterations consume the random stream in
    a scheduling-dependent order (measured: 2-4 different results in 30 identical calls). One thread gives the
    same planes on every run; the previous thread limit is restored afterwards.
    """
    o3d = open3d()
    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        o3d.utility.random.seed(int(seed))
        thr = cfg.distance_threshold_m if threshold_m is None else threshold_m
        model, inliers = pcd.segment_plane(thr, 3, cfg.ransac_iterations)
    finally:
        o3d.utility.set_max_threads(before)
    return model, inliers


def pack_keys(idx: IntArray) -> IntArray:
    """Pack integer grid indices (N, 3) into sortable int64 keys (N,); |index| must be below 2**20."""
    i = np.asarray(idx, dtype=np.int64) + _KEY_OFF
    return (i[:, 0] * _KEY_BASE + i[:, 1]) * _KEY_BASE + i[:, 2]


def _offset_key(o: NDArray[np.int64]) -> int:
    return int((o[0] * _KEY_BASE + o[1]) * _KEY_BASE + o[2])


def neighbour_index(keys_sorted: IntArray, offset: NDArray[np.int64]) -> IntArray:
    """For each key, the index of the key shifted by the grid ``offset`` (3,), or -1 when absent; (M,)."""
    target = keys_sorted + _offset_key(offset)
    pos = np.searchsorted(keys_sorted, target)
    pos_c = np.minimum(pos, keys_sorted.shape[0] - 1)
    found = keys_sorted[pos_c] == target
    return np.where(found, pos_c, -1)


def connected_components(n: int, a: IntArray, b: IntArray) -> IntArray:
    """Labels 0..k-1 of the connected components of an undirected graph (n nodes, edges a[i]-b[i]), (n,).

    Vectorized union-find (min-label hooking with pointer jumping); labels are numbered by their smallest node,
    so the result depends only on the graph.
    """
    lab = np.arange(n, dtype=np.int64)
    if a.size:
        while True:
            la, lb = lab[a], lab[b]
            m = np.minimum(la, lb)
            new = lab.copy()
            np.minimum.at(new, la, m)
            np.minimum.at(new, lb, m)
            while True:
                jumped = new[new]
                if np.array_equal(jumped, new):
                    break
                new = jumped
            if np.array_equal(new, lab):
                break
            lab = new
    _, compact = np.unique(lab, return_inverse=True)
    return compact.astype(np.int64)


@dataclass(frozen=True)
class VoxelGrid:
    """Points reduced to one centroid per occupied voxel.

    Attributes:
        keys: (M,) sorted packed voxel keys.
        inverse: (N,) voxel index of every input point.
        counts: (M,) points per voxel.
        centroids: (M, 3) mean of the points in each voxel (same frame and units as the input).
    """

    keys: IntArray
    inverse: IntArray
    counts: IntArray
    centroids: FloatArray


def voxel_reduce(points: FloatArray, size_m: float) -> VoxelGrid:
    """Reduce (N, 3) points (metres, any frame) to voxel centroids of edge ``size_m``."""
    keys_all = pack_keys(np.floor(points / size_m).astype(np.int64))
    keys, inverse = np.unique(keys_all, return_inverse=True)
    inverse = inverse.reshape(-1).astype(np.int64)
    counts = np.bincount(inverse, minlength=keys.shape[0]).astype(np.int64)
    sums = np.stack([np.bincount(inverse, weights=points[:, k], minlength=keys.shape[0]) for k in range(3)], 1)
    return VoxelGrid(keys, inverse, counts, sums / counts[:, None])


@dataclass(frozen=True)
class CellNormals:
    """Local normals on the cell grid (see module docstring, step 2).

    Attributes:
        keys: (C,) sorted packed cell keys.
        of_point: (M,) cell index of every down-sampled point.
        normal: (C, 3) unit normals oriented toward the observing vehicle (NaN where invalid).
        valid: (C,) whether the cell has a planar, well-spread neighbourhood.
    """

    keys: IntArray
    of_point: IntArray
    normal: FloatArray
    valid: BoolArray


def cell_normals(
    points: FloatArray, vehicle: FloatArray, cfg: MapConfig, noise_per_m: float | FloatArray | None = None
) -> CellNormals:
    """Block normals of the cells holding ``points`` (M, 3) seen from ``vehicle`` (M, 3), same frame, metres.
    ``noise_per_m``: the range noise k (1/m), one for all points or (M,) one per point (None:
    ``cfg.range_noise_per_m``; 0 everywhere: the fixed planarity test)."""
    noise = cfg.range_noise_per_m if noise_per_m is None else noise_per_m
    per_point = np.ndim(noise) > 0
    noisy = bool(np.any(np.asarray(noise) > 0.0))
    cells = np.floor(points / cfg.cell_m).astype(np.int64)
    keys, of_point = np.unique(pack_keys(cells), return_inverse=True)
    of_point = of_point.reshape(-1).astype(np.int64)
    c = keys.shape[0]
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    cols: tuple[FloatArray, ...] = (np.ones_like(x), x, y, z, x * x, x * y, x * z, y * y, y * z, z * z)
    if noisy:  # the squared range (m^2), or each point's expected error (m), summed only where it is read
        r2 = np.einsum("ij,ij->i", points - vehicle, points - vehicle)
        cols += (noise * r2 if per_point else r2,)
    st = np.stack([np.bincount(of_point, weights=w, minlength=c) for w in cols], 1)  # (C, 10 or 11)
    n = st[:, 0]
    s = st[:, 1:4]
    v = np.stack([np.bincount(of_point, weights=vehicle[:, k], minlength=c) for k in range(3)], 1)
    block = np.zeros_like(st)
    for off in _NEIGHBOURS_27:
        nb = neighbour_index(keys, off)
        ok = nb >= 0
        block[ok] += st[nb[ok]]
    bn = block[:, 0]
    bs = block[:, 1:4]
    bss = block[:, (4, 5, 6, 5, 7, 8, 6, 8, 9)].reshape(c, 3, 3)
    mu = bs / bn[:, None]
    cov = bss / bn[:, None, None] - mu[:, :, None] * mu[:, None, :]
    w, axes = np.linalg.eigh(cov)
    w = np.maximum(w, 0.0)
    normal = axes[:, :, 0]
    to_vehicle = v / n[:, None] - s / n[:, None]
    flip = np.einsum("ij,ij->i", normal, to_vehicle) < 0
    normal[flip] *= -1.0
    thick = w[:, 0]
    if noisy:
        # the points' own mean expected error (k r^2) is thickness a plane has
        sigma = (1.0 if per_point else noise) * block[:, 10] / bn
        thick = np.maximum(thick - sigma * sigma, 0.0)
    valid = (
        (bn >= 6) & (np.sqrt(w[:, 1]) >= cfg.min_width_m) & (np.sqrt(thick) <= cfg.cell_planarity * np.sqrt(w[:, 1]))
    )
    normal[~valid] = np.nan
    return CellNormals(keys, of_point, normal, valid)


def grow_regions(cn: CellNormals, cfg: MapConfig) -> IntArray:
    """Region label per cell (C,), -1 for cells without a valid normal (step 3 of the module docstring)."""
    c = cn.keys.shape[0]
    cos_min = math.cos(math.radians(cfg.grow_angle_deg))
    aa: list[IntArray] = []
    bb: list[IntArray] = []
    for off in _FORWARD_13:
        nb = neighbour_index(cn.keys, off)
        i = np.nonzero((nb >= 0) & cn.valid)[0]
        j = nb[i]
        keep = cn.valid[j] & (np.einsum("ij,ij->i", cn.normal[i], cn.normal[j]) >= cos_min)
        aa.append(i[keep])
        bb.append(j[keep])
    labels = connected_components(c, np.concatenate(aa), np.concatenate(bb))
    labels[~cn.valid] = -1
    # Renumber the valid regions 0..k-1 in order of their smallest cell (deterministic).
    valid_labels = labels[cn.valid]
    if valid_labels.size:
        _uniq, compact = np.unique(valid_labels, return_inverse=True)
        labels[cn.valid] = compact.reshape(-1)
    return labels


@dataclass(frozen=True)
class PlaneCandidate:
    """A plane accepted in one window.

    Attributes:
        normal: (3,) unit normal in NED, oriented toward the observing vehicle.
        d: offset, ``normal . p + d = 0`` (NED metres).
        voxel_index: (K,) indices (into the down-sampled window) of the RANSAC inliers.
        rms_m, width_m, sagitta_m: quality figures of the inliers (metres).
    """

    normal: FloatArray
    d: float
    voxel_index: IntArray
    rms_m: float
    width_m: float
    sagitta_m: float


@dataclass(frozen=True)
class Rejection:
    """Why a RANSAC plane was refused (for diagnostics and tests)."""

    reason: str
    n_inliers: int
    value: float


def plane_quality(points: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """Fit of (K, 3) points: (centroid (3,), eigvals (3,) ascending, axes (3, 3) columns, sagitta metres).

    The sagitta is half the spread of a quadratic model ``r = a u^2 + b uv + c v^2 + e u + f v + g`` of the
    residuals ``r`` over the in-plane coordinates ``(u, v)``: ~0 for a noisy plane, the bulge of a curved one.
    """
    c = points.mean(axis=0)
    x = points - c
    w, axes = np.linalg.eigh(x.T @ x / points.shape[0])
    return c, np.maximum(w, 0.0), axes, sagitta(x, axes)


def sagitta(x: FloatArray, axes: FloatArray) -> float:
    """The bulge (metres) of a quadratic model of the residuals of centred points ``x`` (K, 3) along ``axes[:, 0]``
    over the in-plane axes ``axes[:, 2]``, ``axes[:, 1]`` (see :func:`plane_quality`)."""
    r = x @ axes[:, 0]
    u = x @ axes[:, 2]
    v = x @ axes[:, 1]
    su = max(float(np.abs(u).max()), 1e-9)
    sv = max(float(np.abs(v).max()), 1e-9)
    un, vn = u / su, v / sv
    design = np.stack([un * un, un * vn, vn * vn, un, vn, np.ones_like(un)], 1)
    gram = design.T @ design + 1e-9 * np.eye(6)
    coef = np.linalg.solve(gram, design.T @ r)
    pred = design @ coef  # the projection is unique even when the design is rank-deficient (two lines)
    return 0.5 * float(pred.max() - pred.min()) if pred.size else 0.0


def _check_inliers(
    pts: FloatArray, veh: FloatArray, cfg: MapConfig, sigma: FloatArray | None = None
) -> tuple[PlaneCandidate | None, Rejection | None, FloatArray, float]:
    """Quality gate for one RANSAC inlier set; returns (candidate-without-index, rejection, normal, d). ``sigma``
    (K,): the inliers' expected errors, metres, for the tilt prior (:mod:`mapping.noisy_faces`)."""
    k = pts.shape[0]
    noise_m = 0.0
    if sigma is not None and cfg.tilt_prior_deg > 0:
        c, w, axes, noise_m = prior_fit(pts, sigma, cfg)
        sag = max(sagitta(pts - c, axes) - noise_m, 0.0)
    else:
        c, w, axes, sag = plane_quality(pts)
    normal = axes[:, 0].copy()
    to_vehicle = veh.mean(axis=0) - c
    if normal @ to_vehicle < 0:
        normal = -normal
    d = float(-normal @ c)
    rms = math.sqrt(w[0])
    width = math.sqrt(w[1])
    proj_u = (pts - c) @ axes[:, 2]
    proj_v = (pts - c) @ axes[:, 1]
    extent = min(float(np.ptp(proj_u)), float(np.ptp(proj_v)))
    sensor_dist = float(np.median(veh @ normal + d))
    spread_down = float(np.std(pts[:, 2]))  # the lasers are horizontal: two stripes are ~baseline apart in down
    along = horizontal_spread(pts - c, normal) if noise_m > 0 else math.inf
    checks = (
        ("too few inliers", k < cfg.min_inliers, float(k)),
        ("line-like (degenerate)", width < cfg.min_width_m, width),
        ("short for its noise (yaw undetermined)", along < YAW_SPREAD_SIGMAS * noise_m, along),
        ("one stripe (no spread across the laser sheets)", spread_down < cfg.min_down_spread_m, spread_down),
        ("too small", extent < cfg.min_extent_m, extent),
        ("rms too large", rms > cfg.max_rms_m, rms),
        ("curved", sag > cfg.max_sagitta_m, sag),
        ("laser sheet (passes through the vehicle)", sensor_dist < cfg.min_sensor_distance_m, sensor_dist),
    )
    for reason, failed, value in checks:
        if failed:
            return None, Rejection(reason, k, value), normal, d
    cand = PlaneCandidate(normal, d, np.zeros(0, dtype=np.int64), rms, width, sag)
    return cand, None, normal, d


def _refine(
    points: FloatArray, members: IntArray, inliers: IntArray, cfg: MapConfig, threshold_m: float, rounds: int = 3
) -> IntArray:
    """RANSAC's plane comes from 3 points; refit it to its inliers and re-select the inliers, a few rounds.

    A laser band on a wall is a thin slab (10-30 cm tall): a plane tilted across it still collects many inliers,
    and the least-squares refit over the re-selected inliers pulls it back into the slab. Returns indices into
    ``points`` (a subset of ``members``); ``threshold_m`` is the inlier distance (metres).
    """
    chosen = members[inliers]
    for _ in range(rounds):
        if chosen.shape[0] < 3:
            break
        pts = points[chosen]
        c = pts.mean(axis=0)
        _w, axes = np.linalg.eigh((pts - c).T @ (pts - c))
        n = axes[:, 0]
        dist = np.abs((points[members] - c) @ n)
        new = members[dist <= threshold_m]
        if np.array_equal(new, chosen):
            break
        chosen = new
    return chosen


@dataclass(frozen=True)
class Extraction:
    """Planes found in one window (down-sampled), with what was refused.

    Attributes:
        grid: the voxel grid of the window (its ``inverse`` maps full-resolution points to voxels).
        candidates: accepted planes.
        rejections: refused RANSAC planes.
        cells: cell keys (at ``cell_m``) of each down-sampled point, (M,).
    """

    grid: VoxelGrid
    candidates: list[PlaneCandidate]
    rejections: list[Rejection]
    cell_keys: IntArray


def extract_planes(
    points: FloatArray,
    vehicle: FloatArray,
    cfg: MapConfig,
    seed: int,
    noise_per_m: float | FloatArray | None = None,
) -> Extraction:
    """Find planes in one window.

    Args:
        points: (N, 3) window points, NED metres (may be shifted by a constant origin; ``vehicle`` likewise).
        vehicle: (N, 3) position of the observing vehicle for every point, same frame.
        cfg: thresholds.
        seed: base seed of Open3D's RNG for this window (call i uses ``seed + i``).
        noise_per_m: the range noise k (1/m), one for the window or (N,) one per point (None:
            ``cfg.range_noise_per_m``); see the module docstring.

    Returns:
        The :class:`Extraction`; candidates are in a deterministic order (regions by size, then peel order).
    """
    o3d = open3d()
    grid = voxel_reduce(points, cfg.voxel_m)
    m = grid.keys.shape[0]
    veh_sum = np.stack([np.bincount(grid.inverse, weights=vehicle[:, k], minlength=m) for k in range(3)], 1)
    vpts = grid.centroids
    vveh = veh_sum / grid.counts[:, None]
    k: float | FloatArray = cfg.range_noise_per_m if noise_per_m is None else noise_per_m
    if np.ndim(k) > 0:  # one per voxel: the mean of its points'
        k = np.bincount(grid.inverse, weights=np.asarray(k, dtype=np.float64), minlength=m) / grid.counts
    noisy = bool(np.any(np.asarray(k) > 0.0))
    candidates: list[PlaneCandidate] = []
    rejections: list[Rejection] = []
    cn = cell_normals(vpts, vveh, cfg, k)
    cell_keys = cn.keys[cn.of_point]
    if m < cfg.min_region_points:
        return Extraction(grid, candidates, rejections, cell_keys)
    region_of_cell = grow_regions(cn, cfg)
    region = region_of_cell[cn.of_point]
    sizes = np.bincount(region[region >= 0]) if np.any(region >= 0) else np.zeros(0, dtype=np.int64)
    order = sorted(range(sizes.shape[0]), key=lambda r: (-int(sizes[r]), r))
    call = 0
    for r in order:
        if sizes[r] < cfg.min_region_points:
            continue
        members = np.nonzero(region == r)[0]
        thr = cfg.distance_threshold_m
        if noisy:  # the region's points' median expected range error, k r^2
            r2 = np.einsum("ij,ij->i", vpts[members] - vveh[members], vpts[members] - vveh[members])
            if isinstance(k, np.ndarray):
                thr = max(thr, _NOISE_THRESHOLD_SIGMAS * float(np.median(k[members] * r2)))
            else:
                thr = max(thr, _NOISE_THRESHOLD_SIGMAS * k * float(np.median(r2)))
        for _ in range(cfg.max_planes_per_region):
            if members.shape[0] < cfg.min_inliers:
                break
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(vpts[members]))
            _model, inl = seeded_segment_plane(pcd, cfg, (seed + call) % (2**31 - 1), thr)
            call += 1
            inl_idx = np.asarray(inl, dtype=np.int64)
            if inl_idx.shape[0] < cfg.min_inliers:
                break
            chosen = _refine(vpts, members, inl_idx, cfg, thr)
            sig = None
            if noisy:  # each inlier's expected error, k r^2
                sig = expected_error_m(vpts[chosen], vveh[chosen], k[chosen] if isinstance(k, np.ndarray) else k)
            cand, rej, _n, _d = _check_inliers(vpts[chosen], vveh[chosen], cfg, sig)
            if cand is not None:
                candidates.append(PlaneCandidate(cand.normal, cand.d, chosen, cand.rms_m, cand.width_m, cand.sagitta_m))
            elif rej is not None:
                rejections.append(rej)
            keep = np.ones(members.shape[0], dtype=bool)
            keep[inl_idx] = False
            members = members[keep & ~np.isin(members, chosen)]
    return Extraction(grid, candidates, rejections, cell_keys)


def claim_points(
    points: FloatArray,
    grid: VoxelGrid,
    candidates: list[PlaneCandidate],
    voxel_cell_keys: IntArray,
    cfg: MapConfig,
    eligible: BoolArray,
) -> list[IntArray]:
    """Full-resolution points claimed by each candidate: (K_i,) index arrays into ``points``.

    A point is claimed when it is ``eligible``, within ``distance_threshold_m`` of the candidate's plane, and its
    voxel lies in a cell that holds one of the candidate's inliers or touches one. Each point goes to the first
    candidate claiming it (candidates are in deterministic order).

    Args:
        points: (N, 3) full-resolution points, same frame as the extraction.
        grid: the window's voxel grid (``grid.inverse`` maps points to voxels).
        candidates: accepted planes of the window.
        voxel_cell_keys: (M,) cell key (``cell_m``) of each voxel.
        cfg: thresholds.
        eligible: (N,) which points may be claimed (the new, not yet committed clouds).
    """
    taken = ~eligible
    out: list[IntArray] = []
    m = grid.keys.shape[0]
    for cand in candidates:
        base = np.unique(voxel_cell_keys[cand.voxel_index])
        dilated = np.unique((base[:, None] + _NEIGHBOUR_KEYS[None, :]).ravel())
        near = np.abs(grid.centroids @ cand.normal + cand.d) <= cfg.distance_threshold_m + cfg.voxel_m
        vox_ok = np.zeros(m, dtype=bool)
        cand_vox = np.nonzero(near)[0]
        vox_ok[cand_vox[np.isin(voxel_cell_keys[cand_vox], dilated)]] = True
        idx = np.nonzero(vox_ok[grid.inverse] & ~taken)[0]
        idx = idx[np.abs(points[idx] @ cand.normal + cand.d) <= cfg.distance_threshold_m]
        taken[idx] = True
        out.append(idx)
    return out


def describe(extraction: Extraction) -> dict[str, Any]:
    """Small diagnostic summary of an extraction (counts and rejection reasons)."""
    reasons: dict[str, int] = {}
    for rej in extraction.rejections:
        reasons[rej.reason] = reasons.get(rej.reason, 0) + 1
    return {
        "voxels": int(extraction.grid.keys.shape[0]),
        "planes": len(extraction.candidates),
        "rejected": reasons,
    }
