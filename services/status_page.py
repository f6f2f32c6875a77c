"""The base station's status page (``lrsensor base --http [HOST:]PORT``): one self-contained page, no internet.

Routes (all GET):

* ``/``: the page: the fleet table (a row per robot: name, alive, received, missed, rejected, pose quality)
  and a top view of the map's planes and the robots' tracks (north up, east right, metres), refreshed every
  second by the page itself (``fetch``), without a reload; no script or style comes from elsewhere;
* ``/status.json``: what ``<root>/base/status`` answers;
* ``/map.json``: what ``<root>/map`` answers (planes in NED with their extent);
* ``/tracks.json``: ``{"<robot>": [[north_m, east_m], ...]}``, at most :data:`TRACK_POINTS` per robot.

Pose quality: with navigation, the robot's ``position`` (constrained / partly / unconstrained / unknown) and
its horizontal standard deviation; without, ``fix`` or ``no fix`` from the clouds it could not place.

The server is the standard library's threading HTTP server in a daemon thread; the default host is
127.0.0.1 (give another host to serve a ship's network on purpose).
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

import numpy as np

from .errors import ServiceError

log = logging.getLogger(__name__)

#: At most this many positions per robot on ``/tracks.json``.
TRACK_POINTS = 1000


class StatusPageError(ServiceError):
    """The status page cannot listen where it was asked to."""


PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>lrsensor fleet</title>
<style>
body { font: 14px system-ui, sans-serif; margin: 16px; color: #222; background: #fafafa; }
h1 { font-size: 18px; margin: 0 0 8px; }
#meta { color: #666; margin-bottom: 12px; }
table { border-collapse: collapse; margin-bottom: 16px; background: #fff; }
th, td { border: 1px solid #ccc; padding: 4px 10px; text-align: right; }
th:first-child, td:first-child { text-align: left; }
td.yes { color: #080; } td.no { color: #b00; }
canvas { border: 1px solid #ccc; background: #fff; }
</style></head>
<body>
<h1>lrsensor fleet <span id="fleet"></span></h1>
<div id="meta">waiting for the base station ...</div>
<table id="robots"><thead><tr><th>robot</th><th>alive</th><th>received</th><th>missed</th><th>rejected</th>
<th>pose quality</th></tr></thead><tbody></tbody></table>
<canvas id="top" width="900" height="600"></canvas>
<div id="legend">top view: north up, east right; orange: map planes, coloured lines: robot tracks</div>
<script>
const COLORS = ["#1f77b4", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22"];
function quality(r) {
  if (r.nav) {
    const sd = (r.nav.north_m_std != null && r.nav.east_m_std != null)
      ? " (\\u00b1" + Math.max(r.nav.north_m_std, r.nav.east_m_std).toFixed(2) + " m)" : "";
    return r.nav.position + sd;
  }
  return (r.unplaced || 0) > 0 ? "no fix (" + r.unplaced + " unplaced)" : "fix";
}
function cell(text, cls) { const td = document.createElement("td"); td.textContent = text;
  if (cls) td.className = cls; return td; }
function drawTable(st) {
  document.getElementById("fleet").textContent = st.fleet || "";
  const body = document.querySelector("#robots tbody"); body.replaceChildren();
  for (const [name, r] of Object.entries(st.robots || {}).sort()) {
    const tr = document.createElement("tr"); tr.dataset.robot = name;
    tr.append(cell(name), cell(r.alive ? "yes" : "no", r.alive ? "yes" : "no"), cell(r.received),
              cell(r.missed), cell(r.rejected), cell(quality(r)));
    body.append(tr);
  }
  const planes = (st.map && st.map.planes != null) ? st.map.planes : "?";
  document.getElementById("meta").textContent =
    "updated " + new Date(st.t_ns / 1e6).toISOString() + " \\u2014 map planes: " + planes;
}
function drawTop(map, tracks) {
  const cv = document.getElementById("top"), g = cv.getContext("2d");
  const shapes = [];
  for (const p of (map.planes || [])) {
    const c = p.extent && p.extent.corners; if (c && c.length === 4) shapes.push(c.map(q => [q[1], q[0]]));
  }
  const lines = Object.entries(tracks).map(([name, pts]) => [name, pts.map(q => [q[1], q[0]])]);
  const all = shapes.flat().concat(lines.flatMap(l => l[1]));
  g.clearRect(0, 0, cv.width, cv.height);
  if (!all.length) { g.fillStyle = "#888"; g.fillText("no planes or tracks yet", 20, 30); return; }
  let x0 = Math.min(...all.map(p => p[0])), x1 = Math.max(...all.map(p => p[0]));
  let y0 = Math.min(...all.map(p => p[1])), y1 = Math.max(...all.map(p => p[1]));
  const m = 0.5; x0 -= m; x1 += m; y0 -= m; y1 += m;
  const s = Math.min(cv.width / (x1 - x0), cv.height / (y1 - y0));
  const X = e => (e - x0) * s, Y = n => cv.height - (n - y0) * s;
  g.lineWidth = 4; g.strokeStyle = "#ff8c1a"; g.fillStyle = "rgba(255,140,26,0.25)";
  for (const sh of shapes) {
    g.beginPath(); sh.forEach((p, i) => i ? g.lineTo(X(p[0]), Y(p[1])) : g.moveTo(X(p[0]), Y(p[1])));
    g.closePath(); g.fill(); g.stroke();
  }
  g.lineWidth = 2;
  lines.forEach(([name, pts], k) => {
    g.strokeStyle = COLORS[k % COLORS.length]; g.beginPath();
    pts.forEach((p, i) => i ? g.lineTo(X(p[0]), Y(p[1])) : g.moveTo(X(p[0]), Y(p[1]))); g.stroke();
    if (pts.length) { const p = pts[pts.length - 1]; g.fillStyle = g.strokeStyle;
      g.fillText(name, X(p[0]) + 5, Y(p[1]) - 5); }
  });
}
async function refresh() {
  try {
    const [st, map, tracks] = await Promise.all(
      ["status.json", "map.json", "tracks.json"].map(u => fetch(u, {cache: "no-store"}).then(r => r.json())));
    drawTable(st); drawTop(map, tracks);
  } catch (e) { document.getElementById("meta").textContent = "base station not answering: " + e; }
}
refresh(); setInterval(refresh, 1000);
</script></body></html>
"""


