"""The base station's per-robot sequence tracker: counts, gaps, duplicates, persistence, order independence."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from services.seqtrack import SeqTracker, SeqTrackError


def test_counts_gaps_and_duplicates() -> None:
    t = SeqTracker()
    for seq in [0, 1, 2, 5, 6, 9]:
        assert t.add("rov1", seq)
    assert not t.add("rov1", 5)
    assert t.counters("rov1") == {"received": 6, "missed": 4, "duplicates": 1, "highest": 9}
    assert t.gaps("rov1") == [[3, 4], [7, 8]]
    assert t.gaps("rov1", limit=1) == [[3, 4]]
    assert t.ranges("rov1") == [[0, 2], [5, 6], [9, 9]]
    assert ("rov1", 6) in t
    assert ("rov1", 7) not in t
    assert ("rov2", 0) not in t
    # a redelivery closes the gaps
    for seq in [3, 4, 7, 8]:
        assert t.add("rov1", seq)
    assert t.counters("rov1") == {"received": 10, "missed": 0, "duplicates": 1, "highest": 9}
    assert t.counters("nobody") == {"received": 0, "missed": 0, "duplicates": 0, "highest": -1}


def test_late_start_counts_the_missing_head() -> None:
    t = SeqTracker()
    t.add("rov1", 10)
    assert t.missed("rov1") == 10  # 0..9 never came
    assert t.gaps("rov1") == [[0, 9]]


def test_robots_are_independent_and_listed() -> None:
    t = SeqTracker()
    t.add("b", 0)
    t.add("a", 3)
    t.ensure("c")
    assert t.robots() == ["a", "b", "c"]
    assert t.received("c") == 0
    assert t.highest("a") == 3


@pytest.mark.parametrize("seq", [-1, 1.5, "3", True, None])
def test_bad_sequence_numbers_are_refused(seq: Any) -> None:
    with pytest.raises(SeqTrackError):
        SeqTracker().add("rov1", seq)


def test_save_load_round_trip_and_dirty(tmp_path: Path) -> None:
    t = SeqTracker()
    assert not t.dirty
    t.merge("rov1", [0, 1, 2, 7, 7])
    t.add("rov2", 4)
    assert t.dirty
    path = tmp_path / "state" / "seq.json"
    t.save(path)
    assert not t.dirty
    u = SeqTracker.load(path)
    assert u.to_dict() == t.to_dict()
    assert u.counters("rov1") == {"received": 4, "missed": 4, "duplicates": 1, "highest": 7}
    assert not list(path.parent.glob(".*.tmp"))
    assert SeqTracker.load(tmp_path / "missing.json").robots() == []


@pytest.mark.parametrize(
    "data",
    [
        [],
        {"format": "other", "version": 1, "robots": {}},
        {"format": "lrsensor-seqtrack", "version": 2, "robots": {}},
        {"format": "lrsensor-seqtrack", "version": 1, "robots": []},
        {"format": "lrsensor-seqtrack", "version": 1, "robots": {"r": {"ranges": [[2, 1]]}}},
        {"format": "lrsensor-seqtrack", "version": 1, "robots": {"r": {"ranges": [[-1, 1]]}}},
        {"format": "lrsensor-seqtrack", "version": 1, "robots": {"r": {"ranges": [[0, 1.5]]}}},
        {"format": "lrsensor-seqtrack", "version": 1, "robots": {"r": {"ranges": "x"}}},
        {"format": "lrsensor-seqtrack", "version": 1, "robots": {"r": {"ranges": [], "duplicates": -2}}},
        {"format": "lrsensor-seqtrack", "version": 1, "robots": {"a/b": {"ranges": []}}},
        {"format": "lrsensor-seqtrack", "version": 1, "robots": {"base": {"ranges": []}}},
        {"format": "lrsensor-seqtrack", "version": 1, "robots": {"r": 3}},
    ],
)
def test_inconsistent_state_is_refused(data: Any) -> None:
    with pytest.raises(SeqTrackError):
        SeqTracker.from_dict(data)


def test_unreadable_file_is_refused(tmp_path: Path) -> None:
    p = tmp_path / "s.json"
    p.write_bytes(b"\x00\xff{")
    with pytest.raises(SeqTrackError, match="unreadable"):
        SeqTracker.load(p)


seq_lists = st.lists(st.integers(0, 300), max_size=200)


@settings(max_examples=200, deadline=None)
@given(seqs=seq_lists, data=st.data())
def test_order_independent_and_matches_a_set_model(seqs: list[int], data: st.DataObject) -> None:
    shuffled = data.draw(st.permutations(seqs))
    a, b = SeqTracker(), SeqTracker()
    new_a = [a.add("r", s) for s in seqs]
    b.merge("r", shuffled)
    assert a.to_dict() == b.to_dict()
    distinct = set(seqs)
    assert sum(new_a) == len(distinct)
    assert a.received("r") == len(distinct)
    assert a.duplicates("r") == len(seqs) - len(distinct)
    highest = max(seqs, default=-1)
    assert a.highest("r") == highest
    assert a.missed("r") == (highest + 1 - len(distinct) if seqs else 0)
    holes = {x for lo, hi in a.gaps("r") for x in range(lo, hi + 1)}
    assert holes == set(range(highest + 1)) - distinct
    held = {x for lo, hi in a.ranges("r") for x in range(lo, hi + 1)}
    assert held == distinct


@settings(max_examples=100, deadline=None)
@given(per_robot=st.dictionaries(st.sampled_from(["r1", "r2", "r3"]), seq_lists, max_size=3))
def test_json_round_trip(per_robot: dict[str, list[int]]) -> None:
    t = SeqTracker()
    for robot, seqs in per_robot.items():
        t.merge(robot, seqs)
    text = json.dumps(t.to_dict())
    assert SeqTracker.from_dict(json.loads(text)).to_dict() == t.to_dict()


json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 10**12) | st.floats() | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=20,
)


@settings(max_examples=150, deadline=None)
@given(
    robots=st.dictionaries(
        st.text(max_size=6), st.dictionaries(st.sampled_from(["ranges", "duplicates", "x"]), json_values), max_size=3
    )
    | json_values
)
def test_from_dict_raises_only_seqtrack_errors(robots: Any) -> None:
    data = {"format": "lrsensor-seqtrack", "version": 1, "robots": robots}
    try:
        t = SeqTracker.from_dict(data)
    except SeqTrackError:
        return
    for r in t.robots():  # whatever was accepted is consistent
        c = t.counters(r)
        assert c["received"] >= 0
        assert c["missed"] >= 0
