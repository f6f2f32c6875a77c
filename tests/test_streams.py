"""Camera streams as frame sources, against the real tools: ffmpeg streams rendered PNGs of a wall 1 m away as
H.264 in MPEG-TS to a free UDP port on loopback (and as RTP described by an .sdp file, as a BlueROV2 camera),
read by :class:`services.stream.StreamSource` in-process and by a
``lrsensor rov --source udp://...`` process whose clouds are checked against the wall; a silent URL fails within
its timeout; a stream that ends is reported and the source stops on its stop event."""

from __future__ import annotations

import logging
import shutil
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mavsender import free_udp_port
from procs import Proc, lrsensor_cmd
from waiting import wait_until

from lrsensor import Sensor
from lrsensor.sim import named_scene
from services.errors import SourceError
from services.rov import channel_choice
from services.sources import FolderSource, VideoSource, open_source
from services.stream import StreamSource, is_stream
from services.testnet import free_port
from services.wire import decode_cloud
from services.zconfig import NetworkOptions, open_session

FFMPEG = shutil.which("ffmpeg")
needs_ffmpeg = pytest.mark.skipif(FFMPEG is None, reason="ffmpeg is not installed (./run installs it with apt)")
N_PNG = 20
WALL_M = 1.0
#: H.264 (ultrafast, default quality) moves stripe centres by tenths of a pixel: a few mm at 1 m for this camera.
WALL_TOL_M = 0.01


@pytest.fixture(scope="module")
def scene() -> Any:
    return named_scene("wall_1.0", width=640, height=360)


@pytest.fixture(scope="module")
def pngs(scene: Any, tmp_path_factory: pytest.TempPathFactory) -> Path:
    import cv2

    d = tmp_path_factory.mktemp("png")
    for i in range(N_PNG):
        assert cv2.imwrite(str(d / f"{i:03d}.png"), scene.render(seed=i).image)
    return d


def stream_pngs(folder: Path, port: int, loops: int = 2, rtp: bool = False) -> subprocess.Popen[bytes]:
    """ffmpeg streaming ``folder``'s PNGs ``loops`` times at 10 frames/s as H.264 to 127.0.0.1:PORT, in MPEG-TS
    over UDP (or RTP with ``rtp``, as a BlueROV2 camera), a keyframe a second (as a camera sends them, so a
    reader that joins late decodes from the next one)."""
    assert FFMPEG is not None
    cmd = [FFMPEG, "-hide_banner", "-loglevel", "error", "-re", "-stream_loop", str(loops - 1), "-framerate", "10"]
    cmd += ["-pattern_type", "glob", "-i", str(folder / "*.png"), "-c:v", "libx264", "-preset", "ultrafast"]
    cmd += ["-tune", "zerolatency", "-g", "10", "-pix_fmt", "yuv420p"]
    if rtp:
        cmd += ["-f", "rtp", f"rtp://127.0.0.1:{port}?pkt_size=1200"]
    else:
        cmd += ["-f", "mpegts", f"udp://127.0.0.1:{port}?pkt_size=1316"]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


#: The session description of ffmpeg's RTP output (``-f rtp``): H.264, payload type 96, on PORT.
SDP = """v=0
o=- 0 0 IN IP4 127.0.0.1
s=camera
c=IN IP4 127.0.0.1
t=0 0
m=video {port} RTP/AVP 96
a=rtpmap:96 H264/90000
a=fmtp:96 packetization-mode=1
"""


@pytest.fixture
def ffmpegs() -> Iterator[list[subprocess.Popen[bytes]]]:
    started: list[subprocess.Popen[bytes]] = []
    yield started
    for p in started:
        if p.poll() is None:
            p.kill()
        p.wait(10)


# ----------------------------------------------------------------------------- without ffmpeg


