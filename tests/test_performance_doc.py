"""docs/performance.md is what benchmarks/report.py makes of benchmarks/results/*.md: no drift, nothing left out."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks import report

RESULTS = sorted(report.RESULTS_DIR.glob("*.md"))
REGENERATE = "run `python -m benchmarks.report` and commit docs/performance.md with the results"


def test_the_page_is_what_the_results_give() -> None:
    page = report.PAGE_PATH.read_text(encoding="utf-8")
    assert page == report.build_page(), f"docs/performance.md is out of date: {REGENERATE}"


@pytest.mark.parametrize("path", RESULTS, ids=lambda p: p.name)
def test_every_results_file_is_on_the_page(path: Path) -> None:
    page = report.PAGE_PATH.read_text(encoding="utf-8")
    assert f"(../benchmarks/results/{path.name})" in page, f"{path.name} is not linked: {REGENERATE}"
    on_page = set(page.splitlines())
    text_lines = [ln.rstrip() for ln in path.read_text(encoding="utf-8").splitlines()]
    missing = [ln for ln in text_lines if ln and not ln.startswith("#") and ln not in on_page]
    assert not missing, f"{path.name}: {len(missing)} lines not on the page, first {missing[0]!r}"


@pytest.mark.parametrize("path", RESULTS, ids=lambda p: p.name)
def test_every_results_file_has_its_command(path: Path) -> None:
    sources = [s for s in report.SOURCES if s.file == path.name]
    assert sources, f"name {path.name} in benchmarks/report.py SOURCES with its topic and command"
    assert all(s.command.startswith("python benchmarks/") for s in sources)


def test_split_files_are_split_without_overlap(tmp_path: Path) -> None:
    (tmp_path / "a.md").write_text("intro\n\n### First part\nx 1\n\n## Second part\nx 2\n", encoding="utf-8")
    (tmp_path / "zz_new.md").write_text("run by `python benchmarks/bench_new.py --fast` today\n", encoding="utf-8")
    sources = (
        report.Source("a.md", "accuracy", "cmd one", ("", "First")),
        report.Source("a.md", "speed", "cmd two", ("Second",)),
    )
    page = report.build_page(tmp_path, sources)
    accuracy, speed = page.split("## Extraction speed")
    assert ("intro" in accuracy, "x 1" in accuracy, "x 2" in accuracy) == (True, True, False)
    assert ("x 2" in speed, "x 1" in speed) == (True, False)
    # the file's headings nest under the subsection that names the command
    assert ("#### First part" in accuracy, "#### Second part" in speed) == (True, True)
    # a file SOURCES does not name is kept, headed with the command its text names
    assert "## Other results" in page
    assert "### `python benchmarks/bench_new.py --fast`" in page
