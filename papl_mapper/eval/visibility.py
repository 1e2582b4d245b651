"""Which parts of ground-truth segments a recording shows: in front, inside the image, not occluded.

Recall against ground truth the camera never saw does not measure a mapper, so the line metrics also
score against the *visible clip* of the ground truth: every GT segment is cut into pieces no longer
than `spacing`, and a piece counts as seen in a frame when its midpoint is more than `near` in front
of the camera, projects inside the image, and no occluder quad lies between the camera and it.

Per frame and segment everything is an exact interval along the segment (its points are linear in
the segment parameter t): the view frustum is five half-spaces, and the region hidden by a convex
planar quad is the pyramid from the camera centre through its edges beyond the quad's plane (by more
than `margin`, so a segment lying on a quad is not hidden by it). Pieces only turn those intervals
into lengths; a visible length is exact to within a piece at each end of a visible run. The camera is
taken as a pinhole (lens distortion moves the image border a little; the synthetic recordings have none).
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from papl_mapper.errors import InputError
from papl_mapper.map import Camera, Map
from papl_mapper.synth.project import quads_in_view

log = logging.getLogger(__name__)

NEAR = 0.1
"""Closest depth (GT units) at which a point is seen; the synthetic observations use the same."""
OCCLUSION_MARGIN = 0.02
"""A point is hidden by a quad only when it lies more than this beyond the quad's plane (GT units)."""
DEFAULT_MIN_FRAMES = 5
"""Frames a part of a segment must be seen in to count as visible (`EvalConfig.line_visible_min_frames`)."""
_EPS = 1e-12


@dataclass
class Visibility:
    """GT segments (S, 2, 3) cut into pieces, and in how many frames each piece was seen."""

    endpoints: np.ndarray  # (S, 2, 3)
    axis: np.ndarray  # (S,) axis id per segment, -1 non-structural
    owner: np.ndarray  # (K,) segment of each piece, pieces of a segment are consecutive and in order
    t0: np.ndarray  # (K,) start of each piece along its segment, in [0, 1]
    t1: np.ndarray  # (K,) end of each piece
    frames: np.ndarray  # (K,) number of frames in which the piece's midpoint is seen
    n_frames: int  # frames tested
    occlusion: bool  # whether occluders were tested

    def piece_lengths(self) -> np.ndarray:
        """(K,) length of each piece."""
        L = np.linalg.norm(self.endpoints[:, 1] - self.endpoints[:, 0], axis=1)
        return (self.t1 - self.t0) * L[self.owner]

    def visible(self, min_frames: int) -> np.ndarray:
        """(K,) whether each piece is seen in at least `min_frames` frames."""
        return self.frames >= max(int(min_frames), 1)

    def visible_length(self, min_frames: int) -> np.ndarray:
        """(S,) length of each segment seen in at least `min_frames` frames."""
        w = self.piece_lengths() * self.visible(min_frames)
        return np.bincount(self.owner, weights=w, minlength=len(self.endpoints))

    def parts(self, min_frames: int) -> tuple[np.ndarray, np.ndarray]:
        """The visible clip: runs of consecutive visible pieces as segments (P, 2, 3) and their axis (P,)."""
        vis = self.visible(min_frames)
        if not vis.any():
            return np.zeros((0, 2, 3)), np.zeros(0, np.int64)
        k = np.arange(len(vis))
        prev_same = np.r_[False, vis[:-1] & (self.owner[1:] == self.owner[:-1])]
        next_same = np.r_[vis[1:] & (self.owner[1:] == self.owner[:-1]), False]
        starts = k[vis & ~prev_same]
        stops = k[vis & ~next_same]
        seg = self.owner[starts]
        a, d = self.endpoints[seg, 0], self.endpoints[seg, 1] - self.endpoints[seg, 0]
        ends = np.stack([a + self.t0[starts, None] * d, a + self.t1[stops, None] * d], axis=1)
        return ends, self.axis[seg]


def frustum_intervals(
    camera: Camera, T_wc: np.ndarray, endpoints_w: np.ndarray, near: float = NEAR
) -> tuple[np.ndarray, np.ndarray]:
    """(lo (S,), hi (S,)): the parameter range of each segment (S, 2, 3) in front of `near` and inside the
    image (pixel centres at integers, borders at -0.5 and size - 0.5); lo > hi where it is out of view."""
    T_cw = np.linalg.inv(T_wc)
    a = endpoints_w[:, 0] @ T_cw[:3, :3].T + T_cw[:3, 3]  # (S, 3) camera frame
    d = endpoints_w[:, 1] @ T_cw[:3, :3].T + T_cw[:3, 3] - a
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    W, H = camera.width, camera.height
    planes = np.array(  # rows (n, b): n . X_c + b >= 0 inside
        [
            [0.0, 0.0, 1.0, -near],
            [fx, 0.0, cx + 0.5, 0.0],
            [-fx, 0.0, W - 0.5 - cx, 0.0],
            [0.0, fy, cy + 0.5, 0.0],
            [0.0, -fy, H - 0.5 - cy, 0.0],
        ]
    )
    c0 = a @ planes[:, :3].T + planes[:, 3]  # (S, 5)
    c1 = d @ planes[:, :3].T
    return _clip(c0, c1, strict=False)


