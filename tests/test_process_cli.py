"""``lrsensor process``: in-process CLI runs on rendered images (tmp_path, capsys)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from lrsensor.cli import main
from lrsensor.ply import read_ply, read_ply_points

sim = pytest.importorskip("lrsensor.sim")


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """Two images of walls at 0.8 m and 1.2 m (640x360) and their calibration file."""
    d = tmp_path_factory.mktemp("process")
    paths = []
    calib = None
    for dist in (0.8, 1.2):
        r = sim.wall_scene(dist, width=640, height=360).render(seed=1)
        p = d / f"wall_{dist:.1f}.png"
        cv2.imwrite(str(p), r.image)
        paths.append(p)
        calib = r.calibration
    assert calib is not None
    cpath = d / "calib.json"
    calib.save(cpath)
    return paths[0], paths[1], cpath


def test_one_image_to_ply(scene: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    img, _, calib = scene
    out = tmp_path / "out" / "scan.ply"
    assert main(["process", str(img), "--calib", str(calib), "--out", str(out)]) == 0
    assert "points (subpixel)" in capsys.readouterr().out
    d = read_ply(out)
    assert set(d) == {"x", "y", "z", "laser", "quality", "u", "v"}
    assert d["x"].dtype == np.float32
    assert d["laser"].dtype == np.uint8
    pts = read_ply_points(out)
    assert pts.shape[0] > 0.95 * 2 * 640
    assert np.median(np.abs(pts[:, 0] - 0.8)) < 0.002  # the wall at 0.8 m, body frame
    assert set(np.unique(d["laser"]).tolist()) == {0, 1}
    assert np.all((d["quality"] >= 0) & (d["quality"] <= 1))


def test_batch_to_out_dir_with_paper_method(
    scene: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    a, b, calib = scene
    out = tmp_path / "plys"
    code = main(["process", str(a), str(b), "--calib", str(calib), "--out-dir", str(out), "--method", "paper"])
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == ["wall_0.8.ply", "wall_1.2.ply"]
    far = read_ply_points(out / "wall_1.2.ply")
    assert 20 <= far.shape[0] <= 128
    assert np.median(np.abs(far[:, 0] - 1.2) / 1.2) < 0.05
    assert "processed 2 of 2 images" in capsys.readouterr().out


def test_missing_unreadable_and_wrong_size_images(
    scene: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    a, _, calib = scene
    assert main(["process", str(tmp_path / "nope.png"), "--calib", str(calib), "--out", str(tmp_path / "x.ply")]) == 2
    assert "not found" in capsys.readouterr().err
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image")
    assert main(["process", str(junk), "--calib", str(calib), "--out", str(tmp_path / "x.ply")]) == 2
    assert "cannot read image" in capsys.readouterr().err
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((100, 200, 3), np.uint8))
    assert main(["process", str(small), "--calib", str(calib), "--out", str(tmp_path / "x.ply")]) == 2
    assert "200x100" in capsys.readouterr().err
    assert not (tmp_path / "x.ply").exists()
    # in a batch the good images are still written and the exit code says something failed
    out = tmp_path / "batch"
    assert main(["process", str(a), str(junk), "--calib", str(calib), "--out-dir", str(out), "--no-progress"]) == 2
    assert (out / f"{a.stem}.ply").exists()
    assert not (out / "junk.ply").exists()
    assert "processed 1 of 2" in capsys.readouterr().out


def test_flag_errors(scene: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a, b, calib = scene
    assert main(["process", str(a), str(b), "--calib", str(calib), "--out", str(tmp_path / "x.ply")]) == 2
    assert "--out-dir" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    assert main(["process", str(a), "--calib", str(bad), "--out", str(tmp_path / "x.ply")]) == 2
    assert "camera" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["process", str(a), "--calib", str(calib)])  # neither --out nor --out-dir


def test_ply_round_trip_and_bad_files(tmp_path: Path) -> None:
    from lrsensor.ply import PlyError, write_ply

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3))
    props = {"laser": rng.integers(0, 2, 50).astype(np.uint8), "quality": rng.uniform(size=50)}
    p = write_ply(tmp_path / "a.ply", pts, props, comments=("test",))
    d = read_ply(p)
    assert np.allclose(read_ply_points(p), pts.astype(np.float32))
    assert np.array_equal(d["laser"], props["laser"])
    assert np.allclose(d["quality"], props["quality"].astype(np.float32))
    raw = p.read_bytes()
    (tmp_path / "t.ply").write_bytes(raw[:-10])
    with pytest.raises(PlyError, match="truncated"):
        read_ply(tmp_path / "t.ply")
    (tmp_path / "n.ply").write_bytes(b"hello")
    with pytest.raises(PlyError, match="not a PLY"):
        read_ply(tmp_path / "n.ply")
    with pytest.raises(PlyError, match="shape"):
        write_ply(tmp_path / "b.ply", pts[:, :2])
    # ASCII PLY (as other tools write) reads too
    (tmp_path / "asc.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
        "end_header\n1 2 3\n4 5 6\n"
    )
    assert np.allclose(read_ply_points(tmp_path / "asc.ply"), [[1, 2, 3], [4, 5, 6]])


def test_overlay_pictures(scene: tuple[Path, Path, Path], tmp_path: Path) -> None:
    img, img2, calib = scene
    views = tmp_path / "views"
    args = ["process", str(img), str(img2), "--calib", str(calib), "--out-dir", str(tmp_path / "ply")]
    assert main([*args, "--overlay", str(views), "--no-progress"]) == 0
    for p in (img, img2):
        pic = cv2.imread(str(views / f"{p.stem}_overlay.png"))
        src = cv2.imread(str(p))
        assert pic is not None
        assert pic.shape == src.shape
        d = read_ply(tmp_path / "ply" / f"{p.stem}.ply")
        u = np.rint(d["u"]).astype(int)
        v = np.rint(d["v"]).astype(int)
        laser = d["laser"].astype(int)
        # every point is drawn in its laser's colour (magenta / yellow, dimmed by quality), on a darkened image
        top = pic[v[laser == 0], u[laser == 0]].astype(int)
        bottom = pic[v[laser == 1], u[laser == 1]].astype(int)
        assert np.all(top[:, 1] < 0.2 * top[:, 0])
        assert np.all(top[:, 0] > 80)
        assert np.all(bottom[:, 0] < 0.2 * bottom[:, 1])
        assert np.all(bottom[:, 1] > 80)
        # the rest is the image darkened: the top rows hold no stripe and no band (0.2 m is 46 rows off centre)
        assert np.all(pic[:20] <= src[:20])
        assert pic[:20].mean() < 0.7 * src[:20].mean()


def test_overlay_rejects_a_bad_image() -> None:
    from lrsensor.errors import ExtractionError
    from lrsensor.overlay import draw_scan
    from lrsensor.scan import Scan

    empty = Scan(np.zeros((0, 3)), np.zeros(0, int), np.zeros((0, 2)), np.zeros(0))
    with pytest.raises(ExtractionError, match="uint8 BGR"):
        draw_scan(np.zeros((10, 10), np.uint8), empty)
    assert draw_scan(np.full((4, 5, 3), 100, np.uint8), empty).max() == 60  # darkened, nothing drawn


def test_channel_flag(scene: tuple[Path, Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--channel luma`` reaches the sub-pixel extractor (a JPEG copy of the wall still measures 0.8 m); with
    another method it is refused, naming the flag; an unknown channel is an argparse error."""
    img, _, calib = scene
    jpg = tmp_path / "wall.jpg"
    cv2.imwrite(str(jpg), cv2.imread(str(img)), [cv2.IMWRITE_JPEG_QUALITY, 85])
    out = tmp_path / "luma.ply"
    assert main(["process", str(jpg), "--calib", str(calib), "--out", str(out), "--channel", "luma"]) == 0
    pts = read_ply_points(out)
    assert pts.shape[0] > 0.95 * 2 * 640
    assert np.median(np.abs(pts[:, 0] - 0.8)) < 0.002
    capsys.readouterr()
    bad = ["process", str(jpg), "--calib", str(calib), "--out", str(out), "--channel", "luma", "--method", "paper"]
    assert main(bad) == 2
    assert "--channel is an option of the subpixel extractor" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["process", str(jpg), "--calib", str(calib), "--out", str(out), "--channel", "blue"])


