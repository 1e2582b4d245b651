"""COLMAP text model (a folder: cameras.txt, images.txt, points3D.txt) of keyframes and points.

Lets other line mappers run on our poses. Conventions handled here:
- COLMAP puts the centre of the top-left pixel at (0.5, 0.5); we put it at (0, 0). So the principal
  point and every 2D observation get +0.5 pixel.
- COLMAP stores world-to-camera poses (`T_cw`, quaternion w first); the map stores `T_wc`.
- IMAGE_ID is the keyframe's rank in time order + 1 and POINT3D_ID the point's row + 1 (COLMAP ids
  start at 1); image names come from `options.image_name` (frame index by default).
Distortion maps to PINHOLE (none), OPENCV (k1 k2 p1 p2) or FULL_OPENCV (k1 k2 p1 p2 k3 k4 k5 k6).
ERROR is each point's mean reprojection error in pixels over its observations.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial.transform import Rotation

from papl_mapper.errors import InputError
from papl_mapper.map import Camera, Map

from .scene import ExportOptions, check_finite, header_text, scale_note
from .text import format_rows

log = logging.getLogger(__name__)
#: COLMAP pixel centres sit at +0.5 of ours
PIXEL_CENTRE_OFFSET = 0.5


def colmap_camera(cam: Camera) -> tuple[str, np.ndarray]:
    """COLMAP model name and parameters (principal point shifted by +0.5) for our camera."""
    if cam.model != "pinhole":
        raise InputError(f"camera model {cam.model!r} has no COLMAP text export; only pinhole is supported")
    dist = np.asarray(cam.distortion, np.float64).ravel()
    base = [cam.fx, cam.fy, cam.cx + PIXEL_CENTRE_OFFSET, cam.cy + PIXEL_CENTRE_OFFSET]
    nz = np.flatnonzero(dist)
    last = int(nz[-1]) + 1 if len(nz) else 0
    if last == 0:
        return "PINHOLE", np.array(base)
    if last <= 4:
        return "OPENCV", np.array(base + list(np.pad(dist, (0, max(0, 4 - len(dist))))[:4]))
    if last <= 8:
        return "FULL_OPENCV", np.array(base + list(np.pad(dist, (0, max(0, 8 - len(dist))))[:8]))
    raise InputError(
        f"camera distortion has {last} coefficients (thin prism or tilt terms); "
        "COLMAP text models take at most 8"
    )


def project(cam: Camera, T_cw: np.ndarray, xyz_w: np.ndarray) -> np.ndarray:
    """(K, 2) pixels (our convention) of world points seen by cameras T_cw (K, 4, 4), OpenCV distortion."""
    pc = np.einsum("kij,kj->ki", T_cw[:, :3, :3], xyz_w) + T_cw[:, :3, 3]
    z = np.where(np.abs(pc[:, 2]) > 1e-12, pc[:, 2], 1e-12)
    x, y = pc[:, 0] / z, pc[:, 1] / z
    d = np.pad(np.asarray(cam.distortion, np.float64).ravel(), (0, 8))
    k1, k2, p1, p2, k3, k4, k5, k6 = d[:8]
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([cam.fx * xd + cam.cx, cam.fy * yd + cam.cy], axis=1)


def _lines_of(blob: bytes) -> list[bytes]:
    return blob.split(b"\n")[:-1] if blob else []


def export_colmap(m: Map, options: ExportOptions | None = None) -> dict[str, bytes]:
    """The COLMAP text model of the map's keyframes and (if parts has points) points."""
    options = options or ExportOptions()
    options.check()
    kf, pts = m.keyframes, m.points
    check_finite(kf.T_wc, kf.ids, "keyframes.T_wc")
    with_points = "points" in options.parts
    if with_points:
        check_finite(pts.xyz, pts.ids, "points.xyz")
    model, params = colmap_camera(m.camera)
    cameras = b"# Camera list with one line of data per camera:\n"
    cameras += b"#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
    cameras += b"# Number of cameras: 1\n"
    units = (
        f"# Units: {header_text(m.metadata.get('units', 'arbitrary'), 40)}; scale {scale_note(m.metadata)}\n"
    )
    cameras += units.encode()
    cameras += f"1 {model} {m.camera.width} {m.camera.height} ".encode()
    cameras += " ".join(f"{p:.17g}" for p in params).encode() + b"\n"
    if len(kf) == 0:
        log.warning("the map has no keyframes: writing an empty COLMAP model")
    order = np.argsort(kf.timestamp, kind="stable")
    T_cw = np.linalg.inv(kf.T_wc[order])
    # observations of exported points by known keyframes, sorted by image then by point
    obs = pts.obs_ids if with_points else np.zeros((0, 2), np.int64)
    uv = pts.obs_uv if with_points else np.zeros((0, 2))
    if len(obs):
        pid_sort = np.argsort(pts.ids)
        prow = pid_sort[np.searchsorted(pts.ids, obs[:, 0], sorter=pid_sort)]  # point row of each obs
        kf_rank = np.argsort(order)  # keyframe row -> time rank
        kid_sort = np.argsort(kf.ids)
        krow = kid_sort[np.searchsorted(kf.ids, obs[:, 1], sorter=kid_sort)]
        img = kf_rank[krow] + 1  # IMAGE_ID of each obs
    else:
        prow = img = np.zeros(0, np.int64)
    by_img = np.lexsort((prow, img))
    img_sorted = img[by_img]
    starts = np.searchsorted(img_sorted, np.arange(1, len(kf) + 2))
    point2d_idx = np.empty(len(obs), np.int64)
    point2d_idx[by_img] = np.arange(len(obs)) - starts[img_sorted - 1] if len(obs) else 0
    # images.txt: a pose line and a POINTS2D line per image
    q_xyzw = Rotation.from_matrix(T_cw[:, :3, :3]).as_quat() if len(kf) else np.zeros((0, 4))
    q_wxyz = q_xyzw[:, [3, 0, 1, 2]]
    q_wxyz *= np.where(q_wxyz[:, :1] < 0, -1.0, 1.0)
    names = [
        options.image_name.format(id=int(i), frame_index=int(f))
        for i, f in zip(kf.ids[order], kf.frame_index[order], strict=True)
    ]
    bad = [n for n in names if not n or any(c.isspace() for c in n)]
    if bad:
        raise InputError(f"COLMAP image names may not be empty or hold spaces: {bad[:3]} (option image_name)")
    pose_rows = _lines_of(
        format_rows(
            "%d %.17g %.17g %.17g %.17g %.17g %.17g %.17g 1\n",
            np.arange(1, len(kf) + 1),
            q_wxyz,
            T_cw[:, :3, 3],
        )
    )
    p2d_rows = _lines_of(format_rows("%.9g %.9g %d\n", uv[by_img] + PIXEL_CENTRE_OFFSET, prow[by_img] + 1))
    mean_obs = len(obs) / max(len(kf), 1)
    images = [
        b"# Image list with two lines of data per image:\n",
        b"#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n",
        b"#   POINTS2D[] as (X, Y, POINT3D_ID)\n",
        f"# Number of images: {len(kf)}, mean observations per image: {mean_obs:.6g}\n".encode(),
        units.encode(),
    ]
    for i in range(len(kf)):
        images.append(pose_rows[i] + b" " + names[i].encode() + b"\n")
        images.append(b" ".join(p2d_rows[starts[i] : starts[i + 1]]) + b"\n")
    # points3D.txt: one line per point with its track
    n_pts = len(pts) if with_points else 0
    points = [
        b"# 3D point list with one line of data per point:\n",
        b"#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n",
        f"# Number of points: {n_pts}, mean track length: {len(obs) / max(n_pts, 1):.6g}\n".encode(),
        units.encode(),
    ]
    if n_pts:
        err = np.zeros(n_pts)
        if len(obs):
            proj = project(m.camera, T_cw[img - 1], pts.xyz[prow])
            e = np.linalg.norm(proj - uv, axis=1)
            cnt = np.bincount(prow, minlength=n_pts)
            err = np.where(cnt > 0, np.bincount(prow, weights=e, minlength=n_pts) / np.maximum(cnt, 1), 0.0)
        by_pt = np.lexsort((point2d_idx, img, prow))
        tstarts = np.searchsorted(prow[by_pt], np.arange(n_pts + 1))
        # rows without a per-point loop: each head starts with a newline, each track pair with a space,
        # and one object array puts every point's pairs right after its head
        tracks = _lines_of(format_rows(" %d %d\n", img[by_pt], point2d_idx[by_pt]))
        head_format = "\n%d %.17g %.17g %.17g %d %d %d %.9g"
        heads = format_rows(head_format + "\v", np.arange(1, n_pts + 1), pts.xyz, pts.color, err).split(
            b"\v"
        )[:-1]
        tokens = np.empty(n_pts + len(tracks), dtype=object)
        head_at = tstarts[:-1] + np.arange(n_pts)
        is_head = np.zeros(len(tokens), bool)
        is_head[head_at] = True
        tokens[head_at] = heads
        tokens[~is_head] = tracks
        points.append(b"".join(tokens.tolist())[1:] + b"\n")
    return {"cameras.txt": cameras, "images.txt": b"".join(images), "points3D.txt": b"".join(points)}


FORMATS = {".colmap": export_colmap}
