"""The tuning of the per-robot pose graph (:class:`mapping.posegraph.GraphNav`) and the gated setting measured for
depth-only fleets (:data:`TRACKED`)."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class GraphConfig:
    """Tuning of :class:`GraphNav` (metres, seconds, degrees where named ``_deg``).

    ``velocity_walk_m_s``: the velocity's random walk (m/s per sqrt(s)); ``relinearize_threshold`` /
    ``relinearize_skip``: iSAM2 relinearises, every that many updates, the variables whose estimate moved more than
    that (rad or m; a pose's heading ``relinearize_heading_rad``) from where their factors were linearised
    (:func:`mapping.graph_factors.isam2`); ``max_speed_m_s`` bounds one scan's move
    (a weak isotropic prior on each increment); ``compass_every_s`` / ``compass_bias_deg``: a heading prior that
    often, that wide; ``map_gate_chi2``: a registration whose correction lies beyond the marginal covariance (3
    degrees of freedom) is a wrong association and left out; ``map_min_sigma_m``: floor of a plane's residual
    sigma (planes are not exact); ``own_min_age_s``: own planes first seen at least that long before count as loop
    closures (younger ones carry what the odometry already says); ``own_sigma_m``: their residual sigma (a plane
    made from several poses); ``observed_std_m``: a registration's direction counts where it alone pins the pose
    within this (the heading at a 2 m lever); ``window_s`` / ``rebase_every_s``: the bounded window;
    ``place_std_m``: clouds are placed while the horizontal standard deviation is below it; ``lost_std_m``: beyond
    it no plane is registered. ``stretch_s`` (off: ``inf``): the others' planes that one robot made (the most points)
    within one stretch of this many seconds share one horizontal offset (a 2-D variable, prior
    ``map_plane_sigma_m``; each plane's own offset then ``stretch_plane_sigma_m``): one robot's planes of one
    stretch carry one drift, not independent errors. ``odometry_observed_std_m`` (off: ``inf``): a scan
    increment's direction counts only where it pins the move within this (m; see
    :func:`mapping.odometry.own_increment`); ``odometry_prior_m_s`` widens the prior the scan matching starts
    from by this speed (m/s; 0: the velocity walk's alone). The guards of the odometry on a broken track
    (:mod:`mapping.graph_odometry`, all off): ``odometry_speed_bound`` how the bound on one scan's move from
    ``max_speed_m_s`` joins the scan's move (``added``: its information added, the move the scan's;
    ``prediction`` / ``rest``: combined with the move by their information, centred at the prediction or at no
    move); ``odometry_spread_m`` (0: off) the registration run again from starts that far either side along its
    weakest direction, the spread of the results bounding its information; ``odometry_residual_scale`` the scan's
    information divided by its residuals' scatter (``OdometryConfig.residual_scale``); ``odometry_guard_broken_only``
    those three only while the track is broken. ``second_hypothesis`` (off): a plane factor
    is left out when another plane would explain the scan's points on it within the pose's marginal
    (:func:`mapping.graph_gate.ambiguous`).
    ``track_break_std_m``: past this horizontal std the track is broken and nothing more is placed
    (:class:`mapping.graph_gate.TrackGate`; ``inf``: never), and so it does where one scan moves the position
    beyond ``track_jump_chi2`` (squared Mahalanobis, its marginal before the scan). ``relocalize``: a broken
    track is taken up again
    from a scan that matches one place alone (:func:`mapping.relocalize.unique_place`, tried every
    ``relocalize_every_s``, within ``relocalize_max_m`` and the speed bound since the break), that place then a
    prior of ``relocalize_sigma_m``. ``verify_every_s``: that often an unbroken track is checked the same way
    (within ``verify_radius_m``); a unique place more than ``verify_tol_m`` from the estimate re-anchors it there.
    ``verify_anchor_m`` (off: ``inf``): a passed check whose place lies more than this from the estimate (but
    within ``verify_tol_m``) also becomes a prior of ``relocalize_sigma_m`` on that pose before the held clouds
    are committed, so they go in where the map has the faces rather than a few centimetres beside them.
    ``verify_own_share`` (off: 1): the checks (and the hold's checks of each held cloud) leave out the planes the
    robot contributed more than this share of the points to (its own copies would vouch for its slide).
    ``hold_until_verified``: clouds are held until the next check passes (:mod:`mapping.graph_hold`; after a slide
    or a break each is checked alone within ``hold_check_radius_m``; while clouds wait, a check that found no unique
    place is tried again after ``hold_retry_s``; a held cloud whose scan pinned one wall goes in only where at least
    ``hold_one_wall_share`` of its points fit the map's planes: the rest may be a face along the free direction).
    ``commit_at_place`` (off): at a passed check the held clouds go in moved by the check's place minus the
    estimate there (the place, a consensus of the map's planes, not the graph's estimate, says where they are), and
    stay there (their poses frozen: the graph's later estimates would take them back).
    ``heading_check`` (off): at the checks, at most every ``heading_every_s``, the heading is also taken from the
    direction of the walls the scan sees (:mod:`mapping.graph_heading`), against the planes the robot contributed
    at most ``heading_own_share`` of the points to (0: the others' alone); a prior on that pose's heading, its
    standard deviation ``heading_floor_deg`` at least; an offset beyond ``heading_max_deg`` is left out.
    """

    velocity_walk_m_s: float = 0.1
    relinearize_threshold: float = 0.1
    relinearize_skip: int = 10
    relinearize_heading_rad: float = 0.1
    odometry_info_scale: float = 0.3
    odometry_observed_std_m: float = math.inf
    odometry_prior_m_s: float = 0.0
    odometry_spread_m: float = 0.0
    odometry_speed_bound: str = "added"
    odometry_residual_scale: bool = False
    odometry_guard_broken_only: bool = False
    max_speed_m_s: float = 0.6
    compass_every_s: float = 5.0
    compass_bias_deg: float = 3.0
    map_gate_chi2: float = 16.0
    map_min_sigma_m: float = 0.02
    map_plane_sigma_m: float = 0.05
    map_plane_sigma_deg: float = 1.0
    stretch_s: float = math.inf
    stretch_plane_sigma_m: float = 0.02
    own_min_age_s: float = 15.0
    own_sigma_m: float = 0.03
    own_planes: bool = True
    window_s: float = 120.0
    rebase_every_s: float = 30.0
    place_std_m: float = 0.1
    boot_std_m: float = 1.0
    lost_std_m: float = 0.3
    observed_std_m: float = 0.1
    plane_gate_m: float = 0.1
    second_hypothesis: bool = False
    track_break_std_m: float = math.inf
    track_jump_chi2: float = math.inf
    relocalize: bool = False
    relocalize_every_s: float = 2.0
    relocalize_max_m: float = 1.5
    relocalize_sigma_m: float = 0.03
    verify_every_s: float = math.inf
    verify_radius_m: float = 0.5
    verify_tol_m: float = 0.08
    verify_anchor_m: float = math.inf
    verify_own_share: float = 1.0
    hold_until_verified: bool = False
    hold_check_radius_m: float = 0.3
    hold_retry_s: float = 0.5
    hold_one_wall_share: float = 0.6
    commit_at_place: bool = False
    heading_check: bool = False
    heading_every_s: float = 2.0
    heading_floor_deg: float = 0.3
    heading_max_deg: float = 5.0
    heading_own_share: float = 0.99


#: The gated graph measured for depth-only fleets (docs/navigation-design.md, "Tracked anchors"): an unbroken track, a
#: broken one taken up again only where a scan matches one place alone, checked every 2 s, a passed check more than 3 cm
#: from its place anchoring the pose there (within 6 cm); with ``NavConfig.frame_graph_launches``. What
#: ``lrsensor base --no-fix graph`` (the default) runs.
TRACKED = GraphConfig(
    second_hypothesis=True,
    track_break_std_m=0.1,
    relocalize=True,
    verify_every_s=2.0,
    verify_tol_m=0.06,
    verify_anchor_m=0.03,
    hold_until_verified=True,
)
