"""Sequence tracking of the base station: property tests of ``SeqSet`` and of the acknowledged state file.

The base station keeps, per robot, the distinct sequence numbers received as a :class:`services.seqset.SeqSet`
(intervals), counts duplicates, and persists the ranges in ``<state>/fleet.json`` with the ``acked`` ranges
it has made durable (issue 7). These tests pin the properties the fault tolerance relies on: the result does
not depend on the order of arrival, duplicates are recognised, gaps are exactly the numbers not received,
and a restarted base de-duplicates against what it acknowledged.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.base import BaseStation
from services.keys import FleetKeys
from services.seqset import SeqSet

seq_lists = st.lists(st.integers(0, 300), max_size=200)


def gaps(s: SeqSet) -> set[int]:
    out: set[int] = set()
    nxt = 0
    for lo, hi in s.ranges():
        out |= set(range(nxt, lo))
        nxt = hi + 1
    return out


@settings(max_examples=200, deadline=None)
@given(seqs=seq_lists, data=st.data())
def test_order_independent_and_matches_a_set_model(seqs: list[int], data: st.DataObject) -> None:
    shuffled = data.draw(st.permutations(seqs))
    a, b = SeqSet(), SeqSet()
    new_a = [a.add(x) for x in seqs]
    for x in shuffled:
        b.add(x)
    assert a.ranges() == b.ranges()
    distinct = set(seqs)
    seen: set[int] = set()
    for x, new in zip(seqs, new_a, strict=True):  # add() tells a duplicate from a new number
        assert new == (x not in seen)
        seen.add(x)
    assert len(a) == len(distinct)
    highest = max(seqs, default=-1)
    assert a.highest == highest
    assert a.missed() == (highest + 1 - len(distinct) if seqs else 0)
    assert gaps(a) == set(range(highest + 1)) - distinct
    held = {x for lo, hi in a.ranges() for x in range(lo, hi + 1)}
    assert held == distinct
    for x in range(0, 305, 7):
        assert (x in a) == (x in distinct)
    assert SeqSet(a.ranges()).ranges() == a.ranges()  # the persisted form round-trips


@settings(max_examples=100, deadline=None)
@given(ranges=st.lists(st.tuples(st.integers(0, 100), st.integers(0, 20)), max_size=12))
def test_built_from_overlapping_unsorted_ranges_is_their_union(ranges: list[tuple[int, int]]) -> None:
    s = SeqSet([[lo, lo + w] for lo, w in ranges])
    union = {x for lo, w in ranges for x in range(lo, lo + w + 1)}
    assert {x for lo, hi in s.ranges() for x in range(lo, hi + 1)} == union
    rs = s.ranges()
    assert all(rs[i][1] + 1 < rs[i + 1][0] for i in range(len(rs) - 1))  # disjoint, not adjacent


@pytest.mark.parametrize("bad", [[[-1, 2]], [[3, 2]]])
def test_bad_ranges_are_refused(bad: list[list[int]]) -> None:
    with pytest.raises(ValueError, match="invalid"):
        SeqSet(bad)


def _station(state: Path) -> BaseStation:
    return BaseStation(None, FleetKeys("t"), state, map_mode="off")


def test_restart_deduplicates_against_the_acknowledged_ranges(tmp_path: Path) -> None:
    st = _station(tmp_path)
    rec = st._record("rov1")
    for x in [0, 1, 2, 3, 5]:
        rec.seqs.add(x)
    st.checkpoint()  # without the map: what arrived is durable once the file is written
    assert rec.acked == [[0, 3], [5, 5]]
    rec.seqs.add(6)  # arrived after the checkpoint, then the base dies before the next one
    st.save_state()  # counters written, acknowledgement unchanged
    saved = json.loads((tmp_path / "fleet.json").read_text())
    assert saved["robots"]["rov1"]["ranges"] == [[0, 3], [5, 6]]
    assert saved["robots"]["rov1"]["acked"] == [[0, 3], [5, 5]]
    again = _station(tmp_path)
    r2 = again.records["rov1"]
    assert r2.seqs.ranges() == [[0, 3], [5, 5]]  # 6 was never acknowledged: the robot still holds it
    assert r2.seqs.add(6)  # so its re-sent copy is taken, not dropped as a duplicate
    assert not r2.seqs.add(5)


def test_old_state_files_without_acked_are_read(tmp_path: Path) -> None:
    (tmp_path / "fleet.json").write_text(
        json.dumps({"format": "lrsensor-base-state", "version": 1, "robots": {"rov1": {"ranges": [[0, 9]]}}})
    )
    st = _station(tmp_path)
    assert st.records["rov1"].acked == [[0, 9]]
    assert len(st.records["rov1"].seqs) == 10
