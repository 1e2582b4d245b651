"""The synthetic ground truth is right numerically: GT segments project onto intensity edges of the
rendered frames, GT points onto rendered surfaces, and the paths stay in free space."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from papl_mapper.map import Camera
from papl_mapper.synth import SynthConfig, make_scene, tracks_from_scene, walkthrough
from papl_mapper.synth.path import U_TURN_OFFSET_M
from papl_mapper.synth.project import occluded, project, visible_segments
from papl_mapper.synth.render import Renderer, gaussian_noise, make_texture

SCENE_NAMES = ("corridor", "atlanta", "garage")
EDGE_OFFSET_PX = 4.0  # "a few pixels away" from the projected segment
EDGE_RATIO = 2.5  # gradient on the segment vs the weaker side
MIN_EDGE_GRADIENT = 6.0  # grey levels per pixel (Sobel / 8) on the segment
MIN_EDGE_FRACTION = 0.8  # of the visible, long-enough GT segments that must sit on an edge
SHIFTED_MAX_FRACTION = 0.35  # the same test with a 1.5 deg wrong pose must mostly fail
MIN_CLEARANCE_M = 0.3  # camera distance to any surface
DEPTH_TOL_REL = 0.02  # rendered vs projected depth of visible GT points
FRAMES = (0, 20, 45, 70, 90, 110)
DECAL_MARGIN_M = 0.1  # occluders closer than this along the ray are decals


def _gray_gradient(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    g = cv2.cvtColor(np.clip(img * 230, 0, 255).astype(np.float32), cv2.COLOR_BGR2GRAY)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8
    return gx, gy


def _bilinear(a: np.ndarray, xy: np.ndarray) -> np.ndarray:
    m = cv2.remap(a, xy[:, 0].astype(np.float32)[None], xy[:, 1].astype(np.float32)[None], cv2.INTER_LINEAR)
    return m[0]


def edge_scores(cam, img, depth, T_wc, scene) -> tuple[int, int]:
    """(segments on an edge, segments tested) for one frame: perpendicular gradient on vs beside."""
    gx, gy = _gray_gradient(img)
    sidx, xy = visible_segments(scene, cam, T_wc, scene.segments, occlusion=False, min_length_px=30)
    tested = passed = 0
    margin = EDGE_OFFSET_PX + 3
    near_depth = cv2.erode(np.where(np.isfinite(depth), depth, 1e6).astype(np.float32), np.ones((3, 3)))
    for i, s in enumerate(sidx):
        if _has_close_parallel(xy, i, max_px=EDGE_OFFSET_PX + 2):
            continue  # another GT edge lies where the gradient should be weak (skirting, thin strips)
        a, b = scene.segments[s]
        X = a + np.linspace(0.05, 0.95, 40)[:, None] * (b - a)
        uv, z = project(cam, T_wc, X)
        inside = (
            (z > 0.2)
            & (uv[:, 0] > margin)
            & (uv[:, 0] < cam.width - 1 - margin)
            & (uv[:, 1] > margin)
            & (uv[:, 1] < cam.height - 1 - margin)
        )
        if inside.sum() < 8:
            continue
        uv, z = uv[inside], z[inside]
        d_img = near_depth[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)]
        seen = z <= d_img * (1 + DEPTH_TOL_REL) + 0.02
        if seen.sum() < 8:
            continue
        uv = uv[seen]
        t = uv[-1] - uv[0]
        if np.linalg.norm(t) < 20:
            continue
        n = np.array([-t[1], t[0]]) / np.linalg.norm(t)

        def perp(p, n=n):
            return np.abs(_bilinear(gx, p) * n[0] + _bilinear(gy, p) * n[1])

        on = np.median(np.maximum.reduce([perp(uv + k * n) for k in (-1.0, -0.5, 0.0, 0.5, 1.0)]))
        left = np.median(perp(uv - EDGE_OFFSET_PX * n))
        right = np.median(perp(uv + EDGE_OFFSET_PX * n))
        tested += 1
        passed += bool(on >= MIN_EDGE_GRADIENT and on >= EDGE_RATIO * min(left, right))
    return passed, tested


def edge_offsets(cam, img, depth, T_wc, scene) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel offsets (K,) of the gradient peaks of strong isolated GT edges along their normals (K, 2)."""
    gx, gy = _gray_gradient(img)
    sidx, xy = visible_segments(scene, cam, T_wc, scene.segments, occlusion=True, min_length_px=40)
    steps = np.arange(-2.0, 2.01, 0.25)
    offsets, normals = [], []
    for i, s in enumerate(sidx):
        if _has_close_parallel(xy, i):
            continue  # two edges within the profile window (a thin stripe) bias each other's peak
        a, b = scene.segments[s]
        uv, z = project(cam, T_wc, a + np.linspace(0.1, 0.9, 30)[:, None] * (b - a))
        m = 5
        ok = (z > 0.2) & (uv[:, 0] > m) & (uv[:, 0] < cam.width - 1 - m) & (uv[:, 1] > m)
        ok &= uv[:, 1] < cam.height - 1 - m
        if ok.sum() < 10:
            continue
        uv = uv[ok]
        t = (uv[-1] - uv[0]) / np.linalg.norm(uv[-1] - uv[0])
        n = np.array([-t[1], t[0]])
        prof = np.stack(
            [np.abs(_bilinear(gx, uv + k * n) * n[0] + _bilinear(gy, uv + k * n) * n[1]) for k in steps]
        )
        mean = prof.mean(axis=1)  # (steps,) gradient profile across the edge, averaged along it
        i = int(np.argmax(mean))
        if not 0 < i < len(steps) - 1 or mean[i] < MIN_EDGE_GRADIENT:
            continue
        y0, y1, y2 = mean[i - 1 : i + 2]
        peak = steps[i] + 0.25 * 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)  # parabola through the top three
        offsets.append(peak)
        normals.append(n)
    return np.array(offsets), np.array(normals).reshape(-1, 2)


