"""The shared plane map: association of observed planes with map planes and exact fusion.

An observation (the points one robot's window gave one plane) joins a map plane when

* their normals agree within ``merge_angle_deg`` (normals are oriented toward the observing vehicle, so the two
  faces of a thin wall point in opposite directions and never fuse),
* the observation's centroid lies within ``merge_offset_m`` of the map plane,
* their bounding boxes, inflated by ``merge_gap_m`` (``merge_gap_down_m`` along down, since the horizontal laser
  sheets scan faces in horizontal bands), overlap or touch (coplanar faces that are apart stay apart); two
  *bands* of one vertical face (:meth:`PlaneMap.bands`: both normals within ``merge_band_tilt_deg`` of horizontal
  and within ``merge_band_angle_deg`` of each other, points within ``merge_band_offset_m``) may be up to
  ``merge_band_gap_down_m`` apart along down instead: a robot that crossed a face at two depths leaves a gap between
  its bands as wide as its change of depth, yet a vertical face is one plane over its whole height,
* and the fusion does not make the plane thick: the fused plane's RMS stays within ``merge_max_rms_m``, or the
  scatter it adds to its parts' own (:func:`added_rms_m`: their separation and relative tilt over their points,
  weighted by their shares) within ``merge_added_rms_m``.
  What the parts already carry does not count: a face all robots saw is as thick as their pose errors make it
  (about 3 cm RMS in the demo, whose trusted poses disagree by 3-7 cm between robots), and a test of the fused
  plane's whole RMS against the bound then refused every later view of that face, even one lying 1 cm from it,
  which became a second plane of the face (docs/mapping.md, "The demo's duplicate").

Two planes that fail those tests may still be one surface: seen from poses that disagree by more than
``merge_offset_m``, one wall gives two parallel planes a decimetre apart. When they face the same way, lie within
``same_face_offset_m`` and cover the same part of the face (:mod:`mapping.same_face`: the rays that made the far
one would have stopped at the near one; :meth:`PlaneMap.same_face`), they fuse too: the one fewer robots (then
fewer points) made is first moved along the other's normal onto it (:meth:`PlaneRecord.shifted`, exact), since what
separates them is the pose error of the robots that made it, not the surface.

Fusion adds the exact integer statistics and refits. When an observation matches several map planes (it bridges
them), all of them fuse into the one with the smallest id, and the result is checked against the remaining planes
again. The integer statistics make fusion order-independent: merging A then B gives exactly what B then A gives.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .noisy_faces import excess_rms_m, mean_var_m2, prior_within
from .planes import pack_keys
from .same_face import shared_fraction
from .stats import Contribution, VoxelSet, merge_contributions
from .types import MapChange, MapConfig, PlaneFit, PlaneStats, scatter_matrix

FloatArray = NDArray[np.float64]

#: Scale of the integer orientation vector (normal components in millionths, weighted by point count).
_ORIENT_SCALE = 1_000_000


@dataclass(frozen=True)
class PlaneRecord:
    """One plane (an observation or a map plane) with everything needed to fuse it exactly.

    Attributes:
        stats: exact sufficient statistics of its points (quanta).
        orient: integer orientation vector: sum over fused observations of round(1e6 * normal) * n_points; the
            fitted normal is signed to agree with it (toward the observing vehicles).
        aabb_min, aabb_max: exact bounding box of its points (quanta).
        contributions: robot -> :class:`Contribution`.
        voxels: down-sampled points for export and extents.
        n_obs: number of observations fused.
        hint_normal: (3,) normal of the window fit (only for associating a fresh observation; not persisted).
        within: the pooled scatter of the fused observations about their own centroids (see :func:`fit_parts`),
            with each observation's tilt prior (:func:`mapping.noisy_faces.prior_within`).
        noise: the sum of its points' expected variances (quanta^2; 0 unless ``MapConfig.tilt_prior_deg``): the RMS
            gates test the thickness beyond it (:mod:`mapping.noisy_faces`).
    """

    stats: PlaneStats
    orient: tuple[int, int, int]
    aabb_min: tuple[int, int, int]
    aabb_max: tuple[int, int, int]
    contributions: dict[str, Contribution]
    voxels: VoxelSet
    n_obs: int = 1
    hint_normal: tuple[float, float, float] | None = field(default=None, compare=False)
    within: tuple[int, int, int, int, int, int] = (0, 0, 0, 0, 0, 0)
    noise: int = 0

    def __add__(self, other: PlaneRecord) -> PlaneRecord:
        return PlaneRecord(
            self.stats + other.stats,
            (self.orient[0] + other.orient[0], self.orient[1] + other.orient[1], self.orient[2] + other.orient[2]),
            (
                min(self.aabb_min[0], other.aabb_min[0]),
                min(self.aabb_min[1], other.aabb_min[1]),
                min(self.aabb_min[2], other.aabb_min[2]),
            ),
            (
                max(self.aabb_max[0], other.aabb_max[0]),
                max(self.aabb_max[1], other.aabb_max[1]),
                max(self.aabb_max[2], other.aabb_max[2]),
            ),
            merge_contributions(self.contributions, other.contributions),
            self.voxels + other.voxels,
            self.n_obs + other.n_obs,
            None,
            tuple(a + b for a, b in zip(self.within, other.within, strict=True)),  # type: ignore[arg-type]
            self.noise + other.noise,
        )

    def shifted(self, t_q: tuple[int, int, int], voxel_quanta: int) -> PlaneRecord:
        """This record with every point moved by ``t_q`` (quanta, NED), exactly: sums and bounds move, the scatter
        about the centroid and the orientation do not; export voxels move by their centroids (``voxel_quanta`` per
        edge)."""
        st = self.stats
        n, s, t = st.n, st.s, t_q
        pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
        ss = tuple(st.ss[k] + t[i] * s[j] + t[j] * s[i] + n * t[i] * t[j] for k, (i, j) in enumerate(pairs))
        vox = self.voxels
        tv = np.array(t, dtype=np.int64)
        sums = vox.sums + vox.counts[:, None] * tv[None, :]
        keys = pack_keys(np.floor_divide(np.floor_divide(sums, vox.counts[:, None]), voxel_quanta))
        return replace(
            self,
            stats=PlaneStats(n, (s[0] + n * t[0], s[1] + n * t[1], s[2] + n * t[2]), ss),  # type: ignore[arg-type]
            aabb_min=(self.aabb_min[0] + t[0], self.aabb_min[1] + t[1], self.aabb_min[2] + t[2]),
            aabb_max=(self.aabb_max[0] + t[0], self.aabb_max[1] + t[1], self.aabb_max[2] + t[2]),
            voxels=VoxelSet.reduced(keys, vox.counts, sums),
        )

    @classmethod
    def from_points(
        cls,
        points_q: NDArray[np.integer],
        normal: FloatArray,
        robot: str,
        first_ns: int,
        last_ns: int,
        cfg: MapConfig,
        noise_q2: int = 0,
    ) -> PlaneRecord:
        """An observation from its quantized points (N, 3) and the oriented window normal (3,); ``noise_q2``: the
        sum of the points' expected variances (quanta^2), with the tilt prior it makes (:mod:`mapping.noisy_faces`)."""
        p = np.asarray(points_q, dtype=np.int64)
        n = int(p.shape[0])
        o = [round(float(x) * _ORIENT_SCALE) * n for x in normal]
        lo = p.min(axis=0)
        hi = p.max(axis=0)
        vq = max(1, round(cfg.export_voxel_m / cfg.quantum_m))
        stats = PlaneStats.from_quantized(p)
        within = [(2 * m + n) // (2 * n) for m in stats.centred_scatter()]
        within[5] += prior_within(noise_q2, normal, cfg)
        return cls(
            stats,
            (o[0], o[1], o[2]),
            (int(lo[0]), int(lo[1]), int(lo[2])),
            (int(hi[0]), int(hi[1]), int(hi[2])),
            {robot: Contribution(n, int(first_ns), int(last_ns))},
            VoxelSet.from_quantized(p, vq),
            1,
            (float(normal[0]), float(normal[1]), float(normal[2])),
            (within[0], within[1], within[2], within[3], within[4], within[5]),
            noise_q2,
        )

    def fit(self, quantum_m: float, between_weight: float = 1.0) -> PlaneFit:
        """Refit from the statistics, normal signed by the orientation vector (see :func:`fit_parts`)."""
        return fit_parts(self.stats, self.within, self.orient, quantum_m, between_weight)


def fit_parts(
    stats: PlaneStats,
    within: tuple[int, ...],
    orient: tuple[int, int, int],
    quantum_m: float,
    between_weight: float = 1.0,
) -> PlaneFit:
    """The plane of exact statistics: centroid and covariance of all points; normal from ``within``.

    ``within`` is the sum over fused observations of each one's centred scatter (``n`` times its covariance,
    rounded to whole quanta^2 once per observation, so sums stay exact): its smallest
    axis is the normal once per-observation offsets (navigation drift) are removed. The normal is the smallest
    axis of ``W + between_weight * B``, where ``B = T - W`` is the between-observation part of the total scatter
    ``T``: weight 1 gives the plain fit of all points, 0 ignores where observations sit relative to each other.
    The normal is signed to agree with ``orient``; ``eigvals`` are the plain covariance's variances along the
    chosen axes.
    """
    f = stats.fit(quantum_m)
    axes = f.axes
    if between_weight < 1.0 and any(within):
        w = scatter_matrix(within, 1.0)
        t = f.cov * (float(stats.n) / (quantum_m * quantum_m))
        _w, axes = np.linalg.eigh(w + between_weight * (t - w))
    normal = axes[:, 0].copy()
    if normal @ np.array(orient, dtype=np.float64) < 0:
        normal = -normal
    eig = np.einsum("ij,ik,kj->j", axes, f.cov, axes)
    return PlaneFit(f.centroid, normal, float(-normal @ f.centroid), np.maximum(eig, 0.0), axes, f.cov)


def _angle_deg(a: FloatArray, b: FloatArray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, float(a @ b)))))


