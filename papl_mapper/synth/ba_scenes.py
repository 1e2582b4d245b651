"""Seeded synthetic bundle-adjustment problems with a known answer (the oracle of tests and benchmarks).

A camera path runs along a corridor-like scene of structural lines on three orthogonal axes (world +Z up)
and points; observations are exact projections plus optional pixel noise. `perturb` makes a start for
BA; `errors` measures an estimate against the truth after a similarity alignment
(monocular maps are defined up to one).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from papl_mapper import geometry as geo
from papl_mapper.geometry.similarity import umeyama
from papl_mapper.map import Axes, Camera, Keyframes, Lines, LineState, Map, Points

# camera looking along world +Y with world +Z up: x_c = +X, y_c = -Z, z_c = +Y
R_LOOK_Y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


@dataclass
class SceneSpec:
    """Size of a synthetic problem."""

    n_keyframes: int = 12
    n_points: int = 150
    lines_per_axis: tuple[int, ...] = (10, 10, 10)
    n_free_lines: int = 0
    """Extra non-structural lines (random directions), stored as ORTHONORMAL."""
    step: float = 0.3
    """Distance between consecutive keyframes along the path."""
    obs_noise_px: float = 0.0
    max_views: int = 0
    """If > 0, each landmark is observed by at most this many consecutive keyframes (sparse, large maps)."""
    path_amplitude: float = 1.0
    """Scale of the lateral and vertical wiggle of the camera path (a straight path leaves lines along it
    unobservable)."""
    line_direction_noise_deg: float = 0.0
    """Structural lines only approximately parallel to their axis (the paper's toy data)."""
    seed: int = 0


def make_scene(spec: SceneSpec) -> Map:
    """The true Map: poses, points, anchored (and free) lines with observations, three axes."""
    rng = np.random.default_rng(spec.seed)
    cam = Camera(640, 480, 450.0, 450.0, 319.5, 239.5)
    K = cam.K
    N = spec.n_keyframes
    s = np.arange(N) * spec.step
    length = max(s[-1], 1.0)
    amp = spec.path_amplitude
    C = np.stack([s, amp * 0.3 * np.sin(s / max(length, 1e-9) * np.pi), amp * 0.2 * np.cos(s * 0.7)], 1)
    T = np.stack(
        [
            geo.make_T(
                R_LOOK_Y @ geo.so3_exp(np.array([0.03 * np.sin(i * 0.5), 0.08 * np.sin(i * 0.3), 0.0])), c
            )
            for i, c in enumerate(C)
        ]
    )
    lo = np.array([-3.0, 4.0, -2.0])
    hi = np.array([length + 3.0, 9.0, 3.0])
    axes = np.eye(3)[[2, 0, 1]]  # vertical first
    X = rng.uniform(lo, hi, (spec.n_points, 3))
    mids, dirs, labels = [], [], []
    for a, n in enumerate(spec.lines_per_axis):
        mids.append(rng.uniform(lo, hi, (n, 3)))
        tilt = geo.so3_exp(rng.normal(scale=np.radians(spec.line_direction_noise_deg), size=(n, 3)))
        dirs.append(tilt @ axes[a])
        labels += [a] * n
    if spec.n_free_lines:
        d = rng.normal(size=(spec.n_free_lines, 3))
        mids.append(rng.uniform(lo, hi, (spec.n_free_lines, 3)))
        dirs.append(d / np.linalg.norm(d, axis=1, keepdims=True))
        labels += [-1] * spec.n_free_lines
    mid = np.concatenate(mids) if mids else np.zeros((0, 3))
    d = np.concatenate(dirs) if dirs else np.zeros((0, 3))
    half = rng.uniform(0.5, 1.5, len(mid))[:, None]
    ends = np.stack([mid - half * d, mid + half * d], 1)
    labels = np.array(labels, np.int64)

    def visible(uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        return (
            (z > 0.5)
            & (uv[..., 0] > 0)
            & (uv[..., 0] < cam.width - 1)
            & (uv[..., 1] > 0)
            & (uv[..., 1] < cam.height - 1)
        )

    def windowed(P: np.ndarray) -> np.ndarray:
        """(n, N) which keyframes may observe each landmark: all, or max_views around the nearest camera."""
        n = len(P)
        if spec.max_views <= 0:
            return np.ones((n, N), bool)
        nearest = np.argmin(np.abs(P[:, None, 0] - C[None, :, 0]), axis=1)
        start = np.clip(nearest - spec.max_views // 2 + rng.integers(-1, 2, n), 0, max(N - spec.max_views, 0))
        k = np.arange(N)[None]
        return (k >= start[:, None]) & (k < start[:, None] + spec.max_views)

    # points
    uv, z = geo.project_points(K, T[None], X[:, None])  # (P, N, 2)
    vis = visible(uv, z) & windowed(X)
    twice = vis.sum(1) >= 2  # every landmark is seen at least twice
    X, vis, uv = X[twice], vis[twice], uv[twice]
    pi, ki = np.nonzero(vis)
    obs_uv = uv[pi, ki] + rng.normal(scale=spec.obs_noise_px, size=(len(pi), 2))
    # lines: both endpoints visible
    uve, ze = geo.project_points(K, T[None, :, None], ends[:, None])  # (M, N, 2, 2)
    lvis = visible(uve, ze).all(-1) & windowed(ends.mean(1))
    two = lvis.sum(1) >= 2
    ends, labels, lvis, uve = ends[two], labels[two], lvis[two], uve[two]
    li, lk = np.nonzero(lvis)
    obs_xy = uve[li, lk].reshape(-1, 4) + rng.normal(scale=spec.obs_noise_px, size=(len(li), 4))

    kf_ids = np.arange(N, dtype=np.int64)
    kf = Keyframes(kf_ids, kf_ids * 5, kf_ids / 10.0, T)
    pts = Points(
        np.arange(len(X), dtype=np.int64),
        X,
        np.full((len(X), 3), 200, np.uint8),
        np.stack([pi, ki], 1).astype(np.int64),
        obs_uv,
    )
    M = len(ends)
    w = np.zeros((M, 3))
    w[labels >= 0, labels[labels >= 0]] = 1.0
    ref = np.full(M, -1, np.int64)
    first = np.full(M, N, np.int64)
    np.minimum.at(first, li, lk)
    has = first < N
    ref[has] = first[has]
    inv = np.full(M, np.nan)
    if has.any():
        _, r = geo.anchor_from_endpoints(ends[has], T[ref[has]])
        inv[has] = r
    anchored = (labels >= 0) & has
    state = np.where(anchored, LineState.ANCHORED, LineState.ORTHONORMAL).astype(np.int8)
    lines = Lines(
        np.arange(M, dtype=np.int64),
        ends,
        w,
        state,
        np.where(anchored, ref, -1),
        np.where(anchored, inv, np.nan),
        np.stack([li, lk], 1).astype(np.int64),
        obs_xy,
    )
    return Map(cam, kf, pts, lines, Axes(axes.copy(), 0), {"units": "arbitrary", "synthetic_seed": spec.seed})


def perturb(
    m: Map,
    seed: int = 1,
    rot_deg: float = 0.0,
    trans: float = 0.0,
    point_sigma: float = 0.0,
    line_sigma: float = 0.0,
    line_angle_deg: float = 0.0,
    axis_deg: float = 0.0,
    keep_first: bool = True,
) -> Map:
    """A start for BA: noise on poses (all but the first when keep_first), points, line endpoints and
    line directions (lines rotate about their midpoints), and axis directions."""
    rng = np.random.default_rng(seed)
    out = copy.deepcopy(m)
    N = len(out.keyframes)
    xi = np.concatenate(
        [rng.normal(scale=np.radians(rot_deg), size=(N, 3)), rng.normal(scale=trans, size=(N, 3))], 1
    )
    if keep_first:
        xi[0] = 0
    Tn = out.keyframes.T_wc.copy()
    Tn[:, :3, :3] = Tn[:, :3, :3] @ geo.so3_exp(xi[:, :3])
    Tn[:, :3, 3] += xi[:, 3:]
    out.keyframes.T_wc = Tn
    out.points.xyz = out.points.xyz + rng.normal(scale=point_sigma, size=out.points.xyz.shape)
    ends = out.lines.endpoints_w
    mid = ends.mean(1) + rng.normal(scale=line_sigma, size=(len(ends), 3))
    half = (ends[:, 1] - ends[:, 0]) / 2
    Rn = geo.so3_exp(rng.normal(scale=np.radians(line_angle_deg), size=(len(ends), 3)))
    half = np.einsum("nij,nj->ni", Rn, half)
    out.lines.endpoints_w = np.stack([mid - half, mid + half], 1)
    if len(out.axes):
        Ra = geo.so3_exp(rng.normal(scale=np.radians(axis_deg), size=(len(out.axes), 3)))
        dirs = np.einsum("nij,nj->ni", Ra, out.axes.directions)
        out.axes.directions = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    has = out.lines.ref_keyframe_id >= 0
    if has.any():
        rows = np.searchsorted(out.keyframes.ids, out.lines.ref_keyframe_id[has])
        _, r = geo.anchor_from_endpoints(out.lines.endpoints_w[has], Tn[rows])
        out.lines.inverse_depth[has] = r
    return out


def errors(est: Map, truth: Map, align: bool | str = True) -> dict[str, float]:
    """ATE RMSE of camera centres, point RMSE, mean and median Pluecker line error (paper's Error_l, |v| = 1),
    mean line angle (deg). `align`: True for a similarity alignment on camera centres and points together
    (a near-straight camera path alone leaves the rotation about it undetermined); "scale" for a scale
    about the first camera only (when the gauge holds the first pose at the truth); False for none."""
    c_e = est.keyframes.T_wc[:, :3, 3]
    c_t = truth.keyframes.T_wc[:, :3, 3]
    if align == "scale":
        a, b = c_e - c_e[0], c_t - c_t[0]
        s = float(np.sum(a * b) / max(np.sum(a * a), 1e-300))
        R_, t = np.eye(3), c_t[0] - s * c_e[0]
    elif align:
        src = np.concatenate([c_e, est.points.xyz])
        dst = np.concatenate([c_t, truth.points.xyz])
        sim = umeyama(src, dst)
        s, R_, t = sim.scale, sim.R, sim.t
    else:
        s, R_, t = 1.0, np.eye(3), np.zeros(3)

    def tf(x: np.ndarray) -> np.ndarray:
        return s * x @ R_.T + t

    out = {"ate_rmse": float(np.sqrt(np.mean(np.sum((tf(c_e) - c_t) ** 2, 1))))}
    if len(truth.points):
        out["point_rmse"] = float(np.sqrt(np.mean(np.sum((tf(est.points.xyz) - truth.points.xyz) ** 2, 1))))
    if len(truth.lines):
        Le = geo.plucker_from_endpoints(tf(est.lines.endpoints_w[:, 0]), tf(est.lines.endpoints_w[:, 1]))
        Lt = geo.plucker_from_endpoints(truth.lines.endpoints_w[:, 0], truth.lines.endpoints_w[:, 1])
        dist = geo.line_distance(Le, Lt)
        out["line_error"] = float(np.mean(dist))
        out["line_error_median"] = float(np.median(dist))  # the mean is ruled by a few depth-starved lines
        d_e, d_t = (L[:, 3:] / np.linalg.norm(L[:, 3:], axis=1, keepdims=True) for L in (Le, Lt))
        out["line_angle_deg"] = float(np.mean(geo.line_angle_deg(d_e, d_t)))
    if len(truth.axes):
        da = np.abs(np.sum((est.axes.directions @ R_.T) * truth.axes.directions, 1))
        out["axis_angle_deg"] = float(np.degrees(np.arccos(np.clip(da, 0, 1))).max())
    return out
