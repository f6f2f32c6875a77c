"""Build docs/performance.md from benchmarks/results/*.md: every measured table on one page, grouped by topic.

    python -m benchmarks.report           # rewrite docs/performance.md
    python benchmarks/report.py --check   # exit 1 if docs/performance.md is not what the results give

Layout of the page: a title, a note that says it is generated, a table of contents (one line per topic with its
results files), then one section per topic in :data:`TOPICS` order. Each results file, or a part of one selected
by its headings, is one subsection headed with the command that produced it; the file's text follows as it is,
its headings moved down so that they nest under that subsection.

Policy: the results files are the only source of figures. This script copies them and adds nothing measured, so
the page cannot say more than the last runs did; ``tests/test_performance_doc.py`` regenerates the page in
memory and compares it with docs/performance.md, and checks that every line of every results file is on it.
After running a benchmark, run this script and commit both.

Where a file comes from is written once, in :data:`SOURCES` (its topic and command, taken from the file's text
or the benchmark's docstring). A results file that SOURCES does not name is not dropped: it goes to "Other
results", headed with the first ``python benchmarks/...`` command found in its text. Name it in SOURCES.

Only the standard library: this runs on an ROV install and in CI without the sensor's dependencies.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ROOT / "benchmarks" / "results"
PAGE_PATH = ROOT / "docs" / "performance.md"
#: The page links the results files relative to docs/.
RESULTS_LINK = "../benchmarks/results"

#: Topic key -> section title, in page order.
TOPICS: dict[str, str] = {
    "accuracy": "Extraction accuracy",
    "speed": "Extraction speed",
    "independent": "Independent renders",
    "port": "The flat port",
    "calibration": "Calibration",
    "simulator": "Simulator",
    "mapping": "Mapping",
    "ingest": "Ingest",
    "wire": "Wire encoding",
    "soak": "Soak",
    "fuzz": "Fuzz",
    "other": "Other results",
}

_HEADING_RE = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
_COMMAND_RE = re.compile(r"python3? (?:-m )?benchmarks[/.][A-Za-z0-9_./-]+(?: [^`\n]*)?")
#: Level of the subsection that heads each source; the file's own headings start one below it.
_SOURCE_LEVEL = 3


@dataclass(frozen=True)
class Source:
    """Where (part of) one results file goes on the page.

    Attributes:
        file: name of the results file in benchmarks/results/.
        topic: key of :data:`TOPICS`.
        command: the command that wrote it (from the file's text or its benchmark's docstring).
        sections: only the blocks whose heading starts with one of these texts (``""`` names the text before the
            first heading); None takes the whole file.
        note: a few words after the file's name, for a file split over topics or holding several runs.
    """

    file: str
    topic: str
    command: str
    sections: tuple[str, ...] | None = None
    note: str = ""


_EXTRACT = "python benchmarks/bench_extract.py"
_FOREIGN = "python benchmarks/bench_foreign_render.py"
_SOAK = "python benchmarks/bench_soak.py"

SOURCES: tuple[Source, ...] = (
    Source("extract.md", "accuracy", f"{_EXTRACT} --seeds 2 --repeats 30", ("Accuracy",), "accuracy tables"),
    Source("extract_flank_gate.md", "accuracy", f"{_EXTRACT} --flank-gate --seeds 6"),
    Source(
        "extract_reshape.md",
        "accuracy",
        "python benchmarks/compare_points.py compare REF.npz --out benchmarks/results/extract_reshape.md",
        note="the extractor's reshape against the points saved before it (`compare_points.py save REF.npz`)",
    ),
    Source("extract.md", "speed", f"{_EXTRACT} --seeds 2 --repeats 30", ("Speed", "Where the time goes"), "speed"),
    Source("extract_copies.md", "speed", f"{_EXTRACT} --copies"),
    Source("extract_cold_after_tank.md", "speed", f"{_EXTRACT} --cold-after tank"),
    Source("extract_cold_after_wall_0.3.md", "speed", f"{_EXTRACT} --cold-after wall_0.3 --repeats 30"),
    Source("extract_stages_wall_5.0.md", "speed", f"{_EXTRACT} --stages wall_5.0 --seeds 4"),
    Source(
        "extract_against.md",
        "speed",
        f"{_EXTRACT} --against WORKTREE WORKTREE --rounds 2 --seeds 4",
        note="against the code the reshape (issue 29) started from (2072e3e) and the reshape alone (8e92924), "
        "on the same machine",
    ),
    Source("compile.md", "speed", "python benchmarks/bench_compile.py --repeats 1", note="the one-time compile"),
    Source("extract_foreign.md", "independent", _FOREIGN),
    Source("extract_foreign_integrate_first.md", "independent", f"{_FOREIGN} --integrate-first"),
    Source("extract_foreign_luma.md", "independent", f"{_FOREIGN} --channel luma"),
    Source("extract_foreign_jpeg95.md", "independent", f"{_FOREIGN} --jpeg 95"),
    Source("extract_foreign_jpeg85.md", "independent", f"{_FOREIGN} --jpeg 85"),
    Source("extract_foreign_jpeg85_444.md", "independent", f"{_FOREIGN} --jpeg 85 --jpeg-444"),
    Source("extract_foreign_jpeg85_luma.md", "independent", f"{_FOREIGN} --jpeg 85 --channel luma"),
    Source("extract_turbid.md", "independent", "python benchmarks/bench_turbid.py"),
    Source(
        "glow_shape.md",
        "independent",
        "python benchmarks/glow_shape.py --cells 3:0.5:4 3:0.3:4 3:0.1:4 2:0.5:4 --seed 1 --every 24",
        note="single columns of the turbidity model fitted with the step, the ramp and the sheet's glow shape",
    ),
    Source("port.md", "port", "python benchmarks/bench_port.py"),
    Source("calib.md", "calibration", "python benchmarks/bench_calib.py"),
    Source("sim.md", "simulator", "python benchmarks/bench_sim.py --repeat 3"),
    Source(
        "sim_turbid.md",
        "accuracy",
        "python benchmarks/bench_sim_turbid.py --seeds 2",
        note="the simulator's turbid water by glow model (issue 26)",
    ),
    Source("mapping.md", "mapping", "python benchmarks/bench_mapping.py"),
    Source(
        "nav.md",
        "mapping",
        "python benchmarks/bench_nav.py --seconds 90 --seed 1 --acceptance 24",
        note="laser-aided navigation: trusted, filtered and smoothed poses; the acceptance run through processes "
        "(issue 27)",
    ),
    Source(
        "nav_procs.md",
        "mapping",
        "python benchmarks/bench_nav_procs.py --mode MODE --seeds S --runs N [--size WxH] [--max-range-m M] "
        "[--smoother thread|wait] [--inprocess]",
        note="a fleet of one navigation through lrsensor base and lrsensor rov processes vs in-process (issue 27)",
    ),
    Source(
        "extracted_nav.md",
        "mapping",
        "python benchmarks/bench_extracted_nav.py [--modes M,...] [--seeds S,...] [--variant NAME=KEY=VALUE,...] "
        "[--order-seeds K,...]",
        note="navigation and map settings judged on 12 extracted dives against the default (issue 27)",
    ),
    Source(
        "fleet_heading.md",
        "mapping",
        "python benchmarks/diag_fleet_heading.py --seeds 1,2,3,5 --seconds 0,1,2,3",
        note="the depth-only fleet's compass biases from the launch fixes and shared walls (issue 27)",
    ),
    Source(
        "heading_workers.md",
        "mapping",
        "python benchmarks/bench_heading_workers.py --modes depth-only,mixed --seeds S",
        note="a depth-only or mixed fleet's map with plane workers against the base's map thread (issue 27)",
    ),
    Source(
        "workers.md",
        "mapping",
        "python benchmarks/bench_workers.py",
        note="plane workers: clouds/s and map latency against worker processes (issue 31)",
    ),
    Source(
        "merger.md",
        "mapping",
        "python benchmarks/bench_merger.py",
        note="the merger's ceiling: plane observations/s one base fuses, per fleet size (issue 31)",
    ),
    Source(
        "ingest.md",
        "ingest",
        "python benchmarks/bench_ingest.py --robots 1,5,10,20,30,40,60,90",
        ("",),
        "one load generator",
    ),
    Source(
        "ingest.md",
        "ingest",
        "python benchmarks/bench_ingest.py --robots 20,60,90,120 --duration-s 6 --generators 2",
        ("Two load-generator processes",),
        "two load generators",
    ),
    Source(
        "ingest_map.md",
        "ingest",
        "python benchmarks/bench_ingest.py --map --robots 5,20 --out benchmarks/results/ingest_map.md",
    ),
    Source(
        "soak.md",
        "soak",
        f"{_SOAK} --robots N --rate 30 --duration S [--points P] [--map auto|off]",
        ("Load and soak",),
        "summary; the runs it copies are the files below",
    ),
    Source(
        "soak_3x30_mapon_15min.md",
        "soak",
        f"{_SOAK} --robots 3 --rate 30 --duration 900 --map auto --out benchmarks/results/soak_3x30_mapon_15min.md",
    ),
    Source(
        "soak_10x30_mapoff.md",
        "soak",
        f"{_SOAK} --robots 10 --rate 30 --duration 180 --map off --out benchmarks/results/soak_10x30_mapoff.md",
    ),
    Source(
        "soak_20x30_500pts_mapoff_10min.md",
        "soak",
        f"{_SOAK} --robots 20 --rate 30 --duration 600 --points 500 --map off "
        "--out benchmarks/results/soak_20x30_500pts_mapoff_10min.md",
    ),
    Source(
        "link.md",
        "soak",
        "python benchmarks/bench_link.py --frames 60 --schema 1 --size 1280x720 --ack-timeout-s 60",
        note="delivery over an impaired link between network namespaces (issue 30)",
    ),
    Source(
        "link_flap5min.md",
        "soak",
        "python benchmarks/bench_link.py --rows flap5min --frames 3300 --schema 2 --size 640x360 --ack-timeout-s 120 "
        "--deadline-s 1200 --out link_flap5min.md",
        note="the link down for 5 minutes",
    ),
    Source(
        "chaos.md",
        "soak",
        "python benchmarks/bench_chaos.py --minutes 30 --seed 1 --robots 3 --rate 5 --dive-frames 300 "
        "--fault-every-s 45",
        note="random kills and restarts of base, router and robots with link flaps (issue 30)",
    ),
    Source("wire.md", "wire", "python benchmarks/bench_wire.py"),
    Source("fuzz.md", "fuzz", "python benchmarks/fuzz_decoders.py --n 3000 --seed 1"),
)


@dataclass(frozen=True)
class _Block:
    """A heading (empty for the text before the first one) and the lines under it, the heading line included."""

    heading: str
    lines: tuple[str, ...]


def _headings(lines: Sequence[str]) -> list[tuple[int, str] | None]:
    """Per line, its heading's level and text, or None (lines inside ``` fences are never headings)."""
    out: list[tuple[int, str] | None] = []
    fenced = False
    for line in lines:
        if line.lstrip().startswith("```"):
            fenced = not fenced
        match = None if fenced else _HEADING_RE.match(line)
        out.append((len(match.group(1)), match.group(2)) if match else None)
    return out