def test_channel_option_of_the_command_lines() -> None:
    """The one translation of ``--channel`` that ``process``, ``rov`` and the benchmark share."""
    from lrsensor.errors import ExtractionError
    from lrsensor.extract import channel_option

    assert channel_option("subpixel", None) == {}
    assert channel_option("paper", None) == {}
    assert channel_option(None, "luma") == {"channel": "luma"}  # None = the default method, sub-pixel
    assert channel_option("subpixel", "green") == {"channel": "green"}
    with pytest.raises(ExtractionError, match="not of --method paper"):
        channel_option("paper", "luma")


def test_command_line_options_of_process_and_rov() -> None:
    """The extractor options ``process`` and ``rov`` build from their flags: only the flags given, ``--channel``
    refused with another method than the sub-pixel extractor."""
    from lrsensor.errors import ExtractionError
    from lrsensor.extract import command_line_options

    assert command_line_options("subpixel", None, None, None) == {}
    assert command_line_options("paper", None, 0.5, None) == {"min_range_m": 0.5}
    assert command_line_options(None, "luma", None, 3.0) == {"channel": "luma", "max_range_m": 3.0}
    assert command_line_options("subpixel", "green", 0.3, 4.0) == {
        "channel": "green",
        "min_range_m": 0.3,
        "max_range_m": 4.0,
    }
    with pytest.raises(ExtractionError, match="not of --method paper"):
        command_line_options("paper", "luma", 0.5, None)