def occluded_intervals(
    centre: np.ndarray, quads: np.ndarray, endpoints_w: np.ndarray, margin: float = OCCLUSION_MARGIN
) -> tuple[np.ndarray, np.ndarray]:
    """(lo (S, Q), hi (S, Q)): the open parameter range of each segment hidden from `centre` by each
    convex planar quad (Q, 4, 3) (corners in order around it); lo >= hi where it hides nothing."""
    S, Q = len(endpoints_w), len(quads)
    lo, hi = np.ones((S, Q)), np.zeros((S, Q))
    si, qi, a, b = occluded_pairs(centre, quads, endpoints_w, margin)
    lo[si, qi], hi[si, qi] = a, b
    return lo, hi


def occluded_pairs(
    centre: np.ndarray, quads: np.ndarray, endpoints_w: np.ndarray, margin: float = OCCLUSION_MARGIN
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The (segment, quad) pairs where the quad hides part of the segment from `centre`, and that part:
    (segment index (P,), quad index (P,), lo (P,), hi (P,)), the open range (lo, hi) of the parameter."""
    A = endpoints_w[:, 0]  # (S, 3)
    D = endpoints_w[:, 1] - A
    n = np.cross(quads[:, 1] - quads[:, 0], quads[:, 3] - quads[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), _EPS)
    dc = np.einsum("qi,qi->q", n, centre - quads[:, 0])
    n *= np.where(dc > 0, -1.0, 1.0)[:, None]  # points away from the centre
    # "beyond the plane by more than margin" first: it rules out most pairs
    c0_pl = A @ n.T - np.einsum("qi,qi->q", n, quads[:, 0])[None] - margin  # (S, Q)
    c1_pl = D @ n.T
    beyond = (np.maximum(c0_pl, c0_pl + c1_pl) > 0) & (np.abs(dc) > 1e-9)[None]  # edge-on hides nothing
    si, qi = np.nonzero(beyond)
    if len(si) == 0:
        e = np.zeros(0)
        return si, qi, e, e
    rel = quads - centre  # (Q, 4, 3)
    n_side = np.cross(rel, np.roll(rel, -1, axis=1))  # (Q, 4, 3) planes through the centre and each edge
    mid = rel.mean(axis=1)  # (Q, 3)
    n_side *= np.where(np.einsum("qij,qj->qi", n_side, mid) < 0, -1.0, 1.0)[..., None]  # quad inside
    ns = n_side[qi]  # (P, 4, 3)
    c0 = np.concatenate([np.einsum("pki,pi->pk", ns, A[si] - centre), c0_pl[si, qi, None]], axis=1)
    c1 = np.concatenate([np.einsum("pki,pi->pk", ns, D[si]), c1_pl[si, qi, None]], axis=1)
    lo, hi = _clip(c0, c1, strict=True)
    keep = lo < hi
    return si[keep], qi[keep], lo[keep], hi[keep]


def _clip(c0: np.ndarray, c1: np.ndarray, strict: bool) -> tuple[np.ndarray, np.ndarray]:
    """The part of t in [0, 1] where every c0 + t c1 >= 0 (> 0 if strict), over the last axis."""
    with np.errstate(divide="ignore", invalid="ignore"):
        root = -c0 / c1
    lo = np.where(c1 > _EPS, root, -np.inf).max(axis=-1)
    hi = np.where(c1 < -_EPS, root, np.inf).min(axis=-1)
    flat = np.abs(c1) <= _EPS
    never = (flat & ((c0 <= 0) if strict else (c0 < 0))).any(axis=-1)
    lo = np.maximum(lo, 0.0)
    hi = np.minimum(hi, 1.0)
    lo[never] = 1.0
    hi[never] = 0.0
    return lo, hi


def segment_visibility(
    endpoints_w: np.ndarray,
    camera: Camera,
    T_wc: np.ndarray,
    spacing: float,
    occluders: np.ndarray | None = None,
    axis: np.ndarray | None = None,
    near: float = NEAR,
    margin: float = OCCLUSION_MARGIN,
) -> Visibility:
    """Count, for pieces of segments (S, 2, 3) no longer than `spacing`, the frames (poses T_wc (F, 4, 4))
    that see them; `occluders` (Q, 4, 3) are convex planar quads that hide what lies behind them."""
    ends = np.asarray(endpoints_w, np.float64).reshape(-1, 2, 3)
    T_wc = np.asarray(T_wc, np.float64).reshape(-1, 4, 4)
    if not spacing > 0:
        raise InputError(f"visibility sampling step must be > 0, got {spacing}")
    if camera.width <= 0 or camera.height <= 0:
        raise InputError(
            f"camera of size {camera.width}x{camera.height}: the visibility of the ground truth needs "
            "the image size; give a camera file with width and height"
        )
    L = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
    pieces = np.maximum(1, np.ceil(L / spacing)).astype(np.int64)
    owner = np.repeat(np.arange(len(ends)), pieces)
    start = np.cumsum(pieces) - pieces
    k = np.arange(len(owner)) - start[owner]
    n_of = pieces[owner]
    t0, t1 = k / n_of, (k + 1) / n_of
    tm = 0.5 * (t0 + t1)
    frames = np.zeros(len(owner), np.int64)
    quads = None if occluders is None else np.asarray(occluders, np.float64).reshape(-1, 4, 3)
    for T in T_wc:
        lo, hi = frustum_intervals(camera, T, ends, near)
        seen = (tm >= lo[owner]) & (tm <= hi[owner])
        segs = np.flatnonzero(lo <= hi)
        if quads is not None and len(quads) and len(segs):
            q = quads_in_view(quads, camera, T)
            if len(q):
                si, _, a, b = occluded_pairs(T[:3, 3], quads[q], ends[segs], margin)
                if len(si):
                    s = segs[si]
                    # pieces of s with a < tm < b, tm = (k + 0.5) / n: k in (a n - 0.5, b n - 0.5)
                    k_lo = np.floor(a * pieces[s] - 0.5).astype(np.int64) + 1
                    k_hi = np.ceil(b * pieces[s] - 0.5).astype(np.int64)  # exclusive
                    k_lo, k_hi = np.clip(k_lo, 0, pieces[s]), np.clip(k_hi, 0, pieces[s])
                    ok = k_lo < k_hi
                    diff = np.zeros(len(owner) + 1, np.int64)
                    np.add.at(diff, start[s[ok]] + k_lo[ok], 1)
                    np.add.at(diff, start[s[ok]] + k_hi[ok], -1)
                    seen &= np.cumsum(diff[:-1]) == 0
        frames += seen
    ax = np.full(len(ends), -1, np.int64) if axis is None else np.asarray(axis, np.int64).reshape(-1)
    return Visibility(ends, ax, owner, t0, t1, frames, len(T_wc), quads is not None)


def recording_camera(gt_folder: str | os.PathLike) -> tuple[Camera | None, str]:
    """The camera of the recording a ground-truth folder belongs to and where it came from:
    camera.json beside the gt/ folder (or in it), else gt/map.papl's camera; (None, why) when neither."""
    folder = Path(gt_folder)
    for path in (folder.parent / "camera.json", folder / "camera.json"):
        if path.is_file():
            from papl_mapper.frontend.camera import read_camera_file  # lazy: the frontend pulls OpenCV

            cam = read_camera_file(path)
            if cam.width > 0 and cam.height > 0:
                return cam, str(path)
    if (folder / "map.papl").is_file():
        cam = Map.load(folder / "map.papl").camera
        if cam.width > 0 and cam.height > 0:
            return cam, str(folder / "map.papl")
    return None, f"no camera.json beside {folder} and no gt/map.papl with an image size"


def scene_occluders(gt_folder: str | os.PathLike, endpoints_w: np.ndarray) -> tuple[np.ndarray | None, str]:
    """The quads of the synthetic scene named in scene.json beside the gt/ folder, when that scene's
    segments are the ground truth's; (None, why not) otherwise."""
    folder = Path(gt_folder)
    path = next((p for p in (folder.parent / "scene.json", folder / "scene.json") if p.is_file()), None)
    if path is None:
        return None, f"no scene.json beside {folder}: occlusion not tested (frustum only)"
    try:
        meta = json.loads(path.read_text())
        name, seed = str(meta["scene"]), int(meta.get("seed", 0))
    except (ValueError, KeyError, TypeError) as exc:
        return None, f"{path}: unreadable scene name/seed ({exc}): occlusion not tested (frustum only)"
    from papl_mapper.synth.scenes import make_scene  # lazy: only synthetic ground truth has a scene

    try:
        scene = make_scene(name, seed)
    except InputError as exc:
        return None, f"{path}: {exc}: occlusion not tested (frustum only)"
    gt = np.asarray(endpoints_w, np.float64).reshape(-1, 2, 3)
    if scene.segments.shape != gt.shape or not np.allclose(scene.segments, gt, atol=1e-4):
        return None, (
            f"{path}: scene '{name}' (seed {seed}) does not hold the ground-truth segments: "
            "occlusion not tested (frustum only)"
        )
    return scene.quad_corners, f"{path}: scene '{name}' seed {seed}, {len(scene.quad_corners)} quads"
