"""Off-screen previews checked as images (colours per axis, legend, framing); bad input; no backend."""

from __future__ import annotations

import functools
import math
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from papl_mapper.errors import BackendUnavailableError, InputError
from papl_mapper.gui import preview as P
from papl_mapper.map import Axes, Camera, Keyframes, Lines, LineState, Map, Points
from papl_mapper.palette import UNANCHORED_RGB, axis_colors

# named tolerances
COLOUR_DIST = 30.0  # a pixel belongs to a palette colour within this RGB distance
SHARE_TOL = 0.35  # relative tolerance of a colour's pixel share against its projected-length share
MIN_INK_FRACTION = 0.002  # a non-blank render has at least this fraction of non-background pixels


def building_map(
    n_per_axis: tuple[int, ...] = (40, 30, 25, 20),
    length_per_axis: tuple[float, ...] = (3.0, 2.0, 4.0, 2.5),
    n_unanchored: int = 15,
    seed: int = 1,
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
    scale: float = 1.0,
    n_points: int = 500,
) -> Map:
    """A sparse synthetic 'building': a vertical axis and Atlanta horizontals at 0, 90 and 30 degrees."""
    rng = np.random.default_rng(seed)
    n_axes = len(n_per_axis)
    dirs = [np.array([0.0, 0.0, 1.0])]
    for ang in (0.0, 90.0, 30.0, 60.0)[: n_axes - 1]:
        a = math.radians(ang)
        dirs.append(np.array([math.cos(a), math.sin(a), 0.0]))
    dirs = np.array(dirs)
    ends, lab = [], []
    for a in range(n_axes):
        mid = rng.uniform([-10, -8, 0], [10, 8, 6], (n_per_axis[a], 3))
        half = 0.5 * length_per_axis[a] * dirs[a]
        ends.append(np.stack([mid - half, mid + half], axis=1))
        lab += [a] * n_per_axis[a]
    d = rng.normal(size=(n_unanchored, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    mid = rng.uniform([-10, -8, 0], [10, 8, 6], (n_unanchored, 3))
    ends.append(np.stack([mid - d, mid + d], axis=1))
    lab += [-1] * n_unanchored
    ends = np.concatenate(ends) * scale + np.asarray(offset)
    lab = np.asarray(lab)
    m_lines = len(lab)
    w = np.zeros((m_lines, n_axes))
    w[lab >= 0, lab[lab >= 0]] = 1.0
    n_kf = 6
    T = np.repeat(np.eye(4)[None], n_kf, axis=0)
    T[:, :3, 3] = (
        np.stack([np.linspace(-8, 8, n_kf), np.zeros(n_kf), np.full(n_kf, 1.6)], 1)
    ) * scale + offset
    kf = Keyframes(np.arange(n_kf), np.arange(n_kf) * 10, np.arange(n_kf) / 3.0, T)
    pts = Points(
        np.arange(n_points),
        rng.uniform([-10, -8, 0], [10, 8, 6], (n_points, 3)) * scale + offset,
        rng.integers(0, 255, (n_points, 3), dtype=np.uint8),
        np.zeros((0, 2), np.int64),
        np.zeros((0, 2)),
    )
    lines = Lines(
        np.arange(m_lines),
        ends,
        w,
        np.where(lab >= 0, LineState.ANCHORED, LineState.ORTHONORMAL).astype(np.int8),
        np.where(lab >= 0, 0, -1),
        np.where(lab >= 0, 0.2, np.nan),
        np.zeros((0, 2), np.int64),
        np.zeros((0, 4)),
    )
    m = Map(
        Camera(640, 480, 500.0, 500.0, 319.5, 239.5), kf, pts, lines, Axes(dirs, 0), {"units": "arbitrary"}
    )
    m.validate()
    return m


def _load(path: Path) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(path).convert("RGB")).astype(np.float64)


def _near(img: np.ndarray, rgb) -> np.ndarray:
    return np.linalg.norm(img - np.asarray(rgb, np.float64), axis=-1) < COLOUR_DIST


def _legend(m: Map, o: P.PreviewOptions | None = None) -> list[str]:
    return [label for label, _ in P.prepare_scene(m, o or _opts()).legend]


def _scene_mask(img: np.ndarray, legend: list[str]) -> np.ndarray:
    """True on pixels of the 3D render (below the title band, outside the legend panel)."""
    h, w = img.shape[:2]
    mask = np.zeros((h, w), bool)
    mask[P._band_height(h) :, :] = True
    x0, y0, x1, y1 = P.legend_box((w, h), legend)
    mask[y0 - 2 : y1 + 3, x0 - 2 : x1 + 3] = False
    return mask


def _opts(**kw) -> P.PreviewOptions:
    base = dict(width=800, height=600, show_points=False, show_trajectory=False)
    base.update(kw)
    return P.PreviewOptions(**base)


@pytest.fixture(scope="module")
def building() -> Map:
    return building_map()


@pytest.fixture(scope="module")
def four_views(tmp_path_factory, building) -> P.PreviewResult:
    return P.render_views(building, tmp_path_factory.mktemp("views"), _opts())


def test_four_views_written_not_blank_and_sized(four_views, building):
    assert [p.name for p in four_views.paths] == [f"{v}.png" for v in P.VIEWS]
    for p in four_views.paths:
        img = _load(p)
        assert img.shape == (600, 800, 3)
        scene = img[_scene_mask(img, _legend(building))]
        ink = (np.abs(scene - 255).sum(axis=1) > 30).mean()
        assert ink > MIN_INK_FRACTION, f"{p.name} looks blank ({ink:.4f})"
    # the views differ from each other
    imgs = [_load(p) for p in four_views.paths]
    for i in range(4):
        for j in range(i + 1, 4):
            assert np.abs(imgs[i] - imgs[j]).mean() > 1.0


def test_axis_colours_in_proportion_to_projected_line_length(four_views, building):
    """Pixels of each axis colour in the isometric view ~ that axis' total on-screen length."""
    img = _load(four_views.paths[0])
    mask = _scene_mask(img, _legend(building))
    n_axes = len(building.axes)
    colours = list(axis_colors(n_axes, 0)) + [UNANCHORED_RGB]
    counts = np.array([(_near(img, c) & mask).sum() for c in colours], np.float64)
    d_view = np.asarray(P._VIEW_GEOMETRY["isometric"][0], np.float64)
    d_view /= np.linalg.norm(d_view)
    seg = building.lines.endpoints_w[:, 1] - building.lines.endpoints_w[:, 0]
    proj = np.linalg.norm(seg - np.outer(seg @ d_view, d_view), axis=1)  # length on screen
    lab = building.lines.axis_of_line()
    expected = np.array([proj[lab == a].sum() for a in range(n_axes)] + [proj[lab < 0].sum()])
    share, want = counts / counts.sum(), expected / expected.sum()
    assert counts.min() > 50, counts
    np.testing.assert_allclose(share, want, rtol=SHARE_TOL)


def test_top_view_shows_vertical_lines_as_dots(four_views, building):
    """Seen from above, vertical segments collapse to dots: their colour nearly vanishes."""
    vert = axis_colors(4, 0)[0]
    iso, top = _load(four_views.paths[0]), _load(four_views.paths[1])
    n_iso = (_near(iso, vert) & _scene_mask(iso, _legend(building))).sum()
    n_top = (_near(top, vert) & _scene_mask(top, _legend(building))).sum()
    assert n_top < 0.1 * n_iso, (n_top, n_iso)


def test_legend_swatches_in_top_right_corner(four_views, building):
    img = _load(four_views.paths[0])
    h, w = img.shape[:2]
    x0, y0, x1, y1 = P.legend_box((w, h), _legend(building))
    assert x0 > w / 2 and y1 < h / 2  # top-right corner
    panel = img[y0:y1, x0:x1]
    for c in list(axis_colors(4, 0)) + [UNANCHORED_RGB]:
        exact = (np.abs(panel - np.asarray(c, np.float64)).sum(axis=-1) == 0).sum()
        assert exact > 50, f"legend swatch {tuple(c)} missing ({exact} px)"


def test_same_map_same_options_same_image(tmp_path, building):
    a = P.render_views(building, tmp_path / "a", _opts(views=("top",), show_points=True, max_points=100))
    b = P.render_views(building, tmp_path / "b", _opts(views=("top",), show_points=True, max_points=100))
    np.testing.assert_array_equal(_load(a.paths[0]), _load(b.paths[0]))


def test_framing_follows_the_map_wherever_it_is_and_keeps_clear_of_the_legend(tmp_path):
    """A map far from the origin and tiny in scale fills the frame the same way, left of the legend."""
    m = building_map(offset=(5000.0, -3000.0, 200.0), scale=0.001)
    for view in ("top", "isometric"):
        res = P.render_views(m, tmp_path, _opts(views=(view,)))
        img = _load(res.paths[0])
        band = P._band_height(600)
        ink = np.abs(img - 255).sum(axis=-1) > 30
        ink[:band] = False
        x0, y0, x1, y1 = P.legend_box((800, 600), _legend(m))
        ink[y0 - 1 : y1 + 2, x0 - 1 : x1 + 2] = False
        ys, xs = np.nonzero(ink)
        assert xs.max() - xs.min() > 0.5 * x0 or ys.max() - ys.min() > 0.6 * (600 - band), view
        assert xs.min() > 5 and xs.max() < x0 - 2 and ys.min() > band and ys.max() < 595, view


def test_points_trajectory_frusta_and_dark_theme(tmp_path, building):
    res = P.render_views(
        building,
        tmp_path,
        _opts(views=("isometric",), show_points=True, show_trajectory=True, show_frusta=True, theme="dark"),
    )
    img = _load(res.paths[0])
    mask = _scene_mask(img, _legend(building, _opts(show_points=True, show_trajectory=True)))
    bg = np.asarray(P.THEMES["dark"]["background"], np.float64)
    assert np.median(np.linalg.norm(img[mask] - bg, axis=1)) < 3  # mostly dark background
    assert (_near(img, P.TRAJECTORY_RGB) & mask).sum() > 30  # trajectory and frusta drawn


def test_empty_map_renders_a_labelled_view(tmp_path):
    m = Map(Camera(640, 480, 500.0, 500.0, 319.5, 239.5))
    res = P.render_views(m, tmp_path, _opts(views=("isometric",)))
    assert any("empty map" in n for n in res.notes)
    img = _load(res.paths[0])
    h, w = img.shape[:2]
    centre = img[h // 2 : h // 2 + 40, w // 4 : 3 * w // 4]
    assert (centre.sum(axis=-1) < 300).sum() > 100  # the dark label text in the middle


def test_single_axis_map_legend(tmp_path):
    m = building_map(n_per_axis=(30,), length_per_axis=(3.0,), n_unanchored=5)
    scene = P.prepare_scene(m, _opts())
    assert [lbl.split()[0] for lbl, _ in scene.legend] == ["vertical", "unanchored"]
    res = P.render_views(m, tmp_path, _opts(views=("front",)))
    img = _load(res.paths[0])
    assert (_near(img, axis_colors(1, 0)[0]) & _scene_mask(img, _legend(m))).sum() > 100


def test_huge_map_is_decimated_and_says_so(tmp_path):
    m = building_map(n_per_axis=(2000, 1500, 1000), length_per_axis=(1.0, 1.0, 1.0), n_unanchored=500)
    res = P.render_views(m, tmp_path, _opts(views=("top",), max_lines=1000))
    assert any("1,000 of 5,000 lines" in n for n in res.notes)
    scene = P.prepare_scene(m, _opts(max_lines=1000))
    assert len(scene.endpoints_w) == 1000
    # the subset is seeded: same options, same subset
    again = P.prepare_scene(m, _opts(max_lines=1000))
    np.testing.assert_array_equal(scene.endpoints_w, again.endpoints_w)


def test_frusta_are_thinned_and_point_forward():
    from .conftest import make_map

    m = make_map(n_kf=100)
    scene = P.prepare_scene(m, _opts(show_frusta=True, max_frusta=10))
    assert len(scene.frusta_w) == 10 and any("every 10th keyframe" in n for n in scene.notes)
    # identity rotations: the image corners lie in front of the apex (+z of the camera = +z of the world)
    np.testing.assert_allclose(scene.frusta_w[:, 0], m.keyframes.T_wc[::10, :3, 3])
    assert (scene.frusta_w[:, 1:, 2] > scene.frusta_w[:, :1, 2]).all()


def test_preview_frusta_are_the_exports_frusta_at_the_image_borders():
    """Preview and exports draw one frustum, through the image's outer corners (-0.5 .. width - 0.5 with
    pixel centres at integers), not through the corner pixels' centres (half a pixel inside)."""
    from papl_mapper.exporters.scene import frustum_segments

    from .conftest import make_map

    m = make_map(n_kf=5)
    scene = P.prepare_scene(m, _opts(show_frusta=True))
    exported = frustum_segments(m, 1.0).reshape(len(m.keyframes), 8, 2, 3)[:, :4, 1]  # ray ends
    apex = scene.frusta_w[:, :1]
    depth = (scene.frusta_w[:, 1:] - apex) @ np.array([0.0, 0.0, 1.0])  # identity rotations: depth = dz
    np.testing.assert_allclose(scene.frusta_w[:, 1:], apex + (exported - apex) * depth[..., None])
    cam = m.camera
    corners_c = scene.frusta_w[0, 1:] - scene.frusta_w[0, 0]
    uv = corners_c[:, :2] / corners_c[:, 2:] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    w, h = cam.width - 0.5, cam.height - 0.5
    np.testing.assert_allclose(uv, [[-0.5, -0.5], [w, -0.5], [w, h], [-0.5, h]], atol=1e-9)


def test_no_backend_is_a_clear_error(tmp_path):
    """Simulate missing GL libraries: broken libEGL/libOSMesa shadow the real ones."""
    fake = tmp_path / "fakegl"
    fake.mkdir()
    for name in (
        "libEGL.so.1",
        "libEGL.so",
        "libOSMesa.so.8",
        "libOSMesa.so.6",
        "libOSMesa.so",
        "libGL.so.1",
    ):
        (fake / name).write_bytes(b"")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "VTK_DEFAULT_OPENGL_WINDOW")}
    env["LD_LIBRARY_PATH"] = str(fake)
    with pytest.raises(BackendUnavailableError) as err:
        P.find_offscreen_backend(env)
    assert "libegl1" in str(err.value) and "libosmesa6" in str(err.value)


