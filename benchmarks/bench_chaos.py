"""Chaos soak: random kills and restarts of the base station, the router and the robots, link flaps; then the
accounting (issue 30, item 5).

    python benchmarks/bench_chaos.py [--minutes 30] [--seed 1] [--robots 3] [--rate 5] [--dive-frames 300]

Topology (what a deployment has: ROVs on a tether to a surface router, the base station behind it)::

    ns "<token>-r" (robots)                        ns "<token>-b" (surface)
    lrsensor rov (x3) --outbox DIR  ---tether--->  relay (delay) -> bare router 127.0.0.1:7447
                                    10 Mbit/s,                       ^ lrsensor base --mode client --state DIR
                                    5 % loss, 100 ms each way

The link is ``tests/netlink.py``'s veth pair (tbf rate, iptables loss, a delaying relay; Zenoh shared memory
off). Without root or ``iptables`` (:func:`netlink.unavailable`) everything runs on loopback instead, without
the impairments or flaps, and the table says so. The router is the bare router of ``tests/procs.py``.

Each robot replays a recorded dive (``--source DIR``, ``--rate`` Hz) into a persistent outbox; when a dive
ends (every cloud acknowledged: exit 0; or not: exit 3, the backlog stays in the outbox) the next dive starts
at once with the same ``--outbox``. **What a restarted robot replays**: a robot process started again (after
a kill or at the end of a dive) replays its dive from the first frame, and its clouds are numbered after the
highest number its outbox ever used (``state.json`` and the message files): the same frames make new clouds
with new numbers, and the clouds pending from the earlier run are forwarded first. So the clouds a robot
**produced** are exactly the numbers ``0 .. next_seq - 1`` of its outbox at the end (numbers are never
skipped: a cloud gets one only when it is published), and the base station must hold exactly those, each once.

The faults are drawn from a seeded random schedule, one every ``--fault-every-s`` on average (exponential
gaps, at least 3 s apart): SIGKILL or SIGTERM of the base station, of the router, or of one robot, restarted
after a random pause (base, router: 2-15 s; robot: 1-8 s); a link flap (``ip link set down`` for 10-60 s).
A target already down is not hit again; the first faults cover every kind once. A base station, router or
robot that exits without being told to (a crash) is counted and restarted as a supervisor would.

At the end the faults stop, everything is brought up, and the soak waits (``--heal-s`` at most) until every
robot has finished a dive with every cloud acknowledged (exit 0); then it stops the base station (SIGTERM: its
final checkpoint) and the router and accounts, from the files: per robot the produced set (its outbox), the
set the base station holds (``fleet.json``'s ranges) and acknowledged (``acked``), clouds pending or dropped
in the outboxes, duplicates the base received (counted in ``fleet.json``; a base SIGKILLed loses the count
since its last save, so this is a lower bound), re-sends (from the summary lines of the robot runs that ended
cleanly: a SIGKILLed run prints none), the faults injected, and every process's resident memory (VmRSS,
sampled every few seconds; per kind of process the peak over the first and the second half of the run).

Prints markdown tables and writes ``benchmarks/results/<out>`` (``chaos.md``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import random
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]  # run as a script or as -m benchmarks.bench_chaos

from netlink import LinkSpec, LoggedProcesses, NetLink, unavailable, zenoh_config  # noqa: E402
from procs import router_cmd  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
FLEET = "chaos"
#: The tether of the soak: moderate impairments (the link tests cover the harsh ones).
TETHER = LinkSpec(rate_mbit=10.0, loss=0.05, delay_ms=100.0)
ROUTER_PORT = 7447
#: Fault kinds, with their weights in the random schedule.
KINDS: dict[str, float] = {
    "robot SIGKILL": 3.0,
    "robot SIGTERM": 1.0,
    "base SIGKILL": 2.0,
    "base SIGTERM": 1.0,
    "router SIGKILL": 2.0,
    "router SIGTERM": 1.0,
    "link flap": 3.0,
}
RSS_EVERY_S = 5.0

_OUTBOX_LINE = re.compile(
    r"rov (\S+): outbox (\d+) pending, (\d+) acknowledged, (\d+) re-sent \((\d+) bytes, (\d+) never heard before\)"
)
_FRAMES_LINE = re.compile(r"rov (\S+): frames (\d+), published (\d+)")


@dataclass(frozen=True)
class ChaosConfig:
    """One soak's parameters.

    Attributes:
        fault_s: how long faults are injected, seconds.
        robots: how many robots.
        rate_hz: each robot's replay rate, frames/s.
        dive_frames: frames of the recorded dive every robot replays (a dive lasts ``dive_frames / rate_hz``).
        seed: the fault schedule's seed.
        fault_every_s: mean gap between two faults, seconds.
        flap_s: shortest and longest link flap, seconds.
        heal_s: how long the end waits for every robot to deliver everything, at most, seconds.
        ack_timeout_s: the robots' ``--ack-timeout-s``.
        spec: the tether's impairments.
        loopback: run on loopback even where namespaces are available.
        cloud_schema: the robots' ``--cloud-schema``.
    """

    fault_s: float = 1800.0
    robots: int = 3
    rate_hz: float = 5.0
    dive_frames: int = 300
    seed: int = 1
    fault_every_s: float = 45.0
    flap_s: tuple[float, float] = (10.0, 60.0)
    heal_s: float = 600.0
    ack_timeout_s: float = 60.0
    spec: LinkSpec = TETHER
    loopback: bool = False
    cloud_schema: int = 2


# ----------------------------------------------------------------------------------------------- the network
class Loopback(LoggedProcesses):
    """Everything on this host's loopback: the stand-in for :class:`netlink.NetLink` without root (no flaps)."""

    ns_base = ns_rov = ""

    def __init__(self, workdir: Path) -> None:
        from services.testnet import free_port

        super().__init__(workdir)
        self.zenoh_port = free_port()

    def rov_endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.zenoh_port}"

    def link_bytes(self) -> dict[str, int]:
        return {"up_bytes": 0, "down_bytes": 0, "up_packets": 0, "down_packets": 0}

    def set_up(self, up: bool) -> None:  # no link to take down on loopback
        return

    def close(self) -> None:
        self.stop_processes()


