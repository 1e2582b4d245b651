"""The job end to end on recordings that do not start with a clean sideways walk.

Real sequences (../shared/data/real, skipped where absent): a photo set taken about 1 s apart and a
rotation-dominated start; synthetic ones with ground truth: dropped frames plus a corrupt image in
a folder, and a camera that only turns in place.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from papl_mapper.cli import main
from papl_mapper.eval import evaluate
from papl_mapper.eval.trajectory import associate_trajectories
from papl_mapper.geometry.se3 import rotation_angle_deg
from papl_mapper.geometry.similarity import umeyama
from papl_mapper.map import Map
from papl_mapper.synth import SynthConfig, generate, with_variants
from papl_mapper.trajectory_io import read_tum

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
MAX_ATE_M = {"tum_fr3_long_office_17": 0.02, "icl_lr_kt1_250_366": 0.005}  # COLMAP: 9.5 and 12.9 mm


def _ate_m(gt_path: Path, est_path: Path) -> tuple[float, int]:
    """ATE RMSE (m) after Sim(3) alignment over the matched poses, and how many matched."""
    gt, est = read_tum(gt_path), read_tum(est_path)
    i_gt, i_est = associate_trajectories(gt, est, 0.01)
    G, E = gt.T_wc[i_gt, :3, 3], est.T_wc[i_est, :3, 3]
    sim = umeyama(E, G)
    err = np.linalg.norm(sim.scale * E @ sim.R.T + sim.t - G, axis=1)
    return float(np.sqrt(np.mean(err**2))), len(i_gt)


@pytest.mark.parametrize("name", sorted(MAX_ATE_M))
def test_real_sequence_fully_posed(name, tmp_path):
    seq = REAL / name
    if not seq.is_dir():
        pytest.skip(f"{seq} is not there (the research data lives beside the checkout)")
    out = tmp_path / "out"
    assert (
        main(["-q", "run", str(seq / "images"), "--camera", str(seq / "camera.json"), "--out", str(out)]) == 0
    )
    n_images = len((seq / "images" / "timestamps.txt").read_text().split())
    assert len(read_tum(out / "trajectory.tum")) == n_images
    ate, matched = _ate_m(seq / "groundtruth.tum", out / "trajectory.tum")
    assert matched >= n_images - 1 and ate < MAX_ATE_M[name]


@pytest.fixture(scope="module")
def dropped_and_corrupt(tmp_path_factory):
    """A 6 s walk with 10% of its frames dropped, as an image folder with one truncated PNG."""
    root = tmp_path_factory.mktemp("dropped")
    base = SynthConfig(scene="corridor", width=480, height=360, seconds=6.0, write_frames=True)
    generate(with_variants(base, "dropped-frames"), root)
    bad = root / "frames" / "000040.png"
    bad.write_bytes(bad.read_bytes()[:3000])
    out = root / "out"
    assert (
        main(["-q", "run", str(root / "frames"), "--camera", str(root / "camera.json"), "--out", str(out)])
        == 0
    )
    return root, out


def test_dropped_frames_and_a_corrupt_image_are_bridged(dropped_and_corrupt):
    root, out = dropped_and_corrupt
    s = json.loads((out / "summary.json").read_text())
    assert s["frontend"]["bad_frames"] == ["000040.png (truncated PNG)"]
    n_kept = len((root / "timestamps.txt").read_text().split())
    assert s["recording"]["frames"] == n_kept - 1 and s["frames_lost"] == 0  # every decoded frame posed
    ev = evaluate(root, Map.load(out / "map.papl"), out / "trajectory.tum")
    assert ev.n_matched_poses == n_kept - 1 and ev.ate_rmse_rel_path < 0.01


def test_a_camera_turning_in_place_is_reported_with_its_orientations(tmp_path, capsys):
    root = tmp_path / "rec"
    cfg = with_variants(SynthConfig(scene="corridor", width=320, height=240, seconds=4.0), "rotation-only")
    generate(cfg, root)
    out = tmp_path / "out"
    assert (
        main(["run", str(root / "video.mp4"), "--camera", str(root / "camera.json"), "--out", str(out)]) == 2
    )
    errors = [line for line in capsys.readouterr().err.splitlines() if ": error: " in line]
    assert len(errors) == 1 and "rotation only" in errors[0]
    assert not (out / "map.papl").exists()
    assert json.loads((out / "summary.json").read_text())["status"] == "unmapped"
    est, gt = read_tum(out / "trajectory.tum"), read_tum(root / "gt" / "trajectory.tum")
    assert len(est) == len(gt) and np.allclose(est.T_wc[:, :3, 3], 0.0)
    # orientations relative to the first frame agree with the ground truth's
    R_est = est.T_wc[0, :3, :3].T @ est.T_wc[:, :3, :3]
    R_gt = gt.T_wc[0, :3, :3].T @ gt.T_wc[:, :3, :3]
    assert np.max(rotation_angle_deg(R_est, R_gt)) < 1.0
