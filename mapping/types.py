"""Shared value types of the mapping package: the configuration, the exact plane statistics, the map changes.

Statistics are kept as *exact integers*: every point is quantized to ``quantum_m`` (0.1 mm by default, far below
the sensor's noise) and the sums of points and of outer products are Python integers. Fusing two planes is then
plain integer addition, which is associative and commutative: the map does not depend on the order in which
observations were fused, and a persisted map reloads bit for bit.

What leaves the package when the map changes is a :class:`MapChange`, one per plane: either the plane as it now
is (created, grown, or fused with others) or the removal of a plane that was fused into another. It carries the
map's own :class:`~mapping.plane_map.MapPlane` (immutable once in a change: the map replaces a plane, it never
edits one), not its JSON form: the plane's serving dict is built only where a change is published
(``services.mapfeed``), and a base station with no one listening never builds it.
"""

from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from .errors import MapConfigError, MappingError

if TYPE_CHECKING:
    from .plane_map import MapPlane

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: int64 limit used to size exact-sum chunks.
_INT64_SAFE = 2**62


@dataclass(frozen=True)
class MapConfig:
    """Configuration of the map builder. Lengths in metres, angles in degrees (``_deg``), times in seconds.

    Windows and rate:
        max_cloud_rate_hz: per robot, the map takes at most this many clouds per second of capture time (0, the
            default: every cloud); the others still make the robot's track and are counted
            (:attr:`~mapping.MapBuilder.rate_skipped`, ``map.rate_skipped`` in the base status). An operator option
            for a map that cannot keep up; plane workers (docs/scaling.md) are the way to keep every cloud.
        window_clouds: clouds per robot kept as context for extraction (>= ``extract_every_clouds``).
        extract_every_clouds: run extraction for a robot after this many new clouds ...
        extract_every_points: ... or this many new points ...
        extract_every_s: ... or when the new clouds span this much capture time.
        window_max_age_s: context clouds older than this (relative to the newest) are dropped.
        max_range_m: points farther than this from the vehicle are dropped (attitude noise grows with range).
        cloud_voxel_m: each incoming cloud keeps one point per voxel of this size (the stripes are sampled every
            ~1 mm per metre of range: near clouds are thinned several times, which bounds the map's cost per cloud).

    Extraction (per window, see :mod:`mapping.planes`):
        voxel_m: voxel size of the down-sampled window that RANSAC sees.
        cell_m: cell size of the local-normal grid; a cell's normal comes from its 3x3x3 block of cells, so the
            block (3 * cell_m) must span both laser lines (0.1 m apart on a wall).
        grow_angle_deg: neighbouring cells join one region when their normals agree within this angle.
        cell_planarity: a cell normal is valid when sqrt(l0) <= cell_planarity * sqrt(l1) (l0 <= l1 <= l2).
        range_noise_per_m: the sensor's expected range error per squared metre of range, k (1/m: a point at
            range r is expected k r^2 off; about the stripe's sub-pixel error over focal length x baseline).
            When > 0, a cell's l0 loses (k r^2)^2 before the planarity test and a region's RANSAC inlier distance
            grows with it (:mod:`mapping.planes`). When > 0 it is every cloud's k (an explicit override); 0
            (default): each cloud's own k, from its robot's calibration and ``stripe_sigma_px``
            (:mod:`mapping.range_noise`).
        stripe_sigma_px: the extractor's stripe row error (pixels, standard deviation) that turns a robot's
            calibration into its clouds' k, ``stripe_sigma_px / (f_px c)`` (:func:`lrsensor.range_theory.
            range_error_per_px`); clouds without a calibration (schema 1, traced) keep the fixed thresholds.
            Default 0.0185 px (:data:`mapping.range_noise.STRIPE_SIGMA_PX`, the extractor's row error at 2-2.5 m):
            k 0.002 for the 640x360 camera of the simulated dives, 0.00067 for the paper's 1920x1080 one; 0: off
            (docs/mapping.md, "Range noise").
        tilt_prior_deg: with a range noise (either of the two above), a near-vertical plane's tilt gets a prior of
            this standard deviation about vertical, weighed against its points' expected errors, and its RMS gates
            test the thickness beyond those errors (:mod:`mapping.noisy_faces`; docs/mapping.md, "Noisy far
            faces"). Default 10 deg; 0: off. Clouds without an expected error (no calibration) are not affected.
        distance_threshold_m: RANSAC inlier distance (Open3D ``segment_plane``).
        ransac_iterations, seed: RANSAC iterations; base seed (Open3D's global RNG is re-seeded per call).
        max_planes_per_region: RANSAC peels at most this many planes off one region.
        min_region_points, min_inliers: down-sampled point counts below which a region / plane is ignored.
        min_width_m: the inliers' second principal standard deviation must reach this (rejects a single line).
        min_down_spread_m: the inliers' standard deviation along down must reach this: the two horizontal laser
            sheets cross any face a baseline (0.1 m, std 0.05 m) apart, so a plane made of one stripe and its
            noise (a thin band tilted toward the horizontal, seen in the camera demo) has far less.
        min_extent_m: both in-plane extents (max - min) must reach this.
        max_rms_m: inlier RMS distance to the fitted plane must stay below this.
        max_sagitta_m: a quadratic fit of the window's residuals over the in-plane coordinates may not bend
            more than this over the plane's extent (a coarse curvature gate; frame-to-frame pose noise adds to it).
        max_frame_sagitta_m: the median bulge of the stripes of one frame across the plane may not exceed this
            (:func:`mapping.frame_checks.frame_sagitta`; pose noise cannot fake it: this is what rejects pipes).
        min_sensor_distance_m: a plane passing closer than this to the observing vehicle is the laser sheet
            itself (all hits of one laser are coplanar), not a surface; rejected.
        min_commit_points: full-resolution points an observation needs to enter the map.
        min_obs_frames, min_frame_points: an observation needs at least ``min_obs_frames`` frames of its window
            with ``min_frame_points`` points each on the plane (:func:`mapping.frame_checks.frame_support`): the two
            stripes of one frame always fit a plane, also when that one image was triangulated wrongly.
        min_obs_publish: a plane is served (``map_json``, changes) once this many observations confirmed it; a
            single window's plane stays tentative (one odd window must not put a plane on the map).

    Merging (see :mod:`mapping.plane_map`):
        between_window_weight: a map plane's normal is the smallest axis of ``W + w B``: ``W`` pools the scatter of
            each fused observation (one window of one robot) about its own centroid, ``B`` is the rest of the
            scatter of all points (where the observations sit relative to each other). Navigation drift moves
            whole windows, so it lives in ``B``: with w = 0 (default) a drifting robot cannot tilt a plane; w = 1
            is the plain least-squares fit of all points. The offset ``d`` always averages every point.
        merge_angle_deg: oriented normals within this angle (opposite faces of a thin wall never fuse);
        merge_offset_m: the points of one plane within this RMS distance of the other plane (either way round).
        merge_gap_m: bounding boxes (inflated by this in north and east) must overlap or touch.
        merge_gap_down_m: the same along down: the horizontal laser sheets scan a face in horizontal bands
            (one per robot depth), so bands of one face seen at different depths are expected to leave gaps.
        merge_band_gap_down_m, merge_band_tilt_deg, merge_band_angle_deg, merge_band_offset_m: two planes whose
            boxes are farther apart along down than ``merge_gap_down_m`` (but at most ``merge_band_gap_down_m``;
            0 turns the rule off) and touch in north and east are bands of one vertical face when both normals
            are within ``merge_band_tilt_deg`` of horizontal and ``merge_band_angle_deg`` of each other and their
            points within ``merge_band_offset_m`` (RMS, either way round) of the other plane
            (:meth:`mapping.plane_map.PlaneMap.bands`; both planes confirmed: a single window's band never joins).
            Off by default (docs/mapping.md, "Bands of one face"); 3.0 turns it on.
        serve_band_gap_down_m: the same rule (up to this far apart along down; 0: off) applied only to the map as
            served (:mod:`mapping.served`: ``map_json``), not to the planes navigation registers against.
        serve_copy_offset_m, serve_copy_angle_deg, serve_copy_max_rms_m: also only as served (0: off), two confirmed
            planes whose boxes touch (the same depths) join when their normals lie within ``serve_copy_angle_deg``
            and each one's centroid within ``serve_copy_offset_m`` of the other's plane, up to a joined RMS of
            ``serve_copy_max_rms_m``: copies the map kept apart only because the fused plane would pass
            ``merge_max_rms_m``.
        merge_max_rms_m, merge_added_rms_m: fusion may not make a plane thick: the fused plane's RMS within
            ``merge_max_rms_m``, or the RMS the fusion adds to the parts' own scatter about their planes
            (:func:`mapping.plane_map.added_rms_m`, each part's own counted up to ``merge_max_rms_m``) within
            ``merge_added_rms_m``: a plane as thick as the poses' errors make it still takes views that lie within
            that thickness. The added bound is below the whole one because a looser one (3 cm) let the smoother's
            rebuilt maps fuse more than its re-placed poses could hold (tests/test_nav_smoother.py: the smoothed
            poses ended further from the truth than the filter's); at 2.25 cm the demo's recorded dives give the
            same maps as at 3 cm (``python -m benchmarks.diag_demo_map replay``).
        same_face_offset_m, same_face_angle_deg, same_face_cell_m, same_face_block_cells, same_face_share: two
            planes facing the same way (normals within ``same_face_angle_deg``), within ``same_face_offset_m`` of
            each other (RMS, either way round, as ``merge_offset_m``) are one surface seen from poses that disagree
            when at least ``same_face_share`` of the smaller one's points lie where both cover the face over a
            whole square of ``same_face_block_cells`` x ``same_face_block_cells`` in-plane cells of
            ``same_face_cell_m``: the lasers' rays would have stopped at the nearer one (occlusion,
            :mod:`mapping.same_face`). ``same_face_offset_m`` must stay below ``min_sensor_distance_m`` (the
            vehicle that saw the farther plane was then in front of the nearer one); 0 (the default, see
            docs/mapping.md "Measured") turns the rule off, 0.15 turns it on.

    Storage:
        quantum_m: quantum of the exact integer statistics.
        export_voxel_m: voxel size of the points kept per plane for export.
        track_interval_s: one track sample per robot per this much capture time.
        autosave_every_s: wall-clock seconds between automatic saves (0 disables; needs a state dir).
    """

    max_cloud_rate_hz: float = 0.0
    window_clouds: int = 10
    extract_every_clouds: int = 10
    extract_every_points: int = 40_000
    extract_every_s: float = 1.0
    window_max_age_s: float = 3.0
    max_range_m: float = 5.0
    cloud_voxel_m: float = 0.01

    voxel_m: float = 0.03
    cell_m: float = 0.1
    grow_angle_deg: float = 12.0
    cell_planarity: float = 0.35
    range_noise_per_m: float = 0.0
    stripe_sigma_px: float = 0.0185
    tilt_prior_deg: float = 10.0
    distance_threshold_m: float = 0.03
    ransac_iterations: int = 400
    seed: int = 1234
    max_planes_per_region: int = 3
    min_region_points: int = 25
    min_inliers: int = 25
    min_width_m: float = 0.02
    min_down_spread_m: float = 0.03
    min_extent_m: float = 0.1
    max_rms_m: float = 0.02
    max_sagitta_m: float = 0.015
    max_frame_sagitta_m: float = 0.008
    min_sensor_distance_m: float = 0.2
    min_commit_points: int = 100
    min_obs_frames: int = 2
    min_frame_points: int = 20
    min_obs_publish: int = 2

    between_window_weight: float = 0.0
    merge_angle_deg: float = 40.0
    merge_offset_m: float = 0.06
    merge_gap_m: float = 0.3
    merge_gap_down_m: float = 1.0
    merge_band_gap_down_m: float = 0.0
    merge_band_tilt_deg: float = 10.0
    merge_band_angle_deg: float = 3.0
    merge_band_offset_m: float = 0.045
    serve_band_gap_down_m: float = 3.0
    serve_copy_offset_m: float = 0.0
    serve_copy_angle_deg: float = 1.0
    serve_copy_max_rms_m: float = 0.05
    merge_max_rms_m: float = 0.03
    merge_added_rms_m: float = 0.0225
    same_face_offset_m: float = 0.0
    same_face_angle_deg: float = 3.0
    same_face_cell_m: float = 0.05
    same_face_block_cells: int = 3
    same_face_share: float = 0.2

    quantum_m: float = 1e-4
    export_voxel_m: float = 0.05
    track_interval_s: float = 0.1
    autosave_every_s: float = 10.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                msg = f"MapConfig.{f.name} must be a finite number, got {value!r}"
                raise MapConfigError(msg)
            if f.type == "int" and not isinstance(value, int):
                msg = f"MapConfig.{f.name} must be an integer, got {value!r}"
                raise MapConfigError(msg)
            if (
                f.name
                not in (
                    "seed",
                    "autosave_every_s",
                    "extract_every_s",
                    "max_cloud_rate_hz",
                    "between_window_weight",
                    "same_face_offset_m",
                    "merge_band_gap_down_m",
                    "serve_band_gap_down_m",
                    "serve_copy_offset_m",
                    "range_noise_per_m",
                    "stripe_sigma_px",
                    "tilt_prior_deg",
                )
                and value <= 0
            ):
                msg = f"MapConfig.{f.name} must be > 0, got {value!r}"
                raise MapConfigError(msg)
            if value < 0:
                msg = f"MapConfig.{f.name} must be >= 0, got {value!r}"
                raise MapConfigError(msg)
        if self.window_clouds < self.extract_every_clouds:
            msg = (
                f"MapConfig.window_clouds ({self.window_clouds}) must be >= extract_every_clouds "
                f"({self.extract_every_clouds})"
            )
            raise MapConfigError(msg)
        if self.ransac_iterations < 1 or not 0 < self.cell_planarity < 1:
            msg = "MapConfig: ransac_iterations must be >= 1 and cell_planarity in (0, 1)"
            raise MapConfigError(msg)
        if self.same_face_offset_m >= self.min_sensor_distance_m or self.same_face_share > 1.0:
            msg = (
                f"MapConfig: same_face_offset_m ({self.same_face_offset_m}) must be below min_sensor_distance_m "
                f"({self.min_sensor_distance_m}) and same_face_share ({self.same_face_share}) at most 1"
            )
            raise MapConfigError(msg)
        if self.tilt_prior_deg >= 90.0:
            msg = f"MapConfig.tilt_prior_deg must be below 90, got {self.tilt_prior_deg}"
            raise MapConfigError(msg)
        if self.quantum_m > 0.001:
            msg = f"MapConfig.quantum_m must be <= 1 mm, got {self.quantum_m}"
            raise MapConfigError(msg)

    def to_dict(self) -> dict[str, Any]:
        """The configuration as a JSON-ready dict."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MapConfig:
        """Build from a dict; unknown keys are rejected with a :class:`MapConfigError` naming them."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            msg = f"unknown MapConfig keys: {', '.join(unknown)}"
            raise MapConfigError(msg)
        return cls(**data)


