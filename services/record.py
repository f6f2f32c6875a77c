"""Recording a fleet into an MCAP file (``lrsensor record``), readable by Foxglove and the ``mcap`` reader.

The recorder is a :class:`~services.fleet_tap.FleetTap` (a Zenoh subscriber like the base station) with a
:class:`~services.foxglove_views.FoxgloveSink` logging on a foxglove context whose one sink is foxglove-sdk's
MCAP writer. The file holds the foxglove views (point clouds, transforms, the map's planes) and the raw wire
payloads and calibrations that make it replayable (:mod:`services.replay`); docs/recording.md lists the
topics. The file's metadata record ``lrsensor`` names the key prefix, the fleet and the start time.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from .errors import ServiceError
from .fleet_tap import FleetTap
from .foxglove_views import RAW_SCHEMA_NAME, FoxgloveSink, import_foxglove
from .keys import FleetKeys

__all__ = ["RAW_SCHEMA_NAME", "RecordError", "Recorder"]


class RecordError(ServiceError):
    """The recording cannot be written (the file exists, its folder is missing)."""


class Recorder:
    """Records a fleet's clouds, poses and map into ``path``.

    Args:
        session: an open Zenoh session (the caller owns it).
        keys: the fleet's key expressions.
        path: the ``.mcap`` file to write.
        overwrite: replace an existing file (otherwise an existing file is refused).
    """

    def __init__(self, session: Any, keys: FleetKeys, path: str | Path, *, overwrite: bool = False) -> None:
        foxglove = import_foxglove()
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            msg = f"{self.path} exists; choose another --out or remove it"
            raise RecordError(msg)
        if not self.path.parent.is_dir():
            msg = f"cannot record to {self.path}: folder {self.path.parent} does not exist"
            raise RecordError(msg)
        context = foxglove.Context()
        try:
            self._writer = foxglove.open_mcap(str(self.path), allow_overwrite=overwrite, context=context)
        except Exception as err:
            msg = f"cannot open {self.path} for recording: {err}"
            raise RecordError(msg) from err
        self._writer.write_metadata(
            "lrsensor", {"prefix": keys.prefix, "fleet": keys.fleet, "started_ns": str(time.time_ns())}
        )
        self.tap = FleetTap(session, keys, [FoxgloveSink(context, keys.root, raw=True)])
        self._closed = False

    def stats(self) -> dict[str, Any]:
        """What was written so far (:class:`~services.fleet_tap.TapCounters` as JSON)."""
        return self.tap.stats()

    def idle(self) -> bool:
        """True when everything received so far has been written."""
        return self.tap.idle()

    def close(self) -> dict[str, Any]:
        """Stop recording, write what is queued and finish the file; returns the counters."""
        stats = self.tap.close()
        if not self._closed:
            self._closed = True
            self._writer.close()
        return stats

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
