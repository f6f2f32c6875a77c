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

# Layout: this module is the command line and the report it writes; every name it had stays importable from here
# (__all__). Its parts: benchmarks.chaos_setup (the parameters, the tether or loopback), benchmarks.chaos_soak (the
# supervised processes, the faults, the heal) and benchmarks.chaos_accounting (what the files say at the end).

from __future__ import annotations

import argparse
import sys
import tempfile
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: python benchmarks/bench_chaos.py
    sys.path.insert(0, str(ROOT))

from benchmarks.chaos_accounting import ChaosResult, outbox_next_seq  # noqa: E402
from benchmarks.chaos_setup import FLEET, ROUTER_PORT, TETHER, ChaosConfig, Loopback, open_net  # noqa: E402
from benchmarks.chaos_soak import KINDS, RSS_EVERY_S, Chaos, Service, rss_kib, run_chaos  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"


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


__all__ = [
    "FLEET",
    "KINDS",
    "RESULTS",
    "ROOT",
    "ROUTER_PORT",
    "RSS_EVERY_S",
    "TETHER",
    "Chaos",
    "ChaosConfig",
    "ChaosResult",
    "Loopback",
    "Service",
    "main",
    "open_net",
    "outbox_next_seq",
    "report",
    "rss_kib",
    "run_chaos",
    "tables",
]


if __name__ == "__main__":
    sys.exit(main())
