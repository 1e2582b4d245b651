"""Segment tracks joined across verified keyframe pairs: the epipolar band and the LBD matches in it."""

from __future__ import annotations

import numpy as np

from papl_mapper.frontend.line_links import LineLinkConfig, epipolar_overlap, link_line_tracks
from papl_mapper.frontend.lines import LineConfig
from papl_mapper.geometry.se3 import skew

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])


def _camera(yaw_deg: float, centre) -> np.ndarray:
    """T_cw of a camera looking along +z (turned by yaw about y) from `centre`."""
    a = np.radians(yaw_deg)
    R_wc = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_wc.T, -R_wc.T @ np.asarray(centre, float)
    return T


def _project(T_cw: np.ndarray, ends_w: np.ndarray) -> np.ndarray:
    """Segments (N, 4) of 3D segments (N, 2, 3)."""
    X = ends_w @ T_cw[:3, :3].T + T_cw[:3, 3]
    x = X @ K.T
    return (x[..., :2] / x[..., 2:]).reshape(-1, 4)


def _essential(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    T = T_b @ np.linalg.inv(T_a)  # camera a -> camera b
    return skew(T[:3, 3]) @ T[:3, :3]


def _scene(rng: np.random.Generator, n: int = 12) -> np.ndarray:
    """n 3D segments (n, 2, 3) 4-7 m in front of the cameras, of every direction but the viewing one."""
    mid = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(4, 7, n)])
    d = rng.normal(size=(n, 3))
    d[:, 2] *= 0.2
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.stack([mid - 0.6 * d, mid + 0.6 * d], axis=1)


def test_a_segment_lies_in_the_epipolar_band_of_its_match_and_a_moved_one_does_not():
    rng = np.random.default_rng(0)
    lines_w = _scene(rng)
    T_a, T_b = _camera(0, np.zeros(3)), _camera(12, np.array([0.8, 0.1, 0.2]))
    F = np.linalg.inv(K).T @ _essential(T_a, T_b) @ np.linalg.inv(K)
    sa, sb = _project(T_a, lines_w), _project(T_b, lines_w)
    ov = epipolar_overlap(F, sa, sb, 5.0)
    steep = np.diag(ov) > 0
    assert steep.sum() >= 10 and np.allclose(np.diag(ov)[steep], 1.0)
    # the baseline is sideways, so the epipolar lines run across the image: the segment moved 300 px
    # up or down (more than its length and its band) is outside the band
    moved = sb + np.array([0.0, 300.0, 0.0, 300.0]) * np.where(sb[:, 1:2] > 240, -1, 1)
    assert (np.diag(epipolar_overlap(F, sa, moved, 5.0))[steep] == 0).all()
    # a segment 3 deg off the epipolar line through line 0's middle is hardly located by the band: it
    # counts as overlapping only when the angle gate is off
    e = np.linalg.svd(F.T)[2][-1]  # epipole in b: F^T e = 0
    mid = (sb[0, :2] + sb[0, 2:]) / 2
    v = (mid - e[:2] / e[2]) / np.linalg.norm(mid - e[:2] / e[2])
    c, s = np.cos(np.radians(3)), np.sin(np.radians(3))
    v = np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])
    grazing = np.concatenate([mid - 40 * v, mid + 40 * v])[None]
    assert epipolar_overlap(F, sa[:1], grazing, 0.0)[0, 0] > 0.5
    assert epipolar_overlap(F, sa[:1], grazing, 5.0)[0, 0] == 0


def test_tracks_of_one_line_broken_at_every_photo_are_joined_and_a_look_alike_elsewhere_is_not():
    rng = np.random.default_rng(1)
    lines_w = _scene(rng)
    n = len(lines_w)
    poses = [_camera(0, np.zeros(3)), _camera(10, [0.7, 0.0, 0.1]), _camera(-8, [1.5, 0.1, 0.0])]
    base_desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    frame, track, xy, desc = [], [], [], []
    next_id = 0
    for f, T in enumerate(poses):
        segs = _project(T, lines_w)
        noisy = base_desc ^ np.packbits(rng.random((n, 256)) < 0.04, axis=1)  # about 10 of 256 bits flip
        frame += [f] * n
        track += list(range(next_id, next_id + n))  # a new track per photo: tracking broke
        next_id += n
        xy.append(segs)
        desc.append(noisy)
    # in photo 1, a look-alike of line 0 (its exact descriptor) 150 px away, off its epipolar band
    decoy = xy[1][0] + np.array([0.0, 150.0, 0.0, 150.0])
    frame.append(1)
    track.append(next_id)
    xy.append(decoy[None])
    desc.append(base_desc[:1])
    frame, track = np.array(frame), np.array(track)
    xy, desc = np.vstack(xy), np.vstack(desc)
    rows = np.arange(len(frame))
    geometry = [(a, b, _essential(poses[a], poses[b])) for a, b in ((0, 1), (1, 2), (0, 2))]
    out, joined = link_line_tracks(frame, track, xy, rows, desc, geometry, K, LineLinkConfig(), LineConfig())
    per_line = out[: 3 * n].reshape(3, n)
    # every line through the epipolar band of its views is one track, named by its first photo's id
    steep = (per_line == per_line[0]).all(axis=0)
    assert steep.sum() >= n - 2 and (per_line[0] == np.arange(n)).all()
    assert joined == int(np.sum(out != track))
    assert out[-1] == track[-1]  # the look-alike stays apart
    # no track holds two segments of one photo
    for t in np.unique(out):
        assert len(np.unique(frame[out == t])) == np.sum(out == t)
    # without verified pairs nothing changes
    same, none = link_line_tracks(frame, track, xy, rows, desc, [], K, LineLinkConfig(), LineConfig())
    assert none == 0 and (same == track).all()