def _blocks(text: str) -> list[_Block]:
    """Split a Markdown text at its headings."""
    lines = text.splitlines()
    blocks: list[_Block] = []
    heading, start = "", 0
    for i, found in enumerate(_headings(lines)):
        if found is None:
            continue
        if i > start:
            blocks.append(_Block(heading, tuple(lines[start:i])))
        heading, start = found[1], i
    if len(lines) > start:
        blocks.append(_Block(heading, tuple(lines[start:])))
    return blocks


def _selected(text: str, sections: tuple[str, ...] | None) -> list[str]:
    """The lines of the blocks that ``sections`` names (every line when it is None)."""
    if sections is None:
        return text.splitlines()
    out: list[str] = []
    for block in _blocks(text):
        if any((block.heading.startswith(p) if p else not block.heading) for p in sections):
            out.extend(block.lines)
    return out


def _nest(lines: Sequence[str], below: int) -> list[str]:
    """Move the headings of ``lines`` down so that the highest becomes level ``below + 1`` (at most level 6);
    trailing spaces and the blank lines at both ends go."""
    headings = _headings(lines)
    levels = [h[0] for h in headings if h is not None]
    shift = below + 1 - min(levels) if levels else 0
    out = [
        line.rstrip() if h is None else f"{'#' * min(6, h[0] + shift)} {h[1]}"
        for line, h in zip(lines, headings, strict=True)
    ]
    while out and not out[0]:
        out.pop(0)
    while out and not out[-1]:
        out.pop()
    return out