def _has_close_parallel(xy: np.ndarray, i: int, max_px: float = 5.0, max_deg: float = 10.0) -> bool:
    """Whether another observed segment runs nearly parallel within max_px of segment i's midpoint."""
    p, q = xy[:, :2], xy[:, 2:]
    d = q - p
    u = d / np.linalg.norm(d, axis=1, keepdims=True)
    parallel = np.abs(u @ u[i]) > math.cos(math.radians(max_deg))
    mid = (p[i] + q[i]) / 2
    t = np.clip(((mid - p) * d).sum(1) / (d * d).sum(1), 0, 1)
    near = np.linalg.norm(p + t[:, None] * d - mid, axis=1) < max_px
    near[i] = False
    return bool((parallel & near).any())


def global_shift(offsets: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Least-squares image shift (2,) explaining per-edge normal offsets: offset_i = shift . n_i."""
    return np.linalg.lstsq(normals, offsets, rcond=None)[0]


@pytest.fixture(scope="module", params=SCENE_NAMES)
def rendered(request):
    cfg = SynthConfig(scene=request.param, width=320, height=240, fps=10, seconds=12.0, supersample=2)
    scene = make_scene(cfg.scene, 0)
    cam = cfg.camera()
    t, T = walkthrough(scene, cfg.n_frames, cfg.fps, 0)
    r = Renderer(scene, cam, cfg.supersample)
    frames = [(T[i], *r.render(T[i], with_depth=True)) for i in FRAMES]
    return scene, cam, frames


def test_gt_segments_lie_on_rendered_edges(rendered):
    scene, cam, frames = rendered
    ok = n = 0
    for T, img, depth in frames:
        p, k = edge_scores(cam, img, depth, T, scene)
        ok, n = ok + p, n + k
    assert n >= 10, f"{scene.name}: only {n} GT segments visible in the test frames"
    assert ok / n >= MIN_EDGE_FRACTION, f"{scene.name}: {ok}/{n} GT segments on edges"


def test_edge_check_fails_with_a_wrong_pose(rendered):
    """The check above can fail: a pose off by 1.5 degrees puts the segments beside the edges."""
    scene, cam, frames = rendered
    ok = n = 0
    c, s = math.cos(math.radians(1.5)), math.sin(math.radians(1.5))
    for T, img, depth in frames:
        Tw = T.copy()
        Tw[:3, :3] = (
            T[:3, :3]
            @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
            @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
        )
        p, k = edge_scores(cam, img, depth, Tw, scene)
        ok, n = ok + p, n + k
    assert n >= 10
    assert ok / n <= SHIFTED_MAX_FRACTION, f"{scene.name}: {ok}/{n} still pass with a wrong pose"


def test_visible_points_are_on_rendered_surfaces(rendered):
    """Points the geometric occlusion test calls visible sit at the rendered depth; hidden ones behind it."""
    scene, cam, frames = rendered
    T_all = np.stack([f[0] for f in frames])
    tracks, pts = tracks_from_scene(scene, cam, T_all, np.arange(len(frames)) / 10.0, n_surface_points=3000)
    for f, (T, _img, depth) in enumerate(frames):
        ids, uv = tracks.points_in(f)
        _, z = project(cam, T, pts[ids])
        px = np.clip(np.round(uv).astype(int), 0, [cam.width - 1, cam.height - 1])
        finite = np.where(np.isfinite(depth), depth, 1e6).astype(np.float32)
        lo = cv2.erode(finite, np.ones((3, 3)))[px[:, 1], px[:, 0]]  # the pixel and its neighbours
        hi = cv2.dilate(finite, np.ones((3, 3)))[px[:, 1], px[:, 0]]
        agree = (z >= lo * (1 - DEPTH_TOL_REL) - 0.02) & (z <= hi * (1 + DEPTH_TOL_REL) + 0.02)
        assert agree.mean() >= 0.95, f"{scene.name} frame {f}: {agree.mean():.3f} at rendered depth"
        # points in view and in front but not observed must be hidden behind a nearer surface
        uv_all, z_all = project(cam, T, pts)
        inview = (z_all > 0.2) & (uv_all[:, 0] >= 0) & (uv_all[:, 0] <= cam.width - 1)
        inview &= (uv_all[:, 1] >= 0) & (uv_all[:, 1] <= cam.height - 1)
        hidden = np.setdiff1d(np.flatnonzero(inview), ids)
        # leave out points under decals (paint, posters) a few mm above their surface
        hidden = hidden[occluded(scene, T[:3, 3], pts[hidden], margin=DECAL_MARGIN_M)]
        if len(hidden) >= 10:
            ph = np.round(uv_all[hidden]).astype(int)
            nearer = (
                cv2.dilate(finite, np.ones((3, 3)))[ph[:, 1], ph[:, 0]]
                < z_all[hidden] * (1 - DEPTH_TOL_REL) - 0.02
            )
            assert nearer.mean() >= 0.9, f"{scene.name} frame {f}: hidden points not behind a surface"


@pytest.mark.parametrize("name", SCENE_NAMES)
@pytest.mark.parametrize("seconds", [3.0, 40.0])
def test_path_stays_in_free_space_and_returns(name, seconds):
    scene = make_scene(name, 0)
    t, T = walkthrough(scene, int(seconds * 15), 15.0, seed=3)
    c = T[:, :3, 3]
    assert scene.clearance(c).min() >= MIN_CLEARANCE_M
    assert scene.in_free_space(c[:, :2], margin=MIN_CLEARANCE_M).all()
    step = np.linalg.norm(np.diff(c, axis=0), axis=1) * 15.0
    assert 0.5 <= np.median(step) <= 1.6, "walking speed about 1 m/s"
    back = np.linalg.norm(c[-1] - c[0])
    assert back <= 0.1 * max(np.sum(step) / 15.0, 1.0) + 0.3 + 2 * U_TURN_OFFSET_M, "returns near the start"
    R = T[:, :3, :3]
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)
    assert np.allclose(np.linalg.det(R), 1.0)
    # the camera looks roughly horizontally (small pitch and roll): its y axis points down
    assert (R[:, 2, 1] < -0.97).all()
    pitch = np.degrees(np.arcsin(R[:, 2, 2]))  # elevation of the optical axis
    assert np.abs(pitch - scene.pitch_deg).max() < 6.0
    yaw = np.unwrap(np.arctan2(R[:, 1, 2], R[:, 0, 2]))
    assert np.ptp(yaw) > math.radians(80), "the walk turns"


def test_scene_axes_and_segment_labels():
    for name in SCENE_NAMES:
        scene = make_scene(name, 0)
        assert np.allclose(scene.axes[0], [0, 0, 1])
        assert np.allclose(np.linalg.norm(scene.axes, axis=1), 1)
        assert np.allclose(scene.axes[1:, 2], 0), "the other axes are horizontal"
        d = scene.segments[:, 1] - scene.segments[:, 0]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        cos = np.abs(d @ scene.axes.T)  # (S, A)
        lab = scene.segment_axis
        assert (cos[lab >= 0, lab[lab >= 0]] > math.cos(math.radians(0.01))).all()
        assert (cos[lab < 0].max(axis=1) < math.cos(math.radians(5))).all()
        assert (lab < 0).sum() >= 4, "a few non-structural segments"
        assert set(lab[lab >= 0].tolist()) == set(range(len(scene.axes))), "every axis has segments"


def test_atlanta_has_three_non_orthogonal_horizontal_axes():
    scene = make_scene("atlanta", 0)
    h = scene.axes[1:]
    ang = np.degrees(np.arccos(np.clip(np.abs(h @ h.T), 0, 1)))
    found = [
        (i, j, k)
        for i in range(len(h))
        for j in range(i + 1, len(h))
        for k in range(j + 1, len(h))
        if all(10 < ang[p, q] < 80 for p, q in ((i, j), (i, k), (j, k)))
    ]
    assert found, f"no three pairwise non-orthogonal horizontal axes in {ang.round(1)}"


def test_scenes_are_deterministic():
    a, b = make_scene("corridor", 5), make_scene("corridor", 5)
    assert np.array_equal(a.quad_corners, b.quad_corners) and np.array_equal(a.segments, b.segments)
    assert [m.seed for m in a.materials] == [m.seed for m in b.materials]
    c = make_scene("corridor", 6)
    assert [m.seed for m in a.materials] != [m.seed for m in c.materials]


AA_MEAN_ABS_DIFF = 3.0  # grey levels between 2x supersampling and a 4x reference
AA_GAIN = 1.5  # 1x sampling must be at least this much further from the reference


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_supersampling_approaches_a_4x_reference(name):
    """Anti-aliasing: 2x supersampling is close to a 4x render, and closer than plain 1x sampling."""
    scene = make_scene(name, 0)
    cfg = SynthConfig(scene=name, width=160, height=120)
    cam = cfg.camera()
    _, T = walkthrough(scene, 60, 10.0, 0)
    r4 = Renderer(scene, cam, 4)
    ref = r4.render(T[30])[0] * 230
    d2 = np.abs(Renderer(scene, cam, 2, r4.pyramids).render(T[30])[0] * 230 - ref).mean()
    d1 = np.abs(Renderer(scene, cam, 1, r4.pyramids).render(T[30])[0] * 230 - ref).mean()
    assert d2 < AA_MEAN_ABS_DIFF and d1 > AA_GAIN * d2, (d1, d2)


MAX_SHIFT_PX = 0.1  # systematic shift of rendered edges against projected GT (pixel-centre convention)
MAX_MEDIAN_OFFSET_PX = 0.1


def test_rendered_edges_sit_on_the_gt_to_a_tenth_of_a_pixel(rendered):
    scene, cam, frames = rendered
    off, nrm = [], []
    for T, img, depth in frames:
        o, n = edge_offsets(cam, img, depth, T, scene)
        off.append(o)
        nrm.append(n)
    off, nrm = np.concatenate(off), np.concatenate(nrm)
    assert len(off) >= 8, f"{scene.name}: only {len(off)} strong edges"
    assert np.linalg.norm(global_shift(off, nrm)) < MAX_SHIFT_PX
    assert np.median(np.abs(off)) < MAX_MEDIAN_OFFSET_PX
    # and the measurement sees a half-pixel shift of the camera
    T, img, depth = frames[0]
    shifted = cv2.warpAffine(img, np.float32([[1, 0, 0.5], [0, 1, 0.0]]), (cam.width, cam.height))
    o, n = edge_offsets(cam, shifted, depth, T, scene)
    assert abs(global_shift(o, n)[0] - 0.5) < 0.15


def test_sample_video_edges_sit_on_the_gt():
    """The bundled video itself (mp4, noise, blur, exposure) against its GT files, to a fraction of a px."""
    root = Path(__file__).resolve().parents[1] / "samples" / "tiny"
    if not (root / "video.mp4").is_file():
        pytest.skip("samples/tiny is not bundled")
    cam = Camera.from_dict(json.loads((root / "camera.json").read_text()))
    tum = np.loadtxt(root / "gt" / "trajectory.tum")
    info = json.loads((root / "scene.json").read_text())
    scene = make_scene(info["scene"], info["seed"])
    seg = np.loadtxt(root / "gt" / "segments.txt")
    assert np.allclose(seg[:, :6].reshape(-1, 2, 3), scene.segments, atol=1e-6)
    cap = cv2.VideoCapture(str(root / "video.mp4"))
    off, nrm = [], []
    for f in range(0, 75, 15):
        cap.set(cv2.CAP_PROP_POS_FRAMES, f)
        ok, frame = cap.read()
        assert ok
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(tum[f, 4:]).as_matrix()
        T[:3, 3] = tum[f, 1:4]
        depth = np.full((cam.height, cam.width), np.inf, np.float32)
        o, n = edge_offsets(cam, frame.astype(np.float32) / 230, depth, T, scene)
        off.append(o)
        nrm.append(n)
    off, nrm = np.concatenate(off), np.concatenate(nrm)
    assert len(off) >= 20
    assert np.linalg.norm(global_shift(off, nrm)) < 2 * MAX_SHIFT_PX
    assert np.median(np.abs(off)) < 2 * MAX_MEDIAN_OFFSET_PX


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_multisampled_edges_sit_on_the_gt(name):
    """With msaa (textures once per pixel) coverage is still per sample: edges as exact as with SSAA."""
    scene = make_scene(name, 0)
    cfg = SynthConfig(scene=name, width=320, height=240, fps=10, seconds=12.0)
    cam = cfg.camera()
    _, T = walkthrough(scene, cfg.n_frames, cfg.fps, 0)
    r = Renderer(scene, cam, 2, msaa=True)
    off, nrm = [], []
    ok = n = 0
    for i in FRAMES:
        img, depth = r.render(T[i], with_depth=True)
        o, nn = edge_offsets(cam, img, depth, T[i], scene)
        off.append(o)
        nrm.append(nn)
        p, k = edge_scores(cam, img, depth, T[i], scene)
        ok, n = ok + p, n + k
    off, nrm = np.concatenate(off), np.concatenate(nrm)
    assert np.linalg.norm(global_shift(off, nrm)) < MAX_SHIFT_PX
    assert np.median(np.abs(off)) < MAX_MEDIAN_OFFSET_PX
    assert ok / n >= MIN_EDGE_FRACTION


NOISE_STD_TOL = 0.05  # relative, unit-std Gaussian noise fields
NOISE_CORR_TOL = 0.05  # autocorrelation at a lag of sigma against exp(-1/4)
MAX_REPEAT_NCC = 0.8  # best correlation of a 0.5 m texture patch elsewhere on its canvas (a repeat: 1)
SPLIT_QUAD_MAX_DIFF = 1.0  # grey levels: a wall drawn as one quad or as two sharing its texture frame


@pytest.mark.parametrize("sigma", [1.5, 4.0, 24.0])  # drawn at full resolution, on a 2x and an 8x grid
def test_gaussian_noise_has_unit_std_and_the_asked_correlation(sigma):
    """Known answer: white noise through a Gaussian of std sigma correlates as exp(-d^2 / (4 sigma^2))."""
    field = gaussian_noise(np.random.default_rng(0), (1200, 1500), sigma)
    assert field.shape == (1200, 1500) and field.dtype == np.float32
    assert abs(field.std() - 1) < NOISE_STD_TOL, field.std()
    lag = round(sigma)
    corr = np.mean(field[:, lag:] * field[:, :-lag]) / field.var()
    assert abs(corr - math.exp(-(lag**2) / (4 * sigma**2))) < NOISE_CORR_TOL, corr


def test_textures_do_not_repeat_over_a_long_wall():
    """A 16 m wall's canvas: no patch of it shows up again elsewhere (the old 2 m periodic texture did)."""
    mat = make_scene("corridor", 0).materials[0]
    canvas = make_texture(mat, (512, 4096), 256.0, seed=0)
    assert np.array_equal(canvas, make_texture(mat, (512, 4096), 256.0, seed=0)), "deterministic"
    for x0 in (300, 1700, 3500):
        patch = canvas[200:328, x0 : x0 + 128]
        ncc = cv2.matchTemplate(canvas, patch, cv2.TM_CCOEFF_NORMED)
        ncc[200 - 128 : 200 + 128, x0 - 128 : x0 + 128] = -1  # its own place
        assert ncc.max() < MAX_REPEAT_NCC, (x0, ncc.max())


def test_quads_sharing_a_texture_frame_render_without_a_seam():
    """A wall drawn as one quad or as two abutting quads on one texture frame gives the same image: split on
    a tile boundary, 2 m from the wall's end, facing the camera, so that both draw the same tiles at the
    same mip levels."""
    from papl_mapper.synth.scenes import SceneBuilder

    def wall(cuts):
        b = SceneBuilder("wall", [[0, 0, 1], [1, 0, 0], [0, 1, 0]], ["vertical", "x", "y"], 0)
        mat = b.material("wall", (0.7, 0.7, 0.7), 0.3, 0.1)
        for a0, a1 in zip(cuts[:-1], cuts[1:], strict=True):
            b.quad([a0, 2, 0], [a1 - a0, 0, 0], [0, 0, 2.5], mat, tex_origin=[-3, 2, 0])
        return b.build([[0, 0], [1, 0], [1, 1]], [np.array([[-3, -1], [3, -1], [3, 1.9], [-3, 1.9]])])

    cam = Camera(320, 240, 200.0, 200.0, 159.5, 119.5)
    T_wc = np.eye(4)
    T_wc[:3, :3] = Rotation.from_euler("x", -90, degrees=True).as_matrix()  # looking along +y
    T_wc[:3, 3] = [1.0, 0.5, 1.2]
    one = Renderer(wall([-3.0, 3.0]), cam, 2).render(T_wc)[0] * 170
    two = Renderer(wall([-3.0, 1.0, 3.0]), cam, 2).render(T_wc)[0] * 170
    assert one.std() > 5, "textured"
    assert np.abs(one - two).max() < SPLIT_QUAD_MAX_DIFF, np.abs(one - two).max()
