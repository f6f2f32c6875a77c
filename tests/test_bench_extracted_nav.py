"""benchmarks.bench_extracted_nav: its arguments, its order shuffle and its table."""

from __future__ import annotations

import pytest

from benchmarks.bench_extracted_nav import DEFAULT, Row, Variant, parse_args, parse_variant, shuffle_ticks, table


def test_variants_parse_with_their_settings_and_the_default_first() -> None:
    v = parse_variant("nav26=smoother.drift_max_m_s=0.05,nav.fix_quality_factor=1.5")
    assert v == Variant("nav26", ("smoother.drift_max_m_s=0.05", "nav.fix_quality_factor=1.5"))
    for bad in ("smoother.drift_max_m_s=0.05", "k=0.002", f"{DEFAULT}=map.range_noise_per_m=0.002"):
        with pytest.raises(ValueError):
            parse_variant(bad)
    a = parse_args(["--seeds", "1,2", "--variant", "k=map.range_noise_per_m=0.002", "--order-seeds", "3"])
    assert [v.name for v in a.variants] == [DEFAULT, "k", "order 3"]
    assert a.variants[2].order_seed == 3
    assert not a.variants[2].sets
    assert a.seeds == [1, 2]
    assert a.modes == ["good", "drift", "depth-only"]
    assert a.ways == ["smoothed"]
    with pytest.raises(SystemExit):
        parse_args(["--ways", "filter"])


def test_the_shuffle_keeps_every_frame_within_its_tick() -> None:
    from benchmarks.fleet_dives import dive_frames

    frames = dive_frames("good", 1, 2.0)
    out = shuffle_ticks(frames, 1)
    assert [f.t_ns for f in out] == [f.t_ns for f in frames]
    assert sorted((f.robot, f.t_ns) for f in out) == sorted((f.robot, f.t_ns) for f in frames)
    assert [f.robot for f in out] != [f.robot for f in frames]  # 20 ticks of 3 robots: some order moves


def test_the_table_sums_per_mode_and_counts_wins_against_the_default() -> None:
    rows = [
        Row("good", 1, "smoothed", DEFAULT, 4, 12, 0, 2, 0.09, 10.0),
        Row("good", 1, "smoothed", "k", 9, 12, 1, 0, 0.03, 10.0),
        Row("drift", 1, "smoothed", DEFAULT, 8, 12, 0, 0, 0.05, 10.0),
        Row("drift", 1, "smoothed", "k", 8, 12, 0, 3, 0.07, 10.0),
    ]
    text = table(rows, [Variant(DEFAULT), Variant("k", ("map.range_noise_per_m=0.002",))])
    lines = text.splitlines()
    assert "| good seed 1 | 4 / 12, 0, 2 (9) | 9 / 12, 1, 0 (3) |" in lines
    assert "| sum, drift | **8 / 12, 0, 0** | **8 / 12, 0, 3** |" in lines
    assert "| sum, all | **12 / 24, 0, 2** | **17 / 24, 1, 3** |" in lines
    assert "| wins / ties / losses against the default | - | 1 / 0 / 1 |" in lines
