"""Principal-axis management on synthetic direction sets with known axes."""

from __future__ import annotations

import numpy as np
import pytest

from papl_mapper.axes import (
    AxesConfig,
    AxisState,
    associate,
    create_axes,
    mean_angles_deg,
    pack_observations,
    remap_weights,
    update_axes,
)
from papl_mapper.errors import GeometryError
from papl_mapper.geometry.lines import line_angle_deg

MAX_AXIS_ERROR_DEG = 0.5  # mean-shift mode vs the true axis, 1-degree direction noise
MAX_AXIS_ERROR_NOISELESS_DEG = 1e-6


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _h(deg):
    a = np.radians(deg)
    return np.array([np.cos(a), np.sin(a), 0.0])


def _perturb(d, sigma_deg, rng):
    """Directions scattered about d by a normal angle (per component, small-angle) with random signs."""
    n = len(d)
    noise = rng.normal(scale=np.radians(sigma_deg), size=(n, 3))
    noise -= np.sum(noise * d, axis=1, keepdims=True) * d
    out = _unit(d + noise)
    return out * rng.choice([-1.0, 1.0], size=(n, 1))


def _lines(axes, per_axis, sigma_deg, n_outliers, rng):
    dirs = [_perturb(np.repeat(a[None], per_axis, 0), sigma_deg, rng) for a in axes]
    out = _unit(rng.normal(size=(n_outliers, 3)))
    return np.concatenate(dirs + [out]), np.repeat(np.arange(len(axes)), per_axis)


TRUE_AXES = np.array([[0.0, 0.0, 1.0], _h(10.0), _h(70.0)])  # Atlanta: horizontals 60 deg apart


@pytest.mark.parametrize("sigma_deg,tol", [(0.0, MAX_AXIS_ERROR_NOISELESS_DEG), (1.0, MAX_AXIS_ERROR_DEG)])
def test_mean_shift_finds_atlanta_axes_among_outliers(sigma_deg, tol):
    rng = np.random.default_rng(1)
    dirs, _ = _lines(TRUE_AXES, 60, sigma_deg, 40, rng)
    res = create_axes(dirs, np.zeros((0, 3)), n_nonstructural=len(dirs), config=AxesConfig(max_new_axes=5))
    assert len(res.new_axes) == 3, res.reason
    err = line_angle_deg(TRUE_AXES[:, None], res.new_axes[None]).min(axis=1)
    assert err.max() < tol, err


def test_near_duplicate_axes_become_one():
    rng = np.random.default_rng(2)
    near = np.array([_h(10.0), _h(12.0)])  # two "axes" 2 degrees apart: one physical direction
    dirs, _ = _lines(near, 50, 0.5, 10, rng)
    res = create_axes(dirs, np.zeros((0, 3)), len(dirs), AxesConfig(max_new_axes=5))
    assert len(res.new_axes) == 1
    assert line_angle_deg(_h(11.0), res.new_axes)[0] < 1.5


def test_creation_discards_existing_and_gates():
    rng = np.random.default_rng(3)
    dirs, _ = _lines(TRUE_AXES, 40, 0.5, 0, rng)
    cfg = AxesConfig(max_new_axes=5)
    # the vertical and one horizontal exist (off by 5 deg < 10): only the 70-degree axis is new
    existing = np.array([[0.0, 0.0, 1.0], _unit(_h(15.0))])
    res = create_axes(dirs, existing, len(dirs), cfg)
    assert len(res.new_axes) == 1
    assert line_angle_deg(_h(70.0), res.new_axes)[0] < 0.5
    assert any("existing axis" in c.reason for c in res.candidates)
    # paper's ratio test: too few non-structural lines -> nothing created
    assert len(create_axes(dirs, existing, 10, cfg, n_structural=100).new_axes) == 0
    assert len(create_axes(dirs, existing, 70, cfg, n_structural=100).new_axes) == 1
    # tau_n: too few lines
    assert len(create_axes(dirs[:5], existing, 5, cfg).new_axes) == 0
    # default creates only the optimal one
    assert len(create_axes(dirs, np.zeros((0, 3)), len(dirs)).new_axes) == 1


