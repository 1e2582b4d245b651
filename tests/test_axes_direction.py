"""direction_checked: the axes a line's views reject, on synthetic segments with known directions."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from papl_mapper.axes import AxesConfig
from papl_mapper.axes.association import direction_checked
from papl_mapper.geometry.triangulation import observation_planes

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
R_WC = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # camera looks along world +y
AXES = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # vertical, one horizontal
SIGMA_PX = 1.0


def _segments(directions: np.ndarray, baseline_m: float, views: int, sigma_px: float, seed: int):
    """Each line (unit direction, 1.5 m long, 3-6 m ahead) seen from `views` cameras along x over
    `baseline_m`, endpoints with pixel noise: (normals (K,3), lengths (K,), line of each (K,))."""
    rng = np.random.default_rng(seed)
    normals, lengths, line = [], [], []
    for i, d in enumerate(directions):
        centre = np.array([rng.uniform(-1, 1), rng.uniform(3, 6), rng.uniform(-0.8, 0.8)])
        ends = centre + np.outer([-0.75, 0.75], d)
        T = np.tile(np.eye(4), (views, 1, 1))
        T[:, :3, :3] = R_WC
        T[:, 0, 3] = np.linspace(-baseline_m / 2, baseline_m / 2, views)
        X_c = np.einsum("ij,vkj->vki", R_WC.T, ends[None] - T[:, None, :3, 3])
        uv = X_c[..., :2] / X_c[..., 2:] * K[0, 0] + K[:2, 2]
        xy = uv.reshape(views, 4) + rng.normal(scale=sigma_px, size=(views, 4))
        normals.append(observation_planes(T, K, xy)[:, :3])
        lengths.append(np.linalg.norm(xy[:, 2:] - xy[:, :2], axis=1))
        line.append(np.full(views, i))
    return np.concatenate(normals), np.concatenate(lengths), np.concatenate(line)


def _tilted(axis: np.ndarray, deg: float, n: int, seed: int) -> np.ndarray:
    """n unit directions `deg` from `axis`, about random perpendiculars."""
    rng = np.random.default_rng(seed)
    perp = rng.normal(size=(n, 3))
    perp -= np.outer(perp @ axis, axis)
    perp /= np.linalg.norm(perp, axis=1, keepdims=True)
    return np.cos(np.radians(deg)) * axis + np.sin(np.radians(deg)) * perp


def _flagged(directions, axis_index, config=None, baseline_m=1.0, views=10, sigma_px=SIGMA_PX, seed=0):
    normals, lengths, line = _segments(directions, baseline_m, views, sigma_px, seed)
    weights = np.zeros((len(directions), len(AXES)))
    weights[:, axis_index] = 1.0
    return direction_checked(normals, lengths, line, weights, AXES, config or AxesConfig(), SIGMA_PX)[1]


@pytest.mark.parametrize("axis_index", [0, 1])
def test_lines_along_their_axis_are_kept(axis_index):
    directions = np.tile(AXES[axis_index], (300, 1))
    assert _flagged(directions, axis_index).sum() == 0


@pytest.mark.parametrize("axis_index", [0, 1])
def test_lines_far_from_their_axis_are_found(axis_index):
    directions = _tilted(AXES[axis_index], 40.0, 300, seed=axis_index)
    assert _flagged(directions, axis_index).mean() >= 0.95


def test_the_test_holds_its_significance_on_noise():
    """Without the angle gate, lines on their axis are flagged about as often as alpha says."""
    config = dataclasses.replace(AxesConfig(), gate_deg=0.0, direction_alpha=0.05)
    rate = _flagged(np.tile(AXES[0], (600, 1)), 0, config, seed=3).mean()
    assert 0.02 <= rate <= 0.10, rate


@pytest.mark.parametrize("baseline_m", [1.0, 1e-3])
def test_views_along_the_line_do_not_decide(baseline_m):
    """Cameras moving along the line (or standing still) see planes that nearly coincide: the free
    direction fits their noise anywhere in them, and the line on its axis stays."""
    directions = np.tile(AXES[1], (300, 1))
    assert _flagged(directions, 1, baseline_m=baseline_m).sum() == 0


def test_lines_within_the_gate_are_kept():
    directions = _tilted(AXES[0], 8.0, 200, seed=5)
    assert _flagged(directions, 0, sigma_px=0.2).sum() == 0
    assert _flagged(directions, 0, dataclasses.replace(AxesConfig(), gate_deg=5.0), sigma_px=0.2).mean() > 0.9


def test_off_disables_it_and_unassociated_lines_are_not_tested():
    directions = _tilted(AXES[0], 40.0, 50, seed=6)
    assert _flagged(directions, 0, dataclasses.replace(AxesConfig(), direction_alpha=0.0)).sum() == 0
    normals, lengths, line = _segments(directions, 1.0, 10, SIGMA_PX, 0)
    none = np.zeros((50, len(AXES)))
    weights, unfit = direction_checked(normals, lengths, line, none, AXES, AxesConfig(), SIGMA_PX)
    assert unfit.sum() == 0 and not weights.any()


def test_a_soft_line_keeps_the_axis_its_views_accept():
    """A horizontal line shared by both axes by EM keeps only the one it lies along, renormalised."""
    normals, lengths, line = _segments(np.tile(AXES[1], (20, 1)), 1.0, 10, SIGMA_PX, 7)
    weights = np.tile([0.7, 0.3], (20, 1))
    checked, unfit = direction_checked(normals, lengths, line, weights, AXES, AxesConfig(), SIGMA_PX)
    assert not unfit.any()
    assert np.array_equal(checked, np.tile([0.0, 1.0], (20, 1)))


def test_the_axis_update_leaves_rejected_lines_unanchored():
    """update_structure re-associates lines from their vanishing directions, but not to the axes their
    segments' planes reject."""
    from papl_mapper.axes import AxisState
    from papl_mapper.map import LineState
    from papl_mapper.mapping.structure import AxisInputs, update_structure

    from .conftest import make_map

    m = make_map()
    n = len(m.lines)
    anchored = np.flatnonzero(m.lines.state == LineState.ANCHORED)
    dirs = m.lines.endpoints_w[:, 1] - m.lines.endpoints_w[:, 0]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    obs_line = np.repeat(np.arange(n), 3)  # three views of each line
    obs = np.where((m.lines.state == LineState.ANCHORED)[obs_line, None], dirs[obs_line], np.nan)
    rng = np.random.default_rng(0)
    normals = np.cross(dirs[obs_line], rng.normal(size=(3 * n, 3)))  # planes holding each line
    rejected = anchored[0]
    normals[obs_line == rejected] = dirs[rejected]  # planes that cannot hold its axis
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    inputs = AxisInputs(
        m.axes.directions.copy(),
        AxisState.new(len(m.axes), 0),
        obs,
        obs_line,
        m.lines.ids,
        normals,
        np.full(3 * n, 100.0),
    )
    update_structure(m, inputs, AxesConfig(), SIGMA_PX)
    assert m.lines.axis_weights[rejected].sum() == 0
    assert m.lines.state[rejected] != LineState.ANCHORED
    assert (m.lines.state[anchored[1:]] == LineState.ANCHORED).all()


