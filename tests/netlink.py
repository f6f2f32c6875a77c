"""A real, impaired link between a base station and its robots: two network namespaces joined by a veth pair.

Used by ``tests/test_link.py`` and ``benchmarks/bench_link.py``. Layout::

    ns "<token>-r" (robots)                       ns "<token>-b" (base station)
    lrsensor rov ... --connect tcp/10.77.0.1:R    relay 10.77.0.1:R --(hold delay_ms)--> 127.0.0.1:Z
         |  veth "vr<token>" 10.77.0.2              lrsensor base --listen tcp/127.0.0.1:Z (router)
         +------------- rate (tbf), loss (iptables) each way ------------+ veth "vb<token>" 10.77.0.1

What each impairment uses (this kernel has no ``netem``, see ../shared/FIELD-NOTES.md):

* rate: ``tc qdisc ... root tbf`` on both ends of the veth pair (each direction);
* loss: ``iptables -A INPUT -i DEV -m statistic --mode random --probability P -j DROP`` in both namespaces;
* latency: :func:`relay`, a TCP proxy in the base's namespace that holds every chunk ``delay_ms`` in each
  direction before passing it on. TCP across the veth therefore sees a short round trip (it recovers losses
  quickly, as it would not on a real 400 ms tether); the application's request and answer see the delay;
* outages: ``ip link set DEV down`` / ``up``.

Zenoh's shared memory is switched off in every process's configuration (:func:`zenoh_config`): between
processes of one host it would carry large messages through ``/dev/shm`` and leave the link idle. The bytes
that crossed the link are read from the veth pair's counters (:meth:`NetLink.link_bytes`), retransmissions
included. Nothing is sent to any address but the two namespaces'.

Every namespace has a unique name and is deleted on exit, also after a failure (deleting a namespace removes
its end of the veth pair and its processes' sockets). :func:`unavailable` says why the harness cannot run
(not root, no ``ip netns``, no ``iptables``) so that a test can skip with that reason.

Run as a script, this module is the relay (``relay``) or a status probe (``probe``) inside a namespace.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import time
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

BASE_ADDR = "10.77.0.1"
ROV_ADDR = "10.77.0.2"
#: Bytes a relay direction holds before it stops reading (keeps its buffer bounded: backpressure to TCP).
RELAY_MAX_HELD = 1 << 20
HERE = Path(__file__).resolve()
ROOT = HERE.parents[1]


@dataclass(frozen=True)
class LinkSpec:
    """The impairments of the link, the same each way.

    Attributes:
        rate_mbit: bandwidth, Mbit/s (None: unlimited).
        loss: probability that a packet is dropped, 0..1.
        delay_ms: time the relay holds the bytes, ms (each way).
    """

    rate_mbit: float | None = 10.0
    loss: float = 0.1
    delay_ms: float = 200.0

    def label(self) -> str:
        rate = "unlimited" if self.rate_mbit is None else f"{self.rate_mbit:g} Mbit/s"
        return f"{rate}, {self.loss * 100:g} % loss, {self.delay_ms:g} ms each way"


def unavailable(need_loss: bool = True) -> str | None:
    """Why the harness cannot run here, or None when it can."""
    if sys.platform != "linux":
        return "network namespaces need Linux"
    if os.geteuid() != 0:
        return "network namespaces need root"
    for tool in ("ip", "tc", *(("iptables",) if need_loss else ())):
        if shutil.which(tool) is None:
            return f"{tool} is not installed"
    probe = f"lrsprobe-{secrets.token_hex(3)}"
    r = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True, check=False)
    if r.returncode != 0:
        return f"ip netns add failed: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True, check=False)
    return None


def zenoh_config(path: Path, mode: str, *, listen: Sequence[str] = (), connect: Sequence[str] = ()) -> Path:
    """Write a Zenoh JSON5 configuration with shared memory and multicast scouting off; returns ``path``."""
    conf: dict[str, Any] = {
        "mode": mode,
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"shared_memory": {"enabled": False}},
    }
    if listen:
        conf["listen"] = {"endpoints": list(listen)}
    if connect:
        conf["connect"] = {"endpoints": list(connect), "timeout_ms": 60000}
    path.write_text(json.dumps(conf, indent=1))
    return path


def _run(*cmd: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    r = subprocess.run(list(cmd), capture_output=True, text=True, check=False)
    if check and r.returncode != 0:
        msg = f"{' '.join(cmd)} failed ({r.returncode}): {r.stderr.strip()}"
        raise RuntimeError(msg)
    return r


class LoggedProcesses:
    """Processes started with their output in ``<workdir>/<name>.log``, all stopped by :meth:`stop_processes`.

    The shared part of :class:`NetLink` and the chaos soak's loopback stand-in: a subclass says where a command
    runs by overriding :meth:`command`.
    """

    def __init__(self, workdir: Path) -> None:
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self._procs: list[subprocess.Popen[bytes]] = []
        self._logs: list[IO[bytes]] = []

    def command(self, ns: str, args: Sequence[str]) -> list[str]:
        """The argument vector that runs ``args`` in namespace ``ns`` (here: as it is)."""
        return list(args)

    def start(self, name: str, ns: str, args: Sequence[str]) -> subprocess.Popen[bytes]:
        """Start ``args`` inside namespace ``ns``, output to ``<workdir>/<name>.log``; stopped at exit."""
        fh = (self.workdir / f"{name}.log").open("ab")
        self._logs.append(fh)
        env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(ROOT))
        p = subprocess.Popen(self.command(ns, args), stdout=fh, stderr=subprocess.STDOUT, env=env)
        self._procs.append(p)
        return p

    def log(self, name: str) -> str:
        """The output of the process started as ``name`` so far."""
        for fh in self._logs:
            fh.flush()
        path = self.workdir / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def stop_processes(self) -> None:
        """SIGTERM every process started here (newest first), SIGKILL what is left after 10 s (idempotent)."""
        for p in reversed(self._procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + 10.0
        for p in reversed(self._procs):
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)
        self._procs.clear()
        for fh in self._logs:
            fh.close()
        self._logs.clear()


class NetLink(LoggedProcesses):
    """Two namespaces, a veth pair with ``spec``'s impairments and a delaying relay; a context manager.

    Args:
        spec: the link's impairments.
        workdir: where logs and configuration files go.
    """

    def __init__(self, spec: LinkSpec, workdir: Path) -> None:
        super().__init__(workdir)
        self.spec = spec
        token = secrets.token_hex(3)
        self.ns_base = f"lrs{token}-b"
        self.ns_rov = f"lrs{token}-r"
        self.dev_base = f"vb{token}"
        self.dev_rov = f"vr{token}"
        self.zenoh_port = 7447
        self.relay_port = 7448
        self._made: list[str] = []

    # ------------------------------------------------------------------------------------------- set up
    def __enter__(self) -> NetLink:
        # a SIGTERM must tear the namespaces down too (the default action would skip every ``finally``)
        if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
            signal.signal(signal.SIGTERM, _terminate)
        try:
            self._setup()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _setup(self) -> None:
        for ns in (self.ns_base, self.ns_rov):
            _run("ip", "netns", "add", ns)
            self._made.append(ns)
            _run("ip", "-n", ns, "link", "set", "lo", "up")
        _run("ip", "link", "add", self.dev_base, "type", "veth", "peer", "name", self.dev_rov)
        try:
            _run("ip", "link", "set", self.dev_base, "netns", self.ns_base)
            _run("ip", "link", "set", self.dev_rov, "netns", self.ns_rov)
        except RuntimeError:
            _run("ip", "link", "del", self.dev_base, check=False)
            raise
        for ns, dev, addr in ((self.ns_base, self.dev_base, BASE_ADDR), (self.ns_rov, self.dev_rov, ROV_ADDR)):
            _run("ip", "-n", ns, "addr", "add", f"{addr}/30", "dev", dev)
            _run("ip", "-n", ns, "link", "set", dev, "up")
            if self.spec.rate_mbit is not None:
                _run(
                    "ip", "netns", "exec", ns, "tc", "qdisc", "add", "dev", dev, "root", "tbf",
                    "rate", f"{self.spec.rate_mbit:g}mbit", "burst", "64kbit", "latency", "500ms",
                )  # fmt: skip
            if self.spec.loss > 0:
                _run(
                    "ip", "netns", "exec", ns, "iptables", "-A", "INPUT", "-i", dev, "-m", "statistic",
                    "--mode", "random", "--probability", f"{self.spec.loss:g}", "-j", "DROP",
                )  # fmt: skip
        relay = [
            sys.executable, str(HERE), "relay", "--listen", f"{BASE_ADDR}:{self.relay_port}",
            "--to", f"127.0.0.1:{self.zenoh_port}", "--delay-ms", f"{self.spec.delay_ms:g}",
        ]  # fmt: skip
        self.start("relay", self.ns_base, relay)

    # ------------------------------------------------------------------------------------------- processes
    def command(self, ns: str, args: Sequence[str]) -> list[str]:
        return ["ip", "netns", "exec", ns, *args]

    def base_endpoint(self) -> str:
        """Where the base station (router) listens inside its namespace."""
        return f"tcp/127.0.0.1:{self.zenoh_port}"

    def rov_endpoint(self) -> str:
        """Where a robot connects: the relay, across the link."""
        return f"tcp/{BASE_ADDR}:{self.relay_port}"

    def base_config(self) -> Path:
        return zenoh_config(self.workdir / "base.json5", "router", listen=[self.base_endpoint()])

    def rov_config(self) -> Path:
        return zenoh_config(self.workdir / "rov.json5", "client", connect=[self.rov_endpoint()])

    # ------------------------------------------------------------------------------------------- link
    def link_bytes(self) -> dict[str, int]:
        """Bytes and packets sent by each end of the veth pair (``up``: robots to base, ``down``: back)."""
        out: dict[str, int] = {}
        for ns, dev, key in ((self.ns_rov, self.dev_rov, "up"), (self.ns_base, self.dev_base, "down")):
            r = _run("ip", "-n", ns, "-s", "-j", "link", "show", "dev", dev)
            stats = json.loads(r.stdout)[0]["stats64"]["tx"]
            out[f"{key}_bytes"] = int(stats["bytes"])
            out[f"{key}_packets"] = int(stats["packets"])
        return out

    def set_up(self, up: bool) -> None:
        """Take the link down (an outage: both ends lose carrier) or bring it back."""
        state = "up" if up else "down"
        _run("ip", "-n", self.ns_rov, "link", "set", self.dev_rov, state)
        _run("ip", "-n", self.ns_base, "link", "set", self.dev_base, state)

    # ------------------------------------------------------------------------------------------- tear down
    def close(self) -> None:
        """Stop every process started here and delete the namespaces (idempotent)."""
        self.stop_processes()
        for ns in self._made:
            _run("ip", "netns", "del", ns, check=False)
        self._made.clear()


def _terminate(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)


class StatusProbe:
    """A long-lived Zenoh client in the base's namespace that answers the base station's status on demand."""

    def __init__(self, link: NetLink, fleet: str) -> None:
        conf = zenoh_config(link.workdir / "probe.json5", "client", connect=[link.base_endpoint()])
        env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(ROOT))
        self.p = subprocess.Popen(
            ["ip", "netns", "exec", link.ns_base, sys.executable, str(HERE), "probe", "--config", str(conf),
             "--key", f"lrs/{fleet}/base/status"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env,
        )  # fmt: skip
        link._procs.append(self.p)  # stopped with the link

    def status(self) -> dict[str, Any] | None:
        """The base station's status JSON, or None when it did not answer."""
        assert self.p.stdin is not None
        assert self.p.stdout is not None
        self.p.stdin.write(b"?\n")
        self.p.stdin.flush()
        line = self.p.stdout.readline()
        if not line:
            return None
        data = json.loads(line)
        return data if isinstance(data, dict) else None