def in_plane_axes(normal: FloatArray) -> tuple[FloatArray, FloatArray]:
    """In-plane unit axes (u, v) of a plane, (3,) each: u horizontal for non-horizontal planes, v = n x u."""
    down = np.array([0.0, 0.0, 1.0])
    u = np.cross(down, normal)
    if np.linalg.norm(u) < 0.2:  # nearly horizontal plane: u along north projected
        u = np.cross(normal, np.array([0.0, 1.0, 0.0]))
    u = u / np.linalg.norm(u)
    v = np.cross(normal, u)
    return u, v / np.linalg.norm(v)


@dataclass
class MapPlane:
    """A plane of the map: its id, record, cached fit and cached JSON form.

    Never edited once in the map (a change of the plane is a new ``MapPlane``), so a :class:`MapChange` may hold
    it; the caches are filled on first use and take no part in equality.
    """

    id: int
    record: PlaneRecord
    cfg: MapConfig
    _fit: PlaneFit | None = field(default=None, compare=False, repr=False)
    _json: dict[str, Any] | None = field(default=None, compare=False, repr=False)

    @property
    def fit(self) -> PlaneFit:
        """The plane fitted to the record's statistics (cached)."""
        if self._fit is None:
            self._fit = self.record.fit(self.cfg.quantum_m, self.cfg.between_window_weight)
        return self._fit

    def to_json(self) -> dict[str, Any]:
        """The serving form (see :meth:`PlaneMap.to_json`)."""
        if self._json is None:
            self._json = plane_json(self.id, self.record, self.cfg)
        return self._json