def test_falls_back_to_osmesa_without_egl(tmp_path):
    """With libEGL broken (shadowed by an empty file), the probe picks OSMesa."""
    fake = tmp_path / "noegl"
    fake.mkdir()
    for name in ("libEGL.so.1", "libEGL.so", "libEGL_mesa.so.0"):
        (fake / name).write_bytes(b"")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "VTK_DEFAULT_OPENGL_WINDOW")}
    env["LD_LIBRARY_PATH"] = str(fake)
    assert P.find_offscreen_backend(env) == "vtkOSOpenGLRenderWindow"


def test_backend_failure_writes_nothing(tmp_path, monkeypatch, building):
    def broken(env=None):
        raise BackendUnavailableError("no off-screen OpenGL backend (simulated)")

    monkeypatch.setattr(P, "find_offscreen_backend", broken)
    with pytest.raises(BackendUnavailableError):
        P.render_views(building, tmp_path / "out", _opts())
    assert not list((tmp_path / "out").glob("*.png"))


def test_the_working_backend_is_found():
    assert P.find_offscreen_backend() in [b[0] for b in P.BACKENDS] + [
        os.environ.get("VTK_DEFAULT_OPENGL_WINDOW")
    ]


def test_turntable_gif_and_mp4(tmp_path, building):
    import cv2
    from PIL import Image, ImageSequence

    o = _opts(views=("isometric",), turntable="gif", turntable_frames=6, turntable_size=(320, 240))
    res = P.render_views(building, tmp_path, o)
    with Image.open(res.turntable) as gif:
        frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(gif)]
    assert len(frames) == 6 and frames[0].shape[:2] == (240, 320)
    assert np.abs(frames[0].astype(float) - frames[3].astype(float)).mean() > 1.0  # it turns
    o.turntable = "mp4"
    res = P.render_views(building, tmp_path, o)
    cap = cv2.VideoCapture(str(res.turntable))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 6