def thin_track(track: np.ndarray, limit: int = TRACK_POINTS) -> list[list[float]]:
    """``[[north_m, east_m], ...]`` of an (M, >= 3) ``t_ns, north, east, ...`` track, at most ``limit`` rows."""
    if track.shape[0] == 0:
        return []
    step = max(1, -(-track.shape[0] // limit))
    rows = track[::step, 1:3]
    rows = rows[np.all(np.isfinite(rows), axis=1)]
    return [[round(float(n), 3), round(float(e), 3)] for n, e in rows]


class StatusPage:
    """Serves the status page (see the module docstring).

    Args:
        status: the base station's status JSON.
        map_json: the whole map JSON.
        tracks: per robot, an (M, 4) ``t_ns, north_m, east_m, down_m`` array.
        host: address to listen on.
        port: port to listen on (0: any free port, see :attr:`port`).
    """

    def __init__(
        self,
        status: Callable[[], dict[str, Any]],
        map_json: Callable[[], dict[str, Any]],
        tracks: Callable[[], dict[str, np.ndarray]],
        host: str = "127.0.0.1",
        port: int = 8080,
    ) -> None:
        routes: dict[str, Callable[[], bytes]] = {
            "/": lambda: PAGE.encode(),
            "/status.json": lambda: json.dumps(status()).encode(),
            "/map.json": lambda: json.dumps(map_json()).encode(),
            "/tracks.json": lambda: json.dumps({r: thin_track(t) for r, t in tracks().items()}).encode(),
        }

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                path = self.path.split("?", 1)[0]
                route = routes.get("/" if path == "/index.html" else path)
                if route is None:
                    self.send_error(404, f"no page {path}; try / or /status.json")
                    return
                try:
                    body = route()
                except Exception as err:  # the page must say why, not hang
                    log.warning("status page %s failed: %s", path, err)
                    self.send_error(500, f"{path}: {err}")
                    return
                self.send_response(200)
                ctype = "text/html; charset=utf-8" if path in ("/", "/index.html") else "application/json"
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, format: str, *args: Any) -> None:
                log.debug("status page: " + format, *args)

        try:
            self.server = ThreadingHTTPServer((host, port), Handler)
        except OSError as err:
            msg = f"the status page cannot listen on {host}:{port}: {err}"
            raise StatusPageError(msg) from err
        self.server.daemon_threads = True
        self.host = host
        self._thread = threading.Thread(target=self.server.serve_forever, name="status-page", daemon=True)
        self._thread.start()

    @property
    def port(self) -> int:
        """The port the page is served on."""
        return int(self.server.server_address[1])

    @property
    def url(self) -> str:
        """``http://host:port/``."""
        return f"http://{self.host}:{self.port}/"

    def close(self) -> None:
        """Stop serving."""
        self.server.shutdown()
        self.server.server_close()
        self._thread.join(timeout=5.0)

    def __enter__(self) -> StatusPage:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
