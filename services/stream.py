"""A camera stream as a frame source: H.264 over UDP (MPEG-TS), RTSP, or RTP described by an ``.sdp`` file.

Layout: a reader thread owns the ``cv2.VideoCapture(url, cv2.CAP_FFMPEG)`` and keeps only the newest decoded
frame in a one-frame slot; the ROV's loop takes frames from the slot. A live camera must not queue stale
frames: when the ROV is slower than the camera, a frame replaced before it was taken is dropped and counted
(:attr:`StreamSource.dropped`). Each frame is stamped with its arrival time on this machine's clock (UTC ns,
taken when the decoder delivered it) and posed by the ROV from the samples around that time.

Timeouts: OpenCV's ``CAP_PROP_OPEN_TIMEOUT_MSEC`` and ``CAP_PROP_READ_TIMEOUT_MSEC`` open parameters, not
udp's ``?timeout=`` URL option or the ``OPENCV_FFMPEG_CAPTURE_OPTIONS`` variable: they work through FFmpeg's
interrupt callback for every protocol alike (udp, rtsp, an .sdp's rtp), whereas ``timeout`` means a different
thing per protocol and cannot be put into an .sdp path. A stream that sends nothing fails to open within
``timeout_s``; a stream that falls silent ends a read within ``timeout_s``.

Probing: FFmpeg reads 5 s of a stream before it opens (``analyzeduration``), then hands those frames over in a
burst. Unless ``OPENCV_FFMPEG_CAPTURE_OPTIONS`` is set (then it is used unchanged), the reader sets it for the
moment of the open to :data:`CAPTURE_OPTIONS` (0.5 s probe, RTSP over TCP first as OpenCV's default does, and
for an .sdp the protocols RTP needs). One decoder thread (``CAP_PROP_N_THREADS``): frame threading would hold
back a frame per extra thread.

Silence and reopening (policy): after the first frame, a read that fails or waits ``timeout_s`` (the stream
ended or sent nothing) is logged with how long no frame came; the frames FFmpeg then drains from its decoder
arrived up to a timeout earlier and are discarded (``stale``). The capture is released and reopened after a
backoff of 0.5 s that doubles up to 10 s and returns to 0.5 s once a frame arrives; it keeps trying until the
source is closed (a camera whose topside restarts comes back). Each silent attempt itself waits ``timeout_s``.
The first open is done by ``__enter__`` and fails with a :class:`SourceError` that names the URL and the time
waited: a wrong address is reported at once, not retried forever.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import SourceError
from .sources import Frame

log = logging.getLogger(__name__)

#: URL schemes read as live streams.
STREAM_SCHEMES = ("udp://", "rtp://", "rtsp://", "rtsps://", "tcp://", "srt://")
#: FFmpeg options of the open unless OPENCV_FFMPEG_CAPTURE_OPTIONS is set: probe 0.5 s / 500 kB of the stream
#: (microseconds, bytes), RTSP over TCP first (OpenCV's own default, lost once the variable is set).
CAPTURE_OPTIONS = "analyzeduration;500000|probesize;500000|rtsp_flags;prefer_tcp"
#: What an .sdp file needs on top (FFmpeg refuses rtp/udp from a file-described stream otherwise).
SDP_OPTIONS = "protocol_whitelist;file,rtp,udp,crypto,data"
ENV_OPTIONS = "OPENCV_FFMPEG_CAPTURE_OPTIONS"
#: Reopen backoff after a silence, seconds: first, factor, cap.
BACKOFF_FIRST_S = 0.5
BACKOFF_FACTOR = 2.0
BACKOFF_MAX_S = 10.0
#: A read that took this fraction of the timeout ended with the timeout: the frames FFmpeg then drains from
#: its decoder were received up to a timeout earlier, so their arrival time is unknown.
STALL_FRACTION = 0.9
#: How often the ROV's wait for a frame checks its stop event, seconds.
POLL_S = 0.2

_env_lock = threading.Lock()


def is_stream(spec: str) -> bool:
    """Whether a ``--source`` spec names a stream: a URL of :data:`STREAM_SCHEMES` or an ``.sdp`` file."""
    return spec.lower().startswith(STREAM_SCHEMES) or spec.lower().endswith(".sdp")


class StreamSource:
    """A live camera stream read through OpenCV's FFmpeg backend (see the module documentation).

    Args:
        url: ``udp://HOST:PORT`` (H.264 in MPEG-TS), ``rtsp://...``, or the path of an ``.sdp`` file (RTP).
        timeout_s: how long the open waits for the stream, and a read for a frame, before giving up.
        stop: set by SIGINT/SIGTERM: the wait for the next frame returns and the iteration ends.

    Counters: ``frames`` (decoded), ``dropped`` (replaced by a newer one before the ROV took them),
    ``silences`` (reads that failed after frames had come), ``reopens`` (open attempts after a silence),
    ``stale`` (frames drained from the decoder after a read timed out: their arrival time is unknown, so they
    are discarded and the capture is reopened).
    """

    finite = False
    live = True
    compressed = True

    def __init__(self, url: str, timeout_s: float = 10.0, stop: threading.Event | None = None) -> None:
        if timeout_s <= 0:
            msg = f"stream timeout must be positive, got {timeout_s} s"
            raise SourceError(msg)
        if url.lower().endswith(".sdp") and not Path(url).is_file():
            msg = f"{url}: no such .sdp file"
            raise SourceError(msg)
        self.url = url
        self.timeout_s = float(timeout_s)
        self.stop = stop if stop is not None else threading.Event()
        self.name = f"stream:{url}"
        self.frames = 0
        self.dropped = 0
        self.silences = 0
        self.reopens = 0
        self.stale = 0
        self._slot: Frame | None = None
        self._cond = threading.Condition()
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_arrival = 0.0  # monotonic s of the last frame

    # ------------------------------------------------------------------ capture
    def _options(self) -> str | None:
        """The FFmpeg options to put in OPENCV_FFMPEG_CAPTURE_OPTIONS for the open (None: the user's own)."""
        if os.environ.get(ENV_OPTIONS) is not None:
            return None
        sdp = self.url.lower().endswith(".sdp")
        return CAPTURE_OPTIONS + ("|" + SDP_OPTIONS if sdp else "")

    def _open(self) -> Any:
        """A capture of the stream, or None when it sent nothing decodable within the timeout."""
        import cv2

        ms = round(self.timeout_s * 1000)
        params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms, cv2.CAP_PROP_N_THREADS, 1]
        options = self._options()
        with _env_lock:
            if options is not None:
                os.environ[ENV_OPTIONS] = options
            try:
                cap = cv2.VideoCapture(self.url, cv2.CAP_FFMPEG, params)
            finally:
                if options is not None:
                    os.environ.pop(ENV_OPTIONS, None)
        if cap.isOpened():
            return cap
        cap.release()
        return None

    def __enter__(self) -> StreamSource:
        t0 = time.monotonic()
        cap = self._open()
        if cap is None:
            msg = (
                f"{self.url}: no stream within {time.monotonic() - t0:.1f} s (timeout {self.timeout_s:.0f} s): "
                "nothing arrived, or nothing OpenCV's FFmpeg backend could decode"
            )
            raise SourceError(msg)
        log.info("stream %s opened in %.1f s", self.url, time.monotonic() - t0)
        self._last_arrival = time.monotonic()
        self._closing.clear()
        self._thread = threading.Thread(target=self._read_loop, args=(cap,), name="stream-reader", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._closing.set()
        with self._cond:
            self._cond.notify_all()
        if self._thread is not None:
            # a read blocked in FFmpeg returns within the timeout; the thread is a daemon if it does not
            self._thread.join(self.timeout_s + 1.0)
            if self._thread.is_alive():
                log.warning("stream %s: the reader is still blocked in FFmpeg; left to end with the process", self.url)
        log.info(
            "stream %s: %d frames decoded, %d dropped (a newer one came before the ROV took them), %d stale "
            "(drained after a timeout), %d silences, %d reopen attempts",
            self.url,
            self.frames,
            self.dropped,
            self.stale,
            self.silences,
            self.reopens,
        )

    def _read_loop(self, cap: Any) -> None:
        backoff_s = BACKOFF_FIRST_S
        try:
            while not self._closing.is_set():
                if cap is None:
                    silent_s = time.monotonic() - self._last_arrival
                    log.warning(
                        "stream %s: no frame for %.1f s; reopening in %.1f s (attempt %d)",
                        self.url,
                        silent_s,
                        backoff_s,
                        self.reopens + 1,
                    )
                    if self._closing.wait(backoff_s):
                        return
                    self.reopens += 1
                    cap = self._open()
                    backoff_s = min(backoff_s * BACKOFF_FACTOR, BACKOFF_MAX_S)
                    if cap is not None:
                        log.info("stream %s: reopened (attempt %d)", self.url, self.reopens)
                    continue
                t_grab = time.monotonic()
                ok = cap.grab()
                t_ns = time.time_ns()
                stalled = time.monotonic() - t_grab >= STALL_FRACTION * self.timeout_s
                image: NDArray[np.uint8] | None = None
                if ok and not stalled:
                    ok, image = cap.retrieve()
                if not ok or stalled or image is None:
                    if self._closing.is_set():
                        return
                    if ok:  # a frame drained from the decoder after the read timed out: stale, not stamped
                        self.stale += 1
                    self.silences += 1
                    log.warning(
                        "stream %s: ended or silent: no frame for %.1f s (%d frames so far)",
                        self.url,
                        time.monotonic() - self._last_arrival,
                        self.frames,
                    )
                    cap.release()
                    cap = None
                    continue
                self._last_arrival = time.monotonic()
                backoff_s = BACKOFF_FIRST_S
                with self._cond:
                    if self._slot is not None:
                        self.dropped += 1
                    self._slot = Frame(t_ns, np.asarray(image, dtype=np.uint8), self.frames)
                    self.frames += 1
                    self._cond.notify_all()
        except Exception:  # a reader that dies must not leave the ROV waiting silently
            log.exception("stream %s: the reader failed", self.url)
        finally:
            if cap is not None:
                cap.release()

    # ------------------------------------------------------------------ frames
    def __iter__(self) -> Iterator[Frame]:
        if self._thread is None:
            msg = "StreamSource must be used inside 'with'"
            raise SourceError(msg)
        while True:
            with self._cond:
                while self._slot is None:
                    if self.stop.is_set() or self._closing.is_set() or not self._thread.is_alive():
                        return
                    self._cond.wait(POLL_S)
                frame, self._slot = self._slot, None
            yield frame