def test_bad_options_are_input_errors(tmp_path, building):
    with pytest.raises(InputError, match="unknown preview view"):
        P.render_views(building, tmp_path, _opts(views=("diagonal",)))
    with pytest.raises(InputError, match="size"):
        P.render_views(building, tmp_path, _opts(width=10))


def test_cli_render(tmp_path, building, capsys):
    from papl_mapper.cli import main

    path = building.save(tmp_path / "b.papl")
    rc = main(
        ["render", str(path), "--out", str(tmp_path / "prev"), "--size", "320x240", "--views", "top,side"]
    )
    assert rc == 0
    assert sorted(p.name for p in (tmp_path / "prev").glob("*.png")) == ["side.png", "top.png"]
    assert _load(tmp_path / "prev" / "top.png").shape == (240, 320, 3)
    rc = main(["render", str(tmp_path / "missing.papl"), "--out", str(tmp_path / "x")])
    assert rc == 2
    assert "missing.papl" in capsys.readouterr().err


def test_gui_does_not_import_pyvista_until_rendering():
    import subprocess

    code = "import sys, papl_mapper.gui; print('pyvista' in sys.modules, 'vtk' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


def test_the_backend_is_probed_once_per_environment(monkeypatch):
    """A search begun early (`start_offscreen_probe`) is the one the previews wait for, and the window
    class `_plotter` sets for VTK is no reason to probe again."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "VTK_DEFAULT_OPENGL_WINDOW")}
    env["PAPL_TEST_PROBE_ENV"] = "once"  # an environment no other test has probed
    probes = []
    real = P._probe.__wrapped__

    @functools.lru_cache(maxsize=8)
    def counted(window_class, env_items):
        probes.append(window_class)
        return real(window_class, env_items)

    monkeypatch.setattr(P, "_probe", counted)
    P.start_offscreen_probe(env)
    found = P.find_offscreen_backend(env)
    assert P.find_offscreen_backend({**env, "VTK_DEFAULT_OPENGL_WINDOW": found}) == found
    assert len(probes) == len(set(probes)) >= 1