@contextlib.contextmanager
def netlink(spec: LinkSpec, workdir: Path) -> Iterator[NetLink]:
    """``with netlink(spec, dir) as link:`` a :class:`NetLink`, always torn down."""
    link = NetLink(spec, workdir)
    with link:
        yield link


# ----------------------------------------------------------------------------------------------- a fleet run
@dataclass
class FleetRun:
    """What one run of a base station and replaying robots over the link gave.

    Attributes:
        robots: the robots' names.
        frames: clouds each robot replays.
        received: per robot, distinct clouds the base station holds.
        duplicates: per robot, copies the base station received again.
        acked: per robot, clouds the base station acknowledged.
        exit_codes: per robot, the ``lrsensor rov`` exit code (None: killed at the deadline).
        resent: per robot, re-sends the ROV reported.
        cloud_bytes: per robot, bytes of its clouds (each counted once).
        resent_bytes: per robot, bytes re-sent.
        resent_unheard: per robot, re-sends of clouds whose earlier copies reached no subscriber.
        pending: per robot, clouds left in its outbox.
        link: :meth:`NetLink.link_bytes` at the end (minus the start).
        transit_ms: the base station's transit percentiles (``p50``, ``p99``), ms.
        wall_s: from the robots' start to the last exit.
        logs: per robot, its output.
        budget: per robot, the link-budget counters of its summary line (``published``, ``reloaded``,
            ``live``, ``forwarded``, ``queued``, ``dropped_budget``, ``released``, ``thinned``, ``held``; empty
            if none).
        reported: per robot, the base station's ``robots.<robot>.reported`` (the ROV's last status).
        held_ranges: per robot, the sequence ranges the base station holds (its ``fleet.json``).
        dropped_ranges: per robot, the ranges its outbox dropped by the budget (its ``state.json``).
    """

    robots: tuple[str, ...]
    frames: int
    received: dict[str, int]
    duplicates: dict[str, int]
    acked: dict[str, int]
    exit_codes: dict[str, int | None]
    resent: dict[str, int]
    cloud_bytes: dict[str, int]
    resent_bytes: dict[str, int]
    resent_unheard: dict[str, int]
    pending: dict[str, int]
    link: dict[str, int]
    transit_ms: dict[str, float | None]
    wall_s: float
    logs: dict[str, str]
    budget: dict[str, dict[str, int]] = field(default_factory=dict)
    reported: dict[str, dict[str, Any]] = field(default_factory=dict)
    held_ranges: dict[str, list[list[int]]] = field(default_factory=dict)
    dropped_ranges: dict[str, list[list[int]]] = field(default_factory=dict)

    @property
    def delivered(self) -> int:
        return sum(self.received.values())

    @property
    def expected(self) -> int:
        return self.frames * len(self.robots)

    @property
    def sent_twice(self) -> int:
        """Re-sends of clouds whose earlier copy had gone out on the link."""
        return sum(self.resent.values()) - sum(self.resent_unheard.values())

    @property
    def sent_twice_pct(self) -> float:
        """:attr:`sent_twice` as a share of the clouds, %."""
        return 100.0 * self.sent_twice / max(1, self.expected)

    @property
    def link_ratio(self) -> float:
        """Bytes the robots sent over the link / their clouds' bytes."""
        return self.link["up_bytes"] / max(1, sum(self.cloud_bytes.values()))


