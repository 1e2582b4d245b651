"""Vanishing directions and structural segments, Atlanta world with a vertical prior (paper "Structural
Preprocess", after Lu et al. 2017, "2-line exhaustive searching for real-time vanishing point
estimation in Manhattan world").

Everything works on camera-frame directions (OpenCV frame): a segment with endpoints s, e (pixels)
spans the plane with normal n = (K^-1 s~) x (K^-1 e~); a direction d is consistent with it when
n . d = 0, and its image vanishing point is K d. As in Lu et al., the intersections of segment pairs
are accumulated into a 1-degree grid on the (sign-folded) sphere, weighted by
sqrt(l_i l_j) (sin 2 dtheta + 0.2), and a set of directions is scored by the grid values at its cells.

- With a vertical prior: 360 proposals rotate a horizontal direction about the vertical at 1-degree
  steps; the best two horizontals are kept (Atlanta: any angle between them; Manhattan mode: the
  second is orthogonal to the first, which is the paper's proposal triple). By default they are
  scored by their line support measured directly (config.score; the grid's 1-degree cells miss sharp
  peaks of vanishing points near the image centre), or by the grid as Lu et al.
- Without one (ablation / first frames): the Manhattan 2-line search on the grid: a first direction
  from two random segments, the second exhaustively on its great circle at 1-degree steps, the third
  their cross product.
- Each direction is then refined by SVD on its inlier segments (the smallest right singular vector
  of the stacked segment normals), and segments are classified (index of a direction or -1).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from papl_mapper.errors import GeometryError, InputError
from papl_mapper.geometry.lines import line_angle_deg as _line_angle_deg

log = logging.getLogger(__name__)

UP_C = np.array([0.0, -1.0, 0.0])  # "up" in the image of an upright camera (OpenCV frame: y down)


@dataclass
class VPConfig:
    """Thresholds of vanishing-direction estimation; Lu et al.'s values where they give them."""

    min_length_px: float = 20.0
    """Segments shorter than this are classified but do not vote or refine."""
    max_grid_segments: int = 400
    """Longest segments used for the pairwise sphere grid (pairs grow quadratically)."""
    grid_step_deg: float = 1.0
    """Cell size of the latitude/longitude sphere grid (Lu et al.: 1 degree)."""
    pair_max_angle_deg: float = 60.0
    """Segment pairs whose image orientations differ by more than this do not vote (Lu et al.: 60)."""
    proposal_step_deg: float = 1.0
    """Step of the horizontal proposals about the vertical and of the 2-line search (paper: 1 degree)."""
    n_first_hypotheses: int = 105
    """Random segment pairs of the 2-line search without a prior (105 x 360 = 37,800 proposals, the
    paper's count); segments are drawn with probability proportional to length (Lu et al.: uniform)."""
    inlier_angle_deg: float = 2.0
    """A segment is structural for a direction when its image angle to the line from its midpoint
    to the vanishing point is below this."""
    refine_angle_deg: float = 2.0
    """Inlier angle for the SVD refinement sets."""
    refine_iterations: int = 5
    """Refine-then-reclassify rounds (iteratively reweighted)."""
    refine_cauchy_deg: float = 2.0
    """Scale of the Cauchy weight 1 / (1 + (angle / scale)^2) of a segment in the SVD refinement."""
    min_inliers: int = 3
    """Fewest inlier segments for a horizontal direction to be reported and refined."""
    min_horizontal_separation_deg: float = 10.0
    """The two Atlanta horizontals must differ by at least this."""
    vertical_max_tilt_deg: float = 35.0
    """Without a prior, the vertical is the found direction closest to the image y axis, if within this."""
    manhattan_only: bool = False
    """Second horizontal orthogonal to the first (Manhattan world) instead of the second-best peak."""
    orthogonal_preference: float = 0.0
    """Atlanta mode: take the horizontal orthogonal to the first when its support reaches this fraction
    of the best second's (0: the best second, whatever its angle)."""
    use_vertical_prior: bool = True
    """Use the given vertical to generate proposals; False ignores it (the paper's ablation)."""
    refine_svd: bool = True
    """Refine each direction by SVD on its inlier set (False: keep the 1-degree proposal)."""
    refine_vertical: bool = True
    """Also refine the vertical of this frame on its inliers (the tracker consumes it)."""
    track_gate_deg: float = 5.0
    """The tracker takes a frame's refined vertical only if within this of the predicted vertical."""
    track_gain: float = 0.3
    """Blend weight of a frame's refined vertical in the tracked vertical."""
    score: Literal["support", "grid"] = "support"
    """How the horizontal proposals about the vertical are scored: "grid" is Lu et al.'s sphere grid
    (cells at 1 degree miss sharp peaks near the image centre); "support" sums, over segments not
    explained by the vertical, length x (1 - (angle / support_angle_deg)^2)_+ (Lu et al.'s line support
    measured directly), the second Atlanta horizontal on the segments the first one leaves."""
    support_angle_deg: float = 3.0
    """Angle scale of the "support" score (image angle between a segment and the VP direction)."""


