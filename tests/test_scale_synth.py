"""Synthetic ArUco markers: placed on walls, rendered, detected where the ground truth says, off by
default; and the whole chain `synth --markers` -> `run --marker --camera-height` against the truth."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from papl_mapper.cli import main
from papl_mapper.errors import InputError
from papl_mapper.eval.trajectory import associate_trajectories
from papl_mapper.geometry.similarity import umeyama
from papl_mapper.map import Map
from papl_mapper.scale import detect_markers, parse_marker_spec
from papl_mapper.synth.generate import SynthConfig, camera_path
from papl_mapper.synth.markers import place_markers
from papl_mapper.synth.project import project
from papl_mapper.synth.render import Renderer
from papl_mapper.synth.scenes import make_scene
from papl_mapper.trajectory_io import read_tum


@pytest.mark.parametrize("scene_name", ["corridor", "atlanta"])
def test_marker_renders_where_the_ground_truth_says(scene_name):
    cfg = SynthConfig(scene=scene_name, seconds=10, width=480, height=360)
    scene, camera = make_scene(scene_name, 0), cfg.camera()
    _, T_wc = camera_path(cfg, scene)
    with_marker, truth = place_markers(scene, camera, T_wc, 1, 0.2, "4X4_50", 0)
    assert len(with_marker.quad_corners) > len(scene.quad_corners)
    assert np.array_equal(with_marker.quad_corners[: len(scene.quad_corners)], scene.quad_corners)
    corners = np.array(truth[0]["corners_w"])
    sides = np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1)
    np.testing.assert_allclose(sides, 0.2, atol=1e-9)
    # the closest face-on frame between 1 and 3 m
    centre, normal = corners.mean(axis=0), np.array(truth[0]["normal_w"])
    d = T_wc[:, :3, 3] - centre
    dist = np.linalg.norm(d, axis=1)
    ok = (dist > 1) & (dist < 3) & ((d @ normal) / dist > 0.6)
    for i in np.flatnonzero(ok):
        uv, z = project(camera, T_wc[i], corners)
        ok[i] = (z > 0).all() and (uv > 10).all() and (uv < [camera.width - 10, camera.height - 10]).all()
    k = int(np.flatnonzero(ok)[np.argmin(dist[ok])])  # the closest view that sees it whole
    img, _ = Renderer(with_marker, camera, 2).render(T_wc[k])
    gray = cv2.cvtColor((np.clip(img / 1.5, 0, 1) * 255).astype(np.uint8), cv2.COLOR_BGR2GRAY)
    specs = [parse_marker_spec("aruco:4X4_50:0=0.2"), parse_marker_spec("aruco:4X4_50:1=0.2")]
    found = detect_markers([(k, gray)], specs)
    assert found[specs[1]] == [] and len(found[specs[0]]) == 1
    uv, _ = project(camera, T_wc[k], corners)
    assert np.abs(found[specs[0]][0][1] - uv).max() < 1.0


def test_markers_are_off_by_default_and_validated():
    d = SynthConfig().to_dict()
    assert not {"markers", "marker_size", "marker_dictionary"} & set(d)  # scene.json as it always was
    on = SynthConfig(markers=2, marker_size=0.15)
    assert on.to_dict()["markers"] == 2 and "--markers 2 --marker-size 0.15" in on.command("out")
    for bad in (
        SynthConfig(markers=-1),
        SynthConfig(markers=1, marker_size=0),
        SynthConfig(marker_dictionary="9X9"),
    ):
        with pytest.raises(InputError):
            bad.validate()


def test_synth_marker_run_is_metric_against_the_truth(tmp_path, capsys):
    rec = tmp_path / "rec"
    assert (
        main(["synth", "corridor", "--out", str(rec), "--seconds", "5", "--fps", "15", "--markers", "1"]) == 0
    )
    truth = json.loads((rec / "gt" / "markers.json").read_text())
    assert truth[0]["size_m"] == 0.2 and truth[0]["dictionary"] == "4X4_50"
    run = tmp_path / "run"
    args = ["run", str(rec / "video.mp4"), "--camera", str(rec / "camera.json"), "--out", str(run)]
    assert main([*args, "--marker", "aruco:4X4_50:0=0.2", "--camera-height", "1.6"]) == 0
    m = Map.load(run / "map.papl")
    assert m.metadata["units"] == "m" and m.metadata["scale"]["source"] in ("marker", "camera_height")
    gt, est = read_tum(rec / "gt" / "trajectory.tum"), read_tum(run / "trajectory.tum")
    i, j = associate_trajectories(gt, est, 0.01)
    assert umeyama(est.positions[j], gt.positions[i]).scale == pytest.approx(1.0, abs=0.03)
    capsys.readouterr()
    # a marker that is not in the recording: one line, and the previous outputs stay
    before = (run / "map.papl").read_bytes()
    assert main([*args, "--resume", "--marker", "aruco:4X4_50:9=0.2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "never detected" in err and "--resume" in err
    assert (run / "map.papl").read_bytes() == before