@dataclass(frozen=True)
class PlaneFit:
    """A plane fitted to statistics, in NED metres.

    Attributes:
        centroid: (3,) mean of the points.
        normal: (3,) unit normal (smallest principal axis), sign chosen by the caller's orientation.
        d: offset so that ``normal . p + d = 0``.
        eigvals: (3,) ascending eigenvalues of the covariance (m^2): rms = sqrt(eigvals[0]).
        axes: (3, 3) eigenvectors as columns, ascending (axes[:, 0] is the unoriented normal).
        cov: (3, 3) covariance of the points (m^2).
    """

    centroid: FloatArray
    normal: FloatArray
    d: float
    eigvals: FloatArray
    axes: FloatArray
    cov: FloatArray

    @property
    def rms_m(self) -> float:
        """RMS distance of the points to the plane, metres."""
        return float(math.sqrt(max(float(self.eigvals[0]), 0.0)))

    @property
    def width_m(self) -> float:
        """Second principal standard deviation (small for a line-like point set), metres."""
        return float(math.sqrt(max(float(self.eigvals[1]), 0.0)))


def scatter_matrix(upper: tuple[int, ...], scale: float) -> FloatArray:
    """(3, 3) symmetric float matrix from an exact upper triangle ``(xx, xy, xz, yy, yz, zz)`` times ``scale``."""
    xx, xy, xz, yy, yz, zz = (float(v) * scale for v in upper)
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


