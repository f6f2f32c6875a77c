"""lrsensor: a line-laser range sensor for small underwater robots (the sensor core).

The core is pure numpy/OpenCV: calibration, camera, triangulation, stripe extraction, range theory and a
ground-truth simulator. It knows nothing of Zenoh or Open3D.
"""

from __future__ import annotations

from .calibration import Calibration, LaserPlane, load_calibration
from .camera import Camera
from .errors import LrsensorError
from .frames import Pose
from .scan import Scan
from .sensor import Sensor

__all__ = [
    "Calibration",
    "Camera",
    "LaserPlane",
    "LrsensorError",
    "Pose",
    "Scan",
    "Sensor",
    "load_calibration",
]
__version__ = "0.1.0"