def plane_json(plane_id: int, rec: PlaneRecord, cfg: MapConfig) -> dict[str, Any]:
    """JSON-ready dict of one plane in NED (``normal . p + d = 0``), metres and nanoseconds."""
    q = cfg.quantum_m
    f = rec.fit(q, cfg.between_window_weight)
    u, v = in_plane_axes(f.normal)
    cen = rec.voxels.centroids_m(q)
    if cen.shape[0]:
        pu = (cen - f.centroid) @ u
        pv = (cen - f.centroid) @ v
        u0, u1, v0, v1 = float(pu.min()), float(pu.max()), float(pv.min()), float(pv.max())
    else:
        u0 = u1 = v0 = v1 = 0.0
    corners = [f.centroid + a * u + b * v for a, b in ((u0, v0), (u1, v0), (u1, v1), (u0, v1))]
    contrib = rec.contributions
    return {
        "id": plane_id,
        "normal": [float(x) for x in f.normal],
        "d": float(f.d),
        "n_points": rec.stats.n,
        "robots": sorted(contrib),
        "extent": {
            "centroid": [float(x) for x in f.centroid],
            "u": [float(x) for x in u],
            "v": [float(x) for x in v],
            "u_range_m": [u0, u1],
            "v_range_m": [v0, v1],
            "size_m": [u1 - u0, v1 - v0],
            "corners": [[float(x) for x in c] for c in corners],
            "aabb_min": [x * q for x in rec.aabb_min],
            "aabb_max": [x * q for x in rec.aabb_max],
        },
        "rms_m": f.rms_m,
        "updated_ns": max(c.last_ns for c in contrib.values()),
        "created_ns": min(c.first_ns for c in contrib.values()),
        "n_obs": rec.n_obs,
        "contributions": {
            r: {"n_points": c.n_points, "first_ns": c.first_ns, "last_ns": c.last_ns} for r, c in contrib.items()
        },
    }


