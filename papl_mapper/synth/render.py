"""Exact perspective rendering of a scene's textured quads with a per-pixel depth buffer.

Each visible quad is clipped to the near plane and projected; its pixels come from one inverse
homography lookup (cv2.warpPerspective) into a mip level of its periodic procedural texture, and its
depth from the plane equation (inverse depth is affine in the pixel coordinates). Rendering at
`supersample` times the resolution and area-averaging down anti-aliases edges; mip levels chosen
per tile by its texel-to-pixel ratio keep textures from shimmering.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from papl_mapper.map import Camera
from papl_mapper.synth.scenes import TEXTURE_PERIOD, Material, Scene

NEAR = 0.05  # near clipping plane in metres
_ONE = np.full((1, 1), 255, np.uint8)  # source of the exact coverage lookup (read-only)
_ONE.setflags(write=False)
LIGHT_DIR = np.array([0.5, 0.3, 0.81]) / np.linalg.norm([0.5, 0.3, 0.81])


def make_texture(mat: Material, texels_per_m: float, period: int = TEXTURE_PERIOD) -> np.ndarray:
    """(period, period, 3) float32 BGR periodic texture: soft-thresholded blobs plus fine detail."""
    rng = np.random.default_rng(mat.seed)
    f2 = np.fft.fftfreq(period)[:, None] ** 2 + np.fft.rfftfreq(period)[None, :] ** 2

    def band(sigma_px: float) -> np.ndarray:
        """Periodic Gaussian-filtered white noise, unit standard deviation."""
        noise = np.fft.rfft2(rng.standard_normal((period, period), dtype=np.float32))
        out = np.fft.irfft2(noise * np.exp(-2 * math.pi**2 * sigma_px**2 * f2), s=(period, period))
        return (out / (out.std() + 1e-12)).astype(np.float32)

    blob_px = max(mat.blob_scale_m * texels_per_m, 1.0)
    blobs = np.tanh(4.0 * band(blob_px / 2))
    detail = band(max(blob_px / 8, 0.7))
    specks = np.clip(band(1.5) - 2.3, 0, 0.5) * 2  # small sharp spots: corners at close range
    tint = band(blob_px)[..., None] * rng.normal(0, 1, 3).astype(np.float32)  # slow colour drift
    base = np.asarray(mat.color_bgr, np.float32)
    lum = 1 + mat.contrast * (0.7 * blobs + 0.25 * detail - 1.5 * specks)
    tex = base * lum[..., None] * (1 + 0.08 * mat.contrast * tint)
    return np.clip(tex, 0, 1.5).astype(np.float32)


def texture_pyramid(tex: np.ndarray) -> list[np.ndarray]:
    """uint8 mip levels of a periodic texture, each tiled 2 x 2 so tile lookups never wrap."""
    levels = []
    level = np.clip(tex * 255 / 1.5, 0, 255)  # headroom: emissive lights go above white
    while True:
        levels.append(np.tile(level.round().astype(np.uint8), (2, 2, 1)))
        if level.shape[0] <= 4:
            return levels
        level = cv2.resize(level, (level.shape[1] // 2, level.shape[0] // 2), interpolation=cv2.INTER_AREA)


class Renderer:
    """Render a scene from camera poses T_wc (camera -> world) with a given pinhole camera."""

    def __init__(
        self,
        scene: Scene,
        camera: Camera,
        supersample: int = 2,
        textures: list[list[np.ndarray]] | None = None,
    ):
        """`textures`: the `pyramids` of another renderer of the same scene, to skip rebuilding them."""
        self.scene = scene
        self.camera = camera
        self.ss = int(supersample)
        s = self.ss
        self.W, self.H = camera.width * s, camera.height * s
        self.K = np.array(
            [
                [camera.fx * s, 0, (camera.cx + 0.5) * s - 0.5],
                [0, camera.fy * s, (camera.cy + 0.5) * s - 0.5],
                [0, 0, 1],
            ]
        )
        self.K_inv = np.linalg.inv(self.K)
        self.ppm = scene.texels_per_m
        if textures is None:
            textures = [texture_pyramid(make_texture(m, self.ppm)) for m in scene.materials]
        self.pyramids = textures
        self.emissive = np.array([m.emissive for m in scene.materials])
        qc = scene.quad_corners
        self.normals = scene.normals
        self.tile_corners, self.tile_parent, self.tile_range = _tiles(scene, self.ppm)
        self.tile_ab = _tex_ab(self.tile_corners, scene, self.tile_parent)
        self.quad_size = np.stack(
            [np.linalg.norm(qc[:, 1] - qc[:, 0], axis=1), np.linalg.norm(qc[:, 3] - qc[:, 0], axis=1)], axis=1
        )
        self.tex_ab = _tex_ab(qc, scene, np.arange(len(qc)))  # (Q, 4, 2) metres in the texture frame
        self.background = np.clip(np.asarray(scene.background_bgr) * 255 / 1.5, 0, 255).astype(np.uint8)

    def render(self, T_wc: np.ndarray, with_depth: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """BGR float32 image (H, W, 3) in [0, 1.5] and, if asked, depth (H, W) (inf where empty)."""
        img, inv_depth = self.render_supersampled(T_wc)
        cam = self.camera
        if self.ss > 1:
            out = cv2.resize(img, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
        else:
            out = img
        out = out.astype(np.float32) * np.float32(1.5 / 255)
        depth = None
        if with_depth:
            s = self.ss
            near = inv_depth[0::s, 0::s].copy()  # the nearest surface of each s x s block
            for dy in range(s):
                for dx in range(s):
                    np.maximum(near, inv_depth[dy::s, dx::s], out=near)
            with np.errstate(divide="ignore"):
                depth = np.where(near > 0, 1.0 / near, np.inf).astype(np.float32)
        return out, depth

    def render_supersampled(self, T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """uint8 image and inverse-depth buffer (0 = nothing) at supersampled resolution."""
        T_cw = np.linalg.inv(T_wc)
        R, t = T_cw[:3, :3], T_cw[:3, 3]
        sc = self.scene
        K, W, H = self.K, self.W, self.H
        img = np.empty((H, W, 3), np.uint8)
        img[:] = self.background
        zbuf = np.zeros((H, W), np.float32)
        Pc = sc.quad_corners @ R.T + t  # (Q, 4, 3)
        x, y, z = Pc[..., 0], Pc[..., 1], Pc[..., 2]
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        visible = ~(z < NEAR).all(1)
        visible &= ~(fx * x + (cx + 0.5) * z < 0).all(1)
        visible &= ~(fx * x + (cx + 0.5 - W) * z > 0).all(1)
        visible &= ~(fy * y + (cy + 0.5) * z < 0).all(1)
        visible &= ~(fy * y + (cy + 0.5 - H) * z > 0).all(1)
        n_c = self.normals @ R.T  # (Q, 3)
        d_c = (n_c * Pc[:, 0]).sum(1)  # plane n_c . X = d_c
        facing = np.where(d_c < 0, 1.0, -1.0)  # flip normals to face the camera
        n_world_facing = self.normals * facing[:, None]
        shade = np.where(self.emissive[sc.quad_material], 1.0, 0.6 + 0.4 * (n_world_facing @ LIGHT_DIR))
        xs_all = np.arange(W, dtype=np.float32)
        ys_all = np.arange(H, dtype=np.float32)
        todo = np.flatnonzero(visible & (np.abs(d_c) > 1e-9))
        # near planes first, so that later ones mostly fail the depth test and skip their warp
        todo = todo[np.argsort(np.abs(d_c[todo]), kind="stable")]
        for q in todo:
            poly = _clip_near(Pc[q], self.tex_ab[q])
            if poly is None:
                continue
            pc, ab = poly
            uv = pc @ K.T
            uv = uv[:, :2] / uv[:, 2:3]
            x0 = max(int(math.floor(uv[:, 0].min())) - 1, 0)
            x1 = min(int(math.ceil(uv[:, 0].max())) + 2, W)
            y0 = max(int(math.floor(uv[:, 1].min())) - 1, 0)
            y1 = min(int(math.ceil(uv[:, 1].max())) + 2, H)
            if x1 <= x0 or y1 <= y0:
                continue
            w, h = x1 - x0, y1 - y0
            mask = self._coverage(q, R, t, x0, y0, w, h)
            if len(pc) != 4 or (pc[:, 2] < Pc[q, :, 2] - 1e-12).any():  # near-clipped: bound by the polygon
                clip = np.zeros((h, w), np.uint8)
                pts = [np.round((uv - [x0, y0]) * 16).astype(np.int32)]
                cv2.fillPoly(clip, pts, 255, lineType=cv2.LINE_8, shift=4)
                cv2.polylines(clip, pts, True, 255, thickness=3, lineType=cv2.LINE_8, shift=4)
                mask = cv2.bitwise_and(mask, clip)
            # inverse depth of pixel (u, v): (n_c . K^-1 [u v 1]) / d_c, affine in u and v
            a, b, c = (self.K_inv.T @ n_c[q]) / d_c[q]
            inv_x = np.float32(a) * xs_all[x0:x1]
            inv_y = np.float32(b) * ys_all[y0:y1] + np.float32(c)
            invz = inv_x[None] + inv_y[:, None]
            zb = zbuf[y0:y1, x0:x1]
            m = cv2.bitwise_and(cv2.compare(invz, zb, cv2.CMP_GT), mask)
            bx, by, bw, bh = cv2.boundingRect(m)  # warp only where the quad wins the depth test
            if bw == 0:
                continue
            m = m[by : by + bh, bx : bx + bw]
            invz = invz[by : by + bh, bx : bx + bw]
            zb = zb[by : by + bh, bx : bx + bw]
            x0, y0, w, h = x0 + bx, y0 + by, bw, bh
            warped = self._texture(q, R, t, pc, ab, x0, y0, w, h)
            if shade[q] != 1.0:
                warped = cv2.convertScaleAbs(warped, alpha=float(shade[q]))
            cv2.copyTo(warped, m, img[y0 : y0 + h, x0 : x0 + w])  # writes through the views
            cv2.copyTo(invz, m, zb)
        return img, zbuf

    def _coverage(self, q, R, t, x0, y0, w, h) -> np.ndarray:
        """(h, w) uint8 mask of the pixels whose centre sees quad q: exact, from the inverse homography.

        A 1 x 1 source image looked up with nearest-neighbour rounding is 255 exactly where the
        quad coordinate (a - a0) / |u| - 1/2 rounds to 0, that is for a in [a0, a0 + |u|) (same for b).
        """
        sc = self.scene
        o = R @ sc.tex_origin[q] + t
        H_ab = self.K @ np.column_stack([R @ sc.tex_u[q], R @ sc.tex_v[q], o])  # metres (a, b) -> pixels
        a0, b0 = self.tex_ab[q, 0]
        lu, lv = self.quad_size[q]
        S = np.array([[1 / lu, 0, -a0 / lu - 0.5], [0, 1 / lv, -b0 / lv - 0.5], [0, 0, 1]])
        shift = np.array([[1.0, 0, x0], [0, 1, y0], [0, 0, 1]])
        return cv2.warpPerspective(
            _ONE,
            S @ np.linalg.inv(H_ab) @ shift,
            (w, h),
            flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )

    def _texture(self, q, R, t, pc, ab, x0, y0, w, h) -> np.ndarray:
        """(h, w, 3) uint8 texture of quad q over the pixel rect at (x0, y0), assembled from its tiles.

        Tiles are drawn with masks grown by a pixel: the texture is continuous across them, and the
        quad's own mask (not the tiles') decides coverage, so tile seams never open gaps.
        """
        first, count = self.tile_range[q]
        mat = self.scene.quad_material[q]
        if count == 1:
            M, level = self._texture_map(first, R, t, pc, ab, x0, y0)
            return _warp(self.pyramids[mat][level], M, w, h)
        out = np.zeros((h, w, 3), np.uint8)
        Pc = self.tile_corners[first : first + count] @ R.T + t
        for k in range(count):
            poly = _clip_near(Pc[k], self.tile_ab[first + k])
            if poly is None:
                continue
            tpc, tab = poly
            uv = tpc @ self.K.T
            uv = uv[:, :2] / uv[:, 2:3]
            tx0 = max(int(math.floor(uv[:, 0].min())) - 2, x0)
            tx1 = min(int(math.ceil(uv[:, 0].max())) + 3, x0 + w)
            ty0 = max(int(math.floor(uv[:, 1].min())) - 2, y0)
            ty1 = min(int(math.ceil(uv[:, 1].max())) + 3, y0 + h)
            if tx1 <= tx0 or ty1 <= ty0:
                continue
            mask = np.zeros((ty1 - ty0, tx1 - tx0), np.uint8)
            pts = [np.round((uv - [tx0, ty0]) * 16).astype(np.int32)]
            cv2.fillPoly(mask, pts, 255, lineType=cv2.LINE_8, shift=4)
            cv2.polylines(mask, pts, True, 255, thickness=3, lineType=cv2.LINE_8, shift=4)
            M, level = self._texture_map(first + k, R, t, tpc, tab, tx0, ty0)
            tile = _warp(self.pyramids[mat][level], M, tx1 - tx0, ty1 - ty0)
            cv2.copyTo(tile, mask, out[ty0 - y0 : ty1 - y0, tx0 - x0 : tx1 - x0])
        return out

    def _texture_map(self, k, R, t, pc, ab, x0, y0) -> tuple[np.ndarray, int]:
        """Matrix from rect pixels to texels of tile k's mip level, and that level."""
        sc = self.scene
        q = self.tile_parent[k]
        o = R @ sc.tex_origin[q] + t
        H_ab = self.K @ np.column_stack([R @ sc.tex_u[q], R @ sc.tex_v[q], o])  # metres (a, b) -> pixels
        zs = pc[:, 2]
        z_ref = math.sqrt(zs.min() * zs.max())
        centre = pc.mean(0)
        cos = abs(float((R @ self.normals[q]) @ (centre / np.linalg.norm(centre))))
        rho = self.ppm * z_ref / (self.K[0, 0] * max(cos, 0.2))  # texels per rendered pixel
        n_levels = len(self.pyramids[sc.quad_material[q]])
        level = int(np.clip(math.floor(math.log2(max(rho, 1e-6)) + 0.5), 0, n_levels - 1))
        scale = self.ppm / 2**level
        half = (2**level - 1) / 2 ** (level + 1)
        period = TEXTURE_PERIOD / 2**level
        off = np.floor(ab.min(0) * scale / period) * period  # keep lookups inside the 2 x 2 tiled copy
        A = np.array([[scale, 0, -half - off[0]], [0, scale, -half - off[1]], [0, 0, 1]])
        shift = np.array([[1.0, 0, x0], [0, 1, y0], [0, 0, 1]])
        return A @ np.linalg.inv(H_ab) @ shift, level


