"""Delivery over an impaired link: a base station and robots in two network namespaces (issue 30).

    python benchmarks/bench_link.py [--frames 60] [--robots 3] [--rate 10] [--rows default] [--out link.md]

Real processes (``lrsensor base`` and one ``lrsensor rov`` per robot replaying a simulated dive with its
delivery path: disk outbox, acknowledgements, re-sends) across a veth pair built by ``tests/netlink.py``:
``tc tbf`` for the rate, ``iptables`` random drops for the loss (each way), a delaying relay for the latency
(each way), ``ip link set down`` for an outage; Zenoh's shared memory off so that every cloud crosses the link.
Needs root (skips otherwise).

Rows (``--rows``): ``default`` runs 10 Mbit/s, 10 % loss, 200 ms without and with a 30 s outage 2 s into the
replay, the same at 2 Mbit/s, and 2 Mbit/s with a 1 MiB outbox budget per robot (``--outbox-max-mb 1``), for
which it adds a table of the link-budget counters (live, forwarded, queued, dropped by the budget, released;
docs/reliability.md), whether the identity ``published = live + forwarded + queued + dropped_budget`` holds,
and whether every cloud the base station lacks was dropped by the budget.

Reported per row: clouds delivered (distinct, held by the base) of those replayed; sent twice (re-sends / clouds,
%); bytes the robots sent over the link (retransmissions included) / the clouds' own bytes; transit
(publication to the base) p50 / p99 as the base station measures it; whether every outbox drained; the ROVs'
exit codes; the wall time until the last ROV exited. Prints a markdown table and writes
``benchmarks/results/<out>``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]  # run as a script or as -m benchmarks.bench_link

from netlink import FleetRun, LinkSpec, netlink, run_fleet, unavailable  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"


@dataclass(frozen=True)
class Row:
    """One benchmark row: a link and an optional outage."""

    name: str
    spec: LinkSpec
    outage: tuple[float, float] | None = None
    rov_args: tuple[str, ...] = ()


ROWS: dict[str, tuple[Row, ...]] = {
    "default": (
        Row("10 Mbit/s, 10 % loss, 200 ms", LinkSpec(10.0, 0.10, 200.0)),
        Row("same + 30 s outage 2 s into the stream", LinkSpec(10.0, 0.10, 200.0), (2.0, 30.0)),
        Row("2 Mbit/s, 10 % loss, 200 ms", LinkSpec(2.0, 0.10, 200.0)),
        Row("2 Mbit/s, 10 % loss, 200 ms, 1 MiB budget", LinkSpec(2.0, 0.10, 200.0), None, ("--outbox-max-mb", "1")),
    ),
    "flap5min": (
        Row(
            "10 Mbit/s, 10 % loss, 200 ms + 5 min outage 2 s into the stream", LinkSpec(10.0, 0.10, 200.0), (2.0, 300.0)
        ),
    ),
}


def _fmt_ms(v: float | None) -> str:
    return "-" if v is None else f"{v / 1000:.1f} s" if v >= 1000 else f"{v:.0f} ms"


def table(rows: list[tuple[Row, FleetRun]]) -> str:
    head = (
        "| link | delivered | sent twice | re-sent in all | duplicates at base | link bytes / clouds' bytes "
        "| transit p50 / p99 | backlog drained | ROV exit codes | wall |\n"
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | :---: | --- | ---: |"
    )
    lines = [head]
    for row, run in rows:
        drained = all(p == 0 for p in run.pending.values())
        codes = ", ".join("killed" if c is None else str(c) for c in run.exit_codes.values())
        lines.append(
            f"| {row.name} | {run.delivered} of {run.expected} | {run.sent_twice} ({run.sent_twice_pct:.0f} %) "
            f"| {sum(run.resent.values())} | {sum(run.duplicates.values())} | {run.link['up_bytes'] / 1e6:.1f} MB / "
            f"{sum(run.cloud_bytes.values()) / 1e6:.1f} MB = {run.link_ratio:.2f}x | "
            f"{_fmt_ms(run.transit_ms['p50'])} / {_fmt_ms(run.transit_ms['p99'])} | {'yes' if drained else 'no'} "
            f"| {codes} | {run.wall_s:.0f} s |"
        )
    return "\n".join(lines)


def budget_table(rows: list[tuple[Row, FleetRun]]) -> str:
    """The link-budget counters summed over the robots, and whether they add up."""
    head = (
        "| link | published | live | forwarded | queued | dropped by the budget | released | thinned / held "
        "| identity holds | base lacks only dropped ones | delivered |\n"
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | :---: | :---: | ---: |"
    )
    lines = [head]
    for row, run in rows:
        tot = {k: sum(b.get(k, 0) for b in run.budget.values()) for k in next(iter(run.budget.values()), {})}
        if not tot:
            continue
        adds_up = all(
            b and b["published"] + b["reloaded"] == b["live"] + b["forwarded"] + b["queued"] + b["dropped_budget"]
            for b in run.budget.values()
        )
        only_budget = all(
            set(range(run.frames)) - {s for lo, hi in run.held_ranges[r] for s in range(lo, hi + 1)}
            <= {s for lo, hi in run.dropped_ranges[r] for s in range(lo, hi + 1)}
            for r in run.robots
        )
        lines.append(
            f"| {row.name} | {tot['published']} | {tot['live']} | {tot['forwarded']} | {tot['queued']} "
            f"| {tot['dropped_budget']} | {tot['released']} | {tot['thinned']} / {tot['held']} "
            f"| {'yes' if adds_up else 'NO'} | {'yes' if only_budget else 'NO'} | {run.delivered} of {run.expected} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60, help="clouds each robot replays")
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--rate", type=float, default=10.0, help="replay rate, Hz")
    ap.add_argument("--rows", choices=sorted(ROWS), default="default")
    ap.add_argument("--only", type=int, default=None, help="run only this row of --rows (0-based)")
    ap.add_argument("--schema", type=int, choices=(1, 2), default=2, help="the ROVs' --cloud-schema")
    ap.add_argument("--size", default="640x360", help="simulated camera, WxH")
    ap.add_argument("--ack-timeout-s", type=float, default=60.0, help="the ROVs' --ack-timeout-s")
    ap.add_argument("--deadline-s", type=float, default=600.0, help="kill ROVs still running after this")
    ap.add_argument("--out", default="link.md", help="results file name under benchmarks/results/")
    ap.add_argument("--note", default="", help="a line said under the table (e.g. which code was measured)")
    args = ap.parse_args(argv)
    why = unavailable()
    if why:
        print(f"bench_link skipped: {why}")
        return 0
    from services.simsource import record_sim_dive

    robots = tuple(f"rov{i + 1}" for i in range(args.robots))
    measured: list[tuple[Row, FleetRun]] = []
    with tempfile.TemporaryDirectory(prefix="lrs-bench-link-") as tmp:
        w, _, h = args.size.partition("x")
        dive = record_sim_dive(Path(tmp) / "dive", "rov1", n_frames=args.frames, width=int(w), height=int(h), seed=5)
        for i, row in enumerate(ROWS[args.rows]):
            if args.only is not None and i != args.only:
                continue
            t = time.monotonic()
            with netlink(row.spec, Path(tmp) / f"row{i}") as link:
                run = run_fleet(
                    link,
                    dive,
                    robots=robots,
                    frames=args.frames,
                    rate_hz=args.rate,
                    outage=row.outage,
                    ack_timeout_s=args.ack_timeout_s,
                    deadline_s=args.deadline_s,
                    rov_args=("--cloud-schema", str(args.schema), *row.rov_args),
                )
            measured.append((row, run))
            print(f"{row.name}: {time.monotonic() - t:.0f} s", flush=True)
            print(table([(row, run)]).splitlines()[-1], flush=True)
    text = (
        "# Delivery over an impaired link\n\n"
        f"`python benchmarks/bench_link.py --frames {args.frames} --robots {args.robots} --rate {args.rate:g} "
        f"--rows {args.rows} --ack-timeout-s {args.ack_timeout_s:g} --schema {args.schema} --size {args.size}`\n\n"
        f"{args.robots} robots replaying {args.frames} simulated clouds each at {args.rate:g} Hz ({args.size} camera, "
        f"cloud schema {args.schema}) "
        "through a veth pair between two network namespaces (rate: tbf, loss: iptables, each way; latency: a "
        "delaying relay, each way; shared memory off). Sent twice: re-sends of clouds whose earlier copy had "
        "gone out on the link (a share of the clouds); re-sent in all adds the clouds published while the base "
        "station was unreachable (zenoh sent nothing then), forwarded from the outbox once it is back. "
        "Link bytes: what the robots' end of the veth pair sent, TCP retransmissions included. "
        "Duplicates: copies the base station received of clouds it already held. "
        "Exit code 3: the replay ended with clouds not acknowledged (kept in "
        "the outbox).\n\n"
        f"{table(measured)}\n"
    )
    if any(row.rov_args and any(run.budget.values()) for row, run in measured):
        text += (
            "\nThe link-budget counters (summed over the robots; dropped by the budget: never sent, lost; "
            "released: sent, disk copy dropped before the acknowledgement; thinned / held: not sent live because "
            "the window was full / the acknowledgements were late):\n\n"
            f"{budget_table([(r, run) for r, run in measured if r.rov_args])}\n"
        )
    if args.note:
        text += f"\n{args.note}\n"
    print(text)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / args.out).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
