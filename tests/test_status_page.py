"""The status page (issue 28, item 5), checked in a real headless browser (Debian's chromium).

The page is loaded by chromium with scripts running: the DOM it ends with must hold the fleet table, the
page must have refreshed itself several times without a reload, and its screenshot must show the map's planes
and the robots' tracks in their colours. Without chromium the browser tests are skipped (``./run`` installs it).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import threading
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.liveview import LiveViewError, parse_host_port
from services.status_page import StatusPage, StatusPageError, thin_track

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (./run installs it)")
FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
    "--disable-component-update", "--hide-scrollbars",
]  # fmt: skip


class FakeBase:
    """A base station's three views, counting how often the status was asked for."""

    def __init__(self) -> None:
        self.calls = 0
        self.lock = threading.Lock()

    def status(self) -> dict[str, Any]:
        with self.lock:
            self.calls += 1
            n = self.calls
        return {
            "fleet": "tank",
            "t_ns": 1_790_000_000_000_000_000,
            "robots": {
                "rov1": {"alive": True, "received": 100 + n, "missed": 0, "rejected": 1, "unplaced": 0,
                         "nav": {"position": "constrained", "north_m_std": 0.04, "east_m_std": 0.05}},
                "rov2": {"alive": False, "received": 7, "missed": 2, "rejected": 0, "unplaced": 7},
            },
            "map": {"planes": 2},
        }  # fmt: skip

    def map_json(self) -> dict[str, Any]:
        wall = lambda n0, e0, n1, e1: {"corners": [[n0, e0, 0], [n1, e1, 0], [n1, e1, 2], [n0, e0, 2]]}  # noqa: E731
        return {"planes": [{"id": 1, "extent": wall(0, 0, 0, 6)}, {"id": 2, "extent": wall(0, 6, 4, 6)}]}

    def tracks(self) -> dict[str, np.ndarray]:
        t = np.linspace(0, 1, 50)
        return {"rov1": np.stack([t, 1 + 2 * t, 1 + 4 * t, 0 * t], axis=1)}


@pytest.fixture
def page() -> Any:
    base = FakeBase()
    with StatusPage(base.status, base.map_json, base.tracks, port=0) as p:
        p.base = base  # type: ignore[attr-defined]
        yield p


def get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=10) as r:
        return bytes(r.read())


def test_json_routes_answer_what_the_base_answers(page: StatusPage) -> None:
    st = json.loads(get(page.url + "status.json"))
    assert st["robots"]["rov2"]["missed"] == 2
    assert len(json.loads(get(page.url + "map.json"))["planes"]) == 2
    tracks = json.loads(get(page.url + "tracks.json"))
    assert tracks["rov1"][0] == [1.0, 1.0]
    html = get(page.url).decode()
    assert "<canvas" in html
    assert "http" not in html.split("<script>")[1]  # nothing is loaded from elsewhere
    with pytest.raises(urllib.error.HTTPError, match="404"):
        get(page.url + "nothing")


def test_bad_addresses_are_refused(page: StatusPage) -> None:
    with pytest.raises(LiveViewError, match="--http takes"):
        parse_host_port("host:port", "--http")
    with pytest.raises(StatusPageError, match="cannot listen"):
        StatusPage(dict, dict, dict, port=page.port)


def test_thin_track_keeps_at_most_the_limit() -> None:
    track = np.stack([np.arange(5000), np.arange(5000), -np.arange(5000), np.zeros(5000)], axis=1).astype(float)
    rows = thin_track(track, 1000)
    assert len(rows) <= 1000
    assert rows[0] == [0.0, 0.0]


@needs_chromium
def test_chromium_shows_the_table_and_refreshes_it(page: StatusPage) -> None:
    dom = subprocess.run(
        [CHROMIUM, *FLAGS, "--virtual-time-budget=4500", "--dump-dom", page.url],
        capture_output=True, text=True, timeout=120,
    ).stdout  # fmt: skip
    assert 'data-robot="rov1"' in dom
    assert 'data-robot="rov2"' in dom
    assert "constrained (±0.05 m)" in dom
    assert "no fix (7 unplaced)" in dom
    assert 'class="no">no<' in dom  # rov2 is gone
    assert page.base.calls >= 3  # type: ignore[attr-defined]  # the page refreshed itself


@needs_chromium
def test_chromium_screenshot_shows_planes_and_tracks(page: StatusPage, tmp_path: Path) -> None:
    import cv2

    shot = tmp_path / "page.png"
    subprocess.run(
        [CHROMIUM, *FLAGS, "--virtual-time-budget=2500", "--window-size=1000,1000", f"--screenshot={shot}", page.url],
        capture_output=True, timeout=120, check=False,
    )  # fmt: skip
    img = cv2.imread(str(shot))
    assert img is not None, "no screenshot"
    b, g, r = (img[..., i].astype(int) for i in range(3))
    orange = (r > 230) & (abs(g - 140) < 30) & (b < 80)  # the planes' #ff8c1a outline
    blue = (abs(r - 31) < 40) & (abs(g - 119) < 40) & (b > 150)  # rov1's track, #1f77b4
    assert orange.sum() > 500
    assert blue.sum() > 50