def test_creation_rejects_degenerate_directions():
    dirs = np.zeros((20, 3))
    with pytest.raises(GeometryError):
        create_axes(dirs, np.zeros((0, 3)), 20)


def test_em_weights_on_noisy_observations():
    rng = np.random.default_rng(4)
    axes = np.array([[0.0, 0.0, 1.0], _h(0.0), _h(90.0), _h(45.0)])
    true = rng.integers(0, 4, size=200)
    obs = [_perturb(np.repeat(axes[t][None], rng.integers(2, 8), 0), 1.5, rng) for t in true]
    obs.append(_perturb(np.repeat(_unit([1.0, 1.0, 1.0])[None], 3, 0), 1.0, rng))  # outside every gate
    w = associate(obs, axes)
    assert w.shape == (201, 4)
    assert np.all(w >= 0)
    np.testing.assert_allclose(w[:200].sum(axis=1), 1.0, atol=1e-12)
    assert w[200].sum() == 0.0
    acc = np.mean(np.argmax(w[:200], axis=1) == true)
    assert acc > 0.98
    assert np.median(w[np.arange(200), true]) > 0.99
    # packed input gives the same weights
    packed = pack_observations(obs)
    np.testing.assert_allclose(associate(packed, axes, n_lines=201), w)


def test_em_ambiguous_line_gets_split_weight():
    axes = np.array([_h(0.0), _h(6.0)])  # 6 degrees apart: a line at 3 degrees belongs to both
    obs = [np.array([_h(3.0)])] + [np.array([_h(0.0)])] * 10 + [np.array([_h(6.0)])] * 10
    w = associate(obs, axes)
    assert abs(w[0, 0] - 0.5) < 0.05
    ang = mean_angles_deg(*pack_observations(obs), len(obs), axes)
    np.testing.assert_allclose(ang[0], [3.0, 3.0], atol=1e-9)


def test_update_adopt_delete_merge():
    cfg = AxesConfig(tau_diff_deg=1.0, jump_deg=5.0, max_jumps=2, merge_deg=5.0)
    axes = np.array([[0.0, 0.0, 1.0], _h(0.0), _h(90.0), _h(45.0)])
    state = AxisState.new(4, vertical_index=0)
    # small move: not adopted; 3-degree move: adopted; 8-degree move: a jump
    after = np.array([_unit([0.0, 0.005, 1.0]), _h(3.0), _h(98.0), _h(45.0)])
    r = update_axes(axes, after, state, cfg)
    assert r.adopted == [1, 2]
    np.testing.assert_allclose(r.axes[0], axes[0])
    assert line_angle_deg(r.axes[1], _h(3.0)) < 1e-9
    assert r.state.jumps.tolist() == [0, 0, 1, 0]
    # axis 2 jumps again: deleted; the vertical jumping is never deleted
    after2 = r.axes.copy()
    after2[2] = _h(110.0)
    after2[0] = _unit([0.0, 0.2, 1.0])
    r3 = update_axes(r.axes, after2, r.state, cfg)
    assert [i for i, _ in r3.deleted] == [2]
    assert r3.index_map.tolist() == [0, 1, -1, 2]
    assert r3.vertical_index == 0
    # merge: a newer axis drifts next to an older one -> the older survives
    st = r3.state.appended(1)
    axes4 = np.vstack([r3.axes, _h(50.0)])
    after4 = axes4.copy()
    after4[3] = _h(47.0)  # serial 4 (newest) moves within 5 deg of axis 2 (45 deg, serial 3)
    r4 = update_axes(axes4, after4, st, cfg)
    assert r4.merged == [(3, 2)]
    assert r4.index_map.tolist() == [0, 1, 2, 2]
    assert line_angle_deg(r4.axes[2], _h(45.0)) < 1e-9
    w = np.array([[0.0, 0.0, 0.5, 0.5], [1.0, 0.0, 0.0, 0.0]])
    np.testing.assert_allclose(remap_weights(w, r4.index_map, len(r4.axes)), [[0, 0, 1.0], [1.0, 0, 0]])
    assert r4.to_map_axes().vertical_index == 0


