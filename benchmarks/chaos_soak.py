"""A chaos soak's run (:mod:`benchmarks.bench_chaos`): the supervised processes, the faults, the heal.

:class:`Chaos` starts the router, the base station and the robots over the network of
:func:`~benchmarks.chaos_setup.open_net`, supervises them as a supervisor would (a robot whose dive ended
starts the next one at once; a process that exits unasked is counted as a crash and restarted), injects the
faults of a seeded schedule (:data:`KINDS`, with their weights), samples every process's resident memory every
:data:`RSS_EVERY_S` seconds, then stops the faults and waits until every robot has delivered everything; the
accounting from the files is :func:`benchmarks.chaos_accounting.account`. :func:`run_chaos` records a dive and
runs one soak on it.
"""

from __future__ import annotations

import contextlib
import random
import signal
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from .chaos_accounting import ChaosResult, account, outbox_next_seq
from .chaos_setup import (
    FLEET,
    ROUTER_PORT,
    ChaosConfig,
    Loopback,
    NetLink,
    open_net,
    router_cmd,
    unavailable,
    zenoh_config,
)

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


def rss_kib(pid: int) -> int | None:
    """Resident set size of ``pid``, KiB (None once it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


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
        return account(self, network, logs, wall, heal_s, healed, start_bytes, end_bytes, base_exit)


def run_chaos(cfg: ChaosConfig, workdir: Path, *, echo: bool = True) -> ChaosResult:
    """Record a dive into ``workdir`` and run one soak there."""
    from services.simsource import record_sim_dive

    workdir.mkdir(parents=True, exist_ok=True)
    dive = record_sim_dive(workdir / "dive", "rov1", n_frames=cfg.dive_frames, seed=cfg.seed, rate_hz=cfg.rate_hz)
    return Chaos(cfg, workdir, dive, echo=echo).run()
