"""Evaluation: TUM I/O, association, Sim(3), ATE/RPE (hand-computed and against evo), lines, axes, CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from papl_mapper.errors import GeometryError, InputError
from papl_mapper.eval import (
    EvalConfig,
    associate,
    evaluate,
    line_metrics,
    match_axes,
    nearest_segment_distance,
    point_segment_distance,
    read_axes,
    read_segments,
    rpe,
)
from papl_mapper.geometry.similarity import umeyama
from papl_mapper.map import Axes, Camera, Keyframes, Lines, LineState, Map
from papl_mapper.trajectory_io import Trajectory, read_tum, write_tum

# named tolerances
EXACT = 1e-9  # closed-form results on noise-free data
EVO_AGREEMENT = 1e-6  # the brief: ATE RMSE equal to evo's to 1e-6
NOISY_SCALE_REL = 0.01  # relative scale error with 1 % position noise


# ---- helpers ----------------------------------------------------------------------------------


def walk(n: int = 60, seed: int = 0, fps: float = 30.0) -> Trajectory:
    """A hand-held-like loop: varied position in 3D and rotation (yaw sweep, small roll/pitch)."""
    rng = np.random.default_rng(seed)
    a = np.linspace(0, 1.7 * np.pi, n)
    T = np.repeat(np.eye(4)[None], n, axis=0)
    T[:, :3, 3] = np.stack([5 * np.cos(a), 3 * np.sin(a), 1.5 + 0.3 * np.sin(3 * a)], axis=1)
    euler = np.stack([a + np.pi / 2, rng.normal(0, 0.05, n), rng.normal(0, 0.05, n)], axis=1)
    T[:, :3, :3] = Rotation.from_euler("zyx", euler).as_matrix()
    return Trajectory(np.arange(n) / fps, T, "walk")


def random_sim3(seed: int = 1, scale: float = 2.5) -> np.ndarray:
    rng = np.random.default_rng(seed)
    S = np.eye(4)
    S[:3, :3] = scale * Rotation.random(random_state=rng).as_matrix()
    S[:3, 3] = rng.normal(0, 3, 3)
    return S


def transform_traj(traj: Trajectory, S: np.ndarray) -> Trajectory:
    """Apply x -> S x to the camera centres and R -> R_S R to the orientations."""
    s = np.cbrt(np.linalg.det(S[:3, :3]))
    R = S[:3, :3] / s
    T = traj.T_wc.copy()
    T[:, :3, :3] = R @ T[:, :3, :3]
    T[:, :3, 3] = traj.positions @ S[:3, :3].T + S[:3, 3]
    return Trajectory(traj.timestamps.copy(), T, traj.name)


def room_segments() -> tuple[np.ndarray, np.ndarray]:
    """The 12 edges of a 10 x 6 x 3 box around the walk: axes 0 = z (vertical), 1 = x, 2 = y."""
    c = np.array([[x, y, z] for z in (0, 3) for y in (-3, 3) for x in (-5, 5)], float)
    edges = [(0, 1), (2, 3), (4, 5), (6, 7), (0, 2), (1, 3), (4, 6), (5, 7), (0, 4), (1, 5), (2, 6), (3, 7)]
    return c[np.array(edges)], np.array([1] * 4 + [2] * 4 + [0] * 4)


GT_AXES = np.array([[0, 0, 1.0], [1, 0, 0], [0, 1, 0]])


def write_gt(folder: Path, traj: Trajectory, segs: np.ndarray, seg_axis: np.ndarray, axes=GT_AXES) -> Path:
    """A ground-truth folder in the agreed layout (GT/gt/...)."""
    gt = folder / "gt"
    gt.mkdir(parents=True)
    write_tum(gt / "trajectory.tum", traj)
    rows = [" ".join(f"{v:.17g}" for v in s.ravel()) + f" {a}" for s, a in zip(segs, seg_axis, strict=True)]
    (gt / "segments.txt").write_text("# x1 y1 z1 x2 y2 z2 axis\n" + "\n".join(rows) + "\n")
    names = ["vertical"] + [f"horizontal {i}" for i in range(1, len(axes))]
    (gt / "axes.json").write_text(
        json.dumps({"directions": np.asarray(axes).tolist(), "vertical_index": 0, "names": names})
    )
    return folder


def map_from(traj: Trajectory, segs: np.ndarray, seg_axis: np.ndarray, axes=GT_AXES) -> Map:
    """A map whose keyframes are the trajectory and whose lines are the segments (anchored by axis)."""
    n, m = len(traj), len(segs)
    w = np.zeros((m, len(axes)))
    w[seg_axis >= 0, seg_axis[seg_axis >= 0]] = 1.0
    lines = Lines(
        np.arange(m),
        np.asarray(segs, float).copy(),
        w,
        np.where(seg_axis >= 0, LineState.ANCHORED, LineState.ORTHONORMAL).astype(np.int8),
        np.where(seg_axis >= 0, 0, -1),
        np.where(seg_axis >= 0, 0.5, np.nan),
        np.zeros((0, 2), np.int64),
        np.zeros((0, 4)),
    )
    kf = Keyframes(np.arange(n), np.arange(n), traj.timestamps.copy(), traj.T_wc.copy())
    return Map(Camera(640, 480, 500.0, 500.0, 319.5, 239.5), kf, lines=lines, axes=Axes(np.asarray(axes), 0))


def sim3_map(m: Map, S: np.ndarray) -> Map:
    """The same map seen through x -> S x (what a monocular mapper returns: another frame and scale)."""
    traj = transform_traj(Trajectory(m.keyframes.timestamp, m.keyframes.T_wc), S)
    s = np.cbrt(np.linalg.det(S[:3, :3]))
    lines = Lines(
        m.lines.ids,
        m.lines.endpoints_w @ S[:3, :3].T + S[:3, 3],
        m.lines.axis_weights,
        m.lines.state,
        m.lines.ref_keyframe_id,
        m.lines.inverse_depth,
        m.lines.obs_ids,
        m.lines.obs_xy,
    )
    kf = Keyframes(m.keyframes.ids, m.keyframes.frame_index, traj.timestamps, traj.T_wc)
    axes = Axes(m.axes.directions @ (S[:3, :3] / s).T, m.axes.vertical_index)
    out = Map(m.camera, kf, m.points, lines, axes, dict(m.metadata))
    out.validate()
    return out


def orthogonal_offsets(x: np.ndarray, sigma: float, seed: int = 3) -> np.ndarray:
    """Offsets (N, 3) orthogonal to span{1, x columns}: adding them to the reference leaves Umeyama exact."""
    rng = np.random.default_rng(seed)
    A = np.column_stack([np.ones(len(x)), x])
    Q, _ = np.linalg.qr(A)
    e = rng.normal(0, sigma, x.shape)
    return e - Q @ (Q.T @ e)


# ---- TUM files ---------------------------------------------------------------------------------


def test_tum_round_trip(tmp_path):
    t = walk()
    back = read_tum(write_tum(tmp_path / "t.tum", t))
    np.testing.assert_allclose(back.timestamps, t.timestamps, atol=0)
    np.testing.assert_allclose(back.T_wc, t.T_wc, atol=1e-12)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("0 1 2 3 0 0 0 1\n# c\n1 1 2 3 0 0 1\n", r"line 3 has 7 values"),
        ("0 1 2 3 0 0 0 1\n1 a 2 3 0 0 0 1\n", r"line 2 holds a non-number"),
        ("0 1 2 nan 0 0 0 1\n", r"line 1 holds NaN"),
        ("0 1 2 3 0 0 0 0\n", r"line 1 has a zero quaternion"),
        ("0 1 2 3 0 0 0 1\n0 1 2 3 0 0 0 1\n", r"lines 1 and 2 share timestamp 0.0"),
        ("# only a comment\n", r"holds no poses"),
    ],
)
def test_malformed_tum_names_file_and_line(tmp_path, text, match):
    p = tmp_path / "bad.tum"
    p.write_text(text)
    with pytest.raises(InputError, match=match) as info:
        read_tum(p)
    assert str(p) in str(info.value)


def test_unsorted_tum_is_sorted_and_quaternions_normalised(tmp_path):
    p = tmp_path / "u.tum"
    p.write_text("2.0 2 0 0 0 0 0 2\n1.0 1 0 0 0 0 0.7071068 0.7071068\n")
    t = read_tum(p)
    assert t.timestamps.tolist() == [1.0, 2.0] and t.positions[:, 0].tolist() == [1.0, 2.0]
    np.testing.assert_allclose(t.T_wc[1, :3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(t.T_wc[0, :3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-6)


def test_missing_and_binary_tum(tmp_path):
    with pytest.raises(InputError, match="no such trajectory file"):
        read_tum(tmp_path / "none.tum")
    (tmp_path / "bin.tum").write_bytes(b"\xff\xfe\x00\x81" * 10)
    with pytest.raises(InputError, match="bin.tum"):
        read_tum(tmp_path / "bin.tum")


# ---- association and alignment -------------------------------------------------------------------


def test_associate_hand_cases():
    i1, i2 = associate(np.array([0.0, 1.0, 2.0, 3.0]), np.array([0.005, 1.02, 1.995, 5.0]), 0.01)
    assert i1.tolist() == [0, 2] and i2.tolist() == [0, 2]
    i1, i2 = associate(np.array([1.0]), np.array([0.99, 1.01]), 0.02)  # a tie goes to the earlier stamp
    assert i2.tolist() == [0]
    i1, i2 = associate(np.array([1.0]), np.array([0.99, 1.005]), 0.02)
    assert i2.tolist() == [1]


def test_associate_matches_evo():
    sync = pytest.importorskip("evo.core.sync")
    rng = np.random.default_rng(5)
    s2 = np.sort(rng.uniform(0, 10, 400))
    s1 = np.sort(np.concatenate([s2[::3] + rng.normal(0, 0.006, len(s2[::3])), rng.uniform(-1, 11, 30)]))
    want = sync.matching_time_indices(s1, s2, 0.01)
    got = associate(s1, s2, 0.01)
    assert got[0].tolist() == want[0] and got[1].tolist() == want[1]


def test_associate_trajectories_starts_from_the_same_side_as_evo():
    """Equal lengths: evo starts from the estimate; the pairs differ if one starts from the reference."""
    sync = pytest.importorskip("evo.core.sync")
    from evo.core.trajectory import PoseTrajectory3D

    from papl_mapper.eval import associate_trajectories

    ref = Trajectory(np.array([1.000, 1.008, 2.0]), np.repeat(np.eye(4)[None], 3, axis=0))
    est = Trajectory(np.array([0.995, 1.004, 2.001]), np.repeat(np.eye(4)[None], 3, axis=0))
    i_ref, i_est = associate_trajectories(ref, est, 0.01)

    def evo_traj(t):
        return PoseTrajectory3D(poses_se3=list(t.T_wc), timestamps=t.timestamps)

    r, e = sync.associate_trajectories(evo_traj(ref), evo_traj(est), max_diff=0.01)
    np.testing.assert_array_equal(ref.timestamps[i_ref], r.timestamps)
    np.testing.assert_array_equal(est.timestamps[i_est], e.timestamps)
    assert i_ref.tolist() == [0, 0, 2] and i_est.tolist() == [0, 1, 2]


def test_umeyama_recovers_known_sim3_exactly_and_with_noise():
    x = walk().positions
    S = random_sim3()
    y = x @ S[:3, :3].T + S[:3, 3]
    sim = umeyama(x, y)
    np.testing.assert_allclose(sim.matrix, S, atol=EXACT)
    assert sim.scale == pytest.approx(2.5, abs=EXACT)
    noisy = y + np.random.default_rng(2).normal(0, 0.01 * np.std(y), y.shape)
    assert umeyama(x, noisy).scale == pytest.approx(2.5, rel=NOISY_SCALE_REL)
    se3 = umeyama(x, x @ S[:3, :3].T / 2.5 + S[:3, 3], with_scale=False)
    assert se3.scale == 1.0
    np.testing.assert_allclose(se3.R, S[:3, :3] / 2.5, atol=EXACT)


def test_umeyama_collinear_positions_use_orientations():
    t = walk()
    T = t.T_wc.copy()
    T[:, :3, 3] = np.linspace(0, 1, len(T))[:, None] * [4.0, 1.0, 0.5]  # a straight line
    S = random_sim3(seed=4, scale=0.7)
    y = transform_traj(Trajectory(t.timestamps, T), S)
    sim = umeyama(T[:, :3, 3], y.positions, R_x=T[:, :3, :3], R_y=y.T_wc[:, :3, :3])
    assert "orientations" in sim.method
    np.testing.assert_allclose(sim.matrix, S, atol=EXACT)
    with pytest.raises(GeometryError, match="collinear"):
        umeyama(T[:, :3, 3], y.positions)


def test_umeyama_degenerate_inputs():
    with pytest.raises(InputError, match="at least 3"):
        umeyama(np.zeros((2, 3)), np.ones((2, 3)))
    with pytest.raises(GeometryError, match="coincide"):
        umeyama(np.ones((5, 3)), np.random.default_rng(0).normal(size=(5, 3)))


# ---- ATE and RPE ---------------------------------------------------------------------------------


def test_ate_zero_and_scale_recovered_under_a_known_sim3(tmp_path):
    gt = walk()
    segs, lab = room_segments()
    write_gt(tmp_path / "scene", gt, segs, lab)
    S = random_sim3(scale=0.4)
    est = sim3_map(map_from(gt, segs, lab), np.linalg.inv(S))
    res = evaluate(tmp_path / "scene", est)
    assert res.n_matched_poses == len(gt)
    assert res.ate_rmse < EXACT and res.rpe_trans < EXACT and res.rpe_rot_deg < 1e-6
    assert res.scale == pytest.approx(0.4, abs=EXACT)
    np.testing.assert_allclose(res.sim3, S, atol=EXACT)
    assert all(v == pytest.approx(1.0, abs=1e-9) for v in res.line_recall.values())
    assert all(v == pytest.approx(1.0, abs=1e-9) for v in res.line_precision.values())
    np.testing.assert_allclose(res.axis_errors_deg, 0, atol=1e-6)
    assert res.vertical_error_deg == pytest.approx(0, abs=1e-6)
    assert res.gt_path_length == pytest.approx(gt.path_length())


def test_known_offsets_give_known_ate(tmp_path):
    est = walk()
    offsets = orthogonal_offsets(est.positions, 0.05)
    S = random_sim3(seed=7, scale=3.0)
    gt = transform_traj(est, S)
    gt.T_wc[:, :3, 3] += offsets
    segs, lab = room_segments()
    write_gt(tmp_path / "scene", gt, segs, lab)
    res = evaluate(tmp_path / "scene", map_from(est, segs, lab))
    e = np.linalg.norm(offsets, axis=1)
    assert res.ate_rmse == pytest.approx(math.sqrt(np.mean(e**2)), abs=EXACT)
    assert res.ate_max == pytest.approx(e.max(), abs=EXACT)
    np.testing.assert_allclose(res.ate_per_pose[1], e, atol=EXACT)
    np.testing.assert_allclose(res.ate_per_pose[0], gt.timestamps, atol=0)
    assert res.scale == pytest.approx(3.0, abs=EXACT)
    assert res.ate_rmse_rel_path == pytest.approx(res.ate_rmse / gt.path_length())


def test_rpe_of_one_rotated_pose_is_hand_computed():
    gt = walk(n=20)
    est = Trajectory(gt.timestamps, gt.T_wc.copy())
    k, theta = 7, math.radians(3.0)
    Rth = Rotation.from_rotvec([0, 0, theta]).as_matrix()
    est.T_wc[k, :3, :3] = est.T_wc[k, :3, :3] @ Rth
    t_err, r_err = rpe(gt.T_wc, est.T_wc)
    assert len(t_err) == 19
    expect_r = np.zeros(19)
    expect_r[[k - 1, k]] = 3.0
    np.testing.assert_allclose(r_err, expect_r, atol=1e-9)
    A = np.linalg.inv(gt.T_wc[k]) @ gt.T_wc[k + 1]  # pair (k, k+1): E = A^-1 [Rth 0]^-1 A
    expect_t = np.zeros(19)
    expect_t[k] = np.linalg.norm((Rth.T - np.eye(3)) @ A[:3, 3])
    np.testing.assert_allclose(t_err, expect_t, atol=1e-12)


def test_ate_rpe_scale_match_evo(tmp_path):
    """evo_ape tum gt est -as (and evo_rpe on the aligned pair) on the very same files."""
    pytest.importorskip("evo")
    from evo.core import metrics, sync
    from evo.tools import file_interface

    rng = np.random.default_rng(11)
    gt = walk(n=300)
    keep = np.sort(rng.choice(300, 120, replace=False))  # keyframes only, with timestamp jitter
    est = transform_traj(gt.subset(keep), np.linalg.inv(random_sim3(seed=8, scale=1.7)))
    est.T_wc[:, :3, 3] += rng.normal(0, 0.02, (len(keep), 3))
    noise = Rotation.from_rotvec(rng.normal(0, 0.01, (len(keep), 3))).as_matrix()
    est.T_wc[:, :3, :3] = est.T_wc[:, :3, :3] @ noise
    est.timestamps = est.timestamps + rng.uniform(-0.004, 0.004, len(keep))
    segs, lab = room_segments()
    write_gt(tmp_path / "scene", gt, segs, lab)
    run = tmp_path / "run"
    run.mkdir()
    write_tum(run / "trajectory.tum", est)
    map_from(est, segs, lab).save(run / "map.papl")

    from papl_mapper.cli import main

    assert main(["eval", "--gt", str(tmp_path / "scene"), str(run), "--json", str(tmp_path / "r.json")]) == 0
    ours = json.loads((tmp_path / "r.json").read_text())

    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "scene" / "gt" / "trajectory.tum"))
    e = file_interface.read_tum_trajectory_file(str(run / "trajectory.tum"))
    ref, e = sync.associate_trajectories(ref, e, max_diff=0.01)
    r, t, s = e.align(ref, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, e))
    assert ours["n_matched_poses"] == ref.num_poses == 120
    assert ours["ate_rmse"] == pytest.approx(
        ape.get_statistic(metrics.StatisticsType.rmse), abs=EVO_AGREEMENT
    )
    assert ours["ate_max"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.max), abs=EVO_AGREEMENT)
    assert ours["scale"] == pytest.approx(s, abs=EVO_AGREEMENT)
    for relation, key in (
        (metrics.PoseRelation.translation_part, "rpe_trans"),
        (metrics.PoseRelation.rotation_angle_deg, "rpe_rot_deg"),
    ):
        rp = metrics.RPE(relation, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
        rp.process_data((ref, e))
        assert ours[key] == pytest.approx(rp.get_statistic(metrics.StatisticsType.rmse), abs=EVO_AGREEMENT)


def test_ate_matches_the_evo_ape_command(tmp_path):
    """The literal `evo_ape tum gt est -as` on the same files: RMSE, per-pose errors and the Sim(3)."""
    import subprocess
    import sys
    import zipfile

    evo_ape = Path(sys.executable).parent / "evo_ape"
    if not evo_ape.exists():
        pytest.skip("evo_ape is not installed in this environment (dev extra)")
    rng = np.random.default_rng(12)
    gt = walk(n=200)
    est = transform_traj(gt.subset(np.arange(0, 200, 3)), np.linalg.inv(random_sim3(seed=13, scale=0.3)))
    est.T_wc[:, :3, 3] += rng.normal(0, 0.05, (len(est), 3))
    est.timestamps = est.timestamps + rng.uniform(-0.005, 0.005, len(est))
    write_gt(tmp_path / "scene", gt, *room_segments())
    write_tum(tmp_path / "est.tum", est)
    home = tmp_path / "home"  # evo writes its settings file under $HOME
    home.mkdir()
    subprocess.run(
        [str(evo_ape), "tum", str(tmp_path / "scene" / "gt" / "trajectory.tum"), str(tmp_path / "est.tum")]
        + ["-as", "--no_warnings", "--save_results", str(tmp_path / "evo.zip")],
        check=True,
        capture_output=True,
        env={"HOME": str(home), "PATH": str(evo_ape.parent), "MPLBACKEND": "Agg"},
    )
    with zipfile.ZipFile(tmp_path / "evo.zip") as zf:
        stats = json.loads(zf.read("stats.json"))
        errors = np.load(zf.open("error_array.npy"))
        sim3 = np.load(zf.open("alignment_transformation_sim3.npy"))
    m = map_from(est, *room_segments())
    res = evaluate(tmp_path / "scene", m, tmp_path / "est.tum")
    assert res.ate_rmse == pytest.approx(stats["rmse"], abs=EVO_AGREEMENT)
    np.testing.assert_allclose(res.ate_per_pose[1], errors, atol=EVO_AGREEMENT)
    np.testing.assert_allclose(res.sim3, sim3, atol=EVO_AGREEMENT)


# ---- lines ---------------------------------------------------------------------------------------

SQUARE = np.array(
    [[[0, 0, 0], [1, 0, 0]], [[1, 0, 0], [1, 1, 0]], [[1, 1, 0], [0, 1, 0]], [[0, 1, 0], [0, 0, 0]]], float
)


def test_square_half_covered():
    taus = np.array([0.01, 0.02])
    recall, precision, gt_len, est_len = line_metrics(SQUARE, SQUARE[:2], taus, 0.001)
    np.testing.assert_allclose(recall, 0.5 + taus / 2, atol=1e-3)  # the other sides: tau at each corner
    np.testing.assert_allclose(precision, 1.0)
    assert gt_len == pytest.approx(4.0) and est_len == pytest.approx(2.0)
    far = np.array([[[5, 5, 5], [7, 5, 5]]], float)  # 2 units of estimate nowhere near the square
    recall, precision, _, _ = line_metrics(SQUARE, np.concatenate([SQUARE[:2], far]), taus, 0.001)
    np.testing.assert_allclose(recall, 0.5 + taus / 2, atol=1e-3)
    np.testing.assert_allclose(precision, 0.5, atol=1e-12)


def test_partial_and_offset_segments():
    spacing = 1e-3
    half = np.array([[[0, 0, 0], [0.5, 0, 0]]])  # covers [0, 0.5 + tau] of one side within tau
    recall, precision, _, _ = line_metrics(SQUARE, half, np.array([0.01, 0.04]), spacing)
    np.testing.assert_allclose(recall, [(0.5 + 0.01 + 0.01) / 4, (0.5 + 0.04 + 0.04) / 4], atol=spacing)
    np.testing.assert_allclose(precision, 1.0)
    shifted = SQUARE + [0, 0, 0.05]  # the whole square lifted by 0.05: nothing within 0.02, all within 0.1
    recall, precision, _, _ = line_metrics(SQUARE, shifted, np.array([0.02, 0.1]), spacing)
    np.testing.assert_allclose(recall, [0, 1])
    np.testing.assert_allclose(precision, [0, 1])
    recall, precision, _, _ = line_metrics(SQUARE, np.zeros((0, 2, 3)), np.array([0.1]), spacing)
    assert recall.tolist() == [0.0] and np.isnan(precision).all()


def test_nearest_segment_distance_is_exact_on_dense_clutter():
    """Against brute force, with clusters dense enough that the KD-tree candidate search must widen."""
    rng = np.random.default_rng(0)
    mids = np.concatenate([rng.uniform(0, 10, (500, 3)), rng.normal(5, 0.05, (300, 3))])
    d = rng.normal(size=(800, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    segs = np.stack([mids - d * 0.4, mids + d * 0.4], axis=1)
    q = np.concatenate([rng.uniform(0, 10, (2000, 3)), rng.normal(5, 0.2, (500, 3))])
    brute = point_segment_distance(q[:, None], segs[None, :, 0], segs[None, :, 1]).min(axis=1)
    for max_dist, spacing in ((0.3, None), (1.0, 0.05), (0.2, 0.5)):
        got = nearest_segment_distance(q, segs, max_dist, spacing)
        want = np.where(brute <= max_dist, brute, np.inf)
        np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
        np.testing.assert_allclose(got[np.isfinite(got)], want[np.isfinite(want)], atol=1e-12)
        levels = np.array([0.25, 0.5, 1.0]) * max_dist  # levels mode: every "<= level" answer exact
        got = nearest_segment_distance(q, segs, max_dist, spacing, levels=levels)
        for tau in levels:
            np.testing.assert_array_equal(got <= tau, brute <= tau)


def test_nearest_segment_distance_on_crowded_duplicates():
    """Hundreds of near-copies of one segment: the search widens to its last resort and stays exact."""
    rng = np.random.default_rng(1)
    base = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    segs = base + rng.normal(0, 1e-3, (600, 2, 3))
    q = np.array([0.5, 0, 0]) + rng.normal(0, 0.05, (40, 3))
    brute = point_segment_distance(q[:, None], segs[None, :, 0], segs[None, :, 1]).min(axis=1)
    got = nearest_segment_distance(q, segs, 0.2, 0.02)
    np.testing.assert_allclose(got, np.where(brute <= 0.2, brute, np.inf), atol=1e-12)


def test_point_segment_distance_hand_values():
    a, b = np.array([0.0, 0, 0]), np.array([2.0, 0, 0])
    p = np.array([[1, 1, 0], [-3, 4, 0], [5, 0, 4], [1, 0, 0]], float)
    np.testing.assert_allclose(point_segment_distance(p, a, b), [1, 5, 5, 0])
    np.testing.assert_allclose(point_segment_distance(p[:1], a, a), [math.sqrt(2)])  # zero length: a point


def test_read_segments(tmp_path):
    p = tmp_path / "s.txt"
    p.write_text("# header\n0 0 0 1 0 0 2\n\n1 1 1 2 2 2 -1  # trailing comment\n0 0 0 1 1 1\n")
    s = read_segments(p)
    assert s.endpoints.shape == (3, 2, 3) and s.axis.tolist() == [2, -1, -1]
    p.write_text("0 0 0 1 0 0 2\n0 0 0 1 0\n")
    with pytest.raises(InputError, match="line 2 has 5 values"):
        read_segments(p)
    p.write_text("0 0 0 1 0 x 2\n")
    with pytest.raises(InputError, match="line 1 holds a non-number"):
        read_segments(p)


# ---- axes ----------------------------------------------------------------------------------------


ATLANTA = np.array([[0, 0, 1.0], [1, 0, 0], [0, 1, 0], [math.cos(math.pi / 6), math.sin(math.pi / 6), 0]])


def test_axis_matching_permuted_and_sign_flipped():
    R = Rotation.from_rotvec([0, 0, math.radians(2.0)]).as_matrix()  # 2 degrees of yaw
    perm = [2, 0, 3, 1]
    est = (ATLANTA @ R.T)[perm] * np.array([[-1], [1], [-1], [1]])
    m = match_axes(ATLANTA, est)
    assert m.pairs == [(0, 1), (1, 3), (2, 0), (3, 2)]
    np.testing.assert_allclose(m.errors_deg, [0, 2, 2, 2], atol=1e-9)
    assert m.unmatched_gt == [] and m.unmatched_est == []
    m = match_axes(ATLANTA, est[:3])  # one estimated axis short
    assert m.unmatched_gt == [1] and len(m.pairs) == 3
    extra = np.concatenate([est, [[0, math.sqrt(0.5), math.sqrt(0.5)]]])
    m = match_axes(ATLANTA, extra)
    assert m.unmatched_est == [4]
    np.testing.assert_allclose(m.errors_deg, [0, 2, 2, 2], atol=1e-9)


def test_axes_through_evaluate_use_the_sim3_rotation(tmp_path):
    gt = walk()
    segs, lab = room_segments()
    write_gt(tmp_path / "scene", gt, segs, lab, ATLANTA)
    S_inv = np.linalg.inv(random_sim3(seed=9, scale=2.0))
    est = sim3_map(map_from(gt, segs, lab, ATLANTA), S_inv)
    tilt = Rotation.from_rotvec([math.radians(1.0), 0, 0]).as_matrix()  # the vertical tilted by 1 degree
    R_inv = S_inv[:3, :3] / 0.5
    est.axes = Axes((ATLANTA @ tilt.T @ R_inv.T)[[3, 1, 0, 2]], vertical_index=2)
    res = evaluate(tmp_path / "scene", est)
    assert [(p["gt"], p["est"]) for p in res.axis_pairs] == [(0, 2), (1, 1), (2, 3), (3, 0)]
    assert res.vertical_error_deg == pytest.approx(1.0, abs=1e-6)
    assert max(res.axis_errors_deg) <= 1.0 + 1e-6


def test_read_axes_errors(tmp_path):
    p = tmp_path / "axes.json"
    p.write_text(json.dumps({"directions": [[0, 0, 2], [1, 0, 0]], "vertical_index": 0}))
    a = read_axes(p)
    np.testing.assert_allclose(a.directions[0], [0, 0, 1])
    assert a.names == ["axis 0", "axis 1"]
    for bad, match in (
        ("{", "not valid JSON"),
        (json.dumps({"names": []}), "expected an object with 'directions'"),
        (json.dumps({"directions": [[0, 0, 0]]}), "zero, NaN"),
        (json.dumps({"directions": [[0, 0, 1]], "vertical_index": 3}), "out of range"),
    ):
        p.write_text(bad)
        with pytest.raises(InputError, match=match):
            read_axes(p)


# ---- evaluate: inputs, result, CLI ---------------------------------------------------------------


def test_result_dict_is_json_and_table_is_readable(tmp_path):
    gt = walk()
    segs, lab = room_segments()
    write_gt(tmp_path / "scene", gt, segs, lab)
    res = evaluate(tmp_path / "scene" / "gt", map_from(gt, segs, lab))  # the gt/ folder itself works too
    d = json.loads(json.dumps(res.to_dict(), allow_nan=False))
    assert d["n_matched_poses"] == 60 and len(d["ate_per_pose"]["errors"]) == 60
    assert set(d["line_recall"]) == {"0.5%", "1%", "2%"}
    diag = math.sqrt(10**2 + 6**2 + 3**2)
    assert d["line_thresholds"]["1%"] == pytest.approx(0.01 * diag)
    assert np.asarray(d["sim3"]).shape == (4, 4)
    text = res.table()
    for s in ("ATE RMSE", "RPE rotation", "lines @ 1%", "recall", "precision", "vertical"):
        assert s in text


def test_keyframes_only_map_and_missing_optional_gt_files(tmp_path):
    gt = walk()
    (tmp_path / "scene").mkdir()
    write_tum(tmp_path / "scene" / "trajectory.tum", gt)  # flat layout, trajectory only
    res = evaluate(tmp_path / "scene", map_from(gt.subset(np.arange(0, 60, 5)), *room_segments()))
    assert res.n_matched_poses == 12 and res.ate_rmse < EXACT
    assert res.line_recall == {} and res.axis_errors_deg == []
    assert any("no line metrics" in n for n in res.notes) and any("no axis metrics" in n for n in res.notes)


def test_gt_map_stands_in_for_segments_and_axes(tmp_path):
    gt = walk()
    segs, lab = room_segments()
    (tmp_path / "scene" / "gt").mkdir(parents=True)
    write_tum(tmp_path / "scene" / "gt" / "trajectory.tum", gt)
    map_from(gt, segs, lab).save(tmp_path / "scene" / "gt" / "map.papl")
    res = evaluate(tmp_path / "scene", map_from(gt, segs, lab))
    assert res.n_gt_segments == 12 and res.line_recall["1%"] == pytest.approx(1.0)
    assert len(res.axis_errors_deg) == 3


def test_bad_inputs_raise_input_errors(tmp_path):
    gt = walk()
    segs, lab = room_segments()
    m = map_from(gt, segs, lab)
    with pytest.raises(InputError, match="no such ground-truth folder"):
        evaluate(tmp_path / "nope", m)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="trajectory.tum: ground-truth trajectory missing"):
        evaluate(tmp_path / "empty", m)
    write_gt(tmp_path / "scene", gt, segs, lab)
    late = Trajectory(gt.timestamps + 100.0, gt.T_wc)
    with pytest.raises(InputError, match="no timestamp lies within 0.01 s"):
        evaluate(tmp_path / "scene", map_from(late, segs, lab))
    with pytest.raises(InputError, match="only 2 poses match"):
        evaluate(tmp_path / "scene", map_from(gt.subset(np.array([3, 9])), segs, lab))
    empty = Map(Camera(640, 480, 500.0, 500.0, 319.5, 239.5))
    with pytest.raises(InputError, match="no keyframes"):
        evaluate(tmp_path / "scene", empty)
    with pytest.raises(Exception, match="max_time_diff"):
        evaluate(tmp_path / "scene", m, config=EvalConfig(max_time_diff=-1))


def test_cli_bad_inputs_are_one_line(tmp_path, capsys):
    from papl_mapper.cli import main

    gt = walk()
    segs, lab = room_segments()
    write_gt(tmp_path / "scene", gt, segs, lab)
    m = map_from(gt, segs, lab)
    m.save(tmp_path / "m.papl")
    bad = tmp_path / "scene" / "gt" / "trajectory.tum"
    good = bad.read_text()
    bad.write_text(good + "1e9 1 2 3 0 0 0\n")
    cases = [
        (["eval", "--gt", str(tmp_path / "scene"), str(tmp_path / "m.papl")], "has 7 values"),
        (
            ["eval", "--gt", str(tmp_path / "missing"), str(tmp_path / "m.papl")],
            "no such ground-truth folder",
        ),
        (["eval", "--gt", str(tmp_path / "scene"), str(tmp_path / "none.papl")], "no such run folder"),
        (
            ["eval", "--gt", str(tmp_path / "scene"), str(tmp_path / "m.papl"), "--set", "rpe_delta=0"],
            "rpe_delta",
        ),
    ]
    for argv, msg in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert msg in err and "papl-map eval: error:" in err and len(err.splitlines()) == 1
    bad.write_text(good)
    out_json = tmp_path / "no" / "x.json"
    assert (
        main(["eval", "--gt", str(tmp_path / "scene"), str(tmp_path / "m.papl"), "--json", str(out_json)])
        == 2
    )
    assert "x.json: the folder" in capsys.readouterr().err
    assert main(["eval", "--gt", str(tmp_path / "scene"), str(tmp_path / "m.papl")]) == 0
    out = capsys.readouterr().out
    assert "ATE RMSE" in out and "lines @ 2%" in out


def test_parallel_offsets_give_known_recall_with_random_noise():
    """Each estimate is its GT segment shifted sideways at random: recall(tau) = share with offset <= tau."""
    rng = np.random.default_rng(21)
    n = 200
    mids = np.stack([np.arange(n) * 3.0, rng.uniform(0, 5, n), rng.uniform(0, 5, n)], axis=1)  # well apart
    d = np.array([0.0, 0.6, 0.8])
    L = rng.uniform(0.5, 2.0, n)
    gt = np.stack([mids - 0.5 * L[:, None] * d, mids + 0.5 * L[:, None] * d], axis=1)
    offset = rng.uniform(0, 0.2, n)
    est = gt + (offset[:, None] * [1.0, 0, 0])[:, None, :]  # perpendicular to d
    taus = np.array([0.05, 0.1, 0.15])
    recall, precision, _, _ = line_metrics(gt, est, taus, 0.01)
    want = np.array([L[offset <= t].sum() / L.sum() for t in taus])
    np.testing.assert_allclose(recall, want, atol=1e-12)
    np.testing.assert_allclose(precision, want, atol=1e-12)


def test_noisy_trajectory_ate_is_the_noise_level(tmp_path):
    gt = walk(n=400)
    segs, lab = room_segments()
    write_gt(tmp_path / "scene", gt, segs, lab)
    sigma = 0.02
    est = transform_traj(gt, np.linalg.inv(random_sim3(seed=5, scale=0.8)))
    est.T_wc[:, :3, 3] += np.random.default_rng(6).normal(0, sigma / 0.8, (len(gt), 3))  # sigma in GT units
    res = evaluate(tmp_path / "scene", map_from(est, segs, lab))
    assert res.scale == pytest.approx(0.8, rel=NOISY_SCALE_REL)
    assert res.ate_rmse == pytest.approx(sigma * math.sqrt(3), rel=0.1)  # 3D noise: RMSE = sqrt(3) sigma
    assert res.ate_rmse < res.ate_max


def test_recall_per_ground_truth_axis(tmp_path):
    gt = walk()
    segs, lab = room_segments()
    write_gt(tmp_path / "scene", gt, segs, lab)
    only_vertical = map_from(gt, segs[lab == 0], lab[lab == 0])  # the 4 vertical edges, 3 of 32 units
    res = evaluate(tmp_path / "scene", only_vertical)
    by_axis = res.line_recall_by_axis
    assert set(by_axis) == {"vertical", "horizontal 1", "horizontal 2"}
    tau = res.line_thresholds["1%"]
    assert by_axis["vertical"]["1%"] == pytest.approx(1.0)
    # horizontal edges are covered only within tau of the corners: 2 tau per edge
    assert by_axis["horizontal 1"]["1%"] == pytest.approx(2 * tau / 10, abs=1e-3)
    assert by_axis["horizontal 2"]["1%"] == pytest.approx(2 * tau / 6, abs=1e-3)
    assert res.line_recall["1%"] == pytest.approx((12 + 8 * 2 * tau) / 76, abs=1e-3)
    assert res.line_precision["1%"] == pytest.approx(1.0)
    assert "recall, vertical lines" in res.table()


SAMPLE_TINY = Path(__file__).resolve().parents[1] / "samples" / "tiny"


def test_bundled_sample_ground_truth_reads_and_scores_itself(tmp_path):
    """The synth's real ground-truth files: its own map, moved by a Sim(3), scores perfectly."""
    if not (SAMPLE_TINY / "gt" / "map.papl").is_file():
        pytest.skip(f"bundled sample not found at {SAMPLE_TINY}")
    m = Map.load(SAMPLE_TINY / "gt" / "map.papl")
    S = random_sim3(seed=17, scale=4.0)
    res = evaluate(SAMPLE_TINY, sim3_map(m, np.linalg.inv(S)))
    assert res.n_matched_poses == len(m.keyframes) >= 3
    assert res.ate_rmse < 1e-6  # the TUM file holds 9 decimals
    assert res.scale == pytest.approx(4.0, rel=1e-6)
    assert res.n_gt_segments > 0 and all(v == pytest.approx(1.0) for v in res.line_recall.values())
    assert all(v == pytest.approx(1.0) for v in res.line_precision.values())
    assert len(res.axis_errors_deg) == len(m.axes) and max(res.axis_errors_deg) < 1e-4