def test_merge_keeps_vertical_even_if_younger():
    cfg = AxesConfig()
    axes = np.array([_unit([0.0, 0.03, 1.0]), [0.0, 0.0, 1.0]])
    state = AxisState.new(2, vertical_index=1)
    r = update_axes(axes, axes, state, cfg)
    assert r.merged == [(0, 1)]
    assert r.vertical_index == 0
    np.testing.assert_allclose(r.axes[0], [0.0, 0.0, 1.0])


def test_update_shape_mismatch_raises():
    with pytest.raises(GeometryError):
        update_axes(np.eye(3), np.eye(3)[:2], AxisState.new(3))


def test_em_gate_on_3d_direction_and_empty_input():
    axes = np.array([[0.0, 0.0, 1.0], _h(0.0)])
    obs = [np.array([_h(1.0)]), np.array([_h(1.0)]), np.zeros((0, 3))]  # the third line never observed
    # line 1's 3D direction is far from every axis (a wrongly triangulated line): gated out
    dirs = np.array([_h(0.5), _unit([1.0, 1.0, 1.0]), _h(0.0)])
    w = associate(obs, axes, line_dirs_w=dirs)
    np.testing.assert_allclose(w, [[0.0, 1.0], [0.0, 0.0], [0.0, 0.0]], atol=1e-12)
    w2 = associate(obs, axes)  # gate on the mean vanishing-direction angle instead
    np.testing.assert_allclose(w2, [[0.0, 1.0], [0.0, 1.0], [0.0, 0.0]], atol=1e-12)
    assert associate([], axes).shape == (0, 2)
    assert associate(obs, np.zeros((0, 3))).shape == (3, 0)
    packed = (np.zeros((0, 3)), np.zeros(0, np.int64))
    np.testing.assert_array_equal(associate(packed, axes, n_lines=4), np.zeros((4, 2)))
    with pytest.raises(GeometryError):
        associate(obs, axes, line_dirs_w=dirs[:2])


def _atlanta_lines(counts, yaws, n_vertical, rng, stray=0):
    """Structural lines along the vertical and horizontal yaws (counts lines each, 0.5 deg noise), plus
    `stray` lines in random horizontal directions; each seen 4 times with its vanishing direction
    1 deg off: (directions (M,3), structural (M,), obs_dirs (K,3), obs_line (K,))."""
    truth = [np.array([0.0, 0.0, 1.0])] * n_vertical
    for yaw, n in zip(yaws, counts, strict=True):
        truth += [_h(yaw)] * n
    truth += [_h(y) for y in rng.uniform(0, 180, stray)]
    truth = np.array(truth)
    dirs = _perturb(truth, 0.5, rng)
    obs_line = np.repeat(np.arange(len(dirs)), 4)
    return dirs, np.ones(len(dirs), bool), _perturb(dirs[obs_line], 1.0, rng), obs_line


@pytest.mark.parametrize(
    ("yaws", "counts"),
    [((0.0, 35.0, 70.0, 90.0, 125.0, 160.0), (200, 150, 60, 30, 12, 10)), ((0.0, 90.0), (200, 150))],
)
def test_every_direction_of_an_atlanta_world_becomes_an_axis(yaws, counts):
    """Horizontal directions 20-35 degrees apart, seen by very different numbers of lines (a walk faces
    some facades longer), each become an axis with the default support limits; five stray lines in
    random directions found none (so a Manhattan scene keeps its two horizontals)."""
    from papl_mapper.mapping.structure import find_structure

    rng = np.random.default_rng(4)
    dirs, structural, obs, obs_line = _atlanta_lines(counts, yaws, 150, rng, stray=5)
    cfg = AxesConfig()
    s = find_structure(
        dirs,
        structural,
        obs,
        obs_line,
        np.array([0.0, 0.0, 1.0]),
        cfg,
        min_support_fraction=cfg.min_support_fraction,
    )
    axes = s.axes.directions
    assert len(axes) == 1 + len(yaws)
    assert line_angle_deg(axes[0], np.array([[0.0, 0.0, 1.0]]))[0] < 0.5
    err = line_angle_deg(np.array([_h(y) for y in yaws])[:, None], axes[None, 1:]).min(axis=1)
    assert err.max() < 1.0