def test_stream_specs_and_the_channel_default(tmp_path: Path) -> None:
    for url in ("udp://127.0.0.1:5600", "rtsp://192.168.2.2:8554/cam", "RTP://0.0.0.0:5600", str(tmp_path / "c.sdp")):
        assert is_stream(url)
    assert not is_stream(str(tmp_path))
    assert isinstance(open_source("udp://127.0.0.1:5600"), StreamSource)
    with pytest.raises(SourceError, match=r"no such \.sdp file"):
        open_source(str(tmp_path / "missing.sdp"))
    with pytest.raises(SourceError, match="stream"):
        open_source("nothing-here")
    stream = StreamSource("udp://127.0.0.1:5600")
    (tmp_path / "1.png").write_bytes(b"")
    video = tmp_path / "v.mp4"
    video.write_bytes(b"")
    assert channel_choice(stream, None, {})[0] == {"channel": "luma"}
    assert "compressed" in channel_choice(stream, None, {})[1]
    assert channel_choice(VideoSource(video), "subpixel", {"max_range_m": 2.0})[0] == {
        "max_range_m": 2.0,
        "channel": "luma",
    }
    given = ({"channel": "green"}, "channel green (given with --channel)")
    assert channel_choice(stream, None, {"channel": "green"}) == given
    assert channel_choice(FolderSource(tmp_path), None, {})[0] == {}
    assert channel_choice(stream, "paper", {})[0] == {}


# ----------------------------------------------------------------------------- against ffmpeg


@needs_ffmpeg
def test_a_silent_url_fails_within_its_timeout() -> None:
    src = StreamSource(f"udp://127.0.0.1:{free_udp_port()}", timeout_s=1.5)
    t0 = time.monotonic()
    with pytest.raises(SourceError, match=r"no stream within 1\.\d s"), src:
        pass
    assert time.monotonic() - t0 < 3.0


@needs_ffmpeg
def test_frames_arrive_newest_first_and_the_end_is_reported(
    scene: Any, pngs: Path, ffmpegs: list[Any], caplog: pytest.LogCaptureFixture
) -> None:
    port = free_udp_port()
    stop = threading.Event()
    src = StreamSource(f"udp://127.0.0.1:{port}", timeout_s=2.0, stop=stop)
    sensor = Sensor(scene.calibration)
    got: list[Any] = []
    ff: list[subprocess.Popen[bytes]] = []
    # the reader listens first; ffmpeg starts on a timer while the open waits for data
    threading.Timer(0.3, lambda: ff.append(stream_pngs(pngs, port))).start()
    caplog.set_level(logging.INFO, logger="services.stream")

    def stop_when_silent() -> None:  # the stream ended: the wait for the next frame returns on the stop event
        if wait_until(lambda: src.silences > 0, 30):
            stop.set()

    threading.Thread(target=stop_when_silent, daemon=True).start()
    with src:
        ffmpegs.extend(ff)
        for frame in src:
            got.append(frame)
            if len(got) <= 3:
                scan = sensor.process(frame.image, channel="luma")
                assert len(scan) > 0.9 * 2 * 640
                assert abs(np.median(scan.points[:, 0]) - WALL_M) < 0.003
            time.sleep(0.25)  # a slow ROV: the reader keeps only the newest frame
        t_stop = time.monotonic()
    assert time.monotonic() - t_stop < 2.0 + 1.5  # the reader's last open or read ends within its timeout
    assert stop.is_set()
    assert ff[0].wait(10) == 0, ff[0].stderr.read() if ff[0].stderr else ""
    assert len(got) >= 8
    assert src.frames >= 30  # of 40 sent; FFmpeg's probe at the open may lose the first ones
    assert src.dropped > 0
    assert src.frames == len(got) + src.dropped + (1 if src._slot is not None else 0)
    stamps = [f.t_ns for f in got]
    assert stamps == sorted(stamps)
    assert all(f.image.shape == (360, 640, 3) for f in got)
    assert abs(stamps[-1] - time.time_ns()) < 10e9  # this machine's clock
    assert src.silences >= 1
    assert "ended or silent: no frame for" in caplog.text


