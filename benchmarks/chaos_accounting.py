"""A chaos soak's accounting (:mod:`benchmarks.bench_chaos`): what it gave, read from the files at the end.

:func:`account` reads, per robot, the clouds it produced (the numbers ``0 .. next_seq - 1`` of its outbox:
:func:`outbox_next_seq`), the ones the base station holds and acknowledged (``fleet.json``'s ranges), the clouds
pending or dropped in the outboxes, the duplicates the base counted, and the re-sends from the summary lines of
the robot runs that ended cleanly; :class:`ChaosResult` holds them with the faults, the memory samples and the
link's bytes, and says whether every cloud produced is held once (:attr:`ChaosResult.ok`).
"""

from __future__ import annotations

import contextlib
import json
import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .chaos_setup import ChaosConfig

if TYPE_CHECKING:
    from .chaos_soak import Chaos

_OUTBOX_LINE = re.compile(
    r"rov (\S+): outbox (\d+) pending, (\d+) acknowledged, (\d+) re-sent \((\d+) bytes, (\d+) never heard before\)"
)
_FRAMES_LINE = re.compile(r"rov (\S+): frames (\d+), published (\d+)")


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


def account(
    soak: Chaos,
    network: str,
    logs: dict[str, list[str]],
    wall: float,
    heal_s: float,
    healed: bool,
    start_bytes: dict[str, int],
    end_bytes: dict[str, int],
    base_exit: int | None,
) -> ChaosResult:
    """What ``soak`` gave, accounted from its files (see the module docstring of :mod:`benchmarks.bench_chaos`)."""
    try:
        fleet = json.loads((soak.state / "fleet.json").read_text()).get("robots", {})
    except (OSError, ValueError):
        fleet = {}
    produced, held, missing, extra, unacked, pending, dropped, dups = {}, {}, {}, {}, {}, {}, {}, {}
    rejected: dict[str, int] = {}
    reused: dict[str, int] = {}
    for r in soak.robots:
        box = soak.outboxes / r
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
    for r in soak.robots:
        for text in logs[r]:
            m = list(_OUTBOX_LINE.finditer(text))
            f = list(_FRAMES_LINE.finditer(text))
            if m:
                clean += 1
                resent += int(m[-1].group(4))
                unheard += int(m[-1].group(6))
            if f:
                clouds_clean += int(f[-1].group(3))
    crashes = [c for s in (soak.router, soak.base, *soak.rovs.values()) for c in s.crashes]
    return ChaosResult(
        cfg=soak.cfg,
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
        faults=soak.faults,
        flap_down_s=soak.flap_down_s,
        robot_runs={r: s.exits for r, s in soak.rovs.items()},
        dives_done=soak.dives_done,
        crashes=crashes,
        resent=resent,
        resent_unheard=unheard,
        clean_runs=clean,
        all_runs=sum(s.runs for s in soak.rovs.values()),
        clouds_in_clean_runs=clouds_clean,
        rss=soak.rss,
        wall_s=wall,
        heal_s=heal_s,
        healed=healed,
        link={k: end_bytes[k] - start_bytes[k] for k in end_bytes},
        base_exit=base_exit,
        log_dir=soak.work / "net",
    )