def _slug(title: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^a-z0-9 _-]", "", title.lower()).replace(" ", "-")


def _found_command(text: str) -> str:
    match = _COMMAND_RE.search(text)
    return match.group(0).strip() if match else "command not recorded in the file"


def sources_for(names: Sequence[str], sources: Sequence[Source] = SOURCES) -> list[Source]:
    """The page's sources for these results file names: the ``sources`` whose file exists, then an "other"
    source for each file that ``sources`` does not name."""
    present = set(names)
    known = {s.file for s in sources}
    out = [s for s in sources if s.file in present]
    out += [Source(n, "other", "") for n in sorted(present - known)]
    return out


def build_page(results_dir: Path = RESULTS_DIR, sources: Sequence[Source] = SOURCES) -> str:
    """The text of docs/performance.md for the results files in ``results_dir``, placed by ``sources``."""
    texts = {p.name: p.read_text(encoding="utf-8") for p in sorted(results_dir.glob("*.md"))}
    placed = sources_for(list(texts), sources)
    by_topic = {key: [s for s in placed if s.topic == key] for key in TOPICS}
    lines = [
        "# Performance: every measured figure, by topic",
        "",
        "<!-- Generated by `python -m benchmarks.report` from benchmarks/results/*.md: do not edit by hand. -->",
        "",
        "Generated by `python -m benchmarks.report` from the files in `benchmarks/results/`, which the benchmarks",
        "write when they run (`./run bench` runs them all). Each section is headed with the command that wrote it;",
        "the text under it is the results file as the last run left it. Times are from a shared 2-core machine",
        "with other jobs running: compare the ratios measured within one run, not absolute times across runs.",
        "",
        "## Contents",
        "",
    ]
    for key, title in TOPICS.items():
        if not by_topic[key]:
            continue
        files = ", ".join(
            f"[{s.file}]({RESULTS_LINK}/{s.file})" + (f" ({s.note})" if s.note else "") for s in by_topic[key]
        )
        lines.append(f"- [{title}](#{_slug(title)}): {files}")
    for key, title in TOPICS.items():
        if not by_topic[key]:
            continue
        lines += ["", f"## {title}"]
        for source in by_topic[key]:
            text = texts[source.file]
            command = source.command or _found_command(text)
            note = f" ({source.note})" if source.note else ""
            lines += [
                "",
                f"{'#' * _SOURCE_LEVEL} `{command}`",
                "",
                f"From [`benchmarks/results/{source.file}`]({RESULTS_LINK}/{source.file}){note}.",
                "",
                *_nest(_selected(text, source.sections), _SOURCE_LEVEL),
            ]
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """Write docs/performance.md (or, with ``--check``, report whether it is up to date); returns the exit code."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--check", action="store_true", help="do not write; exit 1 if the page is out of date")
    ap.add_argument("--out", type=Path, default=PAGE_PATH, help="page to write (default docs/performance.md)")
    args = ap.parse_args(argv)
    page = build_page()
    if args.check:
        current = args.out.read_text(encoding="utf-8") if args.out.exists() else ""
        if current != page:
            print(f"{args.out} is out of date: run python -m benchmarks.report", file=sys.stderr)
            return 1
        return 0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(args.out.name + ".tmp")
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(args.out)
    print(f"wrote {args.out} from {len(list(RESULTS_DIR.glob('*.md')))} results files")
    return 0


if __name__ == "__main__":
    sys.exit(main())
