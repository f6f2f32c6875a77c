"""mapping: NED clouds, Open3D plane extraction and the shared plane map (knows nothing of Zenoh).

Public API::

    from mapping import MapBuilder, MapConfig
    builder = MapBuilder(MapConfig(), state_dir)          # reloads state_dir/map_state.npz if present
    changes = builder.add_cloud(robot, t_ns, points_ned, pose)   # list[MapChange]
    builder.flush(); builder.map_json(); builder.tracks; builder.save()

Open3D is imported lazily (only plane extraction needs it): loading, exporting and viewing a saved map work on
the ROV-only install.
"""

from __future__ import annotations

from .builder import MapBuilder
from .errors import MapConfigError, MapInputError, MappingError, MapStoreError, Open3DMissingError
from .ned import cloud_to_ned
from .plane_map import PlaneMap, PlaneRecord
from .types import ChangeKind, MapChange, MapConfig, PlaneFit, PlaneStats

__all__ = [
    "ChangeKind",
    "MapBuilder",
    "MapChange",
    "MapConfig",
    "MapConfigError",
    "MapInputError",
    "MapStoreError",
    "MappingError",
    "Open3DMissingError",
    "PlaneFit",
    "PlaneMap",
    "PlaneRecord",
    "PlaneStats",
    "cloud_to_ned",
]