@contextlib.contextmanager
def open_net(cfg: ChaosConfig, workdir: Path) -> Iterator[NetLink | Loopback]:
    """The tether between namespaces, or loopback when namespaces are unavailable (or ``cfg.loopback``)."""
    if cfg.loopback or unavailable() is not None:
        net = Loopback(workdir)
        try:
            yield net
        finally:
            net.close()
        return
    with NetLink(cfg.spec, workdir) as link:
        yield link


def outbox_next_seq(folder: Path) -> int:
    """One past the highest number ``folder``'s outbox ever used (its ``state.json`` and message files), as
    :class:`services.outbox.Outbox` computes it on reload; 0 for a new outbox."""
    n = 0
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
        n = int(json.loads((folder / "state.json").read_text())["next_seq"])
    for p in folder.glob("*.msg"):
        with contextlib.suppress(ValueError):
            n = max(n, int(p.name[:-4]) + 1)
    return n


def rss_kib(pid: int) -> int | None:
    """Resident set size of ``pid``, KiB (None once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def _ranges_set(ranges: Any) -> set[int]:
    return {s for lo, hi in (ranges or []) for s in range(int(lo), int(hi) + 1)}


def _fmt_ranges(seqs: set[int], limit: int = 6) -> str:
    out: list[str] = []
    for s in sorted(seqs):
        if out and out[-1].endswith(f"-{s - 1}"):
            out[-1] = out[-1].rsplit("-", 1)[0] + f"-{s}"
        elif out and out[-1] == str(s - 1):
            out[-1] = f"{s - 1}-{s}"
        else:
            out.append(str(s))
    return ", ".join(out[:limit]) + (" ..." if len(out) > limit else "")


# ----------------------------------------------------------------------------------------------- services
@dataclass
class Service:
    """One supervised process (the base station, the router or a robot) and what happened to it."""

    name: str
    kind: str  # "base", "router" or "robot"
    proc: subprocess.Popen[bytes] | None = None
    runs: int = 0
    restart_at: float | None = None  # monotonic time of a scheduled (re)start
    expected_exit: bool = False  # we signalled it
    exits: Counter[str] = field(default_factory=Counter)
    crashes: list[str] = field(default_factory=list)
    started_t: float = 0.0

    @property
    def up(self) -> bool:
        return self.proc is not None and self.proc.poll() is None


@dataclass
class ChaosResult:
    """What a soak gave (see the module docstring for how each figure is taken)."""

    cfg: ChaosConfig
    network: str
    produced: dict[str, int]
    held: dict[str, int]
    missing: dict[str, list[int]]
    extra: dict[str, list[int]]
    unacked: dict[str, int]
    pending: dict[str, int]
    dropped: dict[str, int]
    duplicates: dict[str, int]
    rejected: dict[str, int]
    reused: dict[str, int]
    faults: Counter[str]
    flap_down_s: float
    robot_runs: dict[str, Counter[str]]
    dives_done: int
    crashes: list[str]
    resent: int
    resent_unheard: int
    clean_runs: int
    all_runs: int
    clouds_in_clean_runs: int
    rss: dict[str, list[tuple[float, int, int]]]  # kind -> (t, pid, KiB)
    wall_s: float
    heal_s: float
    healed: bool
    link: dict[str, int]
    base_exit: int | None
    log_dir: Path

    @property
    def total_produced(self) -> int:
        return sum(self.produced.values())

    @property
    def sent_twice(self) -> int:
        return self.resent - self.resent_unheard

    @property
    def ok(self) -> bool:
        """Every cloud produced held by the base station once and acknowledged, outboxes empty, no crash."""
        return (
            self.healed
            and not any(self.missing.values())
            and not any(self.extra.values())
            and not any(self.unacked.values())
            and not any(self.pending.values())
            and not any(self.dropped.values())
            and not any(self.reused.values())
            and not self.crashes
            and self.total_produced > 0
        )

    def rss_peaks(self, kind: str) -> tuple[int, int]:
        """Peak VmRSS (KiB) of ``kind``'s processes over the first and the second half of the fault period."""
        half = self.cfg.fault_s / 2
        first = [k for t, _, k in self.rss.get(kind, []) if t < half]
        second = [k for t, _, k in self.rss.get(kind, []) if t >= half]
        return max(first, default=0), max(second, default=0)

    def longest_lived(self, kind: str) -> tuple[float, int, int]:
        """``kind``'s longest-sampled process: (seconds sampled, VmRSS at the middle of its life, at its end)."""
        by_pid: dict[int, list[tuple[float, int]]] = {}
        for t, pid, k in self.rss.get(kind, []):
            by_pid.setdefault(pid, []).append((t, k))
        if not by_pid:
            return 0.0, 0, 0
        samples = max(by_pid.values(), key=lambda s: s[-1][0] - s[0][0])
        mid = samples[len(samples) // 2][1]
        return samples[-1][0] - samples[0][0], mid, samples[-1][1]

    def explain(self) -> str:
        """A short account for a failed assertion."""
        return json.dumps(
            {
                "network": self.network,
                "produced": self.produced,
                "held": self.held,
                "missing": {r: _fmt_ranges(set(v)) for r, v in self.missing.items()},
                "extra": {r: _fmt_ranges(set(v)) for r, v in self.extra.items()},
                "unacked": self.unacked,
                "pending": self.pending,
                "dropped": self.dropped,
                "rejected": self.rejected,
                "reused": self.reused,
                "faults": dict(self.faults),
                "robot_runs": {r: dict(c) for r, c in self.robot_runs.items()},
                "crashes": self.crashes,
                "healed": self.healed,
                "heal_s": round(self.heal_s),
                "base_exit": self.base_exit,
                "logs": str(self.log_dir),
            }
        )


class Chaos:
    """Runs one soak (see the module docstring); :meth:`run` returns a :class:`ChaosResult`."""

    def __init__(self, cfg: ChaosConfig, workdir: Path, dive: Path, *, echo: bool = True) -> None:
        self.cfg = cfg
        self.work = workdir
        self.dive = dive
        self.echo = echo
        self.rng = random.Random(cfg.seed)
        self.state = workdir / "state"
        self.outboxes = workdir / "outbox"
        self.robots = [f"rov{i + 1}" for i in range(cfg.robots)]
        self.base = Service("base", "base")
        self.router = Service("router", "router")
        self.rovs = {r: Service(r, "robot") for r in self.robots}
        self.faults: Counter[str] = Counter()
        self.dives_done = 0
        self.link_down_until: float | None = None
        self.flap_down_s = 0.0
        self.rss: dict[str, list[tuple[float, int, int]]] = {}
        self.t0 = 0.0
        self.heal_from: float | None = None
        self.delivered_in_heal: set[str] = set()

    # ------------------------------------------------------------------------------------------- output
    def say(self, text: str) -> None:
        if self.echo:
            print(f"[{time.monotonic() - self.t0:7.1f} s] {text}", flush=True)

    # ------------------------------------------------------------------------------------------- processes
    def _start(self, svc: Service) -> None:
        net = self.net
        svc.runs += 1
        svc.expected_exit = False
        svc.restart_at = None
        svc.started_t = time.monotonic()
        if svc.kind == "router":
            svc.proc = net.start("router", net.ns_base, router_cmd(self._router_port))
        elif svc.kind == "base":
            svc.proc = net.start(
                "base",
                net.ns_base,
                [sys.executable, "-m", "lrsensor", "-v", "base", "--fleet", FLEET, "--config", str(self._base_conf),
                 "--mode", "client", "--state", str(self.state), "--map", "off", "--status-every-s", "0"],
            )  # fmt: skip
        else:
            outbox = self.outboxes / svc.name
            first = outbox_next_seq(outbox)
            svc.proc = net.start(
                f"{svc.name}.{svc.runs:03d}",
                net.ns_rov,
                [sys.executable, "-m", "lrsensor", "-v", "rov", "--fleet", FLEET, "--robot", svc.name,
                 "--config", str(self._rov_conf), "--source", str(self.dive), "--imu", f"csv:{self.dive / 'imu.csv'}",
                 "--calib", str(self.dive / "calib.json"), "--rate", f"{self.cfg.rate_hz:g}",
                 "--ack-timeout-s", f"{self.cfg.ack_timeout_s:g}", "--cloud-schema", str(self.cfg.cloud_schema),
                 "--outbox", str(outbox)],
            )  # fmt: skip
            self.say(f"{svc.name} run {svc.runs} starts (numbering from #{first})")
            return
        self.say(f"{svc.name} starts (run {svc.runs})")

    def _signal(self, svc: Service, sig: int, pause_s: float) -> None:
        assert svc.proc is not None
        svc.expected_exit = True
        svc.proc.send_signal(sig)
        with contextlib.suppress(subprocess.TimeoutExpired):
            svc.proc.wait(20 if sig == signal.SIGTERM else 5)
        if svc.proc.poll() is None:  # a SIGTERM that did not end it in time: a hang, counted
            svc.crashes.append(f"{svc.name} run {svc.runs} did not stop within 20 s of SIGTERM")
            svc.proc.kill()
            svc.proc.wait(5)
        svc.exits[self._code(svc.proc.returncode)] += 1
        svc.restart_at = time.monotonic() + pause_s

    @staticmethod
    def _code(rc: int | None) -> str:
        if rc is None:
            return "running"
        return f"signal {signal.Signals(-rc).name}" if rc < 0 else f"exit {rc}"

    def _supervise(self, now: float) -> None:
        for svc in (self.router, self.base, *self.rovs.values()):
            if svc.proc is not None and svc.proc.poll() is not None and svc.restart_at is None:
                rc = svc.proc.returncode
                svc.exits[self._code(rc)] += 1
                if svc.kind == "robot" and rc in (0, 3):  # a dive ended: the next one starts at once
                    self.dives_done += 1
                    if rc == 0 and self.heal_from is not None:
                        self.delivered_in_heal.add(svc.name)
                        svc.proc = None
                        self.say(f"{svc.name} delivered everything")
                        continue
                    svc.restart_at = now
                    continue
                why = f"{svc.name} run {svc.runs} exited unexpectedly ({self._code(rc)})"
                svc.crashes.append(why)
                self.say(why)
                svc.restart_at = now + 2.0
            if svc.restart_at is not None and now >= svc.restart_at and not svc.up:
                if svc.kind == "robot" and svc.name in self.delivered_in_heal:
                    svc.restart_at = None
                    continue
                self._start(svc)
        if self.link_down_until is not None and now >= self.link_down_until:
            self.net.set_up(True)
            self.link_down_until = None
            self.say("link up")

    def _sample_rss(self, now: float) -> None:
        for svc in (self.router, self.base, *self.rovs.values()):
            if svc.up:
                assert svc.proc is not None
                k = rss_kib(svc.proc.pid)
                if k is not None:
                    self.rss.setdefault(svc.kind, []).append((now - self.t0, svc.proc.pid, k))

    # ------------------------------------------------------------------------------------------- faults
    def _fault(self, kind: str) -> bool:
        """Inject one fault of ``kind``; False when its target is already down."""
        target, _, how = kind.partition(" ")
        if kind == "link flap":
            if isinstance(self.net, Loopback) or self.link_down_until is not None:
                return False
            lo, hi = self.cfg.flap_s
            down = self.rng.uniform(lo, hi)
            self.net.set_up(False)
            self.link_down_until = time.monotonic() + down
            self.flap_down_s += down
            self.say(f"link down for {down:.0f} s")
            return True
        if target == "robot":
            up = [s for s in self.rovs.values() if s.up and s.restart_at is None]
            if not up:
                return False
            svc = self.rng.choice(up)
            pause = self.rng.uniform(1.0, 8.0)
        else:
            svc = self.base if target == "base" else self.router
            if not svc.up:
                return False
            pause = self.rng.uniform(2.0, 15.0)
        sig = signal.SIGKILL if how == "SIGKILL" else signal.SIGTERM
        self.say(f"{how} {svc.name} (run {svc.runs}); back in {pause:.0f} s")
        self._signal(svc, sig, pause)
        return True

    def _schedule(self) -> Iterator[str]:
        """The fault kinds in order: every kind once (shuffled), then weighted random draws."""
        kinds = [k for k in KINDS if not (k == "link flap" and isinstance(self.net, Loopback))]
        first = list(kinds)
        self.rng.shuffle(first)
        yield from first
        weights = [KINDS[k] for k in kinds]
        while True:
            yield self.rng.choices(kinds, weights)[0]

    # ------------------------------------------------------------------------------------------- the run
    def run(self) -> ChaosResult:
        cfg = self.cfg
        with open_net(cfg, self.work / "net") as net:
            self.net = net
            network = (
                f"veth between namespaces, {cfg.spec.label()}"
                if isinstance(net, NetLink)
                else f"loopback (no link impairments, no flaps: {unavailable() or 'asked for'})"
            )
            self._router_port = ROUTER_PORT if isinstance(net, NetLink) else net.zenoh_port
            router_ep = f"tcp/127.0.0.1:{self._router_port}"
            self._base_conf = zenoh_config(self.work / "base.json5", "client", connect=[router_ep])
            self._rov_conf = zenoh_config(self.work / "rov.json5", "client", connect=[net.rov_endpoint()])
            self.t0 = time.monotonic()
            start_bytes = net.link_bytes()
            self.say(f"chaos soak over {network}; faults for {cfg.fault_s:.0f} s, seed {cfg.seed}")
            self._start(self.router)
            time.sleep(1.0)
            self._start(self.base)
            for svc in self.rovs.values():
                self._start(svc)
            kinds = self._schedule()
            next_fault = self.t0 + 15.0 + self.rng.expovariate(1.0 / cfg.fault_every_s)
            last_rss = 0.0
            end_faults = self.t0 + cfg.fault_s
            while True:
                now = time.monotonic()
                self._supervise(now)
                if now - last_rss >= RSS_EVERY_S:
                    last_rss = now
                    self._sample_rss(now)
                if now < end_faults:
                    if now >= next_fault:
                        for _ in range(len(KINDS)):
                            kind = next(kinds)
                            if self._fault(kind):
                                self.faults[kind] += 1
                                break
                        next_fault = time.monotonic() + max(3.0, self.rng.expovariate(1.0 / cfg.fault_every_s))
                elif self.heal_from is None:
                    self.heal_from = now
                    self.say("faults end; healing")
                else:
                    quiet = self.link_down_until is None and self.base.up and self.router.up
                    if quiet and self.delivered_in_heal == set(self.robots):
                        break
                    if now - self.heal_from > cfg.heal_s:
                        self.say("heal timeout")
                        break
                time.sleep(0.2)
            heal_s = time.monotonic() - (self.heal_from or time.monotonic())
            healed = self.delivered_in_heal == set(self.robots)
            if self.link_down_until is not None:
                net.set_up(True)
            end_bytes = net.link_bytes()
            wall = time.monotonic() - self.t0
            base_exit = None
            if self.base.up:  # a SIGTERM: the base station's final checkpoint
                assert self.base.proc is not None
                self.base.expected_exit = True
                self.base.proc.send_signal(signal.SIGTERM)
                try:
                    base_exit = self.base.proc.wait(30)
                except subprocess.TimeoutExpired:
                    self.base.crashes.append("base did not stop within 30 s of the final SIGTERM")
            for svc in self.rovs.values():  # only after a heal timeout
                if svc.up:
                    assert svc.proc is not None
                    svc.proc.send_signal(signal.SIGTERM)
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        svc.proc.wait(30)
            logs = {r: [net.log(f"{r}.{k:03d}") for k in range(1, self.rovs[r].runs + 1)] for r in self.robots}
        return self._account(network, logs, wall, heal_s, healed, start_bytes, end_bytes, base_exit)

    def _account(
        self,
        network: str,
        logs: dict[str, list[str]],
        wall: float,
        heal_s: float,
        healed: bool,
        start_bytes: dict[str, int],
        end_bytes: dict[str, int],
        base_exit: int | None,
    ) -> ChaosResult:
        try:
            fleet = json.loads((self.state / "fleet.json").read_text()).get("robots", {})
        except (OSError, ValueError):
            fleet = {}
        produced, held, missing, extra, unacked, pending, dropped, dups = {}, {}, {}, {}, {}, {}, {}, {}
        rejected: dict[str, int] = {}
        reused: dict[str, int] = {}
        for r in self.robots:
            box = self.outboxes / r
            made = set(range(outbox_next_seq(box)))
            have = _ranges_set(fleet.get(r, {}).get("ranges"))
            acked = _ranges_set(fleet.get(r, {}).get("acked"))
            produced[r], held[r] = len(made), len(have)
            missing[r] = sorted(made - have)
            extra[r] = sorted(have - made)
            unacked[r] = len(made - acked)
            pending[r] = len(list(box.glob("*.msg")))
            try:
                dropped[r] = int(json.loads((box / "state.json").read_text()).get("dropped", 0))
            except (OSError, ValueError):
                dropped[r] = 0
            dups[r] = int(fleet.get(r, {}).get("duplicates", 0))
            rejected[r] = int(fleet.get(r, {}).get("rejected", 0))
            reused[r] = int(fleet.get(r, {}).get("reused", 0))
        resent = unheard = clean = clouds_clean = 0
        for r in self.robots:
            for text in logs[r]:
                m = list(_OUTBOX_LINE.finditer(text))
                f = list(_FRAMES_LINE.finditer(text))
                if m:
                    clean += 1
                    resent += int(m[-1].group(4))
                    unheard += int(m[-1].group(6))
                if f:
                    clouds_clean += int(f[-1].group(3))
        crashes = [c for s in (self.router, self.base, *self.rovs.values()) for c in s.crashes]
        return ChaosResult(
            cfg=self.cfg,
            network=network,
            produced=produced,
            held=held,
            missing=missing,
            extra=extra,
            unacked=unacked,
            pending=pending,
            dropped=dropped,
            duplicates=dups,
            rejected=rejected,
            reused=reused,
            faults=self.faults,
            flap_down_s=self.flap_down_s,
            robot_runs={r: s.exits for r, s in self.rovs.items()},
            dives_done=self.dives_done,
            crashes=crashes,
            resent=resent,
            resent_unheard=unheard,
            clean_runs=clean,
            all_runs=sum(s.runs for s in self.rovs.values()),
            clouds_in_clean_runs=clouds_clean,
            rss=self.rss,
            wall_s=wall,
            heal_s=heal_s,
            healed=healed,
            link={k: end_bytes[k] - start_bytes[k] for k in end_bytes},
            base_exit=base_exit,
            log_dir=self.work / "net",
        )


def run_chaos(cfg: ChaosConfig, workdir: Path, *, echo: bool = True) -> ChaosResult:
    """Record a dive into ``workdir`` and run one soak there."""
    from services.simsource import record_sim_dive

    workdir.mkdir(parents=True, exist_ok=True)
    dive = record_sim_dive(workdir / "dive", "rov1", n_frames=cfg.dive_frames, seed=cfg.seed, rate_hz=cfg.rate_hz)
    return Chaos(cfg, workdir, dive, echo=echo).run()


# ----------------------------------------------------------------------------------------------- tables
def _mib(kib: int) -> str:
    return f"{kib / 1024:.0f}"


def tables(res: ChaosResult) -> str:
    """The soak's markdown tables: the accounting, the faults, the memory."""
    cfg = res.cfg
    n = res.total_produced
    held = sum(res.held.values())
    miss = sum(len(v) for v in res.missing.values())
    extra = sum(len(v) for v in res.extra.values())
    yes = "yes" if res.ok else "**NO**"
    twice_pct = 100 * res.sent_twice / max(1, res.clouds_in_clean_runs)
    acct = (
        "| faults for | robots | clouds produced | held by the base | missing / extra | unacknowledged "
        "| left in outboxes / dropped | duplicates / rejected / numbers reused at base | sent twice (clean runs) "
        "| re-sent in all (clean runs) | healed in "
        "| every cloud once |\n"
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | :---: |\n"
        f"| {cfg.fault_s / 60:.0f} min | {cfg.robots} x {cfg.rate_hz:g} Hz | {n} | {held} | {miss} / {extra} "
        f"| {sum(res.unacked.values())} | {sum(res.pending.values())} / {sum(res.dropped.values())} "
        f"| {sum(res.duplicates.values())} / {sum(res.rejected.values())} / {sum(res.reused.values())} "
        f"| {res.sent_twice} ({twice_pct:.1f} %) "
        f"| {res.resent} | {res.heal_s:.0f} s | {yes} |"
    )
    fault_rows = "\n".join(f"| {k} | {res.faults.get(k, 0)} |" for k in KINDS)
    runs = Counter[str]()
    for c in res.robot_runs.values():
        runs.update(c)
    ends = ", ".join(f"{k}: {v}" for k, v in sorted(runs.items()))
    faults = (
        "| fault | injected |\n| --- | ---: |\n"
        f"{fault_rows}\n"
        f"| link down in all | {res.flap_down_s:.0f} s |\n"
        f"| robot runs (dives started) | {res.all_runs} ({ends}) |\n"
        f"| dives ended by the robot (exit 0 / 3) | {res.dives_done} |\n"
        f"| unexpected exits (crashes, hangs) | {len(res.crashes)} |"
    )
    mem_rows = []
    for kind in ("base", "router", "robot"):
        a, b = res.rss_peaks(kind)
        life, mid, end = res.longest_lived(kind)
        mem_rows.append(
            f"| {kind} | {_mib(a)} | {_mib(b)} | {(b - a) / 1024:+.0f} "
            f"| {life / 60:.1f} min: {_mib(mid)} -> {_mib(end)} |"
        )
    mem = (
        "| process | peak RSS, first half (MiB) | peak RSS, second half (MiB) | growth (MiB) "
        "| longest-lived process: RSS at half its life -> at its end (MiB) |\n"
        "| --- | ---: | ---: | ---: | ---: |\n" + "\n".join(mem_rows)
    )
    return f"{acct}\n\n{faults}\n\n{mem}"


def report(res: ChaosResult, command: str) -> str:
    cfg = res.cfg
    dive_s = cfg.dive_frames / cfg.rate_hz
    text = (
        "# Chaos soak\n\n"
        f"`{command}`\n\n"
        f"Base station (`--state`, map off) behind a bare router, {cfg.robots} robots replaying a {dive_s:.0f} s "
        f"dive ({cfg.dive_frames} frames, 640x360, cloud schema {cfg.cloud_schema}) at {cfg.rate_hz:g} Hz into "
        f"persistent outboxes, dive after dive, over {res.network}. Faults from a seeded schedule (seed {cfg.seed}, "
        f"one every {cfg.fault_every_s:g} s on average): SIGKILL/SIGTERM of the base station, the router or a "
        f"robot, restarted after a pause; link flaps of {cfg.flap_s[0]:g}-{cfg.flap_s[1]:g} s. Then the faults "
        "stop and every robot finishes a dive with every cloud acknowledged; the base station is stopped and the "
        "files are read. Clouds produced: per robot the numbers 0 .. next_seq - 1 of its outbox (a restarted "
        "robot replays its dive from the first frame under new numbers). Held: the ranges in the base "
        "station's `fleet.json`. Duplicates: copies of clouds the base already held (a lower bound: a SIGKILLed "
        "base loses the count since its last save); rejected: clouds the base refused (and did not acknowledge); "
        "numbers reused: duplicates with another capture time (a number given twice). Sent twice / re-sent: "
        "from the summary lines of the robot "
        f"runs that ended cleanly ({res.clean_runs} of {res.all_runs}, {res.clouds_in_clean_runs} clouds); "
        "sent twice as a share of those runs' clouds. "
        f"Link: {res.link.get('up_bytes', 0) / 1e6:.1f} MB up, {res.link.get('down_bytes', 0) / 1e6:.1f} MB down. "
        f"Wall {res.wall_s / 60:.1f} min.\n\n"
        f"{tables(res)}\n"
    )
    if res.crashes:
        text += "\nUnexpected exits:\n\n" + "\n".join(f"- {c}" for c in res.crashes) + "\n"
    return text


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--minutes", type=float, default=30.0, help="how long faults are injected")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--rate", type=float, default=5.0, help="each robot's replay rate, Hz")
    ap.add_argument("--dive-frames", type=int, default=300, help="frames of the dive each robot replays")
    ap.add_argument("--fault-every-s", type=float, default=45.0, help="mean gap between faults, s")
    ap.add_argument("--heal-s", type=float, default=600.0, help="longest wait for the robots to deliver at the end")
    ap.add_argument("--loopback", action="store_true", help="run on loopback even where namespaces are available")
    ap.add_argument("--out", default="chaos.md", help="results file name under benchmarks/results/")
    ap.add_argument("--keep", action="store_true", help="keep the work folder (logs, outboxes, state)")
    args = ap.parse_args(argv)
    cfg = ChaosConfig(
        fault_s=args.minutes * 60,
        robots=args.robots,
        rate_hz=args.rate,
        dive_frames=args.dive_frames,
        seed=args.seed,
        fault_every_s=args.fault_every_s,
        heal_s=args.heal_s,
        loopback=args.loopback,
    )
    command = (
        f"python benchmarks/bench_chaos.py --minutes {args.minutes:g} --seed {args.seed} --robots {args.robots} "
        f"--rate {args.rate:g} --dive-frames {args.dive_frames} --fault-every-s {args.fault_every_s:g}"
        + (" --loopback" if args.loopback else "")
    )
    tmp = Path(tempfile.mkdtemp(prefix="lrs-chaos-"))
    res = run_chaos(cfg, tmp)
    text = report(res, command)
    print(text)
    print(res.explain())
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / args.out).write_text(text)
    if not args.keep and res.ok:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
    else:
        print(f"work folder kept: {tmp}")
    return 0 if res.ok else 1


if __name__ == "__main__":
    sys.exit(main())