def rms_distance(fa: PlaneFit, fb: PlaneFit, noise_var_m2: float = 0.0) -> float:
    """RMS distance of the points behind fit ``fa`` to the plane of fit ``fb`` (metres), from moments only;
    ``noise_var_m2``: the expected variance of ``fa``'s points (m^2), taken out."""
    off = float(fb.normal @ fa.centroid + fb.d)
    return math.sqrt(off * off + max(float(fb.normal @ fa.cov @ fb.normal) - noise_var_m2, 0.0))


def added_rms_m(
    fa: PlaneFit,
    n_a: int,
    fb: PlaneFit,
    n_b: int,
    merged: PlaneFit,
    own_max_m: float,
    var: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> float:
    """The RMS thickness (metres) that fusing two planes adds to what their points already scatter about their
    own planes: ``sqrt(merged.rms^2 - (n_a r_a^2 + n_b r_b^2) / (n_a + n_b))`` (0 when the fused plane is no
    thicker than its parts, pooled), where a part's own RMS ``r`` counts only up to ``own_max_m``.

    ``fa``, ``fb`` are the parts' fits (``n_a``, ``n_b`` points), ``merged`` the fit of their summed statistics.
    What is left is the between-parts scatter along the fused normal: for parts ``s`` apart (the RMS distance
    between the two planes over their points: offset and relative tilt) it is ``s * sqrt(w_a * w_b)`` with
    ``w`` the point shares, so two thin planes of similar size 6 cm apart add 3 cm, while a view lying within a
    face's own thickness adds almost nothing, however thick the face's plane already is. The cap keeps a plane
    from excusing its own thickness without end: a fusion admitted with ``added <= own_max_m`` is at most
    ``sqrt(2) * own_max_m`` thick, and a plane that got thicker (views that bridged planes) takes no more than a
    thin one. ``var``: the expected variances (m^2) of the points of ``fa``, ``fb`` and ``merged``, taken out of
    each RMS first (:func:`mapping.noisy_faces.excess_rms_m`).
    """
    n = n_a + n_b
    ra, rb, rm = (excess_rms_m(f.rms_m, v) for f, v in zip((fa, fb, merged), var, strict=True))
    pooled = (n_a * min(ra, own_max_m) ** 2 + n_b * min(rb, own_max_m) ** 2) / n
    return math.sqrt(max(rm**2 - pooled, 0.0))


class _Boxes:
    """The map planes' bounding boxes (quanta) as arrays: one vectorized overlap test against every plane.

    Association tests a new observation against every plane whose box it touches; a map of a fleet spread over
    a harbour holds hundreds of planes, and a Python loop over all of them would bound the merger. Rows of
    removed planes stay (id -1, an empty box) until the arrays are rebuilt.
    """

    def __init__(self) -> None:
        self.ids = np.full(0, -1, np.int64)
        self.lo = np.zeros((0, 3), np.float64)
        self.hi = np.zeros((0, 3), np.float64)
        self.row: dict[int, int] = {}
        self.used = 0

    def put(self, pid: int, rec: PlaneRecord) -> None:
        r = self.row.get(pid)
        if r is None:
            if self.used == len(self.ids):
                grow = max(16, len(self.ids))
                self.ids = np.concatenate([self.ids, np.full(grow, -1, np.int64)])
                self.lo = np.concatenate([self.lo, np.full((grow, 3), np.inf)])
                self.hi = np.concatenate([self.hi, np.full((grow, 3), -np.inf)])
            r = self.row[pid] = self.used
            self.used += 1
            self.ids[r] = pid
        self.lo[r] = rec.aabb_min
        self.hi[r] = rec.aabb_max

    def drop(self, pid: int) -> None:
        r = self.row.pop(pid)
        self.ids[r] = -1
        self.lo[r] = np.inf
        self.hi[r] = -np.inf

    def touching(self, rec: PlaneRecord, gaps: FloatArray) -> list[int]:
        """Ids (ascending) of the planes whose boxes come within ``gaps`` (quanta per axis) of ``rec``'s: the test
        of :meth:`PlaneMap._touch`, for all planes at once (the same float comparisons, so the same answers)."""
        lo = np.asarray(rec.aabb_min, np.float64)
        hi = np.asarray(rec.aabb_max, np.float64)
        n = self.used
        near = np.all((lo - gaps <= self.hi[:n]) & (self.lo[:n] - gaps <= hi), axis=1)
        return sorted(int(i) for i in self.ids[:n][near])


class PlaneMap:
    """Planes by id; :meth:`add` associates and fuses one observation. Not thread-safe (the builder locks).

    ``planes`` may be filled directly only while the map is being built (loading a saved map): the box index
    follows :meth:`add`'s own changes and is rebuilt when the number of planes disagrees with it.
    """

    def __init__(self, cfg: MapConfig) -> None:
        self.cfg = cfg
        self.planes: dict[int, MapPlane] = {}
        self.next_id = 1
        self._boxes = _Boxes()
        q = cfg.quantum_m
        self._gaps = np.array([cfg.merge_gap_m / q, cfg.merge_gap_m / q, cfg.merge_gap_down_m / q])
        # candidates for matches(): the bands' longer reach along down (matches() decides which rule applies)
        down = max(cfg.merge_gap_down_m, cfg.merge_band_gap_down_m)
        self._match_gaps = np.array([cfg.merge_gap_m / q, cfg.merge_gap_m / q, down / q])

    def _touching(self, rec: PlaneRecord, gaps: FloatArray | None = None) -> list[int]:
        """Ids (ascending) of the planes :meth:`_touch` accepts against ``rec`` (with ``gaps``, quanta per axis:
        those whose boxes come that near)."""
        if len(self._boxes.row) != len(self.planes):
            self._boxes = _Boxes()
            for pid in sorted(self.planes):
                self._boxes.put(pid, self.planes[pid].record)
        return self._boxes.touching(rec, self._gaps if gaps is None else gaps)

    def _put(self, plane: MapPlane) -> None:
        self.planes[plane.id] = plane
        self._boxes.put(plane.id, plane.record)

    def _pop(self, pid: int) -> PlaneRecord:
        self._boxes.drop(pid)
        return self.planes.pop(pid).record

    def __len__(self) -> int:
        return len(self.planes)

    def _touch(self, a: PlaneRecord, b: PlaneRecord, gap_down_m: float | None = None) -> bool:
        """Whether the boxes touch, inflated by ``merge_gap_m`` and along down by ``gap_down_m`` (by default
        ``merge_gap_down_m``)."""
        q = self.cfg.quantum_m
        down = self.cfg.merge_gap_down_m if gap_down_m is None else gap_down_m
        gaps = (self.cfg.merge_gap_m / q, self.cfg.merge_gap_m / q, down / q)
        return all(
            a.aabb_min[i] - gaps[i] <= b.aabb_max[i] and b.aabb_min[i] - gaps[i] <= a.aabb_max[i] for i in range(3)
        )

    def matches(
        self, a: PlaneRecord, fa: PlaneFit, b: PlaneRecord, fb: PlaneFit, a_normal: FloatArray | None = None
    ) -> bool:
        """Whether two planes (records and fits) may fuse (see the module docstring).

        ``a_normal`` replaces ``fa.normal`` in the angle test (an observation's window normal, better
        conditioned than the fit of its new points alone). The offset test passes when either plane's points lie
        within ``merge_offset_m`` (RMS) of the other plane: a narrow observation whose own normal is poorly
        determined still joins the plane its points lie on.
        """
        cfg = self.cfg
        na = fa.normal if a_normal is None else a_normal
        var = (self._var(a), self._var(b), self._var(a + b) if a.noise or b.noise else 0.0)
        if self._touch(a, b):
            off = min(rms_distance(fa, fb, var[0]), rms_distance(fb, fa, var[1]))
            if _angle_deg(na, fb.normal) > cfg.merge_angle_deg or off > cfg.merge_offset_m:
                return False
        elif not self.bands(a, fa, b, fb, na):
            return False
        merged = fit_parts(
            a.stats + b.stats,
            tuple(x + y for x, y in zip(a.within, b.within, strict=True)),
            (a.orient[0] + b.orient[0], a.orient[1] + b.orient[1], a.orient[2] + b.orient[2]),
            cfg.quantum_m,
            cfg.between_window_weight,
        )
        if excess_rms_m(merged.rms_m, var[2]) <= cfg.merge_max_rms_m:  # (thin as a whole)
            return True
        return added_rms_m(fa, a.stats.n, fb, b.stats.n, merged, cfg.merge_max_rms_m, var) <= cfg.merge_added_rms_m

    def _var(self, rec: PlaneRecord) -> float:
        """The mean expected variance of ``rec``'s points (m^2; 0 without the tilt prior's option)."""
        return mean_var_m2(rec.noise, rec.stats.n, self.cfg.quantum_m)

    def bands(
        self, a: PlaneRecord, fa: PlaneFit, b: PlaneRecord, fb: PlaneFit, a_normal: FloatArray | None = None
    ) -> bool:
        """Whether two planes whose boxes are too far apart along down to touch are bands of one vertical face.

        The horizontal laser sheets scan a vertical face in one band per robot depth; a face crossed at depths
        more than ``merge_gap_down_m`` apart leaves bands whose boxes do not touch, though the face is one plane
        over its height. They are one face when the boxes still touch in north and east (inflated by
        ``merge_gap_m``: the same stretch of face), their gap along down is at most ``merge_band_gap_down_m``,
        both normals lie within ``merge_band_tilt_deg`` of horizontal and within ``merge_band_angle_deg`` of each
        other, either plane's points lie within ``merge_band_offset_m`` (RMS) of the other, and both are confirmed
        (``min_obs_publish``: one odd window must not stretch a face over the tank's depth). Those tolerances
        are tighter than ``merge_angle_deg`` and ``merge_offset_m``: two accurate bands of one face agree to a few
        centimetres, while a copy that a pose error set a decimetre off the face must stay apart (navigation
        registers to it and the benchmark counts it). ``merge_band_gap_down_m`` 0 (the default) turns the rule off.
        """
        cfg = self.cfg
        if cfg.merge_band_gap_down_m <= 0 or not self._touch(a, b, cfg.merge_band_gap_down_m):
            return False
        if not (self._published(a) and self._published(b)):
            return False
        na = fa.normal if a_normal is None else a_normal
        max_down = math.sin(math.radians(cfg.merge_band_tilt_deg))
        if abs(float(na[2])) > max_down or abs(float(fb.normal[2])) > max_down:
            return False
        if _angle_deg(na, fb.normal) > cfg.merge_band_angle_deg:
            return False
        return min(rms_distance(fa, fb), rms_distance(fb, fa)) <= cfg.merge_band_offset_m

    def same_face(self, a: PlaneRecord, fa: PlaneFit, b: PlaneRecord, fb: PlaneFit) -> bool:
        """Whether two touching planes are one surface seen from poses that disagree (see :mod:`mapping.same_face`):
        normals within ``same_face_angle_deg``, points within ``same_face_offset_m`` (RMS, either way round), and
        at least ``same_face_share`` of the smaller one's points where both cover the face over a whole block."""
        cfg = self.cfg
        if cfg.same_face_offset_m <= 0 or _angle_deg(fa.normal, fb.normal) > cfg.same_face_angle_deg:
            return False
        if min(rms_distance(fa, fb), rms_distance(fb, fa)) > cfg.same_face_offset_m:
            return False
        n = fa.normal + fb.normal
        u, v = in_plane_axes(n / np.linalg.norm(n))
        q = cfg.quantum_m
        share = shared_fraction(
            a.voxels.centroids_m(q),
            a.voxels.counts,
            b.voxels.centroids_m(q),
            b.voxels.counts,
            u,
            v,
            cfg.same_face_cell_m,
            cfg.same_face_block_cells,
        )
        return share >= cfg.same_face_share

    def _fuse(self, a: PlaneRecord, b: PlaneRecord, fb: PlaneFit | None = None) -> PlaneRecord:
        """``a + b`` for two records of one surface that pose errors set apart: the one fewer robots (then fewer
        points) made moves along the other's normal onto the other's plane first (:meth:`PlaneRecord.shifted`)."""
        q = self.cfg.quantum_m
        ref, other = (a, b) if (len(a.contributions), a.stats.n) >= (len(b.contributions), b.stats.n) else (b, a)
        f_ref = ref.fit(q, self.cfg.between_window_weight)
        f_other = fb if other is b and fb is not None else other.fit(q, self.cfg.between_window_weight)
        step = -(float(f_ref.normal @ f_other.centroid) + f_ref.d) * f_ref.normal / q
        t = np.rint(step).astype(np.int64)
        vq = max(1, round(self.cfg.export_voxel_m / q))
        return ref + other.shifted((int(t[0]), int(t[1]), int(t[2])), vq)

    def can_create(self, obs: PlaneRecord, f: PlaneFit) -> bool:
        """Whether an observation is good enough to start a new plane on its own (not line-like, thin)."""
        return f.width_m >= self.cfg.min_width_m and excess_rms_m(f.rms_m, self._var(obs)) <= self.cfg.max_rms_m

    def _published(self, rec: PlaneRecord) -> bool:
        return rec.n_obs >= self.cfg.min_obs_publish

    def add(self, obs: PlaneRecord) -> list[MapChange]:
        """Associate and fuse one observation; returns the changes (the plane it joined or started, removals).

        A plane ``i`` fused into plane ``j`` is reported as ``MapChange.removed(i, j)``. An observation that matches
        nothing and cannot start a plane of its own (line-like) is dropped and gives no change. Tentative planes
        (fewer than ``min_obs_publish`` observations) are not reported.
        """
        cfg = self.cfg
        if obs.stats.n < 3:
            return []
        f_obs = obs.fit(cfg.quantum_m, cfg.between_window_weight)
        hint = np.array(obs.hint_normal) if obs.hint_normal is not None else None
        hits = [
            pid
            for pid in self._touching(obs, self._match_gaps)
            if self.matches(obs, f_obs, self.planes[pid].record, self.planes[pid].fit, hint)
        ]
        same = False
        if not hits and self.can_create(obs, f_obs):
            # a view of a face from a pose off by more than merge_offset_m is still that face
            same = True
            hits = [
                pid
                for pid in self._touching(obs)
                if self.same_face(obs, f_obs, self.planes[pid].record, self.planes[pid].fit)
            ]
        if not hits:
            if not self.can_create(obs, f_obs):
                return []
            pid = self.next_id
            self.next_id += 1
            self._put(MapPlane(pid, replace(obs, hint_normal=None), cfg))
            return [MapChange.updated(self.planes[pid])] if self._published(obs) else []
        keep = hits[0]
        rec = self._fuse(self.planes[keep].record, obs, f_obs) if same else self.planes[keep].record + obs
        removed: list[int] = []
        for pid in hits[1:]:
            gone = self._pop(pid)
            rec = self._fuse(rec, gone) if same else rec + gone
            if self._published(gone):
                removed.append(pid)
        # Cascade: the grown plane may now meet others.
        while True:
            grown = MapPlane(keep, rec, cfg)
            more: list[tuple[int, bool]] = []
            for pid in self._touching(rec, self._match_gaps):
                if pid == keep:
                    continue
                other, f_other = self.planes[pid].record, self.planes[pid].fit
                if self.matches(rec, grown.fit, other, f_other):
                    more.append((pid, False))
                elif self._touch(rec, other) and self.same_face(rec, grown.fit, other, f_other):
                    more.append((pid, True))
            if not more:
                break
            for pid, moved in more:
                gone = self._pop(pid)
                rec = self._fuse(rec, gone) if moved else rec + gone
                if self._published(gone):
                    removed.append(pid)
        self._put(MapPlane(keep, rec, cfg))
        changes = [MapChange.updated(self.planes[keep])] if self._published(rec) else []
        changes.extend(MapChange.removed(pid, keep) for pid in removed)
        return changes

    def to_json(self, include_tentative: bool = False) -> list[dict[str, Any]]:
        """The planes as dicts, by id; only confirmed ones (``n_obs >= min_obs_publish``) unless asked."""
        return [
            self.planes[pid].to_json()
            for pid in sorted(self.planes)
            if include_tentative or self.planes[pid].record.n_obs >= self.cfg.min_obs_publish
        ]


def record_to_wire(rec: PlaneRecord) -> dict[str, Any]:
    """One observation as plain data for a plane worker's message (lossless: :func:`record_from_wire` gives
    back an equal record, ``hint_normal`` included). The exact integer sums can outgrow 64 bits, so they travel
    as decimal strings; the voxel arrays as little-endian int64 bytes."""
    return {
        "stats": [str(v) for v in rec.stats.to_list()],
        "orient": [str(v) for v in rec.orient],
        "aabb_min": list(rec.aabb_min),
        "aabb_max": list(rec.aabb_max),
        "contributions": {k: [c.n_points, c.first_ns, c.last_ns] for k, c in rec.contributions.items()},
        "vox_keys": rec.voxels.keys.astype("<i8").tobytes(),
        "vox_counts": rec.voxels.counts.astype("<i8").tobytes(),
        "vox_sums": rec.voxels.sums.astype("<i8").tobytes(),
        "n_obs": rec.n_obs,
        "hint": list(rec.hint_normal) if rec.hint_normal is not None else None,
        "within": [str(v) for v in rec.within],
        "noise": str(rec.noise),
    }


def record_from_wire(data: dict[str, Any]) -> PlaneRecord:
    """The observation :func:`record_to_wire` encoded (raises KeyError/ValueError/TypeError when malformed)."""
    o = [int(v) for v in data["orient"]]
    lo = [int(v) for v in data["aabb_min"]]
    hi = [int(v) for v in data["aabb_max"]]
    w = [int(v) for v in data["within"]]
    hint = data.get("hint")
    keys = np.frombuffer(data["vox_keys"], "<i8").astype(np.int64)
    if len(o) != 3 or len(lo) != 3 or len(hi) != 3 or len(w) != 6:
        msg = "observation: orient, aabb_min, aabb_max need 3 values, within 6"
        raise ValueError(msg)
    return PlaneRecord(
        PlaneStats.from_list([int(v) for v in data["stats"]]),
        (o[0], o[1], o[2]),
        (lo[0], lo[1], lo[2]),
        (hi[0], hi[1], hi[2]),
        {str(k): Contribution(int(v[0]), int(v[1]), int(v[2])) for k, v in data["contributions"].items()},
        VoxelSet(
            keys,
            np.frombuffer(data["vox_counts"], "<i8").astype(np.int64),
            np.frombuffer(data["vox_sums"], "<i8").astype(np.int64).reshape(-1, 3),
        ),
        int(data["n_obs"]),
        (float(hint[0]), float(hint[1]), float(hint[2])) if hint is not None else None,
        (w[0], w[1], w[2], w[3], w[4], w[5]),
        int(data.get("noise", 0)),
    )
