"""Exact perspective rendering of a scene's textured quads with a per-pixel depth buffer.

Each visible quad is clipped to the near plane and projected; its pixels come from one inverse
homography lookup (cv2.warpPerspective) into a mip level of its texture canvas, and its depth from
the plane equation (inverse depth is affine in the pixel coordinates). A canvas is the procedural
texture of one texture frame (the quads of one material sharing a plane and texture origin), drawn
from its own noise over the frame's whole extent, so no texture repeats anywhere in a scene (a
periodic texture made views metres apart look alike). Rendering at `supersample` times the
resolution and area-averaging down anti-aliases edges; mip levels chosen per tile by its
texel-to-pixel ratio keep textures from shimmering. With `msaa`, textures are looked up once per
output pixel and only coverage and depth per sample.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from papl_mapper.map import Camera
from papl_mapper.rows import unique_rows
from papl_mapper.synth.scenes import TILE_TEXELS, Material, Scene

NEAR = 0.05  # near clipping plane in metres
_ONE = np.full((1, 1), 255, np.uint8)  # source of the exact coverage lookup (read-only)
_ONE.setflags(write=False)
LIGHT_DIR = np.array([0.5, 0.3, 0.81]) / np.linalg.norm([0.5, 0.3, 0.81])
LUM_SCALE = 150.0  # a canvas texel is the luminance factor times this (factors up to 1.7 fit a byte)
N_LEVELS = 8  # mip levels per canvas; canvas sides are multiples of 2 ** (N_LEVELS - 1) texels
CANVAS_MARGIN_TEXELS = 16  # canvas beyond its quads: lookups at quad edges stay inside it
MAX_NOISE_STEP = 16  # coarsest grid (texels) wide noise bands are drawn on before upsampling


def gaussian_noise(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> np.ndarray:
    """(rows, cols) float32 white noise filtered by a Gaussian of `sigma_px` texels, unit standard
    deviation, not periodic. Wide bands are drawn on a coarser grid (at least 1.5 cells per sigma)
    and upsampled (bicubic): their cost does not grow with their width."""
    step = 1
    while step < MAX_NOISE_STEP and sigma_px / (2 * step) >= 1.5:
        step *= 2
    s = sigma_px / step
    r = int(math.ceil(4 * s))
    k = cv2.getGaussianKernel(2 * r + 1, s, cv2.CV_32F)
    rows, cols = -(-shape[0] // step) + 1, -(-shape[1] // step) + 1
    field = rng.standard_normal((rows + 2 * r, cols + 2 * r), dtype=np.float32)  # padded: no border effects
    cv2.sepFilter2D(field, -1, k, k, dst=field, borderType=cv2.BORDER_REFLECT)  # in place: half the memory
    field = field[r : r + rows, r : r + cols]
    field *= np.float32(1.0 / float((k**2).sum()))  # std of white noise through the separable kernel
    if step > 1:
        field = cv2.resize(field, (cols * step, rows * step), interpolation=cv2.INTER_CUBIC)
    return field[: shape[0], : shape[1]]


def make_texture(mat: Material, shape: tuple[int, int], texels_per_m: float, seed: int) -> np.ndarray:
    """(rows, cols) uint8 luminance canvas (LUM_SCALE = albedo x 1): soft-thresholded blobs plus fine
    detail and dark specks, drawn from noise seeded by the material and `seed` (the canvas)."""
    if mat.contrast == 0:
        return np.full(shape, round(LUM_SCALE), np.uint8)
    rng = np.random.default_rng([mat.seed, seed])
    blob_px = max(mat.blob_scale_m * texels_per_m, 1.0)
    lum = gaussian_noise(rng, shape, blob_px / 2)
    lum *= 4.0
    np.tanh(lum, out=lum)
    lum *= 0.7
    detail = gaussian_noise(rng, shape, max(blob_px / 8, 0.7))
    detail *= 0.25
    lum += detail
    del detail
    specks = gaussian_noise(rng, shape, 1.5)  # small sharp spots: corners at close range
    specks -= 2.3
    np.clip(specks, 0, 0.5, out=specks)
    specks *= 3.0
    lum -= specks
    del specks
    lum *= np.float32(mat.contrast * LUM_SCALE)
    lum += np.float32(LUM_SCALE)
    np.clip(lum, 0, 255, out=lum)
    return np.rint(lum, out=lum).astype(np.uint8)


def texture_pyramid(tex: np.ndarray) -> list[np.ndarray]:
    """N_LEVELS uint8 mip levels of a canvas (sides a multiple of 2 ** (N_LEVELS - 1))."""
    levels = [tex]
    for _ in range(N_LEVELS - 1):
        h, w = levels[-1].shape
        levels.append(cv2.resize(levels[-1], (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    return levels


def texture_canvases(scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Group quads by texture frame (material, origin, u, v): per quad its canvas (Q,); per canvas the
    texture-frame metres (a, b) of texel (0, 0) (C, 2), its (rows, cols) (C, 2) and material (C,)."""
    ab = _tex_ab(scene.quad_corners, scene, np.arange(len(scene.quad_corners)))  # (Q, 4, 2)
    frames = np.concatenate(
        [scene.quad_material[:, None], scene.tex_origin, scene.tex_u, scene.tex_v], axis=1
    ).round(6)
    _, first, canvas_of_quad = unique_rows(frames, return_index=True, return_inverse=True)
    canvas_of_quad = canvas_of_quad.ravel()
    order = np.argsort(first, kind="stable")  # canvases numbered in the order quads were built
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    canvas_of_quad = rank[canvas_of_quad]
    ppm, align = scene.texels_per_m, 2 ** (N_LEVELS - 1)
    origin, shape = np.zeros((len(order), 2)), np.zeros((len(order), 2), np.int64)
    for c in range(len(order)):
        pts = ab[canvas_of_quad == c].reshape(-1, 2)
        lo = pts.min(0) - CANVAS_MARGIN_TEXELS / ppm
        n = np.ceil(((pts.max(0) - lo) * ppm + CANVAS_MARGIN_TEXELS) / align).astype(np.int64) * align
        origin[c], shape[c] = lo, n[::-1]
    return canvas_of_quad, origin, shape, scene.quad_material[first[order]]