_OUTBOX_LINE = re.compile(
    r"rov (\S+): outbox (\d+) pending, (\d+) acknowledged, (\d+) re-sent"
    r"(?: \((\d+) bytes(?:, (\d+) never heard before)?\))?.*?"
    r"(?:, clouds (\d+) bytes)?$",
    re.MULTILINE,
)

_BUDGET_LINE = re.compile(
    r"rov (\S+): link budget: published (\d+) \+ reloaded (\d+) = live (\d+) \+ forwarded (\d+) \+ queued (\d+) "
    r"\+ dropped by the budget (\d+) \((\d+) sent and released by the budget before their acknowledgement, "
    r"(\d+) thinned from the live stream, (\d+) held\)",
)
_BUDGET_KEYS = (
    "published", "reloaded", "live", "forwarded", "queued", "dropped_budget", "released", "thinned", "held"
)


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def run_fleet(
    link: NetLink,
    dive: Path,
    *,
    robots: Sequence[str] = ("rov1", "rov2", "rov3"),
    frames: int,
    rate_hz: float = 10.0,
    outage: tuple[float, float] | None = None,
    ack_timeout_s: float = 60.0,
    deadline_s: float = 300.0,
    rov_args: Sequence[str] = (),
    fleet: str = "lk",
    outbox_dir: Path | None = None,
) -> FleetRun:
    """Run a base station and ``robots`` replaying ``dive`` at ``rate_hz`` over ``link``.

    ``outage``: ``(after_s, for_s)`` takes the link down for ``for_s``, ``after_s`` after the base station
    holds a first cloud of every robot (the robots' start-up takes seconds and must not hide the outage).
    Robots still running ``deadline_s`` after the start are killed (exit code None).
    """
    work = link.workdir
    state = work / "state"
    outboxes = outbox_dir or (work / "outbox")
    base = link.start(
        "base",
        link.ns_base,
        [sys.executable, "-m", "lrsensor", "-v", "base", "--fleet", fleet, "--config", str(link.base_config()),
         "--state", str(state), "--map", "off", "--status-every-s", "0"],
    )  # fmt: skip
    probe = StatusProbe(link, fleet)
    t_ready = time.monotonic() + 60.0
    while probe.status() is None:
        if time.monotonic() > t_ready or base.poll() is not None:
            msg = f"the base station did not answer:\n{link.log('base')}"
            raise RuntimeError(msg)
        time.sleep(0.5)
    start_bytes = link.link_bytes()
    procs = {}
    t0 = time.monotonic()
    for r in robots:
        procs[r] = link.start(
            r,
            link.ns_rov,
            [sys.executable, "-m", "lrsensor", "-v", "rov", "--fleet", fleet, "--robot", r,
             "--config", str(link.rov_config()), "--source", str(dive), "--imu", f"csv:{dive / 'imu.csv'}",
             "--calib", str(dive / "calib.json"), "--rate", f"{rate_hz:g}", "--ack-timeout-s", f"{ack_timeout_s:g}",
             "--outbox", str(outboxes / r), *rov_args],
        )  # fmt: skip
    down_at = up_at = None
    flowing = outage is None  # the outage clock starts once the base holds a cloud of every robot
    codes: dict[str, int | None] = {}
    last_exit = t0
    while len(codes) < len(robots):
        now = time.monotonic()
        if not flowing and outage is not None:
            got = (probe.status() or {}).get("robots", {})
            if all(got.get(r, {}).get("received", 0) > 0 for r in robots):
                flowing = True
                down_at, up_at = now + outage[0], now + outage[0] + outage[1]
            now = time.monotonic()
        if down_at is not None and now >= down_at:
            link.set_up(False)
            down_at = None
        if up_at is not None and down_at is None and now >= up_at:
            link.set_up(True)
            up_at = None
        for r, p in procs.items():
            if r not in codes and p.poll() is not None:
                codes[r] = p.returncode
                last_exit = now
        if now - t0 > deadline_s:
            for r, p in procs.items():
                if r not in codes:
                    p.kill()
                    p.wait(10)
                    codes[r] = None
            last_exit = now
            break
        time.sleep(0.2)
    if up_at is not None:
        link.set_up(True)
    wall = last_exit - t0
    end_bytes = link.link_bytes()
    time.sleep(1.0)
    st = probe.status() or {}
    rob = st.get("robots", {})
    logs = {r: link.log(r) for r in robots}
    resent: dict[str, int] = {}
    cloud_bytes: dict[str, int] = {}
    resent_bytes: dict[str, int] = {}
    pending: dict[str, int] = {}
    unheard: dict[str, int] = {}
    for r in robots:
        found = list(_OUTBOX_LINE.finditer(logs[r]))
        m = found[-1] if found else None
        if m is not None and m.group(1) == r:
            pending[r] = int(m.group(2))
            resent[r] = int(m.group(4))
            resent_bytes[r] = int(m.group(5) or 0)
            cloud_bytes[r] = int(m.group(7) or 0)
            unheard[r] = int(m.group(6) or 0)
        else:
            pending[r], resent[r], resent_bytes[r], cloud_bytes[r], unheard[r] = -1, 0, 0, 0, 0
    transit = st.get("ingest", {}).get("transit_ms", {})
    budget: dict[str, dict[str, int]] = {}
    for r in robots:
        found_b = [b for b in _BUDGET_LINE.finditer(logs[r]) if b.group(1) == r]
        budget[r] = dict(zip(_BUDGET_KEYS, (int(v) for v in found_b[-1].groups()[1:]), strict=True)) if found_b else {}
    fleet_state = _read_json(state / "fleet.json").get("robots", {})
    return FleetRun(
        robots=tuple(robots),
        frames=frames,
        received={r: int(rob.get(r, {}).get("received", 0)) for r in robots},
        duplicates={r: int(rob.get(r, {}).get("duplicates", 0)) for r in robots},
        acked={r: int(rob.get(r, {}).get("acked", 0)) for r in robots},
        exit_codes=codes,
        resent=resent,
        cloud_bytes=cloud_bytes,
        resent_bytes=resent_bytes,
        resent_unheard=unheard,
        pending=pending,
        link={k: end_bytes[k] - start_bytes[k] for k in end_bytes},
        transit_ms={"p50": transit.get("p50"), "p99": transit.get("p99")},
        wall_s=wall,
        logs=logs,
        budget=budget,
        reported={r: dict(rob.get(r, {}).get("reported", {})) for r in robots},
        held_ranges={r: list(fleet_state.get(r, {}).get("ranges", [])) for r in robots},
        dropped_ranges={r: list(_read_json(outboxes / r / "state.json").get("dropped_ranges", [])) for r in robots},
    )


