"""The map as served: bands of one vertical face joined, while navigation keeps registering to the planes as built.

The horizontal laser sheets scan a vertical face in one band per robot depth. A face crossed at depths more than
``MapConfig.merge_gap_down_m`` apart stays two accurate planes in the map (the bands' boxes do not touch), which a
reader of the map counts as a duplicate. :meth:`mapping.plane_map.PlaneMap.bands` tells such bands from copies (a
pose error's copy lies a decimetre off; bands of one face agree to a few centimetres); fusing them *in* the map
(``merge_band_gap_down_m``) changes what the robots register against, and that moved the tracks of depth-only
fleets (docs/mapping.md, "Bands of one face"). Here they are joined only in what the base serves
(:meth:`mapping.MapBuilder.map_json`: the ``lrs/<fleet>/map`` queryable, ``map.json``, the demo's and the
benchmarks' summaries): ``MapConfig.serve_band_gap_down_m`` (0: off; with ``merge_band_gap_down_m`` on, the map
already joins them).

A confirmed plane joins a group of others when, with every member, it is a band (:meth:`PlaneMap.bands` with the
band rule at ``serve_band_gap_down_m``) and does not touch at the map's own ``merge_gap_down_m`` (planes that touch
and yet stayed apart in the map are copies, not bands), and the joined plane stays thin (``merge_max_rms_m``). The
joined plane is the exact sum of the members' statistics and keeps the smallest id.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from .plane_map import MapPlane, PlaneMap, PlaneRecord
from .types import MapConfig


def served_planes(pm: PlaneMap, include_tentative: bool = False) -> list[dict[str, Any]]:
    """``pm``'s planes as :meth:`PlaneMap.to_json` gives them, with bands of one face joined (see the module
    docstring); tentative planes (when asked for) are served as they are."""
    cfg = pm.cfg
    bands = cfg.serve_band_gap_down_m > 0 and cfg.merge_band_gap_down_m <= 0
    if not bands and cfg.serve_copy_offset_m <= 0:
        return pm.to_json(include_tentative)
    groups = join_bands([pm.planes[pid] for pid in sorted(pm.planes)], cfg)
    out = []
    for group in groups:
        if len(group) == 1:
            if include_tentative or group[0].record.n_obs >= cfg.min_obs_publish:
                out.append(group[0].to_json())
            continue
        rec: PlaneRecord = group[0].record
        for mp in group[1:]:
            rec = rec + mp.record
        out.append(MapPlane(group[0].id, rec, cfg).to_json())
    return sorted(out, key=lambda p: int(p["id"]))


def join_bands(planes: list[MapPlane], cfg: MapConfig) -> list[list[MapPlane]]:
    """The planes (by id) grouped into the bands of one face each (a plane alone where it joins none); tentative
    planes stay alone."""
    gap = cfg.serve_band_gap_down_m if cfg.merge_band_gap_down_m <= 0 else 0.0
    band = PlaneMap(replace(cfg, merge_band_gap_down_m=gap))
    own = PlaneMap(cfg)
    groups: list[list[MapPlane]] = []
    joined: list[MapPlane] = []  # per group, its members' sum (fit cached)
    for mp in planes:
        if mp.record.n_obs < cfg.min_obs_publish:
            groups.append([mp])
            joined.append(mp)
            continue
        for k, group in enumerate(groups):
            kind = _joins(band, own, group, mp)
            if kind is None:
                continue
            whole = MapPlane(group[0].id, joined[k].record + mp.record, cfg)
            if whole.fit.rms_m > (cfg.merge_max_rms_m if kind == "band" else cfg.serve_copy_max_rms_m):
                continue
            group.append(mp)
            joined[k] = whole
            break
        else:
            groups.append([mp])
            joined.append(mp)
    return groups


def _joins(band: PlaneMap, own: PlaneMap, group: list[MapPlane], mp: MapPlane) -> str | None:
    """How ``mp`` joins ``group``: ``"band"`` when it is a band of the face of every member (and touches none of
    them at the map's own gap along down), ``"copy"`` when some member touches it and every member is a band of
    it or a copy (:func:`_copy`); else None."""
    cfg = band.cfg
    if group[0].record.n_obs < cfg.min_obs_publish:
        return None
    kind = "band"
    for m in group:
        if own._touch(m.record, mp.record):
            if not _copy(cfg, m, mp):
                return None
            kind = "copy"
        elif not band.bands(m.record, m.fit, mp.record, mp.fit):
            return None
    return kind


def _copy(cfg: MapConfig, a: MapPlane, b: MapPlane) -> bool:
    """Whether two touching planes are one face's copies a few centimetres apart (``serve_copy_offset_m``)."""
    if cfg.serve_copy_offset_m <= 0:
        return False
    fa, fb = a.fit, b.fit
    cos = float(np.clip(fa.normal @ fb.normal, -1.0, 1.0))
    if math.degrees(math.acos(cos)) > cfg.serve_copy_angle_deg:
        return False
    off_a = abs(float(fb.normal @ fa.centroid + fb.d))
    off_b = abs(float(fa.normal @ fb.centroid + fa.d))
    return max(off_a, off_b) <= cfg.serve_copy_offset_m