def _tex_ab(corners: np.ndarray, scene: Scene, quad: np.ndarray) -> np.ndarray:
    """(N, 4, 2) texture-frame coordinates in metres of corners (N, 4, 3) on quads `quad` (N,)."""
    d = corners - scene.tex_origin[quad][:, None]
    return np.stack(
        [(d * scene.tex_u[quad][:, None]).sum(-1), (d * scene.tex_v[quad][:, None]).sum(-1)], axis=-1
    )


def _warp(tex: np.ndarray, M: np.ndarray, w: int, h: int) -> np.ndarray:
    return cv2.warpPerspective(
        tex, M, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_WRAP
    )


def _tiles(scene: Scene, texels_per_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut quads into tiles spanning at most TEXTURE_PERIOD texels: corners (T, 4, 3), parent (T,),
    and per quad its first tile and tile count (Q, 2)."""
    corners, parent, ranges = [], [], []
    for q, c in enumerate(scene.quad_corners):
        u, v = c[1] - c[0], c[3] - c[0]
        nu = max(1, math.ceil(np.linalg.norm(u) * texels_per_m / TEXTURE_PERIOD - 1e-9))
        nv = max(1, math.ceil(np.linalg.norm(v) * texels_per_m / TEXTURE_PERIOD - 1e-9))
        ranges.append((len(parent), nu * nv))
        for i in range(nu):
            for j in range(nv):
                p = c[0] + u * (i / nu) + v * (j / nv)
                du, dv = u / nu, v / nv
                corners.append([p, p + du, p + du + dv, p + dv])
                parent.append(q)
    return np.array(corners), np.array(parent, np.int64), np.array(ranges, np.int64)


def _clip_near(pc: np.ndarray, ab: np.ndarray):
    """Sutherland-Hodgman clip of a quad (camera coords, with texture coords) to z >= NEAR."""
    z = pc[:, 2]
    if (z >= NEAR).all():
        return pc, ab
    out_c, out_ab = [], []
    n = len(pc)
    for i in range(n):
        j = (i + 1) % n
        zi, zj = z[i], z[j]
        if zi >= NEAR:
            out_c.append(pc[i])
            out_ab.append(ab[i])
        if (zi >= NEAR) != (zj >= NEAR):
            s = (NEAR - zi) / (zj - zi)
            out_c.append(pc[i] + s * (pc[j] - pc[i]))
            out_ab.append(ab[i] + s * (ab[j] - ab[i]))
    if len(out_c) < 3:
        return None
    return np.array(out_c), np.array(out_ab)