# ----------------------------------------------------------------------------------------------- relay
async def _pump(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, delay_s: float) -> None:
    """Copy ``reader`` to ``writer``, each chunk held ``delay_s``; reading pauses while too much is held."""
    held: deque[tuple[float, bytes]] = deque()
    held_bytes = 0
    more = asyncio.Event()
    room = asyncio.Event()
    room.set()
    done = False

    async def read() -> None:
        nonlocal held_bytes, done
        try:
            while True:
                await room.wait()
                chunk = await reader.read(65536)
                if not chunk:
                    break
                held.append((time.monotonic() + delay_s, chunk))
                held_bytes += len(chunk)
                if held_bytes >= RELAY_MAX_HELD:
                    room.clear()
                more.set()
        except (ConnectionError, OSError):
            pass
        finally:
            done = True
            more.set()

    async def write() -> None:
        nonlocal held_bytes
        try:
            while True:
                if not held:
                    if done:
                        break
                    more.clear()
                    await more.wait()
                    continue
                due, chunk = held[0]
                wait = due - time.monotonic()
                if wait > 0:
                    await asyncio.sleep(wait)
                held.popleft()
                held_bytes -= len(chunk)
                if held_bytes < RELAY_MAX_HELD:
                    room.set()
                writer.write(chunk)
                await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            with contextlib.suppress(Exception):
                writer.close()

    await asyncio.gather(read(), write())


