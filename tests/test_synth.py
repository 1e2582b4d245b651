"""The synthetic walkthrough generator: folder layout, video, determinism, CLI, bad input, tracks."""

from __future__ import annotations

import json
import math
import shlex
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from papl_mapper.cli import build_parser, main
from papl_mapper.cli.synth import config_from_args
from papl_mapper.errors import InputError
from papl_mapper.map import Camera, LineState, Map
from papl_mapper.synth import SynthConfig, generate, make_scene, tracks_from_scene, walkthrough
from papl_mapper.synth.generate import KEYFRAME_EVERY, _PostProcess
from papl_mapper.synth.project import project

TINY = dict(scene="corridor", width=96, height=72, fps=10.0, seconds=2.1, supersample=1)
PIXEL_TOL = 1e-6
NOISE_PX = 0.7


def _frames(video: Path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(video))
    out = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        out.append(f)
    cap.release()
    return out


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "tiny"
    cfg = SynthConfig(
        **TINY, noise_sigma=1.0, exposure_jitter=0.2, motion_blur=0.5, write_frames=True, seed=4
    )
    generate(cfg, out)
    return cfg, out


def test_layout_video_and_gt_files(tiny):
    cfg, out = tiny
    n = cfg.n_frames
    assert n == 21
    frames = _frames(out / "video.mp4")
    assert len(frames) == n and frames[0].shape == (72, 96, 3)
    pngs = sorted((out / "frames").glob("*.png"))
    assert [p.name for p in pngs[:2]] == ["000000.png", "000001.png"] and len(pngs) == n
    png0 = cv2.imread(str(pngs[0]))
    assert np.abs(png0.astype(int) - frames[0].astype(int)).mean() < 6, "video is the PNG frames, lossy"
    t = np.loadtxt(out / "timestamps.txt")
    assert np.allclose(t, np.arange(n) / cfg.fps)
    tum = np.loadtxt(out / "gt" / "trajectory.tum")
    assert tum.shape == (n, 8) and np.allclose(tum[:, 0], t, atol=1e-9)
    cam = Camera.from_dict(json.loads((out / "camera.json").read_text()))
    assert (cam.width, cam.height) == (96, 72) and np.allclose(cam.distortion, 0)
    assert math.isclose(2 * math.degrees(math.atan(cam.width / 2 / cam.fx)), cfg.hfov_deg)
    seg = np.loadtxt(out / "gt" / "segments.txt")
    scene = make_scene("corridor", cfg.seed)
    assert np.allclose(seg[:, :6].reshape(-1, 2, 3), scene.segments, atol=1e-6)
    assert np.array_equal(seg[:, 6].astype(int), scene.segment_axis)
    axes = json.loads((out / "gt" / "axes.json").read_text())
    assert axes["vertical_index"] == 0 and np.allclose(axes["directions"][0], [0, 0, 1])
    assert len(axes["names"]) == len(axes["directions"]) == 3
    # the TUM poses are the walkthrough's T_wc
    _, T = walkthrough(scene, n, cfg.fps, cfg.seed, cfg.speed)
    assert np.allclose(tum[:, 1:4], T[:, :3, 3], atol=1e-8)
    R = Rotation.from_quat(tum[:, 4:]).as_matrix()
    assert np.allclose(R, T[:, :3, :3], atol=1e-8)
    info = json.loads((out / "scene.json").read_text())
    assert info["scene"] == "corridor" and info["seed"] == 4 and info["frames"] == n
    assert info["path_length_m"] > 0.5
    assert not list(out.glob(".*tmp*")), "no temporary files left"


def test_gt_map(tiny):
    cfg, out = tiny
    m = Map.load(out / "gt" / "map.papl")
    scene = make_scene("corridor", cfg.seed)
    tum = np.loadtxt(out / "gt" / "trajectory.tum")
    assert np.array_equal(m.keyframes.frame_index, np.arange(0, cfg.n_frames, KEYFRAME_EVERY))
    assert np.allclose(m.keyframes.T_wc[:, :3, 3], tum[::KEYFRAME_EVERY, 1:4], atol=1e-8)
    assert m.metadata["units"] == "m"
    assert np.allclose(m.lines.endpoints_w, scene.segments)
    lab = scene.segment_axis
    assert np.array_equal(m.lines.axis_of_line(), lab)
    assert np.array_equal(m.lines.state == LineState.ANCHORED, lab >= 0)
    # anchored lines: inverse depth of the midpoint in their reference keyframe
    a = np.flatnonzero(lab >= 0)
    kf = {int(k): T for k, T in zip(m.keyframes.ids, m.keyframes.T_wc, strict=True)}
    for i in a[:20]:
        T = kf[int(m.lines.ref_keyframe_id[i])]
        _, z = project(m.camera, T, scene.segments[i].mean(0)[None])
        if z[0] > 0.1:
            assert math.isclose(m.lines.inverse_depth[i], 1 / z[0], rel_tol=1e-9)
    # observations reproject: a point observation is the projection of its point
    pid, kid = m.points.obs_ids[0]
    uv, _ = project(m.camera, kf[int(kid)], m.points.xyz[pid][None])
    assert np.allclose(uv[0], m.points.obs_uv[0], atol=PIXEL_TOL)
    assert len(m.points) > 20 and len(m.lines.obs_ids) > 20


