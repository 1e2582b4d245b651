"""Line triangulation from segment tracks: exact on clean data, bounded on noise, degenerate cases dropped."""

from __future__ import annotations

import numpy as np

from papl_mapper.geometry.triangulation import observation_planes
from papl_mapper.map import Camera
from papl_mapper.mapping.lines import (
    LineInitConfig,
    dominant_directions,
    endpoint_extent,
    line_through_planes,
    reprojection_rms,
    triangulate_lines,
    vp_image_angle_deg,
)

CAM = Camera(640, 480, 500.0, 500.0, 319.5, 239.5)
EXACT_TOL = 1e-6  # world units, noise-free
NOISY_ENDPOINT_TOL = 0.05  # world units at ~5 units depth, 0.5 px noise


def _T_wc(centre: np.ndarray, yaw: float) -> np.ndarray:
    fwd = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    T = np.eye(4)
    T[:3, :3] = np.column_stack([np.cross(down, fwd), down, fwd])
    T[:3, 3] = centre
    return T


def _scene(noise_px=0.0, seed=0):
    """Axis-aligned segments on a wall 6 units ahead, seen by 8 cameras moving sideways and up/down."""
    rng = np.random.default_rng(seed)
    axes = np.eye(3)[[2, 1]]  # vertical, along the wall
    mids = np.column_stack([np.full(20, 6.0), rng.uniform(-2, 2, 20), rng.uniform(-1, 1, 20)])
    lab = np.arange(20) % 2
    segs = np.stack([mids - 0.4 * axes[lab], mids + 0.4 * axes[lab]], axis=1)
    ks = np.arange(8)
    poses = np.stack([_T_wc(np.array([-0.2 * k, 0.25 * k - 1, 0.5 * np.cos(k)]), 0.05 * k) for k in ks])
    track, T, xy, vp = [], [], [], []
    for T_wc in poses:
        T_cw = np.linalg.inv(T_wc)
        for i, s in enumerate(segs):
            c = s @ T_cw[:3, :3].T + T_cw[:3, 3]
            uv = (c @ CAM.K.T)[:, :2] / c[:, 2:3]
            track.append(i)
            T.append(T_wc)
            xy.append(uv.ravel() + rng.normal(0, noise_px, 4))
            vp.append(axes[lab[i]])
    return segs, np.array(track), np.stack(T), np.array(xy), np.array(vp)