async def _relay(listen: str, to: str, delay_s: float) -> None:
    host, port = listen.rsplit(":", 1)
    to_host, to_port = to.rsplit(":", 1)

    async def handle(r_in: asyncio.StreamReader, w_in: asyncio.StreamWriter) -> None:
        try:
            r_out, w_out = await asyncio.open_connection(to_host, int(to_port))
        except OSError:
            w_in.close()
            return
        await asyncio.gather(_pump(r_in, w_out, delay_s), _pump(r_out, w_in, delay_s))
        for w in (w_in, w_out):
            with contextlib.suppress(Exception):
                w.close()

    server = await asyncio.start_server(handle, host, int(port))
    print(f"relay {listen} -> {to}, {delay_s * 1000:g} ms each way", flush=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    async with server:
        await stop.wait()


def _probe(config: str, key: str) -> None:
    import zenoh

    with zenoh.open(zenoh.Config.from_file(config)) as session:
        for _ in sys.stdin:
            answer: Any = None
            for reply in session.get(key, timeout=5.0):
                if reply.ok is not None:
                    answer = json.loads(reply.ok.payload.to_bytes())
                    break
            print(json.dumps(answer), flush=True)


def main(argv: Sequence[str] | None = None) -> None:
    """``netlink.py relay --listen HOST:PORT --to HOST:PORT --delay-ms D`` or ``netlink.py probe ...``."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("relay")
    r.add_argument("--listen", required=True)
    r.add_argument("--to", required=True)
    r.add_argument("--delay-ms", type=float, default=0.0)
    p = sub.add_parser("probe")
    p.add_argument("--config", required=True)
    p.add_argument("--key", required=True)
    args = ap.parse_args(argv)
    if args.cmd == "relay":
        asyncio.run(_relay(args.listen, args.to, args.delay_ms / 1000.0))
    else:
        _probe(args.config, args.key)


if __name__ == "__main__":
    main()
