"""ArUco markers of known size stuck on a scene's walls, where the walk sees them face-on from 1-3 m
(on boards standing beside the walk where no wall comes that close, as in an open plaza).

Each marker is made of plain quads (a white quiet zone 1 mm off the wall, black cells 2 mm off), so
the renderer draws it like any other surface. Placement is seeded and only adds quads and
materials after the scene is built, so scenes without markers stay exactly as they were.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from papl_mapper.errors import InputError
from papl_mapper.map import Camera
from papl_mapper.synth.project import occluded, project
from papl_mapper.synth.scenes import Material, Scene

BLACK = Material("marker black", (0.02, 0.02, 0.02), contrast=0.0)
WHITE = Material("marker white", (0.92, 0.92, 0.92), contrast=0.0)
#: marker views that count: distance (m) and largest angle off the marker's normal (deg)
VIEW_DISTANCE_M = (1.0, 3.0)
VIEW_ANGLE_DEG = 60.0


def marker_bits(dictionary: str, marker_id: int) -> np.ndarray:
    """(n+2, n+2) bool, True where the marker (with its one-cell black border) is black."""
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, f"DICT_{dictionary}"))
    cells = d.markerSize + 2
    img = cv2.aruco.generateImageMarker(d, marker_id, cells, borderBits=1)
    return img < 128


def _candidates(scene: Scene, size: float, height: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """(centre, unit horizontal tangent) every 0.4 m along the walls at `height`, fully inside."""
    out = []
    half = size * 8 / 12  # half the quiet zone's side: a cell of white round the black square
    for c in scene.quad_corners:
        u, v = c[1] - c[0], c[3] - c[0]
        n = np.cross(u, v)
        n /= np.linalg.norm(n)
        if abs(n[2]) > 0.05:
            continue  # not a wall
        zmin, zmax = c[:, 2].min(), c[:, 2].max()
        if not zmin + half <= height <= zmax - half:
            continue
        t = np.cross([0.0, 0.0, 1.0], n)
        t /= np.linalg.norm(t)
        s = (c - c[0]) @ t
        lo, hi = s.min() + half, s.max() - half
        for x in np.arange(lo, hi + 1e-9, 0.4):
            base = c[0] + x * t
            out.append((np.array([base[0], base[1], height]), t))
    return out


def _score(scene: Scene, camera: Camera, frames: np.ndarray, candidates, size_m: float) -> list[tuple]:
    """(views, centre, right, outward normal) of the candidates seen whole and unoccluded, face-on from
    1-3 m, in at least 6 of `frames`."""
    centres_cam = frames[:, :3, 3]
    scored = []
    for centre, t in candidates:
        n = np.cross(t, [0.0, 0.0, 1.0])
        for n_out in (n, -n):  # a wall is seen from one side, or from both (a partition)
            to_cam = centres_cam - centre
            dist = np.linalg.norm(to_cam, axis=1)
            cos = (to_cam @ n_out) / dist
            near = (dist >= VIEW_DISTANCE_M[0]) & (dist <= VIEW_DISTANCE_M[1])
            near &= cos >= math.cos(math.radians(VIEW_ANGLE_DEG))
            if near.sum() < 6:
                continue
            right = np.cross([0.0, 0.0, 1.0], n_out)
            corners = _corners(centre + 0.002 * n_out, right, size_m)
            seen = sum(_sees(scene, camera, T, corners) for T in frames[near])
            if seen >= 6:
                scored.append((seen, centre, right, n_out))
    return scored


def _boards(scene: Scene, T_wc: np.ndarray, height: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """(centre, tangent) of free-standing boards 2.5 m ahead of the walk and 1.2 m to its side, in free
    space at least 0.8 m from every camera position, facing back along the walk."""
    path = T_wc[:, :3, 3]
    out = []
    for T in T_wc[:: max(1, len(T_wc) // 40)]:
        f = T[:3, 2].copy()
        f[2] = 0
        if np.linalg.norm(f) < 1e-6:
            continue
        f /= np.linalg.norm(f)
        side = np.cross([0.0, 0.0, 1.0], f)
        for sign in (1.0, -1.0):
            c = T[:3, 3] + 2.5 * f + sign * 1.2 * side
            c[2] = height
            if not scene.in_free_space(c[None, :2], margin=0.3)[0]:
                continue
            if np.linalg.norm(path[:, :2] - c[:2], axis=1).min() < 0.8:
                continue
            n = T[:3, 3] - c
            n[2] = 0
            n /= np.linalg.norm(n)
            out.append((c, np.cross([0.0, 0.0, 1.0], n)))  # tangent: its normal n faces the walker
    return out


def place_markers(
    scene: Scene,
    camera: Camera,
    T_wc: np.ndarray,
    count: int,
    size_m: float,
    dictionary: str,
    seed: int,
) -> tuple[Scene, list[dict]]:
    """The scene with `count` markers (ids 0..count-1) added, and each marker's ground truth."""
    rng = np.random.default_rng([seed, 97])
    frames = T_wc[:: max(1, len(T_wc) // 120)]
    height = float(np.median(frames[:, 2, 3])) - 0.15
    scored = _score(scene, camera, frames, _candidates(scene, size_m, height), size_m)
    if len(scored) < count:  # no wall near the walk (an open plaza): boards standing beside it
        scored += _score(scene, camera, frames, _boards(scene, T_wc, height), size_m)
    if len(scored) < count:
        raise InputError(
            f"scene {scene.name}: only {len(scored)} wall places see the walk face-on for markers"
        )
    chosen: list[tuple] = []
    order = rng.permutation(len(scored))
    best = max(s[0] for s in scored)
    for i in order:
        s = scored[i]
        if s[0] < 0.5 * best or any(np.linalg.norm(s[1] - c[1]) < 1.5 for c in chosen):
            continue
        chosen.append(s)
        if len(chosen) == count:
            break
    if len(chosen) < count:
        raise InputError(f"scene {scene.name}: room for {len(chosen)} markers 1.5 m apart, not {count}")
    quads, mats, truth = [], [], []
    n_mat = len(scene.materials)
    for marker_id, (_, centre, right, n_out) in enumerate(chosen):
        quads += _marker_quads(marker_bits(dictionary, marker_id), centre, right, n_out, size_m)
        corners = _corners(centre + 0.002 * n_out, right, size_m)
        truth.append(
            {
                "dictionary": dictionary,
                "id": marker_id,
                "size_m": size_m,
                "corners_w": corners.tolist(),  # ArUco order: top-left, top-right, bottom-right, bottom-left
                "normal_w": n_out.tolist(),
            }
        )
    mats = [n_mat if white else n_mat + 1 for _, white in quads]
    corners = np.array([c for c, _ in quads])
    p0, u, v = corners[:, 0], corners[:, 1] - corners[:, 0], corners[:, 3] - corners[:, 0]
    out = dataclasses.replace(
        scene,
        quad_corners=np.concatenate([scene.quad_corners, corners]),
        quad_material=np.concatenate([scene.quad_material, np.array(mats, np.int64)]),
        tex_origin=np.concatenate([scene.tex_origin, p0]),
        tex_u=np.concatenate([scene.tex_u, u / np.linalg.norm(u, axis=1, keepdims=True)]),
        tex_v=np.concatenate([scene.tex_v, v / np.linalg.norm(v, axis=1, keepdims=True)]),
        materials=[*scene.materials, WHITE, BLACK],
    )
    return out, truth


def _sees(scene: Scene, camera: Camera, T_wc: np.ndarray, corners: np.ndarray) -> bool:
    """Whether all four corners are in the image and nothing stands in front of them (to 0.1 mm: the
    other face of a thin wall is 1 cm behind its front face)."""
    uv, z = project(camera, T_wc, corners)
    inside = (
        (uv[:, 0] >= 8) & (uv[:, 0] <= camera.width - 9) & (uv[:, 1] >= 8) & (uv[:, 1] <= camera.height - 9)
    )
    if not ((z > 0.1) & inside).all():
        return False
    return not occluded(scene, T_wc[:3, 3], corners, margin=1e-4).any()


def _corners(centre: np.ndarray, right: np.ndarray, size: float) -> np.ndarray:
    """(4, 3) the black square's corners, top-left first, clockwise as seen from the front."""
    up = np.array([0.0, 0.0, 1.0])
    h = size / 2
    return np.array([centre - h * right + h * up, centre + h * right + h * up,
                     centre + h * right - h * up, centre - h * right - h * up])  # fmt: skip


def _marker_quads(bits, centre, right, n_out, size) -> list[tuple[np.ndarray, bool]]:
    """(corners (4, 3), white) quads: the quiet zone, then one quad per run of black cells in a row."""
    up = np.array([0.0, 0.0, 1.0])
    cells = bits.shape[0]
    cell = size / cells
    zone = (cells + 2) * cell
    c1 = centre + 0.001 * n_out
    quads = [(_rect(c1 - zone / 2 * right - zone / 2 * up, right * zone, up * zone), True)]
    c2 = centre + 0.002 * n_out
    top_left = c2 - size / 2 * right + size / 2 * up
    for r in range(cells):
        c = 0
        while c < cells:
            if not bits[r, c]:
                c += 1
                continue
            start = c
            while c < cells and bits[r, c]:
                c += 1
            p0 = top_left + start * cell * right - (r + 1) * cell * up
            quads.append((_rect(p0, right * (c - start) * cell, up * cell), False))
    return quads


def _rect(p0: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.array([p0, p0 + u, p0 + u + v, p0 + v])
