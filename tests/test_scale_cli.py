"""`papl-map scale` on a finished run, `run --marker/--camera-height`, and bad input: one error line,
a non-zero exit, and the run's files exactly as they were."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from papl_mapper.cli import main
from papl_mapper.exporters import export
from papl_mapper.map import Map
from papl_mapper.trajectory_io import Trajectory, read_tum, write_tum
from tests.test_scale import EYE_M, UNITS_PER_M, room_map

EXPORTS = ("map.ply", "map.glb", "map.dxf", "map.colmap")


@pytest.fixture
def run_dir(tmp_path: Path) -> Path:
    """A finished run of the room walk: map, trajectories, summary and exports, in arbitrary units."""
    out = tmp_path / "run"
    out.mkdir()
    m = room_map(0.01)
    m.save(out / "map.papl")
    kf = Trajectory(m.keyframes.timestamp, m.keyframes.T_wc, "keyframes")
    write_tum(out / "keyframes.tum", kf)
    write_tum(out / "trajectory.tum", kf)
    (out / "summary.json").write_text(json.dumps({"counts": m.summary(), "frames_lost": 0}))
    for name in EXPORTS:
        export(m, out / name)
    return out


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_known_length_rescales_every_output(run_dir: Path, capsys):
    before = Map.load(run_dir / "map.papl")
    assert main(["scale", str(run_dir), "--length", "1=4.0"]) == 0
    out = capsys.readouterr().out
    assert "m per map unit" in out and "wrote" in out
    m = Map.load(run_dir / "map.papl")
    assert m.metadata["units"] == "m" and m.metadata["scale"]["source"] == "length"
    assert np.allclose(m.lines.lengths(), 4.0)
    np.testing.assert_allclose(m.points.xyz, before.points.xyz / UNITS_PER_M)
    traj = read_tum(run_dir / "trajectory.tum")
    np.testing.assert_allclose(traj.positions, before.keyframes.T_wc[:, :3, 3] / UNITS_PER_M, atol=1e-9)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["counts"]["units"] == "m" and summary["scale"]["description"].startswith("line 1")
    assert b"comment units m" in (run_dir / "map.ply").read_bytes()[:2000]
    assert "# Units: m; scale m from line 1" in (run_dir / "map.colmap" / "points3D.txt").read_text()
    assert not list(run_dir.glob(".*.tmp"))
    assert main(["info", str(run_dir / "map.papl")]) == 0
    assert "units          m from line 1 of known length 4 m" in capsys.readouterr().out


def test_previews_and_report_follow_the_scale(run_dir: Path, capsys):
    from PIL import Image

    from papl_mapper.gui.preview import PreviewOptions, render_views
    from papl_mapper.gui.report import write_report

    render_views(Map.load(run_dir / "map.papl"), run_dir / "previews", PreviewOptions(views=("top",)))
    write_report(run_dir, run_dir / "report.html")
    top = np.asarray(Image.open(run_dir / "previews" / "top.png"))
    assert "arbitrary (monocular scale unknown)" in (run_dir / "report.html").read_text()
    assert main(["scale", str(run_dir), "--length", "1=4.0"]) == 0
    assert "m from line 1 of known length 4 m" in (run_dir / "report.html").read_text()
    assert not np.array_equal(np.asarray(Image.open(run_dir / "previews" / "top.png")), top)  # new title


def test_camera_height_and_points_on_a_finished_run(run_dir: Path, capsys):
    m = Map.load(run_dir / "map.papl")
    metres = float(np.linalg.norm(m.points.xyz[0] - m.points.xyz[5])) / UNITS_PER_M
    args = ["scale", str(run_dir), "--camera-height", str(EYE_M), "--points", f"0,5={metres}"]
    assert main(args) == 0
    scaled = Map.load(run_dir / "map.papl")
    assert scaled.metadata["scale"]["metres_per_unit"] == pytest.approx(1 / UNITS_PER_M, rel=0.01)


def test_dry_run_writes_nothing(run_dir: Path, capsys):
    before = snapshot(run_dir)
    assert main(["scale", str(run_dir), "--length", "1=4.0", "--dry-run"]) == 0
    assert "m per map unit" in capsys.readouterr().out
    assert snapshot(run_dir) == before


@pytest.mark.parametrize(
    "args, says",
    [
        (["--length", "99=2.0"], "--length 99=2: the map has no line 99"),
        (["--length", "1=-2"], "positive number of metres"),
        (["--length", "one=2"], "--length 'one=2': 'one' is not an id"),
        (["--length", "1"], "expected LENGTH=METRES"),
        (["--points", "0=2"], "expected two point ids"),
        (["--marker", "aruco:5X9_50:7=0.2"], "unknown ArUco dictionary"),
        (["--marker", "aruco:4X4_50:7=0.2"], "the map does not name its recording"),
        (["--camera-height", "-1.6"], "positive number of metres"),
        (["--length", "0=4.0", "--length", "1=8.0"], "conflicting scales"),
        ([], "give a scale source"),
    ],
)
def test_bad_input_is_one_line_and_changes_nothing(run_dir: Path, capsys, args, says):
    before = snapshot(run_dir)
    assert main(["scale", str(run_dir), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("papl-map scale: error:") and says in err and "\n" not in err, err
    assert snapshot(run_dir) == before


def test_no_floor_found_changes_nothing(run_dir: Path, capsys):
    m = Map.load(run_dir / "map.papl")
    high = m.points.xyz[:, 2] > 1.3 * UNITS_PER_M
    m.points.xyz, m.points.ids, m.points.color = m.points.xyz[high], m.points.ids[high], m.points.color[high]
    m.lines = type(m.lines).empty(3)
    m.save(run_dir / "map.papl")
    before = snapshot(run_dir)
    assert main(["scale", str(run_dir), "--camera-height", "1.6"]) == 2
    assert "no floor found" in capsys.readouterr().err
    assert snapshot(run_dir) == before


def test_a_failure_while_writing_leaves_the_run_as_it_was(run_dir: Path, monkeypatch, capsys):
    import papl_mapper.scale.run_dir as rd

    def broken(path, traj):
        Path(path).write_text("half")
        raise OSError("disk full")

    monkeypatch.setattr(rd, "write_tum", broken)
    before = snapshot(run_dir)
    assert main(["scale", str(run_dir), "--length", "1=4.0"]) == 2
    err = capsys.readouterr().err.strip()
    assert "could not write the file (disk full)" in err and "\n" not in err and "Traceback" not in err
    assert snapshot(run_dir) == before  # no temporary file left either


def test_not_a_run_folder(tmp_path: Path, capsys):
    assert main(["scale", str(tmp_path / "nope"), "--length", "1=2"]) == 2
    assert "no such run folder" in capsys.readouterr().err
    assert main(["scale", str(tmp_path), "--length", "1=2"]) == 2
    assert "holds no map.papl" in capsys.readouterr().err


def test_run_refuses_a_bad_marker_before_any_work(tmp_path: Path, capsys):
    out = tmp_path / "out"
    assert main(["run", "samples/demo/video.mp4", "--out", str(out), "--marker", "aruco:4X4_50:70=0.2"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--marker 'aruco:4X4_50:70=0.2'" in err and "ids 0..49" in err and "\n" not in err
    assert not out.exists()
    assert main(["run", "samples/demo/video.mp4", "--out", str(out), "--camera-height", "-2"]) == 2
    assert "positive" in capsys.readouterr().err and not out.exists()
