"""The exception tree of the sensor package: everything raised on purpose derives from :class:`LrsensorError`."""

from __future__ import annotations


class LrsensorError(Exception):
    """Root of every error the ``lrsensor`` package raises on purpose."""


class CalibrationFileError(LrsensorError):
    """A calibration file or mapping is missing a key, holds a bad value, or cannot be read."""


class CalibrationFitError(LrsensorError):
    """A calibration fit was refused: degenerate input, no stripe found, or residuals above the threshold."""


class ExtractionError(LrsensorError):
    """An image could not be processed (wrong shape, dtype, or size for the calibration)."""


class SimulationError(LrsensorError):
    """A simulated scene or camera is inconsistent."""


class GeometryError(LrsensorError):
    """Input arrays of the geometry core have the wrong shape or non-finite values."""