@needs_ffmpeg
def test_rtp_described_by_an_sdp_file(scene: Any, pngs: Path, tmp_path: Path, ffmpegs: list[Any]) -> None:
    port = free_udp_port()
    sdp = tmp_path / "camera.sdp"
    sdp.write_text(SDP.format(port=port))
    stop = threading.Event()
    src = open_source(str(sdp), stream_timeout_s=2.0, stop=stop)
    assert isinstance(src, StreamSource)
    ff: list[subprocess.Popen[bytes]] = []
    threading.Timer(0.3, lambda: ff.append(stream_pngs(pngs, port, loops=1, rtp=True))).start()
    got = []
    with src:
        ffmpegs.extend(ff)
        for frame in src:
            got.append(frame)
            if len(got) == 5:
                break
    scan = Sensor(scene.calibration).process(got[-1].image, channel="luma")
    assert len(scan) > 0.9 * 2 * 640
    assert abs(np.median(scan.points[:, 0]) - WALL_M) < 0.003


# ----------------------------------------------------------------------------- a ROV process


@needs_ffmpeg
@pytest.mark.slow
def test_rov_process_reads_a_udp_stream(
    scene: Any, pngs: Path, tmp_path: Path, procs: list[Proc], ffmpegs: list[Any]
) -> None:
    scene.calibration.save(tmp_path / "calib.json")
    now_s = time.time_ns() // 1_000_000_000
    rows = [f"{(now_s + k) * 1_000_000_000},0,0,0,0,0,2.0" for k in range(-60, 600)]
    (tmp_path / "imu.csv").write_text("t_ns,roll_deg,pitch_deg,yaw_deg,north_m,east_m,down_m\n" + "\n".join(rows))
    zport, uport = free_port(), free_udp_port()
    clouds: list[Any] = []
    lock = threading.Lock()

    def on_cloud(sample: Any) -> None:
        with lock:
            clouds.append(decode_cloud(sample.payload.to_bytes()))

    router = open_session(NetworkOptions(mode="router", listen=(f"tcp/127.0.0.1:{zport}",)), "router")
    try:
        sub = router.declare_subscriber("lrs/strm/*/cloud", on_cloud)
        args = ["rov", "--fleet", "strm", "--robot", "rov1", "--connect", f"tcp/127.0.0.1:{zport}"]
        args += ["--source", f"udp://127.0.0.1:{uport}", "--stream-timeout-s", "2"]
        args += ["--calib", str(tmp_path / "calib.json")]
        args += ["--imu", f"csv:{tmp_path / 'imu.csv'}", "--no-outbox", "--cloud-schema", "1"]
        rov = Proc(lrsensor_cmd(*args), tmp_path / "rov.log")
        procs.append(rov)
        assert wait_until(lambda: "publishing on" in rov.output(), 30), rov.output()  # the reader opens next
        ffmpegs.append(stream_pngs(pngs, uport))
        assert wait_until(lambda: len(clouds) >= 5, 30), rov.output()
        assert ffmpegs[0].wait(15) == 0
        assert wait_until(lambda: "ended or silent" in rov.output(), 10), rov.output()
        assert rov.stop(timeout_s=10) == 0, rov.output()  # SIGTERM while the stream is silent
        sub.undeclare()
    finally:
        router.close()
    out = rov.output()
    assert "channel luma (compressed frames" in out
    assert "rov rov1: frames" in out  # the summary: a clean stop
    assert "dropped" in out
    for m in clouds[:5]:
        assert len(m) > 0.8 * 2 * 640
        x = np.asarray(m.points_body, float)[:, 0]
        assert abs(np.median(x) - WALL_M) < 0.003
        assert np.mean(np.abs(x - WALL_M) < WALL_TOL_M) > 0.99
        assert m.pose.down_m == pytest.approx(2.0)
