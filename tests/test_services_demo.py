"""``lrsensor demo`` end to end (short): simulated ROVs, base station, map, summary, PNG."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from waiting import wait_until

from lrsensor.cli import main
from services.demo import DemoConfig, format_summary, run_demo, score_map, truth_faces

pytestmark = pytest.mark.slow


def test_short_demo_delivers_every_cloud_and_writes_the_map(tmp_path: Path) -> None:
    cfg = DemoConfig(n_robots=2, duration_s=4.0, width=320, height=180, out_dir=tmp_path / "out", progress=False)
    res = run_demo(cfg)
    assert res.ok
    for row in res.rows:
        assert row["published"] > 0
        assert row["received"] == row["published"]
        assert row["missed"] == 0
        assert row["rejected"] == 0
        assert row["delivered"] is True
    assert json.loads((cfg.out_dir / "map.json").read_text())["planes"] == res.map["planes"]
    assert json.loads((cfg.out_dir / "status.json").read_text())["robots"].keys() == {"rov1", "rov2"}
    if res.status["map"]["enabled"]:
        assert res.png is not None
        assert res.png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = format_summary(res, cfg)
    assert "| rov1 |" in text
    assert "every cloud delivered: yes" in text


def test_demo_cli_runs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(
        ["demo", "--robots", "1", "--duration-s", "3", "--size", "320x180", "--no-progress", "--out", str(tmp_path)]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "every cloud delivered: yes" in out


def test_score_map_matches_true_faces_and_flags_spurious_planes() -> None:
    faces = truth_faces()
    assert len(faces) >= 4  # four walls at least
    planes = []
    for f in faces[:3]:
        n = f["normal"]
        planes.append(
            {"normal": list(n), "d": float(-n @ f["center"]) + 0.02, "extent": {"centroid": list(f["center"])}}
        )
    planes.append({"normal": [0.0, 0.0, 1.0], "d": -1.0, "extent": {"centroid": [5.0, 4.0, 1.0]}})
    s = score_map(planes)
    assert len(s["matched"]) == 3
    assert s["spurious"] == 1
    assert all(abs(e["offset_m"] - 0.02) < 1e-9 for e in s["matched"].values())
    assert np.isfinite(next(iter(s["matched"].values()))["angle_deg"])


def test_demo_process_ends_cleanly_on_sigterm(tmp_path: Path) -> None:
    import os
    import signal
    import subprocess
    import sys
    import time

    log = tmp_path / "demo.log"
    with log.open("wb") as fh:
        p = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "lrsensor",
                "-v",
                "demo",
                "--robots",
                "2",
                "--duration-s",
                "120",
                "--size",
                "320x180",
                "--no-progress",
                "--out",
                str(tmp_path / "out"),
            ],
            stdout=fh,
            stderr=subprocess.STDOUT,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
        try:
            # up and publishing within a minute (a process that ends before that fails at once)
            wait_until(lambda: "publishing on" in log.read_text(errors="replace") or p.poll() is not None, 60, 0.1)
            assert "publishing on" in log.read_text(errors="replace"), log.read_text(errors="replace")
            t0 = time.monotonic()
            p.send_signal(signal.SIGTERM)
            assert p.wait(30) == 0, log.read_text(errors="replace")
            assert time.monotonic() - t0 < 30
        finally:
            if p.poll() is None:
                p.kill()
                p.wait()
    assert "every cloud delivered: yes" in log.read_text(errors="replace")