def _endpoint_error(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Largest endpoint distance per segment, whichever way round the endpoints are."""
    a = np.linalg.norm(est - gt, axis=2).max(1)
    b = np.linalg.norm(est[:, ::-1] - gt, axis=2).max(1)
    return np.minimum(a, b)


def test_planes_contain_the_segment():
    segs, track, T, xy, _ = _scene()
    planes = observation_planes(T, CAM.K, xy)
    X = segs[track]  # (n, 2, 3)
    res = np.einsum("ni,nki->nk", planes[:, :3], X) + planes[:, 3:4]
    assert np.abs(res).max() < EXACT_TOL


def test_exact_lines_with_and_without_vanishing_directions():
    segs, track, T, xy, vp = _scene()
    for dirs in (vp, np.full_like(vp, np.nan)):
        est = triangulate_lines(track, T, xy, dirs, CAM.K, LineInitConfig(min_vp_fraction=0.0))
        assert len(est.track) == 20
        assert est.from_vp.all() == np.isfinite(dirs).all()
        assert _endpoint_error(est.endpoints_w, segs[est.track]).max() < EXACT_TOL
        assert est.rms_px.max() < 1e-6


def test_noisy_lines_known_direction():
    """A known direction removes the direction error and keeps the position error of the free fit."""
    segs, track, T, xy, vp = _scene(noise_px=0.5, seed=1)
    perp, angle = [], []
    for dirs in (vp, np.full_like(vp, np.nan)):
        est = triangulate_lines(track, T, xy, dirs, CAM.K, LineInitConfig(min_vp_fraction=0.0))
        assert np.median(_endpoint_error(est.endpoints_w, segs[est.track])) < NOISY_ENDPOINT_TOL
        d = est.endpoints_w[:, 1] - est.endpoints_w[:, 0]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        off = segs[est.track].mean(1) - est.endpoints_w[:, 0]
        perp.append(np.median(np.linalg.norm(off - np.einsum("ni,ni->n", off, d)[:, None] * d, axis=1)))
        cos = np.abs(np.einsum("ni,ni->n", d, vp[est.track]))  # rows 0..19: the first view of tracks 0..19
        angle.append(np.degrees(np.arccos(np.clip(cos, 0, 1))).max())
    assert angle[0] < 1e-6 < 0.1 < angle[1]
    assert perp[0] < 1.2 * perp[1]


def test_degenerate_tracks_are_dropped():
    segs, track, T, xy, vp = _scene()
    one_view = track != 3
    keep = one_view | (np.arange(len(track)) == np.flatnonzero(track == 3)[0])
    est = triangulate_lines(track[keep], T[keep], xy[keep], vp[keep], CAM.K)
    assert 3 not in est.track and len(est.track) == 19
    # every view from the same place: no parallax
    same = np.repeat(T[:1], len(T), axis=0)
    est = triangulate_lines(
        track[track == 0], same[track == 0], np.repeat(xy[:1], 8, 0), vp[track == 0], CAM.K
    )
    assert len(est.track) == 0
    # a wrong direction gives a large reprojection error and is refused
    bad = np.tile(np.array([1.0, 0.0, 0.0]), (len(vp), 1))
    est = triangulate_lines(track, T, xy, bad, CAM.K, LineInitConfig(max_error_px=2.0))
    assert len(est.track) == 0


def test_helpers_agree():
    segs, track, T, xy, _ = _scene()
    sel = track == 5
    p, d = line_through_planes(observation_planes(T[sel], CAM.K, xy[sel]), T[sel, :3, 3])
    assert reprojection_rms(p, d, T[sel], xy[sel], CAM.K).max() < 1e-6
    ends = endpoint_extent(p, d, T[sel], xy[sel], CAM.K, 5.0)
    assert _endpoint_error(ends[None], segs[5:6])[0] < EXACT_TOL


def test_texture_tracks_are_left_out():
    """Tracks classified to a vanishing direction in few views are structural only if their segments
    line up with its vanishing point; others (texture edges) are dropped unless min_vp_fraction is 0."""
    segs, track, T, xy, vp = _scene()
    view = np.arange(len(track)) // 20  # _scene lists the 20 segments camera by camera
    rare = (track >= 10) & (view >= 2)  # tracks 10..19 are classified in 2 of their 8 views only
    vp = vp.copy()
    vp[rare] = np.nan
    cfg = LineInitConfig(min_vp_fraction=0.5, max_vp_angle_deg=1.0)
    # truly along their direction: the rarely classified tracks still line up with its vanishing point
    est = triangulate_lines(track, T, xy, vp, CAM.K, cfg)
    assert len(est.track) == 20 and est.from_vp.all()
    assert _endpoint_error(est.endpoints_w, segs[est.track]).max() < EXACT_TOL
    # texture edges: tracks 10..19 turned by 20 degrees in the wall plane, wrongly classified twice
    tilt = np.radians(20.0)
    mids = segs.mean(axis=1)
    half = 0.4 * np.array([0.0, np.sin(tilt), np.cos(tilt)])
    moved = segs.copy()
    moved[10:] = np.stack([mids[10:] - half, mids[10:] + half], axis=1)
    xy2 = xy.copy()
    for i, T_wc in enumerate(T):
        T_cw = np.linalg.inv(T_wc)
        c = moved[track[i]] @ T_cw[:3, :3].T + T_cw[:3, 3]
        xy2[i] = ((c @ CAM.K.T)[:, :2] / c[:, 2:3]).ravel()
    est = triangulate_lines(track, T, xy2, vp, CAM.K, cfg)
    assert sorted(est.track.tolist()) == list(range(10))
    assert len(triangulate_lines(track, T, xy2, vp, CAM.K, LineInitConfig(min_vp_fraction=0.2)).track) >= 10
    free = triangulate_lines(track, T, xy2, vp * np.nan, CAM.K, LineInitConfig(min_vp_fraction=0.0))
    assert len(free.track) == 20  # 0 keeps every track, triangulated freely
    assert _endpoint_error(free.endpoints_w, moved[free.track]).max() < EXACT_TOL


def test_vp_image_angle():
    """Zero for a segment along the projected direction, the known angle for a rotated one."""
    segs, track, T, xy, vp = _scene()
    ang = vp_image_angle_deg(T, xy, CAM.K, np.array([0.0, 0.0, 1.0]))  # the vertical of tracks 0, 2, ..
    assert np.abs(ang[track % 2 == 0]).max() < 1e-6
    # rotate one image segment by 5 degrees about its midpoint
    k = int(np.flatnonzero(track % 2 == 0)[0])
    a, b = xy[k, :2], xy[k, 2:]
    m, h = 0.5 * (a + b), 0.5 * (b - a)
    c, s_ = np.cos(np.radians(5.0)), np.sin(np.radians(5.0))
    h = np.array([c * h[0] - s_ * h[1], s_ * h[0] + c * h[1]])
    rot = np.concatenate([m - h, m + h])[None]
    assert abs(vp_image_angle_deg(T[k : k + 1], rot, CAM.K, np.array([0.0, 0.0, 1.0]))[0] - 5.0) < 1e-3


def test_dominant_directions():
    """Directions that many rows share, densest first, sign-invariant; rare and NaN rows ignored."""
    rng = np.random.default_rng(3)
    axes = np.array([[0.0, 0.0, 1.0], [np.cos(0.3), np.sin(0.3), 0.0]])
    rows = np.concatenate(
        [
            axes[0] + rng.normal(0, 0.005, (300, 3)),
            -(axes[1] + rng.normal(0, 0.005, (150, 3))),  # opposite sign, same axis
            rng.normal(0, 1, (5, 3)),  # scattered: under min_share each
            np.full((20, 3), np.nan),
        ]
    )
    got = dominant_directions(rows, gate_deg=2.0, min_share=0.05)
    assert got.shape == (2, 3)
    assert np.degrees(np.arccos(np.clip(np.abs(np.sum(got * axes, axis=1)), 0, 1))).max() < 0.2
    assert dominant_directions(np.full((4, 3), np.nan)).shape == (0, 3)


def test_weakly_classified_track_takes_the_common_direction():
    """A track classified once, to a direction 5 degrees off, is anchored to the direction most views
    share when its segments line up with that one's vanishing points."""
    segs, track, T, xy, vp = _scene()
    vp = vp.copy()
    view = np.arange(len(track)) // 20
    off = np.array([np.sin(np.radians(5.0)), 0.0, np.cos(np.radians(5.0))])
    vp[(track == 0) & (view > 0)] = np.nan
    vp[(track == 0) & (view == 0)] = off  # one wrong classification of a vertical segment
    est = triangulate_lines(track, T, xy, vp, CAM.K, LineInitConfig(min_vp_fraction=0.7))
    assert 0 in est.track.tolist()
    assert _endpoint_error(est.endpoints_w, segs[est.track]).max() < EXACT_TOL
