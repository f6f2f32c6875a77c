"""Frame sources of an ROV: a recorded dive (folder of ``<t_ns>.png``), a video file, a camera, the simulator.

Each source is a context manager and an iterator of :class:`Frame` (capture time in ns since the Unix epoch
and a (H, W, 3) uint8 BGR image). ``finite`` sources end; ``live`` sources stamp frames with the host clock;
``compressed`` sources (a video file, a camera stream: :mod:`services.stream`) deliver decoded JPEG/H.264
frames, whose colour is stored at half resolution (the ROV reads them on the luma channel).
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from .errors import SourceError

log = logging.getLogger(__name__)

_STAMP_RE = re.compile(r"^(\d{1,20})\.(png|jpg|jpeg|bmp|tif|tiff)$", re.IGNORECASE)


@dataclass(frozen=True, eq=False)
class Frame:
    """One camera frame.

    Attributes:
        t_ns: capture time, ns since the Unix epoch.
        image: (H, W, 3) uint8 BGR.
        index: running index of the frame in its source, from 0.
    """

    t_ns: int
    image: NDArray[np.uint8]
    index: int


class FrameSource(Protocol):
    """What the ROV loop needs from a camera."""

    finite: bool
    live: bool
    name: str

    def __enter__(self) -> Any: ...

    def __exit__(self, *exc: Any) -> None: ...

    def __iter__(self) -> Iterator[Frame]: ...


def stamped_images(folder: str | Path) -> list[tuple[int, Path]]:
    """The ``<t_ns>.png`` (or .jpg, ...) files of ``folder`` as ``(t_ns, path)`` sorted by time."""
    d = Path(folder)
    out = []
    for p in d.iterdir():
        m = _STAMP_RE.match(p.name)
        if m and p.is_file():
            out.append((int(m.group(1)), p))
    out.sort()
    return out


class FolderSource:
    """A recorded dive: images named ``<t_ns>.png`` in a folder, replayed in time order.

    Files that cannot be read are logged, counted in :attr:`unreadable` and skipped.
    """

    finite = True
    live = False
    compressed = False

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            msg = f"{self.folder}: not a folder of <t_ns>.png images"
            raise SourceError(msg)
        self.files = stamped_images(self.folder)
        if not self.files:
            msg = f"{self.folder}: no image named <t_ns>.png (capture time in ns since the Unix epoch)"
            raise SourceError(msg)
        self.name = f"folder:{self.folder}"
        self.unreadable = 0

    def __len__(self) -> int:
        return len(self.files)

    def __enter__(self) -> FolderSource:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def __iter__(self) -> Iterator[Frame]:
        import cv2

        for i, (t_ns, path) in enumerate(self.files):
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None or image.dtype != np.uint8 or image.ndim != 3:
                self.unreadable += 1
                log.warning("%s: unreadable image, skipped", path)
                continue
            yield Frame(t_ns, np.asarray(image, dtype=np.uint8), i)


class VideoSource:
    """A video file; frame times are ``t0_ns`` plus the container's position of each frame."""

    finite = True
    live = False
    compressed = True

    def __init__(self, path: str | Path, t0_ns: int | None = None) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            msg = f"{self.path}: video file does not exist"
            raise SourceError(msg)
        self.t0_ns = time.time_ns() if t0_ns is None else int(t0_ns)
        self.name = f"video:{self.path}"
        self._cap: Any = None

    def __enter__(self) -> VideoSource:
        import cv2

        self._cap = cv2.VideoCapture(str(self.path))
        if not self._cap.isOpened():
            msg = f"{self.path}: OpenCV cannot open this video"
            raise SourceError(msg)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._cap is not None:
            self._cap.release()

    def __iter__(self) -> Iterator[Frame]:
        import cv2

        if self._cap is None:
            msg = "VideoSource must be used inside 'with'"
            raise SourceError(msg)
        fps = float(self._cap.get(cv2.CAP_PROP_FPS) or 0.0)
        i = 0
        last_ms = -1.0
        while True:
            ok, image = self._cap.read()
            if not ok:
                return
            # after read() the position is the timestamp of the frame just decoded (FFmpeg backend); fall back to
            # index / fps when the container gives nothing usable
            pos_ms = float(self._cap.get(cv2.CAP_PROP_POS_MSEC) or 0.0)
            if pos_ms <= last_ms and fps > 0:
                pos_ms = 1000.0 * i / fps
            if pos_ms <= last_ms:
                pos_ms = last_ms + 1e-3
            last_ms = pos_ms
            yield Frame(self.t0_ns + round(pos_ms * 1e6), image, i)
            i += 1


class CameraSource:
    """A camera device (``cv2.VideoCapture(index)``); frames are stamped with the host clock at grab."""

    finite = False
    live = True
    compressed = False  # a device may deliver MJPEG; give --channel luma then

    def __init__(self, index: int, width: int | None = None, height: int | None = None) -> None:
        self.index = index
        self.width = width
        self.height = height
        self.name = f"camera:{index}"
        self._cap: Any = None
        self.failed_reads = 0

    def __enter__(self) -> CameraSource:
        import cv2

        self._cap = cv2.VideoCapture(self.index)
        if not self._cap.isOpened():
            msg = f"camera device {self.index}: OpenCV cannot open it"
            raise SourceError(msg)
        if self.width and self.height:
            self._cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
            self._cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._cap is not None:
            self._cap.release()

    def __iter__(self) -> Iterator[Frame]:
        if self._cap is None:
            msg = "CameraSource must be used inside 'with'"
            raise SourceError(msg)
        i = 0
        while True:
            ok = self._cap.grab()
            t_ns = time.time_ns()
            if ok:
                ok, image = self._cap.retrieve()
            if not ok:
                self.failed_reads += 1
                if self.failed_reads > 50:
                    msg = f"camera device {self.index}: 50 failed reads in a row"
                    raise SourceError(msg)
                continue
            self.failed_reads = 0
            yield Frame(t_ns, image, i)
            i += 1


def open_source(
    spec: str, t0_ns: int | None = None, *, stream_timeout_s: float = 10.0, stop: threading.Event | None = None
) -> FrameSource:
    """A frame source from its command-line spec: a folder, a video file, a camera index or a stream URL
    (``udp://``, ``rtsp://``, an ``.sdp`` file: :class:`services.stream.StreamSource`, with ``stream_timeout_s``
    and the ``stop`` event that ends its wait for frames).

    ``sim`` is handled by :func:`services.simsource.open_sim` (it also provides the IMU).
    """
    from .stream import StreamSource, is_stream

    if is_stream(spec):
        return StreamSource(spec, stream_timeout_s, stop)
    if spec.isdigit():
        return CameraSource(int(spec))
    if spec.startswith("camera:") and spec[7:].isdigit():
        return CameraSource(int(spec[7:]))
    p = Path(spec)
    if p.is_dir():
        return FolderSource(p)
    if p.is_file():
        return VideoSource(p, t0_ns)
    msg = (
        f"unknown frame source {spec!r}: use sim, a folder of <t_ns>.png, a video file, a camera index or a "
        "stream (udp://HOST:PORT, rtsp://..., FILE.sdp)"
    )
    raise SourceError(msg)
