"""A tiny ray-cast room for frontend tests: textured box faces with rectangular panels.

The camera moves inside a convex box, so no face occludes another and the projected panel
edges are exact ground-truth segments (with ids). Faces carry low-contrast blurred noise (KLT
texture) and panels of distinct grey levels (the segments). World frame: x right, y down,
z forward, like an upright OpenCV camera at the identity pose.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from papl_mapper.map import Camera
from papl_mapper.synth.segment_scores import assign_to_gt
from papl_mapper.synth.segment_scores import covered_fraction as gt_covered

TEX_RES = 0.01  # metres per texel


@dataclass
class Face:
    origin: np.ndarray  # (3,) corner of the face
    u: np.ndarray  # (3,) first edge (full length)
    v: np.ndarray  # (3,) second edge
    texture: np.ndarray  # (H, W) uint8, texel (i, j) at origin + (j / W) u + (i / H) v
    panels: list  # list of (s0, t0, s1, t1) in [0, 1] face coordinates


@dataclass
class Room:
    faces: list[Face]
    segments_w: np.ndarray  # (G, 2, 3) panel edges, world
    segment_axis: np.ndarray  # (G,) 0 x, 1 y (vertical), 2 z


def _texture(w: int, h: int, rng: np.random.Generator, n_panels: int) -> tuple[np.ndarray, list]:
    noise = rng.normal(0, 1, (h // 4 + 1, w // 4 + 1)).astype(np.float32)
    noise = cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC)
    tex = 120 + 12 * noise / (noise.std() + 1e-6)
    panels = []
    tries = 0
    while len(panels) < n_panels and tries < 500:
        tries += 1
        s0, t0 = rng.uniform(0.05, 0.8, 2)
        s1, t1 = s0 + rng.uniform(0.08, 0.25), t0 + rng.uniform(0.08, 0.3)
        if s1 > 0.95 or t1 > 0.95:
            continue
        if any(
            not (s1 + 0.04 < a or s0 > c + 0.04 or t1 + 0.04 < b or t0 > d + 0.04) for a, b, c, d in panels
        ):
            continue
        panels.append((s0, t0, s1, t1))
        level = rng.choice([30.0, 60.0, 190.0, 225.0])
        tex[int(t0 * h) : int(t1 * h), int(s0 * w) : int(s1 * w)] = level + 4 * noise[
            int(t0 * h) : int(t1 * h), int(s0 * w) : int(s1 * w)
        ] / (noise.std() + 1e-6)
    return np.clip(tex, 0, 255).astype(np.uint8), panels


def make_room(seed: int = 0, size=(4.0, 2.6, 8.0), panels_per_face: int = 5) -> Room:
    """A box [-sx/2, sx/2] x [-sy/2, sy/2] x [-1, sz-1] seen from inside."""
    rng = np.random.default_rng(seed)
    sx, sy, sz = size
    x0, x1, y0, y1, z0, z1 = -sx / 2, sx / 2, -sy / 2, sy / 2, -1.0, sz - 1.0
    P = np.array
    specs = [  # origin, u, v
        (P([x0, y0, z1]), P([sx, 0, 0]), P([0, sy, 0])),  # far wall
        (P([x0, y0, z0]), P([0, 0, sz]), P([0, sy, 0])),  # left wall
        (P([x1, y0, z1]), P([0, 0, -sz]), P([0, sy, 0])),  # right wall
        (P([x0, y1, z0]), P([sx, 0, 0]), P([0, 0, sz])),  # floor
        (P([x0, y0, z1]), P([sx, 0, 0]), P([0, 0, -sz])),  # ceiling
    ]
    faces, segs, axes = [], [], []
    for origin, u, v in specs:
        w = int(np.linalg.norm(u) / TEX_RES)
        h = int(np.linalg.norm(v) / TEX_RES)
        tex, panels = _texture(w, h, rng, panels_per_face)
        faces.append(Face(origin.astype(float), u.astype(float), v.astype(float), tex, panels))
        for s0, t0, s1, t1 in panels:
            c = [origin + s * u + t * v for s, t in ((s0, t0), (s1, t0), (s1, t1), (s0, t1))]
            for a, b in ((0, 1), (1, 2), (2, 3), (3, 0)):
                segs.append((c[a], c[b]))
                axes.append(int(np.argmax(np.abs(c[b] - c[a]))))
    return Room(faces, np.array(segs), np.array(axes))


def look_pose(position: np.ndarray, yaw_deg: float = 0.0, pitch_deg: float = 0.0) -> np.ndarray:
    """T_wc of a camera at `position` turned by yaw (about world y) and pitch (about camera x)."""
    a, b = np.radians(yaw_deg), np.radians(pitch_deg)
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    T = np.eye(4)
    T[:3, :3] = Ry @ Rx
    T[:3, 3] = position
    return T


def render(room: Room, camera: Camera, T_wc: np.ndarray) -> np.ndarray:
    """Gray image (H, W) uint8 of the room by ray casting every pixel (bilinear texture lookup)."""
    w, h = camera.width, camera.height
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    rays_c = np.stack([(uu - camera.cx) / camera.fx, (vv - camera.cy) / camera.fy, np.ones_like(uu)], -1)
    R, c = T_wc[:3, :3], T_wc[:3, 3]
    # one product for every face: ray . (n, u, v) with the ray in world coordinates, r_w = R r_c
    basis = np.concatenate([np.stack([np.cross(f.u, f.v), f.u, f.v], 1) for f in room.faces], 1)  # (3, 3F)
    dots = rays_c.reshape(-1, 3) @ (R.T @ basis).astype(np.float32)  # (HW, 3F)
    best = np.full(h * w, np.inf, np.float32)
    out = np.zeros(h * w, np.float32)
    for k, f in enumerate(room.faces):
        n = np.cross(f.u, f.v)
        rn, ru, rv = dots[:, 3 * k], dots[:, 3 * k + 1], dots[:, 3 * k + 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = np.float32((f.origin - c) @ n) / rn
        co = c - f.origin
        s = (np.float32(co @ f.u) + lam * ru) / np.float32(f.u @ f.u)
        t = (np.float32(co @ f.v) + lam * rv) / np.float32(f.v @ f.v)
        ok = (lam > 0) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1) & (lam < best)
        if not ok.any():
            continue
        th, tw = f.texture.shape
        mx = np.where(ok, s * tw - 0.5, -1).astype(np.float32).reshape(h, w)
        my = np.where(ok, t * th - 0.5, -1).astype(np.float32).reshape(h, w)
        val = cv2.remap(f.texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()
        out[ok] = val[ok]
        best[ok] = lam[ok]
    return np.clip(out + 0.5, 0, 255).astype(np.uint8).reshape(h, w)


def project_segments(room: Room, camera: Camera, T_wc: np.ndarray, min_length_px: float = 20.0):
    """Visible GT segments in the image: (G', 4) pixels clipped to the image, their ids (G',)."""
    T_cw = np.linalg.inv(T_wc)
    P = room.segments_w.reshape(-1, 3) @ T_cw[:3, :3].T + T_cw[:3, 3]
    P = P.reshape(-1, 2, 3)
    out, ids = [], []
    for g, (a, b) in enumerate(P):
        za, zb = a[2], b[2]
        if za < 0.05 and zb < 0.05:
            continue
        if za < 0.05 or zb < 0.05:  # clip at the near plane
            t = (0.05 - za) / (zb - za)
            q = a + t * (b - a)
            a, b = (q, b) if za < 0.05 else (a, q)
        pa = camera.K @ a
        pb = camera.K @ b
        pa, pb = pa[:2] / pa[2], pb[:2] / pb[2]
        q1, q2 = _clip_float(pa, pb, camera.width - 1, camera.height - 1)
        if q1 is None or np.linalg.norm(q2 - q1) < min_length_px:
            continue
        out.append(np.concatenate([q1, q2]))
        ids.append(g)
    return np.array(out).reshape(-1, 4), np.array(ids, np.int64)


def _clip_float(a: np.ndarray, b: np.ndarray, xmax: float, ymax: float):
    """Liang-Barsky clip of a->b to [0, xmax] x [0, ymax]; (None, None) when outside."""
    d = b - a
    t0, t1 = 0.0, 1.0
    for p, q in ((-d[0], a[0]), (d[0], xmax - a[0]), (-d[1], a[1]), (d[1], ymax - a[1])):
        if abs(p) < 1e-12:
            if q < 0:
                return None, None
            continue
        r = q / p
        if p < 0:
            t0 = max(t0, r)
        else:
            t1 = min(t1, r)
        if t0 > t1:
            return None, None
    return a + t0 * d, a + t1 * d


def default_camera(width: int = 640, height: int = 480, hfov_deg: float = 70.0) -> Camera:
    f = (width / 2) / np.tan(np.radians(hfov_deg) / 2)
    return Camera(width, height, f, f, (width - 1) / 2, (height - 1) / 2, np.zeros(5))


@functools.lru_cache(maxsize=4)
def rendered_walk(n: int = 30, seed: int = 0, noise_sigma: float = 2.0):
    """n noisy gray frames of the walk through room `seed`, the camera, poses and projected GT.

    Cached for the test session (several test modules use the same frames); do not modify.
    """
    room = make_room(seed)
    cam = default_camera()
    poses = walk_poses(n)
    frames = []
    for k, T in enumerate(poses):
        img = render(room, cam, T).astype(np.float64)
        img += np.random.default_rng(k).normal(0, noise_sigma, img.shape)
        frames.append(np.clip(img, 0, 255).astype(np.uint8))
    gts = [project_segments(room, cam, T, min_length_px=25.0) for T in poses]
    return tuple(frames), cam, tuple(poses), tuple(gts)


def walk_poses(n: int, speed_m: float = 0.03, yaw_rate_deg: float = 0.3) -> list[np.ndarray]:
    """A forward walk with a slow turn and a slight pitch, n poses."""
    return [
        look_pose(np.array([0.1 * np.sin(0.05 * i), 0.0, speed_m * i]), yaw_rate_deg * i, -3.0 + 0.05 * i)
        for i in range(n)
    ]


def segment_match(det: np.ndarray, gt: np.ndarray, dist_px: float = 3.0, angle_deg: float = 3.0):
    """For each detection the GT row it lies on, or -1 (see papl_mapper.synth.segment_scores)."""
    return assign_to_gt(det, gt, dist_px, angle_deg)


def covered_fraction(det: np.ndarray, gt_seg: np.ndarray, match_rows: np.ndarray, g: int) -> float:
    """Fraction of GT segment g covered by the detections matched to it."""
    return float(gt_covered(det, gt_seg, match_rows)[g])


def test_renderer_projects_panel_edges_onto_intensity_steps():
    """Oracle check: image gradients are strong on projected GT edges."""
    room = make_room(0)
    cam = default_camera()
    T = look_pose(np.array([0.0, 0.0, 0.5]), 10.0, -3.0)
    img = render(room, cam, T)
    gt, _ = project_segments(room, cam, T)
    assert len(gt) > 20
    gx = cv2.Sobel(img.astype(np.float32), cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(img.astype(np.float32), cv2.CV_32F, 0, 1)
    mag = np.hypot(gx, gy)
    strong = []
    for x1, y1, x2, y2 in gt:
        t = np.linspace(0.2, 0.8, 10)
        xs = np.rint(x1 + t * (x2 - x1)).astype(int).clip(1, cam.width - 2)
        ys = np.rint(y1 + t * (y2 - y1)).astype(int).clip(1, cam.height - 2)
        m = np.maximum.reduce([mag[ys + dy, xs + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
        strong.append(np.median(m))
    assert np.median(strong) > 100


def backproject(room: Room, camera: Camera, T_wc: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """World points (N, 3) seen at pixels uv (N, 2): the nearest face hit by each pixel's ray."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    rays = np.column_stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy])
    rays = np.column_stack([rays, np.ones(len(uv))]) @ T_wc[:3, :3].T
    c = T_wc[:3, 3]
    best = np.full(len(uv), np.inf)
    for f in room.faces:
        n = np.cross(f.u, f.v)
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = ((f.origin - c) @ n) / (rays @ n)
        rel = c + rays * lam[:, None] - f.origin
        s = rel @ f.u / (f.u @ f.u)
        t = rel @ f.v / (f.v @ f.v)
        ok = (lam > 0) & (s >= -1e-6) & (s <= 1 + 1e-6) & (t >= -1e-6) & (t <= 1 + 1e-6)
        best = np.where(ok & (lam < best), lam, best)
    return c + rays * best[:, None]


def project(camera: Camera, T_wc: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of world points (N, 3)."""
    T_cw = np.linalg.inv(T_wc)
    Xc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    x = Xc @ camera.K.T
    return x[:, :2] / x[:, 2:3]