def test_same_seed_same_output_other_seed_differs(tiny, tmp_path):
    cfg, out = tiny
    generate(cfg, tmp_path / "again")
    a, b = _frames(out / "video.mp4"), _frames(tmp_path / "again" / "video.mp4")
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    for name in ("timestamps.txt", "gt/trajectory.tum", "gt/segments.txt", "gt/axes.json", "camera.json"):
        assert (out / name).read_bytes() == (tmp_path / "again" / name).read_bytes(), name
    other = SynthConfig(**{**TINY, "seconds": 0.3}, seed=5)
    generate(other, tmp_path / "other")
    c = _frames(tmp_path / "other" / "video.mp4")
    assert not np.array_equal(a[0], c[0])


def test_command_in_scene_json_regenerates_the_config(tiny):
    cfg, out = tiny
    info = json.loads((out / "scene.json").read_text())
    argv = shlex.split(info["command"])
    assert argv[:3] == ["papl-map", "synth", "corridor"]
    args = build_parser().parse_args(argv[1:])
    assert config_from_args(args) == cfg
    assert args.out == str(out)


def test_cli_writes_a_walkthrough(tmp_path, capsys):
    out = tmp_path / "cli"
    rc = main(["synth", "garage", "--out", str(out), "--width", "64", "--height", "48", "--seconds", "0.5"])
    assert rc == 0
    assert len(_frames(out / "video.mp4")) == 15
    assert "15 frames" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["synth", "castle"], "known scenes: corridor, atlanta, garage"),
        (["synth", "corridor", "--seconds", "0"], "frames"),
        (["synth", "corridor", "--seconds", "0.01"], "0 frames"),
        (["synth", "corridor", "--width", "-640"], "resolution"),
        (["synth", "corridor", "--height", "0"], "resolution"),
        (["synth", "corridor", "--fps", "0"], "frame rate"),
        (["synth", "corridor", "--blur", "2"], "motion blur"),
        (["synth", "corridor", "--noise", "-1"], "negative"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, message):
    argv = [*argv[:2], "--out", str(tmp_path / "o"), *argv[2:]]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("papl-map synth: error:") and message in err
    assert not (tmp_path / "o").exists(), "nothing is written for a bad option"


def test_unwritable_out_dir(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["synth", "corridor", "--out", str(blocker / "sub"), "--seconds", "0.1"]) == 2
    assert "cannot write there" in capsys.readouterr().err
    with pytest.raises(InputError, match="not a folder"):
        generate(SynthConfig(**{**TINY, "seconds": 0.1}), blocker)


def test_tracks_from_scene_project_exactly_and_with_noise():
    scene = make_scene("corridor", 0)
    cam = SynthConfig(width=320, height=240).camera()
    t, T = walkthrough(scene, 20, 10.0, 0)
    tracks, pts = tracks_from_scene(scene, cam, T, t, n_surface_points=500, occlusion=True)
    assert len(tracks) == 20 and tracks.is_keyframe.sum() == 2
    for f in (0, 13):
        ids, uv = tracks.points_in(f)
        assert len(ids) > 30
        proj, _ = project(cam, T[f], pts[ids])
        assert np.abs(proj - uv).max() < PIXEL_TOL
        lids, xy, vp = tracks.lines_in(f)
        assert len(lids) > 5
        assert np.array_equal(vp, scene.segment_axis[lids])
        # observed endpoints lie on the projected infinite GT line
        a, _ = project(cam, T[f], scene.segments[lids, 0])
        b, _ = project(cam, T[f], scene.segments[lids, 1])
        d = b - a
        nrm = np.stack([-d[:, 1], d[:, 0]], 1) / np.linalg.norm(d, axis=1, keepdims=True)
        for e in (xy[:, :2], xy[:, 2:]):
            assert np.abs(((e - a) * nrm).sum(1)).max() < 1e-6
        R_cw = T[f][:3, :3].T
        assert np.allclose(tracks.vp_dirs_c[f], scene.axes @ R_cw.T)
    noisy, _ = tracks_from_scene(scene, cam, T, t, points_w=pts, noise_px=NOISE_PX, occlusion=True)
    assert np.array_equal(noisy.point_track, tracks.point_track)
    res = noisy.point_uv - tracks.point_uv
    assert abs(res.std() - NOISE_PX) < 0.1 * NOISE_PX
    no_occ, _ = tracks_from_scene(scene, cam, T, t, points_w=pts, occlusion=False)
    assert len(no_occ.point_track) > len(tracks.point_track), "occlusion hides some points"


