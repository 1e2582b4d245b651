"""Map assembly and the upright rotation: ids and observations carried over, geometry preserved."""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper.errors import GeometryError
from papl_mapper.map import Axes, Camera, LineState
from papl_mapper.mapping.assemble import assemble_map, rotation_to_z, transform_map, vertical_in_world
from papl_mapper.mapping.lines import LineEstimates
from papl_mapper.tracks import Tracks

CAM = Camera(640, 480, 500.0, 500.0, 319.5, 239.5)


def _rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _tracks(n=4):
    rng = np.random.default_rng(0)
    pf = np.repeat(np.arange(n), 5)
    pt = np.tile(np.arange(5), n)
    lf = np.repeat(np.arange(n), 2)
    lt = np.tile([7, 9], n)
    vp = np.full((n, 3, 3), np.nan)
    vp[:, 0] = [0.0, -1.0, 0.0]  # camera up is -y
    return Tracks(
        CAM,
        np.arange(n) * 3,
        np.arange(n) / 10.0,
        np.ones(n, bool),
        pf,
        pt,
        rng.uniform(0, 400, (len(pf), 2)),
        lf,
        lt,
        rng.uniform(0, 400, (len(lf), 4)),
        np.tile([0, -1], n),
        vp,
        np.zeros(n, np.int64),
    )


def test_rotation_to_z():
    rng = np.random.default_rng(1)
    for v in [*rng.normal(size=(20, 3)), np.array([0, 0, 1.0]), np.array([0, 0, -1.0])]:
        R = rotation_to_z(v)
        assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(R @ (v / np.linalg.norm(v)), [0, 0, 1])


def test_assemble_carries_ids_and_observations():
    tr = _tracks()
    T = {f: np.eye(4) for f in (0, 1, 3)}  # frame 2 lost
    for f in T:
        T[f][0, 3] = f
    pts = {i: np.array([i, 1.0, 5.0]) for i in range(4)}  # point 4 not triangulated
    lines = LineEstimates(
        np.array([7, 9]),
        np.array([[[0, 0, 5.0], [0, 1, 5]], [[1, 0, 5.0], [2, 0, 5]]]),
        np.array([True, False]),
        np.zeros(2),
    )
    axes = Axes(np.eye(3)[[1, 0]], vertical_index=0)
    m = assemble_map(tr, T, pts, lines, axes, np.array([[1.0, 0.0], [0.0, 0.0]]))
    m.validate()
    assert m.keyframes.ids.tolist() == [0, 1, 3] and m.keyframes.frame_index.tolist() == [0, 3, 9]
    assert len(m.points.obs_ids) == 4 * 3 and set(m.points.obs_ids[:, 1]) == {0, 1, 3}
    assert m.lines.state.tolist() == [LineState.ANCHORED, LineState.ORTHONORMAL]
    assert m.lines.ref_keyframe_id.tolist() == [0, -1]
    assert np.isclose(m.lines.inverse_depth[0], 1 / np.linalg.norm([0, 0.5, 5]))
    assert len(m.lines.obs_ids) == 6


def test_vertical_and_transform_keep_projections():
    tr = _tracks()
    R_wc = _rot([1, 2, 0.5], 0.7)
    T = {}
    for f in range(4):
        T[f] = np.eye(4)
        T[f][:3, :3] = R_wc
        T[f][:3, 3] = [f, 0.5, 0]
    up = vertical_in_world(tr, T)
    assert np.allclose(up, R_wc @ [0, -1, 0])
    pts = {0: np.array([1.0, 2.0, 3.0])}
    lines = LineEstimates.empty()
    m = assemble_map(tr, T, pts, lines)
    before = np.linalg.inv(m.keyframes.T_wc[1]) @ np.r_[m.points.xyz[0], 1]
    R = rotation_to_z(up)
    transform_map(m, R, np.array([1.0, 2, 3]), 2.0)
    after = np.linalg.inv(m.keyframes.T_wc[1]) @ np.r_[m.points.xyz[0], 1]
    assert np.allclose(after[:3], 2 * before[:3])  # same ray, depth scaled
    assert np.allclose(m.keyframes.T_wc[0][:3, :3] @ [0, -1, 0], [0, 0, 1])
    with pytest.raises(GeometryError):
        transform_map(m, np.diag([1.0, 1, -1]))


def test_refine_direction_recovers_the_common_direction():
    """Planes through random centres containing one direction (+ noise, + outliers) give it back."""
    from papl_mapper.mapping.assemble import refine_direction

    rng = np.random.default_rng(3)
    d = np.array([0.3, -0.2, 0.93])
    d /= np.linalg.norm(d)
    other = rng.normal(size=(300, 3))
    normals = np.cross(d, other)  # every plane contains d
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals += rng.normal(0, 0.003, normals.shape)  # about 0.2 degrees of noise
    normals[:60] = rng.normal(size=(60, 3))  # 20% planes of other segments
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    init = d + np.array([0.04, 0.0, -0.02])  # about 2.5 degrees off
    est = refine_direction(normals, np.ones(300), init / np.linalg.norm(init))
    assert np.degrees(np.arccos(abs(est @ d))) < 0.1
    assert est @ init > 0  # the sign of the initial guess is kept


def test_drop_stray_lines():
    from papl_mapper.mapping.assemble import drop_stray_lines

    tr = _tracks()
    T = {f: np.eye(4) for f in range(4)}
    ends = np.array([[[0, 0, 5.0], [0, 1, 5]], [[0, 0, 5.0], [0, 40, 5]]])  # the second runs away
    lines = LineEstimates(np.array([7, 9]), ends, np.array([True, True]), np.zeros(2))
    rng = np.random.default_rng(0)
    pts = {i: x for i, x in enumerate(rng.uniform([-2, -2, 3], [2, 2, 7], (50, 3)))}
    m = assemble_map(tr, T, pts, lines)
    assert drop_stray_lines(m) == 1
    assert m.lines.ids.tolist() == [7] and set(m.lines.obs_ids[:, 0]) == {7}
    m.validate()


def test_set_line_states_keeps_anchor_data_consistent():
    from papl_mapper.mapping.assemble import set_line_states

    tr = _tracks()
    T = {f: np.eye(4) for f in range(4)}
    lines = LineEstimates(
        np.array([7, 9]),
        np.array([[[0, 0, 5.0], [0, 1, 5]], [[1, 0, 4.0], [2, 0, 4]]]),
        np.array([True, False]),
        np.zeros(2),
    )
    axes = Axes(np.eye(3)[[1, 0]], vertical_index=0)
    m = assemble_map(tr, T, {}, lines, axes, np.array([[1.0, 0.0], [0.0, 0.0]]))
    m.lines.axis_weights = np.array([[0.0, 0.0], [0.0, 1.0]])  # the association swapped after an update
    set_line_states(m)
    m.validate()
    assert m.lines.state.tolist() == [LineState.ORTHONORMAL, LineState.ANCHORED]
    assert m.lines.ref_keyframe_id.tolist() == [-1, 0] and np.isclose(m.lines.inverse_depth[1], 1 / 4.0)