class Renderer:
    """Render a scene from camera poses T_wc (camera -> world) with a given pinhole camera."""

    def __init__(
        self,
        scene: Scene,
        camera: Camera,
        supersample: int = 2,
        textures: list[list[np.ndarray]] | None = None,
        msaa: bool = False,
    ):
        """`textures`: the `pyramids` of another renderer of the same scene, to skip rebuilding them.

        Coverage and depth are resolved per sample; textures too, unless `msaa`: then they are looked
        up once per output pixel from a mip level for that rate (multisampling: edges stay
        anti-aliased, textures are a little softer and rendering faster, benchmarks/results/notes.md).
        """
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
        # texture rate: per output pixel (multisampling) or per sample (full supersampling)
        self.tex_rate = s if msaa else 1  # samples per texture lookup, along each axis
        r = self.tex_rate
        self.K_tex = np.array([[r, 0, (r - 1) / 2], [0, r, (r - 1) / 2], [0, 0, 1]])  # tex pixel -> sample px
        self.K_tex_proj = np.linalg.inv(self.K_tex) @ self.K  # camera -> texture-rate pixels
        self.ppm = scene.texels_per_m
        self.canvas_of_quad, canvas_origin, canvas_shape, canvas_material = texture_canvases(scene)
        if textures is None:
            textures = [
                texture_pyramid(make_texture(scene.materials[m], (int(r), int(c)), self.ppm, seed=k))
                for k, (m, (r, c)) in enumerate(zip(canvas_material, canvas_shape, strict=True))
            ]
        self.pyramids = textures
        self.canvas_origin = canvas_origin[self.canvas_of_quad]  # (Q, 2) metres of each quad's texel (0, 0)
        self.emissive = np.array([m.emissive for m in scene.materials])
        albedo = np.array([m.color_bgr for m in scene.materials])[scene.quad_material]  # (Q, 3)
        self.texel_bgr = albedo * (255 / 1.5 / LUM_SCALE)  # canvas byte -> image byte, before shading
        qc = scene.quad_corners
        self.normals = scene.normals
        self.quad_size = np.stack(
            [np.linalg.norm(qc[:, 1] - qc[:, 0], axis=1), np.linalg.norm(qc[:, 3] - qc[:, 0], axis=1)], axis=1
        )
        self.tex_ab = _tex_ab(qc, scene, np.arange(len(qc)))  # (Q, 4, 2) metres in the texture frame
        self.tile_corners, self.tile_parent, self.tile_range = _tiles(scene, self.ppm)
        # coverage: (a, b) metres -> quad coordinates that round to 0 exactly inside the quad
        a0, b0 = self.tex_ab[:, 0, 0], self.tex_ab[:, 0, 1]
        lu, lv = self.quad_size[:, 0], self.quad_size[:, 1]
        self.coverage_S = np.zeros((len(qc), 3, 3))
        self.coverage_S[:, 0, 0] = 1 / lu
        self.coverage_S[:, 0, 2] = -a0 / lu - 0.5
        self.coverage_S[:, 1, 1] = 1 / lv
        self.coverage_S[:, 1, 2] = -b0 / lv - 0.5
        self.coverage_S[:, 2, 2] = 1
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
        shade = np.where(
            self.emissive[sc.quad_material], 1.0, 0.6 + 0.4 * ((self.normals @ LIGHT_DIR) * facing)
        )
        todo = np.flatnonzero(visible & (np.abs(d_c) > 1e-9))
        if not len(todo):
            return img, zbuf
        # per frame, for all quads at once: pixel -> (a, b) metres on each quad's plane
        frame = np.stack([sc.tex_u @ R.T, sc.tex_v @ R.T, sc.tex_origin @ R.T + t], axis=-1)  # (Q, 3, 3)
        with np.errstate(all="ignore"):
            H_inv = np.linalg.inv(K @ frame)  # (Q, 3, 3), singular only for planes through the centre
        coverage = self.coverage_S @ H_inv
        tile_cam = self.tile_corners @ R.T + t  # (T, 4, 3)
        tex_maps, levels = self._tile_maps(tile_cam, n_c, H_inv)
        inv_plane = (n_c @ self.K_inv) / d_c[:, None]  # (Q, 3): inverse depth = a u + b v + c
        xs_all = np.arange(W, dtype=np.float32)
        ys_all = np.arange(H, dtype=np.float32)
        z_all_front = (z >= NEAR).all(1)
        uv_all = (Pc @ K.T)[..., :2] / np.where(z_all_front[:, None], z, 1.0)[..., None]
        # near planes first, so that later ones mostly fail the depth test and skip their warp
        todo = todo[np.argsort(np.abs(d_c[todo]), kind="stable")]
        for q in todo:
            clipped = not z_all_front[q]
            if clipped:
                pc = _clip_near(Pc[q])
                if pc is None:
                    continue
                uv = pc @ K.T
                uv = uv[:, :2] / uv[:, 2:3]
            else:
                uv = uv_all[q]
            x0 = max(int(math.floor(uv[:, 0].min())) - 1, 0)
            x1 = min(int(math.ceil(uv[:, 0].max())) + 2, W)
            y0 = max(int(math.floor(uv[:, 1].min())) - 1, 0)
            y1 = min(int(math.ceil(uv[:, 1].max())) + 2, H)
            if x1 <= x0 or y1 <= y0:
                continue
            w, h = x1 - x0, y1 - y0
            mask = _lookup(_ONE, _shifted(coverage[q], x0, y0), w, h, cv2.INTER_NEAREST, cv2.BORDER_CONSTANT)
            if clipped:  # the homography also maps points behind the camera: bound by the polygon
                mask = cv2.bitwise_and(mask, _polygon_mask(uv, x0, y0, w, h))
            a, b, c = inv_plane[q]
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
            bgr = self.texel_bgr[q, :, None] * shade[q]  # (3, 1): luminance byte -> BGR bytes
            warped = self._texture_at_samples(q, tile_cam, tex_maps, levels, x0, y0, w, h, bgr)
            cv2.copyTo(warped, m, img[y0 : y0 + h, x0 : x0 + w])  # writes through the views
            cv2.copyTo(invz, m, zb)
        return img, zbuf

    def _tile_maps(self, tile_cam, n_c, H_inv) -> tuple[np.ndarray, np.ndarray]:
        """Per tile: matrix from image pixels to texels of its mip level (T, 3, 3), and the level (T,).

        The level follows the texel-to-pixel ratio at the tile: its depth range and obliquity.
        """
        q = self.tile_parent
        tz = np.maximum(tile_cam[..., 2], NEAR)  # (T, 4) depths of the tile corners
        z_ref = np.sqrt(tz.min(1) * tz.max(1))
        centre = tile_cam.mean(1)
        cos = np.abs((n_c[q] * centre).sum(1)) / np.linalg.norm(centre, axis=1)
        rho = self.ppm * z_ref / (self.K_tex_proj[0, 0] * np.maximum(cos, 0.2))  # texels per lookup pixel
        level = np.clip(np.floor(np.log2(np.maximum(rho, 1e-6)) + 0.5), 0, N_LEVELS - 1).astype(np.int64)
        p2 = 2.0**level
        scale = self.ppm / p2
        half = (p2 - 1) / (2 * p2)
        off = self.canvas_origin[q] * scale[:, None]  # texel (0, 0) of the canvas
        A = np.zeros((len(q), 3, 3))
        A[:, 0, 0] = A[:, 1, 1] = scale
        A[:, 0, 2] = -half - off[:, 0]
        A[:, 1, 2] = -half - off[:, 1]
        A[:, 2, 2] = 1
        return A @ H_inv[q] @ self.K_tex, level  # from texture-rate pixels

    def _texture_at_samples(self, q, tile_cam, tex_maps, levels, x0, y0, w, h, bgr) -> np.ndarray:
        """(h, w, 3) texture of quad q over the sample rect at (x0, y0): looked up at the texture
        rate, coloured by `bgr` (3, 1) and repeated to every sample of its pixel."""
        r = self.tex_rate
        if r == 1:
            return cv2.transform(self._texture(q, tile_cam, tex_maps, levels, x0, y0, w, h), bgr)
        X0, Y0 = x0 // r, y0 // r
        X1, Y1 = -(-(x0 + w) // r), -(-(y0 + h) // r)
        tex = cv2.transform(self._texture(q, tile_cam, tex_maps, levels, X0, Y0, X1 - X0, Y1 - Y0), bgr)
        up = cv2.resize(tex, ((X1 - X0) * r, (Y1 - Y0) * r), interpolation=cv2.INTER_NEAREST)
        return up[y0 - Y0 * r : y0 - Y0 * r + h, x0 - X0 * r : x0 - X0 * r + w]

    def _texture(self, q, tile_cam, tex_maps, levels, x0, y0, w, h) -> np.ndarray:
        """(h, w) uint8 luminance of quad q over the pixel rect at (x0, y0), assembled from its tiles.

        Tiles are drawn with masks grown by a pixel: the texture is continuous across them, and the
        quad's own mask (not the tiles') decides coverage, so tile seams never open gaps.
        """
        first, count = self.tile_range[q]
        pyramid = self.pyramids[self.canvas_of_quad[q]]
        if count == 1:
            return _lookup(pyramid[levels[first]], _shifted(tex_maps[first], x0, y0), w, h)
        out = np.zeros((h, w), np.uint8)
        for k in range(first, first + count):
            pc = _clip_near(tile_cam[k])
            if pc is None:
                continue
            uv = pc @ self.K_tex_proj.T
            uv = uv[:, :2] / uv[:, 2:3]
            tx0 = max(int(math.floor(uv[:, 0].min())) - 2, x0)
            tx1 = min(int(math.ceil(uv[:, 0].max())) + 3, x0 + w)
            ty0 = max(int(math.floor(uv[:, 1].min())) - 2, y0)
            ty1 = min(int(math.ceil(uv[:, 1].max())) + 3, y0 + h)
            if tx1 <= tx0 or ty1 <= ty0:
                continue
            tw, th = tx1 - tx0, ty1 - ty0
            mask = _polygon_mask(uv, tx0, ty0, tw, th)
            tile = _lookup(pyramid[levels[k]], _shifted(tex_maps[k], tx0, ty0), tw, th)
            cv2.copyTo(tile, mask, out[ty0 - y0 : ty1 - y0, tx0 - x0 : tx1 - x0])
        return out


def _tex_ab(corners: np.ndarray, scene: Scene, quad: np.ndarray) -> np.ndarray:
    """(N, 4, 2) texture-frame coordinates in metres of corners (N, 4, 3) on quads `quad` (N,)."""
    d = corners - scene.tex_origin[quad][:, None]
    return np.stack(
        [(d * scene.tex_u[quad][:, None]).sum(-1), (d * scene.tex_v[quad][:, None]).sum(-1)], axis=-1
    )


def _lookup(tex, M, w, h, interpolation=cv2.INTER_LINEAR, border=cv2.BORDER_REPLICATE) -> np.ndarray:
    """(h, w) image whose pixel p is tex at M @ p (M: rect pixels -> source pixels)."""
    return cv2.warpPerspective(tex, M, (w, h), flags=interpolation | cv2.WARP_INVERSE_MAP, borderMode=border)


def _shifted(M: np.ndarray, x0: int, y0: int) -> np.ndarray:
    """M @ translation(x0, y0): the same map for a rect whose first pixel is (x0, y0)."""
    out = M.copy()
    out[:, 2] += M[:, 0] * x0 + M[:, 1] * y0
    return out


def _polygon_mask(uv: np.ndarray, x0: int, y0: int, w: int, h: int) -> np.ndarray:
    """(h, w) mask of a convex polygon (K, 2) in pixels, grown by about a pixel all round."""
    mask = np.zeros((h, w), np.uint8)
    pts = [np.round((uv - [x0, y0]) * 16).astype(np.int32)]
    cv2.fillPoly(mask, pts, 255, lineType=cv2.LINE_8, shift=4)
    cv2.polylines(mask, pts, True, 255, thickness=3, lineType=cv2.LINE_8, shift=4)
    return mask


def _tiles(scene: Scene, texels_per_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut quads into tiles spanning at most TILE_TEXELS texels (each gets its own mip level): corners
    (T, 4, 3), parent (T,), and per quad its first tile and tile count (Q, 2)."""
    corners, parent, ranges = [], [], []
    for q, c in enumerate(scene.quad_corners):
        u, v = c[1] - c[0], c[3] - c[0]
        nu = max(1, math.ceil(np.linalg.norm(u) * texels_per_m / TILE_TEXELS - 1e-9))
        nv = max(1, math.ceil(np.linalg.norm(v) * texels_per_m / TILE_TEXELS - 1e-9))
        ranges.append((len(parent), nu * nv))
        for i in range(nu):
            for j in range(nv):
                p = c[0] + u * (i / nu) + v * (j / nv)
                du, dv = u / nu, v / nv
                corners.append([p, p + du, p + du + dv, p + dv])
                parent.append(q)
    return np.array(corners), np.array(parent, np.int64), np.array(ranges, np.int64)


def _clip_near(pc: np.ndarray) -> np.ndarray | None:
    """Sutherland-Hodgman clip of a polygon (K, 3) in camera coordinates to z >= NEAR."""
    z = pc[:, 2]
    if (z >= NEAR).all():
        return pc
    out = []
    n = len(pc)
    for i in range(n):
        j = (i + 1) % n
        if z[i] >= NEAR:
            out.append(pc[i])
        if (z[i] >= NEAR) != (z[j] >= NEAR):
            out.append(pc[i] + (NEAR - z[i]) / (z[j] - z[i]) * (pc[j] - pc[i]))
    return np.array(out) if len(out) >= 3 else None