def test_exposure_and_motion_blur():
    cfg = SynthConfig(width=160, height=120, fps=10, seconds=1.0, exposure_jitter=0.5, motion_blur=1.0)
    cam = cfg.camera()
    t = np.arange(100) / 10
    # pure yaw rotation of 2 degrees per frame about the vertical: image motion is horizontal, fx*tan(2 deg)
    from papl_mapper.synth.path import rotation_wc

    T = np.repeat(np.eye(4)[None], 100, axis=0)
    T[:, :3, :3] = rotation_wc(np.radians(2.0) * np.arange(100), 0.0, 0.0)
    post = _PostProcess(cfg, cam, t, T)
    assert np.ptp(post.gain) > 0.3, "half a stop RMS over 10 s"
    assert np.allclose(_PostProcess(SynthConfig(), cam, t, T).gain, 1.0)
    depth = np.full((120, 160), 5.0, np.float32)
    flow = post.image_motion(3, depth)
    expected = cam.fx * math.tan(math.radians(2.0))  # at the image centre; larger towards the sides
    assert expected <= abs(flow[0]) < 1.2 * expected and abs(flow[1]) < 0.05 * expected
    img = np.zeros((120, 160, 3), np.float32)
    img[:, 80:] = 1.0  # vertical edge: smeared horizontally
    img[60:, :40] = 1.0  # horizontal edge: unchanged
    out = post._blur(3, img, depth)
    width = int(((out[30, :, 0] > 0.02) & (out[30, :, 0] < 0.98)).sum())
    assert abs(width - abs(flow[0])) <= 2.5
    assert np.array_equal(out[:, 10, 0] > 0.5, img[:, 10, 0] > 0.5)


SAMPLES = Path(__file__).resolve().parents[1] / "samples"


@pytest.mark.parametrize(("name", "frames"), [("tiny", 75), ("demo", 420)])
def test_bundled_samples_are_complete_and_say_how_they_were_made(name, frames):
    out = SAMPLES / name
    if not out.is_dir():
        pytest.skip(f"{out} is not bundled in this checkout")
    info = json.loads((out / "scene.json").read_text())
    args = build_parser().parse_args(shlex.split(info["command"])[1:])
    cfg = config_from_args(args)
    assert cfg == SynthConfig(**info["config"]) and args.out == f"samples/{name}"
    assert (cfg.width, cfg.height, cfg.n_frames) == (640, 480, frames)
    assert info["command"] in (out / "README.md").read_text()
    assert len(np.loadtxt(out / "timestamps.txt")) == frames
    assert len(np.loadtxt(out / "gt" / "trajectory.tum")) == frames
    cap = cv2.VideoCapture(str(out / "video.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == frames
    ok, first = cap.read()
    cap.release()
    assert ok and first.shape == (480, 640, 3)
    m = Map.load(out / "gt" / "map.papl")
    assert len(m.keyframes) == math.ceil(frames / KEYFRAME_EVERY) and len(m.lines) > 100
    assert sum(p.stat().st_size for p in out.rglob("*") if p.is_file()) < 4e6, "a few MB at most"


def test_rerun_without_frames_removes_stale_frames_only(tmp_path):
    out = tmp_path / "run"
    cfg = SynthConfig(**{**TINY, "seconds": 0.3, "write_frames": True})
    generate(cfg, out)
    assert len(list((out / "frames").glob("*.png"))) == 3
    generate(SynthConfig(**{**TINY, "seconds": 0.3}), out)
    assert not (out / "frames").exists(), "frames of the earlier run would not match the new video"
    (out / "frames").mkdir()
    (out / "frames" / "notes.txt").write_text("mine")
    generate(SynthConfig(**{**TINY, "seconds": 0.3}), out)
    assert (out / "frames" / "notes.txt").exists(), "a folder holding other files is left alone"


def test_frames_folder_with_other_files_is_refused(tmp_path):
    out = tmp_path / "run"
    (out / "frames").mkdir(parents=True)
    (out / "frames" / "holiday.jpg").write_bytes(b"x")
    with pytest.raises(InputError, match="other than frames"):
        generate(SynthConfig(**{**TINY, "seconds": 0.3, "write_frames": True}), out)
    assert (out / "frames" / "holiday.jpg").exists() and not (out / "video.mp4").exists()


def test_every_option_round_trips_through_the_command_line():
    cfg = SynthConfig(
        scene="atlanta",
        width=320,
        height=200,
        fps=24.0,
        seconds=3.5,
        hfov_deg=80.0,
        noise_sigma=2.5,
        motion_blur=0.3,
        exposure_jitter=0.2,
        seed=9,
        write_frames=True,
        supersample=3,
        speed=1.3,
        msaa=True,
    )
    args = build_parser().parse_args(shlex.split(cfg.command("some dir"))[1:])
    assert config_from_args(args) == cfg and args.out == "some dir"


def test_interrupted_run_leaves_no_video_and_no_temporary_files(tmp_path):
    out = tmp_path / "run"

    def interrupt(done, total, message):
        if done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        generate(SynthConfig(**{**TINY, "seconds": 1.0, "write_frames": True}), out, progress=interrupt)
    assert not list(out.iterdir()), "nothing half-written"