@dataclass(frozen=True)
class PlaneStats:
    """Exact sufficient statistics of a point set, in integer quanta (``q`` metres each).

    Attributes:
        n: number of points.
        s: sum of the quantized points (3 ints).
        ss: sum of the quantized outer products, upper triangle ``(xx, xy, xz, yy, yz, zz)``.
    """

    n: int
    s: tuple[int, int, int]
    ss: tuple[int, int, int, int, int, int]

    @classmethod
    def zero(cls) -> PlaneStats:
        """The empty statistics."""
        return cls(0, (0, 0, 0), (0, 0, 0, 0, 0, 0))

    @classmethod
    def from_quantized(cls, points_q: IntArray) -> PlaneStats:
        """Statistics of quantized points ``points_q`` (N, 3) int64, exact (int64 chunks, Python-int totals)."""
        p = np.asarray(points_q, dtype=np.int64)
        n = int(p.shape[0])
        if n == 0:
            return cls.zero()
        biggest = int(np.abs(p).max()) + 1
        chunk = max(1, _INT64_SAFE // (biggest * biggest))
        s = [0, 0, 0]
        ss = [0, 0, 0, 0, 0, 0]
        pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
        for start in range(0, n, chunk):
            part = p[start : start + chunk]
            part_s = part.sum(axis=0)
            for i in range(3):
                s[i] += int(part_s[i])
            for k, (i, j) in enumerate(pairs):
                ss[k] += int(np.dot(part[:, i], part[:, j]))
        return cls(n, (s[0], s[1], s[2]), (ss[0], ss[1], ss[2], ss[3], ss[4], ss[5]))

    def __add__(self, other: PlaneStats) -> PlaneStats:
        return PlaneStats(
            self.n + other.n,
            (self.s[0] + other.s[0], self.s[1] + other.s[1], self.s[2] + other.s[2]),
            (
                self.ss[0] + other.ss[0],
                self.ss[1] + other.ss[1],
                self.ss[2] + other.ss[2],
                self.ss[3] + other.ss[3],
                self.ss[4] + other.ss[4],
                self.ss[5] + other.ss[5],
            ),
        )

    def fit(self, quantum_m: float) -> PlaneFit:
        """Least-squares plane of the points (eigen-decomposition of the exact scatter), NED metres.

        The centred scatter ``n * SS - s s^T`` is formed in exact integers before conversion to float, so the
        fit does not lose precision far from the NED origin. Raises ``ValueError`` for fewer than 3 points.
        """
        n = self.n
        if n < 3:
            msg = f"a plane needs at least 3 points, got {n}"
            raise ValueError(msg)
        s = self.s
        cov = scatter_matrix(self.centred_scatter(), quantum_m * quantum_m / (float(n) * float(n)))
        eigvals, axes = np.linalg.eigh(cov)
        centroid = np.array([float(s[0]) / n, float(s[1]) / n, float(s[2]) / n]) * quantum_m
        normal = axes[:, 0].copy()
        return PlaneFit(centroid, normal, float(-normal @ centroid), eigvals, axes, cov)

    def centred_scatter(self) -> tuple[int, int, int, int, int, int]:
        """``n * SS - s s^T`` (upper triangle), exact: n^2 times the covariance, in quanta^2."""
        n, s = self.n, self.s
        xx, xy, xz, yy, yz, zz = self.ss
        return (
            n * xx - s[0] * s[0],
            n * xy - s[0] * s[1],
            n * xz - s[0] * s[2],
            n * yy - s[1] * s[1],
            n * yz - s[1] * s[2],
            n * zz - s[2] * s[2],
        )

    def to_list(self) -> list[int]:
        """``[n, s0, s1, s2, xx, xy, xz, yy, yz, zz]`` as exact (possibly big) integers."""
        return [self.n, *self.s, *self.ss]

    @classmethod
    def from_list(cls, values: list[int]) -> PlaneStats:
        """Inverse of :meth:`to_list`."""
        if len(values) != 10 or not all(isinstance(v, int) and not isinstance(v, bool) for v in values):
            msg = f"plane statistics must be 10 integers, got {values!r}"
            raise ValueError(msg)
        v = values
        return cls(v[0], (v[1], v[2], v[3]), (v[4], v[5], v[6], v[7], v[8], v[9]))


class ChangeKind(enum.Enum):
    """What happened to one plane of the map."""

    #: the plane was created, grew, or absorbed others: :attr:`MapChange.plane` is its new state
    UPDATED = "updated"
    #: the plane was fused into another one: :attr:`MapChange.merged_into` names the plane that holds it now
    REMOVED = "removed"


@dataclass(frozen=True)
class MapChange:
    """One change of the shared map, as :meth:`mapping.MapBuilder.add_cloud` and ``flush`` return them.

    Attributes:
        kind: :attr:`ChangeKind.UPDATED` or :attr:`ChangeKind.REMOVED`.
        plane_id: the id of the plane that changed.
        plane: the plane as it now is (``UPDATED`` only; ``plane.to_json()`` is its serving form, the one
            ``MapBuilder.map_json`` lists).
        merged_into: the id of the plane it was fused into (``REMOVED`` only).
    """

    kind: ChangeKind
    plane_id: int
    plane: MapPlane | None = None
    merged_into: int | None = None

    def __post_init__(self) -> None:
        if self.kind is ChangeKind.UPDATED:
            if self.plane is None or self.plane.id != self.plane_id or self.merged_into is not None:
                msg = f"an updated plane {self.plane_id} needs that plane and no merged_into"
                raise MappingError(msg)
        elif self.plane is not None or self.merged_into is None:
            msg = f"a removed plane {self.plane_id} needs merged_into and no plane"
            raise MappingError(msg)

    @classmethod
    def updated(cls, plane: MapPlane) -> MapChange:
        """The new state of ``plane``."""
        return cls(ChangeKind.UPDATED, plane.id, plane)

    @classmethod
    def removed(cls, plane_id: int, merged_into: int) -> MapChange:
        """Plane ``plane_id`` was fused into plane ``merged_into``."""
        return cls(ChangeKind.REMOVED, plane_id, merged_into=merged_into)
