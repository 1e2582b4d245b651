"""Image-free observations of a scene: project GT points and segments into posed cameras.

Visibility is geometric: in front of the camera, inside the image and, optionally, not hidden
behind a quad (a ray-quad test from the camera centre). Segments are sampled along their length;
the observed segment spans the visible samples. `tracks_from_scene` packs it all into the
`Tracks` that mapping takes, so mapping and backend tests need no images.
"""

from __future__ import annotations

import numpy as np

from papl_mapper.map import Camera
from papl_mapper.synth.scenes import Scene
from papl_mapper.tracks import Tracks

NEAR = 0.1  # metres; closer points are not observed
OCCLUSION_MARGIN = 0.02  # metres before the point along the ray that an occluder must be
SEGMENT_SAMPLES = 16  # samples along a segment for its visible extent


def project(camera: Camera, T_wc: np.ndarray, X_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) and depths (N,) of world points (N, 3) seen from pose T_wc."""
    T_cw = np.linalg.inv(T_wc)
    Xc = X_w @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = Xc[:, :2] / z[:, None] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    return uv, z


def occluded(
    scene: Scene,
    centre: np.ndarray,
    X_w: np.ndarray,
    quads: np.ndarray | None = None,
    margin: float = OCCLUSION_MARGIN,
) -> np.ndarray:
    """(N,) whether a quad crosses the ray from `centre` to each point more than `margin` before it."""
    qc = scene.quad_corners if quads is None else scene.quad_corners[quads]
    p0 = qc[:, 0]
    u = qc[:, 1] - p0
    v = qc[:, 3] - p0
    n = np.cross(u, v)
    uu, vv = (u * u).sum(1), (v * v).sum(1)
    out = np.zeros(len(X_w), bool)
    for i in range(0, len(X_w), 512):
        d = X_w[i : i + 512] - centre  # (n, 3) ray directions, the point at s = 1
        length = np.linalg.norm(d, axis=1)
        denom = d @ n.T  # (n, Q)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = ((p0 - centre) * n).sum(1)[None] / denom
            hit = centre + s[..., None] * d[:, None]  # (n, Q, 3)
            a = ((hit - p0) * u).sum(-1) / uu
            b = ((hit - p0) * v).sum(-1) / vv
            before = (s > 1e-6) & (s < 1 - margin / length[:, None])
        out[i : i + 512] = (before & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)).any(axis=1)
    return out


def quads_in_view(quad_corners: np.ndarray, camera: Camera, T_wc: np.ndarray) -> np.ndarray:
    """Indices of the quads (Q, 4, 3 corners) that can hide something in view: not wholly behind
    the camera or wholly outside one side of the image."""
    T_cw = np.linalg.inv(T_wc)
    Pc = quad_corners @ T_cw[:3, :3].T + T_cw[:3, 3]  # (Q, 4, 3)
    x, y, z = Pc[..., 0], Pc[..., 1], Pc[..., 2]
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    out = (z <= 0).all(1)
    out |= (fx * x + (cx + 0.5) * z < 0).all(1)
    out |= (fx * x + (cx + 0.5 - camera.width) * z > 0).all(1)
    out |= (fy * y + (cy + 0.5) * z < 0).all(1)
    out |= (fy * y + (cy + 0.5 - camera.height) * z > 0).all(1)
    return np.flatnonzero(~out)


def visible_points(
    scene: Scene, camera: Camera, T_wc: np.ndarray, X_w: np.ndarray, occlusion: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the visible points and their pixels (K, 2)."""
    uv, z = project(camera, T_wc, X_w)
    ok = (z > NEAR) & _inside(camera, uv)
    idx = np.flatnonzero(ok)
    if occlusion and len(idx):
        idx = idx[~occluded(scene, T_wc[:3, 3], X_w[idx], quads_in_view(scene.quad_corners, camera, T_wc))]
    return idx, uv[idx]