@dataclass
class VPResult:
    """Vanishing directions of one frame and the structural labels of its segments."""

    dirs_c: np.ndarray  # (V, 3) unit camera-frame directions; row 0 vertical when vertical_index == 0
    labels: np.ndarray  # (S,) int64 index into dirs_c, -1 non-structural
    vertical_index: int = -1  # 0 or -1
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (V,) proposal score (grid or support)
    inlier_counts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (V,)
    method: str = ""  # "vertical-prior-atlanta", "vertical-prior-manhattan" or "two-line-manhattan"

    @property
    def vertical_c(self) -> np.ndarray | None:
        return self.dirs_c[0] if self.vertical_index == 0 else None


# ---- segment geometry -----------------------------------------------------------------------------


@dataclass
class _Segments:
    seg: np.ndarray  # (S, 4) px
    normals: np.ndarray  # (S, 3) unit plane normals in the camera frame
    length: np.ndarray  # (S,) px
    orient: np.ndarray  # (S,) image orientation in [0, pi)
    valid: np.ndarray  # (S,) bool: long enough and non-degenerate


def _check_inputs(segments: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    seg = np.asarray(segments, np.float64)
    if seg.ndim != 2 or seg.shape[1] != 4:
        raise InputError(f"segments: expected an (S, 4) array x1 y1 x2 y2, got shape {seg.shape}")
    K = np.asarray(K, np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or abs(np.linalg.det(K)) < 1e-12:
        raise InputError(f"camera matrix K: expected a finite invertible 3x3 matrix, got {K!r}")
    return seg, K


def _prepare(segments: np.ndarray, K: np.ndarray, config: VPConfig) -> _Segments:
    seg, K = _check_inputs(segments, K)
    Kinv = np.linalg.inv(K)
    ones = np.ones((len(seg), 1))
    a = np.hstack([seg[:, :2], ones]) @ Kinv.T  # (S, 3)
    b = np.hstack([seg[:, 2:], ones]) @ Kinv.T
    n = _cross(a, b)
    nn = np.linalg.norm(n, axis=1)
    d = seg[:, 2:] - seg[:, :2]
    length = np.hypot(d[:, 0], d[:, 1])
    finite = np.all(np.isfinite(seg), axis=1)
    valid = finite & (nn > 1e-12) & (length >= config.min_length_px)
    normals = np.zeros_like(n)
    normals[nn > 1e-12] = n[nn > 1e-12] / nn[nn > 1e-12, None]
    orient = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi)
    return _Segments(seg, normals, length, orient, valid)


def _cross_dot(seg: np.ndarray, K: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(S, V) |u x w| and |u . w| of each segment direction u and the direction w from its midpoint
    towards each VP (homogeneous, up to scale): two (S, 3) @ (3, V) products instead of (S, V, 2) arrays.

    With vp = K d = (a, b, c) and midpoint m: w = (a - c m_x, b - c m_y), so
    u x w = u_x b - u_y a + c (u_y m_x - u_x m_y) and u . w = u_x a + u_y b - c (u . m).
    """
    vp = dirs @ K.T  # (V, 3) homogeneous vanishing points
    mid = 0.5 * (seg[:, :2] + seg[:, 2:])  # (S, 2)
    u = seg[:, 2:] - seg[:, :2]  # (S, 2)
    ux, uy = u[:, 0], u[:, 1]
    A_cross = np.stack([-uy, ux, uy * mid[:, 0] - ux * mid[:, 1]], axis=1)  # (S, 3) against (a, b, c)
    A_dot = np.stack([ux, uy, -(ux * mid[:, 0] + uy * mid[:, 1])], axis=1)
    return np.abs(A_cross @ vp.T), np.abs(A_dot @ vp.T)


def _degenerate(seg: np.ndarray, cross: np.ndarray, dot: np.ndarray) -> np.ndarray:
    """(S, V) True where the segment or its midpoint-to-VP direction has (near) zero length."""
    u2 = np.square(seg[:, 2] - seg[:, 0]) + np.square(seg[:, 3] - seg[:, 1])  # (S,)
    # |u|^2 |w|^2 = cross^2 + dot^2; degenerate when |u| < 1e-9 or |w| < 1e-9
    return (u2 < 1e-18)[:, None] | (np.square(cross) + np.square(dot) < 1e-18 * u2[:, None])


def segment_vp_angles_deg(segments: np.ndarray, K: np.ndarray, dirs_c: np.ndarray) -> np.ndarray:
    """(S, V) image angle (0..90 deg) between each segment and the line from its midpoint to each VP."""
    seg, K = _check_inputs(segments, K)
    dirs = np.asarray(dirs_c, np.float64).reshape(-1, 3)
    cross, dot = _cross_dot(seg, K, dirs)
    ang = np.degrees(np.arctan2(cross, dot))
    ang[_degenerate(seg, cross, dot)] = 90.0
    return ang


def classify_segments(
    segments: np.ndarray, K: np.ndarray, dirs_c: np.ndarray, config: VPConfig | None = None
) -> np.ndarray:
    """(S,) index of the closest vanishing direction within config.inlier_angle_deg, else -1."""
    config = config or VPConfig()
    dirs = np.asarray(dirs_c, np.float64).reshape(-1, 3)
    if len(dirs) == 0 or len(segments) == 0:
        return np.full(len(segments), -1, np.int64)
    ang = segment_vp_angles_deg(segments, K, dirs)
    best = np.argmin(ang, axis=1)
    ok = ang[np.arange(len(best)), best] < config.inlier_angle_deg
    return np.where(ok, best, -1).astype(np.int64)


# ---- the sphere grid of Lu et al. --------------------------------------------------------------------


class _SphereGrid:
    """Accumulated segment-pair intersections on a latitude/longitude grid over the folded sphere."""

    def __init__(self, s: _Segments, config: VPConfig):
        self.step = np.radians(config.grid_step_deg)
        self.n_lat = int(round(90.0 / config.grid_step_deg))
        self.n_lon = int(round(360.0 / config.grid_step_deg))
        grid = np.zeros((self.n_lat, self.n_lon))
        idx = np.flatnonzero(s.valid)
        if len(idx) > config.max_grid_segments:
            idx = idx[np.argsort(-s.length[idx])[: config.max_grid_segments]]
        if len(idx) >= 2:
            i, j = np.triu_indices(len(idx), k=1)
            i, j = idx[i], idx[j]
            dev = np.abs(s.orient[i] - s.orient[j])
            dev = np.minimum(dev, np.pi - dev)
            keep = dev <= np.radians(config.pair_max_angle_deg)
            i, j, dev = i[keep], j[keep], dev[keep]
            p = _cross(s.normals[i], s.normals[j])
            pn = np.linalg.norm(p, axis=1)
            ok = pn > 1e-12
            p = p[ok] / pn[ok, None]
            w = np.sqrt(s.length[i[ok]] * s.length[j[ok]]) * (np.sin(2.0 * dev[ok]) + 0.2)
            la, lo = self.cells(p)
            np.add.at(grid, (la, lo), w)
        self.raw = grid
        self.grid = self._smooth(grid)

    def cells(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = np.where(d[:, 2:3] < 0.0, -d, d)  # fold: d and -d are one vanishing point
        lat = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
        lon = np.arctan2(d[:, 0], d[:, 1]) + np.pi
        la = np.clip((lat / self.step).astype(np.int64), 0, self.n_lat - 1)
        lo = np.mod((lon / self.step).astype(np.int64), self.n_lon)
        return la, lo

    def _smooth(self, g: np.ndarray) -> np.ndarray:
        """3x3 binomial filter; longitude wraps, the equator row continues at longitude + 180."""
        half = self.n_lon // 2
        pad = np.vstack([g[:1], g, np.roll(g[-1:], half, axis=1)])  # pole: clamp; equator: antipode
        pad = np.hstack([pad[:, -1:], pad, pad[:, :1]])
        k = np.array([1.0, 2.0, 1.0])
        rows = k[0] * pad[:-2] + k[1] * pad[1:-1] + k[2] * pad[2:]
        out = k[0] * rows[:, :-2] + k[1] * rows[:, 1:-1] + k[2] * rows[:, 2:]
        return out / 16.0

    def score(self, d: np.ndarray) -> np.ndarray:
        """Grid value at each direction (..., 3)."""
        shape = d.shape[:-1]
        la, lo = self.cells(d.reshape(-1, 3))
        return self.grid[la, lo].reshape(shape)


# ---- helpers -----------------------------------------------------------------------------------------


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis of (..., 3) arrays (np.cross without its axis handling overhead)."""
    a, b = np.broadcast_arrays(a, b)
    out = np.empty(a.shape, np.result_type(a, b, np.float64))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _perpendicular(v: np.ndarray) -> np.ndarray:
    """Unit vectors perpendicular to v (3,) or (N, 3) (paper: d_h = [cos b, -sin b, 0] for polar d_v)."""
    helper = np.where(np.abs(v[..., 2:3]) < 0.9, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    return _unit(_cross(v, helper))


def _sign_up(v: np.ndarray) -> np.ndarray:
    return -v if v @ UP_C < 0 else v


def _sign_horizontal(v: np.ndarray) -> np.ndarray:
    """Stable sign for non-vertical directions: in front of the camera, else pointing right."""
    if abs(v[2]) > 1e-6:
        return v if v[2] > 0 else -v
    return v if v[0] >= 0 else -v


def _inlier_sets(
    s: _Segments, K: np.ndarray, dirs: np.ndarray, thr_deg: float
) -> tuple[list[np.ndarray], np.ndarray]:
    """Per direction, the valid segments closest to it within thr_deg; and the (S, V) angles."""
    if len(dirs) == 0:
        return [], np.zeros((len(s.seg), 0))
    ang = segment_vp_angles_deg(s.seg, K, dirs)  # (S, V)
    best = np.argmin(ang, axis=1)
    ok = s.valid & (ang[np.arange(len(best)), best] < thr_deg)
    return [np.flatnonzero(ok & (best == j)) for j in range(len(dirs))], ang


def _svd_direction(s: _Segments, idx: np.ndarray, d0: np.ndarray, robust_w: np.ndarray) -> np.ndarray:
    """Smallest right singular vector of the weighted segment normals (paper: M x = 0), signed like d0.

    Rows are weighted by sqrt(length) (longer segments are better measured) times a Cauchy weight of
    their current angle, so that a stray segment just inside the inlier angle barely pulls."""
    M = s.normals[idx] * (np.sqrt(s.length[idx]) * robust_w)[:, None]
    d = np.linalg.svd(M, full_matrices=False)[2][-1]
    return d if d @ d0 >= 0 else -d


# ---- estimation ----------------------------------------------------------------------------------------


def _two_line_search(
    s: _Segments, grid: _SphereGrid, config: VPConfig, seed: int
) -> tuple[np.ndarray, float]:
    """Lu et al.'s Manhattan search: (3, 3) orthogonal directions with the best summed grid score."""
    idx = np.flatnonzero(s.valid)
    if len(idx) < 2:
        raise GeometryError(f"vanishing points: {len(idx)} usable segments (need at least 2 long ones)")
    rng = np.random.default_rng(seed)
    p = s.length[idx] / s.length[idx].sum()
    a = rng.choice(idx, size=config.n_first_hypotheses, p=p)
    b = rng.choice(idx, size=config.n_first_hypotheses, p=p)
    v1 = _cross(s.normals[a], s.normals[b])  # (H, 3)
    n1 = np.linalg.norm(v1, axis=1)
    ok = n1 > 1e-9
    if not ok.any():
        raise GeometryError("vanishing points: all sampled segment pairs are collinear")
    v1 = v1[ok] / n1[ok, None]
    base = _perpendicular(v1)  # (H, 3)
    other = _cross(v1, base)
    theta = np.radians(np.arange(0.0, 360.0, config.proposal_step_deg))
    v2 = np.cos(theta)[None, :, None] * base[:, None, :] + np.sin(theta)[None, :, None] * other[:, None, :]
    v3 = _cross(v1[:, None, :], v2)
    score = grid.score(v1)[:, None] + grid.score(v2) + grid.score(v3)  # (H, T)
    h, t = np.unravel_index(np.argmax(score), score.shape)
    return np.stack([v1[h], v2[h, t], v3[h, t]]), float(score[h, t])


def _pick_vertical(dirs: np.ndarray, config: VPConfig) -> int:
    """Index of the direction closest to the image y axis if within the tilt limit, else -1."""
    ang = _line_angle_deg(dirs, UP_C[None])
    j = int(np.argmin(ang))
    return j if ang[j] <= config.vertical_max_tilt_deg else -1


def _support(s: _Segments, K: np.ndarray, dirs: np.ndarray, mask: np.ndarray, config: VPConfig) -> np.ndarray:
    """(S, T) line support of each segment for each direction: length x (1 - (angle / tol)^2)_+ .

    The angle (arctan) is evaluated only where it is below tol (cross < tan(tol) dot), a small part of
    the (S, T) grid of segments and proposals.
    """
    seg = s.seg[mask]
    cross, dot = _cross_dot(seg, K, np.asarray(dirs, np.float64).reshape(-1, 3))
    near = (cross < np.tan(np.radians(config.support_angle_deg)) * dot) & ~_degenerate(seg, cross, dot)
    w = np.zeros(cross.shape)
    ang = np.degrees(np.arctan2(cross[near], dot[near]))
    w[near] = np.clip(1.0 - (ang / config.support_angle_deg) ** 2, 0.0, None)
    return w * s.length[mask, None]


def _horizontal_proposals(
    s: _Segments, K: np.ndarray, dv: np.ndarray, grid: _SphereGrid | None, config: VPConfig
) -> tuple[list[np.ndarray], list[float]]:
    """Best horizontal directions about the vertical dv: two peaks (Atlanta) or an orthogonal pair.

    Proposals rotate a horizontal about dv at proposal_step_deg (the paper's 360). With
    config.score == "grid" each is scored by Lu et al.'s sphere grid; with "support" by the
    length-weighted support of the segments not explained by the vertical, the second Atlanta
    horizontal scored on the segments the first one leaves unexplained.
    """
    base = _perpendicular(dv)
    other = _cross(dv, base)
    theta = np.radians(np.arange(0.0, 360.0, config.proposal_step_deg))
    dh = np.cos(theta)[:, None] * base[None] + np.sin(theta)[:, None] * other[None]  # (T, 3)
    dh2 = _cross(dv[None], dh)  # (T, 3) the Manhattan partner of each proposal
    if grid is not None:
        s1 = grid.score(dh)
        if config.manhattan_only:
            i = int(np.argmax(s1 + grid.score(dh2)))
            return [dh[i], dh2[i]], [float(s1[i]), float(grid.score(dh2[i][None])[0])]
        i = int(np.argmax(s1))
        sep = _line_angle_deg(dh, dh[i][None])
        peak = (s1 >= np.roll(s1, 1)) & (s1 >= np.roll(s1, -1)) & (s1 > 0)
        peak &= sep >= config.min_horizontal_separation_deg
        if not peak.any():
            return [dh[i]], [float(s1[i])]
        j = int(np.flatnonzero(peak)[np.argmax(s1[peak])])
        return [dh[i], dh[j]], [float(s1[i]), float(s1[j])]
    # line support, segments of the vertical excluded
    vert = segment_vp_angles_deg(s.seg, K, dv[None])[:, 0] < config.support_angle_deg
    mask = s.valid & ~vert
    if not mask.any():
        return [], []
    sup = _support(s, K, dh, mask, config)  # (S', T)
    if config.manhattan_only:
        sup2 = _support(s, K, dh2, mask, config)
        total = np.maximum(sup, sup2).sum(axis=0)  # a segment supports the pair once
        i = int(np.argmax(total))
        return [dh[i], dh2[i]], [float(sup[:, i].sum()), float(sup2[:, i].sum())]
    # the best proposal, then the best on the segments it leaves unexplained
    s1 = sup.sum(axis=0)
    i = int(np.argmax(s1))
    s2 = sup[sup[:, i] <= 0].sum(axis=0)
    s2[_line_angle_deg(dh, dh[i][None]) < config.min_horizontal_separation_deg] = -1.0
    j = int(np.argmax(s2))
    if s2[j] <= 0:
        return [dh[i]], [float(s1[i])]
    if config.orthogonal_preference > 0.0:
        k = int(np.argmin(np.abs(dh @ dh[i])))  # the proposal orthogonal to the first
        if s2[k] >= config.orthogonal_preference * s2[j]:
            j = k
    return [dh[i], dh[j]], [float(s1[i]), float(s2[j])]


def _finish(
    s: _Segments,
    K: np.ndarray,
    dirs: list[np.ndarray],
    scores: list[float],
    vertical_index: int,
    fixed: set[int],
    config: VPConfig,
    method: str,
    prior: bool,
) -> VPResult:
    """SVD refinement rounds, removal of weak or duplicate directions, classification, signs.

    A vertical given as a prior is always kept; one found by the search needs min_inliers segments
    like the horizontals (a Manhattan triple from two horizontals implies an unsupported vertical)."""
    D = np.array(dirs, np.float64).reshape(-1, 3)
    if config.refine_svd:
        for _ in range(max(1, config.refine_iterations)):
            sets, ang = _inlier_sets(s, K, D, config.refine_angle_deg)
            for j, idx in enumerate(sets):
                if j not in fixed and len(idx) >= max(2, config.min_inliers):
                    robust = 1.0 / (1.0 + (ang[idx, j] / config.refine_cauchy_deg) ** 2)
                    D[j] = _svd_direction(s, idx, D[j], robust)
    sets, _ = _inlier_sets(s, K, D, config.inlier_angle_deg)
    keep: list[int] = []
    for j in range(len(D)):
        if j == vertical_index and (prior or len(sets[j]) >= config.min_inliers):
            keep.append(j)
            continue
        if len(sets[j]) < config.min_inliers:
            continue
        if keep and _line_angle_deg(D[keep], D[j][None]).min() < config.min_horizontal_separation_deg:
            continue
        keep.append(j)
    D = D[keep]
    scores_arr = np.asarray(scores, np.float64)[keep]
    vi = keep.index(vertical_index) if vertical_index in keep else -1
    if vi > 0:  # row 0 is the vertical
        order = [vi] + [k for k in range(len(D)) if k != vi]
        D, scores_arr, vi = D[order], scores_arr[order], 0
    D = np.array([_sign_up(d) if k == vi else _sign_horizontal(d) for k, d in enumerate(D)]).reshape(-1, 3)
    labels = classify_segments(s.seg, K, D, config)
    counts = np.bincount(labels[labels >= 0], minlength=len(D)).astype(np.int64)
    return VPResult(D, labels, vi, scores_arr, counts, method)


def estimate_frame(
    segments: np.ndarray,
    K: np.ndarray,
    vertical_c: np.ndarray | None = None,
    config: VPConfig | None = None,
    seed: int = 0,
) -> VPResult:
    """Vanishing directions of one frame from its undistorted segments (S, 4) in pixels.

    With `vertical_c` (and config.use_vertical_prior): the vertical plus the best two horizontals of
    the 360 proposals about it; otherwise Lu et al.'s Manhattan 2-line search, its vertical being the
    direction nearest the image y axis when within config.vertical_max_tilt_deg (its random segment
    pairs drawn with `seed`). Raises GeometryError when fewer than two usable segments remain.
    """
    config = config or VPConfig()
    s = _prepare(segments, K, config)
    K = np.asarray(K, np.float64)
    if vertical_c is not None and config.use_vertical_prior:
        dv = np.asarray(vertical_c, np.float64).reshape(3)
        if not np.all(np.isfinite(dv)) or np.linalg.norm(dv) < 1e-12:
            raise GeometryError(f"vertical prior {dv} is zero or non-finite; pass None to search without it")
        dv = _sign_up(dv / np.linalg.norm(dv))
        if int(s.valid.sum()) < 2:
            raise GeometryError(f"vanishing points: {int(s.valid.sum())} usable segments (need at least 2)")
        grid = _SphereGrid(s, config) if config.score == "grid" else None
        hs, hscores = _horizontal_proposals(s, K, dv, grid, config)
        dirs = [dv, *hs]
        if grid is not None:
            v_score = float(grid.score(dv[None])[0])
        else:
            v_score = float(_support(s, K, dv[None], s.valid, config).sum())
        scores = [v_score, *hscores]
        fixed = set() if config.refine_vertical else {0}
        method = "vertical-prior-manhattan" if config.manhattan_only else "vertical-prior-atlanta"
        return _finish(s, K, dirs, scores, 0, fixed, config, method, prior=True)
    grid = _SphereGrid(s, config)
    triple, _ = _two_line_search(s, grid, config, seed)
    vi = _pick_vertical(triple, config)
    scores = [float(x) for x in grid.score(triple)]
    return _finish(s, K, list(triple), scores, vi, set(), config, "two-line-manhattan", prior=False)


def estimate_vertical(
    segments_list: list[np.ndarray], K: np.ndarray, config: VPConfig | None = None, seed: int = 0
) -> np.ndarray:
    """Camera-frame unit vertical (pointing up, -y for an upright camera) from early frames.

    Each frame runs the Manhattan 2-line search without a prior (with SVD refinement per config);
    the frames' verticals are sign-aligned and the largest group agreeing within track_gate_deg is
    averaged. Raises GeometryError when no frame shows a near-vertical direction.
    """
    config = config or VPConfig()
    found = []
    for segs in segments_list:
        try:
            res = estimate_frame(segs, K, None, config, seed)
        except GeometryError as exc:
            log.debug("vertical: frame skipped (%s)", exc)
            continue
        if res.vertical_index == 0:
            found.append(res.dirs_c[0])
    if not found:
        raise GeometryError(
            f"no near-vertical vanishing direction (within {config.vertical_max_tilt_deg} deg of the image "
            f"y axis) in {len(segments_list)} frames; give more frames with vertical structure"
        )
    V = np.array([_sign_up(v) for v in found])
    agree = _line_angle_deg(V[:, None, :], V[None, :, :]) <= config.track_gate_deg  # (F, F)
    best = int(np.argmax(agree.sum(axis=1)))
    return _sign_up(_unit(V[agree[best]].mean(axis=0)))


def update_vertical(
    vertical_c: np.ndarray,
    measured_c: np.ndarray | None = None,
    R_cur_prev: np.ndarray | None = None,
    config: VPConfig | None = None,
) -> np.ndarray:
    """Track the vertical: rotate the previous frame's vertical by R_cur_prev (x_cur = R x_prev) when
    given, then blend in this frame's refined vertical if it agrees within config.track_gate_deg."""
    config = config or VPConfig()
    v = np.asarray(vertical_c, np.float64).reshape(3)
    if R_cur_prev is not None:
        v = np.asarray(R_cur_prev, np.float64) @ v
    v = _sign_up(_unit(v))
    if measured_c is not None:
        m = _unit(np.asarray(measured_c, np.float64).reshape(3))
        m = m if m @ v >= 0 else -m
        if _line_angle_deg(m, v) <= config.track_gate_deg:
            v = _unit((1.0 - config.track_gain) * v + config.track_gain * m)
    return _sign_up(v)
