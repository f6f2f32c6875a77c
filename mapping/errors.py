"""The exception tree of the mapping package: everything raised on purpose derives from :class:`MappingError`."""

from __future__ import annotations

from lrsensor.errors import LrsensorError


class MappingError(LrsensorError):
    """Root of every error the ``mapping`` package raises on purpose."""


class MapConfigError(MappingError):
    """A map configuration value is out of range or of the wrong type."""


class MapInputError(MappingError):
    """A cloud or pose handed to the map is malformed (shape, non-finite values, bad robot name)."""


class MapStoreError(MappingError):
    """The persisted map under a state directory cannot be read or written."""


class Open3DMissingError(MappingError, ImportError):
    """Open3D is not installed (the ROV-only install): plane extraction needs the ``base`` extra."""