def visible_segments(
    scene: Scene,
    camera: Camera,
    T_wc: np.ndarray,
    segments_w: np.ndarray,
    occlusion: bool = True,
    min_length_px: float = 15.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Indices of segments (S, 2, 3) seen over >= min_length_px and their visible extents (K, 4)."""
    k = SEGMENT_SAMPLES
    s = np.linspace(0.0, 1.0, k)
    samples = segments_w[:, :1] + s[None, :, None] * (segments_w[:, 1:] - segments_w[:, :1])  # (S, k, 3)
    flat = samples.reshape(-1, 3)
    uv, z = project(camera, T_wc, flat)
    ok = (z > NEAR) & _inside(camera, uv)
    if occlusion and ok.any():
        idx = np.flatnonzero(ok)
        ok[idx[occluded(scene, T_wc[:3, 3], flat[idx], quads_in_view(scene.quad_corners, camera, T_wc))]] = (
            False
        )
    ok = ok.reshape(-1, k)
    uv = uv.reshape(-1, k, 2)
    seen = np.flatnonzero(ok.sum(1) >= 2)
    first = np.argmax(ok[seen], axis=1)
    last = k - 1 - np.argmax(ok[seen, ::-1], axis=1)
    xy = np.concatenate([uv[seen, first], uv[seen, last]], axis=1)
    long = np.linalg.norm(xy[:, 2:] - xy[:, :2], axis=1) >= min_length_px
    return seen[long], xy[long]


def _inside(camera: Camera, uv: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return (
            (uv[:, 0] >= -0.5)
            & (uv[:, 0] <= camera.width - 0.5)
            & (uv[:, 1] >= -0.5)
            & (uv[:, 1] <= camera.height - 0.5)
        )


def tracks_from_scene(
    scene: Scene,
    camera: Camera,
    T_wc: np.ndarray,
    timestamps: np.ndarray,
    points_w: np.ndarray | None = None,
    n_surface_points: int = 2000,
    noise_px: float = 0.0,
    line_noise_px: float | None = None,
    occlusion: bool = True,
    keyframe_every: int = 10,
    seed: int = 0,
) -> tuple[Tracks, np.ndarray]:
    """Tracks from projecting GT points and segments into poses T_wc (F, 4, 4); also the points (P, 3).

    Point track ids index the returned points (the scene's corner points, then `n_surface_points`
    random surface points, unless `points_w` is given); line track ids index `scene.segments`;
    `vp_dirs_c[f]` holds the scene axes in the camera frame, so `line_vp` is the GT axis id.
    """
    rng = np.random.default_rng([seed, 11])
    if points_w is None:
        points_w = np.vstack([scene.corner_points(), scene.sample_surface_points(n_surface_points, seed)])
    line_noise_px = noise_px if line_noise_px is None else line_noise_px
    F = len(T_wc)
    pf, pt, puv, lf, lt, lxy = [], [], [], [], [], []
    for f in range(F):
        idx, uv = visible_points(scene, camera, T_wc[f], points_w, occlusion)
        pf.append(np.full(len(idx), f))
        pt.append(idx)
        puv.append(uv + rng.normal(0, noise_px, uv.shape) if noise_px > 0 else uv)
        sidx, xy = visible_segments(scene, camera, T_wc[f], scene.segments, occlusion)
        lf.append(np.full(len(sidx), f))
        lt.append(sidx)
        lxy.append(xy + rng.normal(0, line_noise_px, xy.shape) if line_noise_px > 0 else xy)
    line_track = np.concatenate(lt).astype(np.int64)
    vp_dirs_c = np.einsum("fji,aj->fai", T_wc[:, :3, :3], scene.axes)  # R_cw @ axis = R_wc^T @ axis
    tracks = Tracks(
        camera=camera,
        frame_index=np.arange(F, dtype=np.int64),
        timestamp=np.asarray(timestamps, float),
        is_keyframe=(np.arange(F) % max(keyframe_every, 1)) == 0,
        point_frame=np.concatenate(pf).astype(np.int64),
        point_track=np.concatenate(pt).astype(np.int64),
        point_uv=np.concatenate(puv).reshape(-1, 2),
        line_frame=np.concatenate(lf).astype(np.int64),
        line_track=line_track,
        line_xy=np.concatenate(lxy).reshape(-1, 4),
        line_vp=scene.segment_axis[line_track].astype(np.int64),
        vp_dirs_c=vp_dirs_c,
        vertical_vp=np.zeros(F, np.int64),
    )
    tracks.validate()
    return tracks, points_w