def _views(ends: np.ndarray, baseline_m: float, views: int, along: np.ndarray, seed: int):
    """Poses (views,4,4) of cameras looking along world +y, spread over `baseline_m` along `along`,
    and the noisy segments (views,4) they see of the 3D segment `ends` (2,3), 0.3 px noise."""
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (views, 1, 1))
    T[:, :3, :3] = R_WC
    T[:, :3, 3] = np.outer(np.linspace(-baseline_m / 2, baseline_m / 2, views), along)
    X_c = np.einsum("ij,vkj->vki", R_WC.T, ends[None] - T[:, None, :3, 3])
    uv = X_c[..., :2] / X_c[..., 2:] * K[0, 0] + K[:2, 2]
    return T, uv.reshape(views, 4) + rng.normal(scale=0.3, size=(views, 4))


def test_lines_freed_from_their_axis_are_placed_by_their_own_planes():
    """A line placed along an axis its planes reject is triangulated afresh from them (to its true
    direction and place); one its views cannot place (cameras moving along it) is left out; lines
    not freed are untouched."""
    from papl_mapper.mapping.lines import LineEstimates, LineInitConfig
    from papl_mapper.mapping.structure import MapLines, freed_lines

    x = np.array([1.0, 0.0, 0.0])
    true_dir = _tilted(AXES[1], 40.0, 1, 3)[0]
    centre = np.array([0.3, 4.0, 0.2])
    truths = [
        centre + np.outer([-0.75, 0.75], AXES[1]),  # on its axis, kept as it is
        centre + np.outer([-0.75, 0.75], true_dir),  # freed: 40 degrees off the axis it was put on
        np.array([0.0, 3.0, 0.5]) + np.outer([-1.0, 1.0], x),  # freed, but seen only along itself
    ]
    tracks, Ts, xys = [], [], []
    for i, ends in enumerate(truths):
        T, xy = _views(ends, 1.0, 8, x, i)
        tracks.append(np.full(8, 10 + i))
        Ts.append(T)
        xys.append(xy)
    placed = np.stack([truths[0], centre + np.outer([-0.75, 0.75], AXES[1]), truths[2]])
    est = LineEstimates(np.array([10, 11, 12]), placed, np.ones(3, bool), np.zeros(3))
    lines = MapLines(
        est, np.concatenate(tracks), np.concatenate(xys), np.concatenate(Ts), np.full((24, 3), np.nan)
    )
    out, keep = freed_lines(est, np.array([False, True, True]), lines, K, LineInitConfig())
    assert keep.tolist() == [True, True, False]
    assert out.track.tolist() == [10, 11]
    assert np.array_equal(out.endpoints_w[0], placed[0]) and out.from_vp.tolist() == [True, False]
    d = out.endpoints_w[1, 1] - out.endpoints_w[1, 0]
    assert np.degrees(np.arccos(abs(d @ true_dir) / np.linalg.norm(d))) < 5.0  # it was put 40 degrees off
    off = truths[1] - out.endpoints_w[1, 0]  # the true endpoints' distances to the fitted line:
    off -= np.outer(off @ d, d) / (d @ d)  # 0.48 m from the line it was placed on
    assert np.linalg.norm(off, axis=1).max() < 0.1
