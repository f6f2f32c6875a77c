"""The exception tree of the fleet services: everything raised on purpose derives from :class:`ServiceError`.

:class:`ServiceError` itself derives from :class:`lrsensor.errors.LrsensorError`, so the ``lrsensor`` command
reports it as a clean error message with a non-zero exit code.
"""

from __future__ import annotations

from lrsensor.errors import LrsensorError


class ServiceError(LrsensorError):
    """Root of every error the ``services`` package raises on purpose."""


class WireError(ServiceError):
    """A wire message could not be encoded or decoded (wrong version, truncated, oversized, inconsistent)."""


class KeyNameError(ServiceError):
    """A fleet, robot or prefix name cannot be used in a Zenoh key expression."""


class NetworkConfigError(ServiceError):
    """The Zenoh network flags or configuration file are invalid."""


class ImuError(ServiceError):
    """An IMU source could not be opened or its data is malformed."""


class SourceError(ServiceError):
    """A frame source (image folder, video, camera, simulator) could not be opened or read."""


class CalibrationUnavailableError(ServiceError):
    """No calibration was given locally and none could be fetched from the base station."""


class MappingUnavailableError(ServiceError):
    """The base station's map needs the ``mapping`` package (Open3D), which is not installed or not built."""
