"""Adversarial synthetic recordings: rotation-only start and recording, dropped frames, a 1 Hz photo
set, a low-texture corridor. Each keeps the generator's layout and ground truth; all are seeded."""

from __future__ import annotations

import dataclasses
import json
import math
import shlex

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from papl_mapper.cli import build_parser, main
from papl_mapper.cli.synth import config_from_args
from papl_mapper.errors import InputError
from papl_mapper.frontend.video import open_recording
from papl_mapper.map import Map
from papl_mapper.synth import (
    VARIANTS,
    Renderer,
    SynthConfig,
    camera_path,
    drop_pattern,
    generate,
    low_texture,
    make_scene,
    walkthrough,
    with_variants,
)
from papl_mapper.synth.generate import _PostProcess
from tests.test_synth_gt import edge_scores

SMALL = dict(scene="corridor", width=64, height=48, fps=10.0, supersample=1)
STILL_M = 1e-12  # "no translation" (metres)


def _video(path) -> tuple[list[np.ndarray], np.ndarray]:
    """Decoded frames and their presentation times (s) as OpenCV reports them."""
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    frames, times = [], []
    while cap.grab():
        times.append(cap.get(cv2.CAP_PROP_POS_MSEC) / 1000)
        frames.append(cap.retrieve()[1])
    cap.release()
    return frames, np.array(times)


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(Ra.T @ Rb).magnitude()))


# ---- rotation-only start and rotation-only recording -----------------------------------------------


def test_rotation_start_pans_in_place_then_walks_as_usual():
    cfg = with_variants(SynthConfig(**SMALL, seconds=6.0, seed=3), "rotation-start")
    scene = make_scene("corridor", 3)
    t, T = camera_path(cfg, scene)
    n_pan = round(cfg.pan_seconds * cfg.fps)
    assert len(t) == cfg.n_frames and np.allclose(np.diff(t), 1 / cfg.fps)
    centre = T[:, :3, 3]
    assert np.abs(centre[: n_pan + 1] - centre[0]).max() < STILL_M, "the pan is a pure rotation"
    steps = np.linalg.norm(np.diff(centre[n_pan:], axis=0), axis=1)
    assert steps.min() > 0.5 * cfg.speed / cfg.fps, "then it walks, moving every frame"
    # it turns by pan_deg about the vertical into the walk's first view; the walk is the usual one
    assert math.isclose(_angle_deg(T[0, :3, :3], T[n_pan, :3, :3]), cfg.pan_deg, abs_tol=1e-6)
    assert np.allclose(T[0, 2, :3], T[n_pan, 2, :3]), "about the vertical: pitch and roll unchanged"
    angles = [_angle_deg(T[i, :3, :3], T[i + 1, :3, :3]) for i in range(n_pan)]
    assert min(angles[1:-1]) > 0 and max(angles) < 2.5 * cfg.pan_deg / n_pan, "a smooth turn"
    _, walk = walkthrough(scene, cfg.n_frames - n_pan, cfg.fps, 3, cfg.speed)
    assert np.allclose(T[n_pan:], walk)


def test_rotation_start_written_ground_truth(tmp_path):
    cfg = with_variants(SynthConfig(**SMALL, seconds=4.0), "rotation-start")
    out = generate(cfg, tmp_path / "rs")
    tum = np.loadtxt(out / "gt" / "trajectory.tum")
    n_pan = round(cfg.pan_seconds * cfg.fps)
    assert len(tum) == cfg.n_frames == len(_video(out / "video.mp4")[0])
    moved = np.linalg.norm(tum[:, 1:4] - tum[0, 1:4], axis=1)
    assert moved[: n_pan + 1].max() < 1e-9 and moved[n_pan + 1 :].min() > 0.05
    info = json.loads((out / "scene.json").read_text())
    assert info["variants"] == ["rotation-start"] and info["config"]["motion"] == "rotation-start"
    assert Map.load(out / "gt" / "map.papl").metadata["config"]["pan_seconds"] == cfg.pan_seconds


@pytest.mark.parametrize("seed", [0, 1])
def test_rotation_only_recording_never_translates(seed):
    cfg = with_variants(SynthConfig(**SMALL, seconds=8.0, seed=seed), "rotation-only")
    scene = make_scene("corridor", seed)
    _, T = camera_path(cfg, scene)
    _, walk = walkthrough(scene, cfg.n_frames, cfg.fps, seed, cfg.speed)
    assert np.abs(T[:, :3, 3] - walk[0, :3, 3]).max() < STILL_M, "stands where the walk starts"
    angles = np.array([_angle_deg(T[0, :3, :3], R) for R in T[:, :3, :3]])
    assert cfg.pan_deg - 3 < angles.max() < cfg.pan_deg + 3, "sweeps pan_deg (plus hand wobble)"
    n_sweep = round(cfg.pan_seconds * cfg.fps)
    assert angles[2 * n_sweep] < 3, "and back"
    assert np.median([_angle_deg(a, b) for a, b in zip(T[:-1, :3, :3], T[1:, :3, :3], strict=True)]) > 0.5


# ---- dropped frames ---------------------------------------------------------------------------------


def _runs(drop: np.ndarray) -> list[int]:
    edges = np.diff(np.concatenate([[0], drop.astype(int), [0]]))
    return (np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)).tolist()


@pytest.mark.parametrize(
    ("n", "fraction", "seed"), [(300, 0.1, 0), (300, 0.1, 7), (90, 0.1, 2), (41, 0.3, 5)]
)
def test_drop_pattern_fraction_runs_and_seed(n, fraction, seed):
    drop = drop_pattern(n, fraction, seed)
    assert drop.sum() == round(fraction * n) and not drop[0] and not drop[-1]
    runs = _runs(drop)
    assert max(runs) <= 4 and {2, 3, 4} <= set(runs), runs
    assert np.array_equal(drop, drop_pattern(n, fraction, seed)), "seeded"
    assert not np.array_equal(drop, drop_pattern(n, fraction, seed + 1))


def test_dropped_frames_are_absent_and_timestamps_gt_and_video_agree(tmp_path):
    plain = SynthConfig(**SMALL, seconds=9.0, noise_sigma=2.0, write_frames=True, seed=1)
    cfg = with_variants(plain, "dropped-frames")
    out = generate(cfg, tmp_path / "drop")
    generate(plain, tmp_path / "plain")
    n = cfg.n_frames
    keep = cfg.frame_indices()
    dropped = np.setdiff1d(np.arange(n), keep)
    assert len(dropped) == 9 and {2, 3, 4} <= set(_runs(~np.isin(np.arange(n), keep)))
    info = json.loads((out / "scene.json").read_text())
    assert info["dropped_frames"] == dropped.tolist() and info["frames"] == len(keep) == n - 9
    assert info["walk_frames"] == n
    # timestamps: the true times of the kept frames, with gaps where frames are missing
    t = np.loadtxt(out / "timestamps.txt")
    assert np.allclose(t, keep / cfg.fps, atol=1e-9)
    gaps = np.round(np.diff(t) * cfg.fps).astype(int)
    assert gaps.min() == 1 and set(gaps[gaps > 1].tolist()) == {3, 4, 5}
    # the GT trajectory holds exactly the kept frames, at the walk's poses
    tum = np.loadtxt(out / "gt" / "trajectory.tum")
    assert np.allclose(tum[:, 0], t, atol=1e-9)
    _, T = camera_path(cfg, make_scene("corridor", cfg.seed))
    assert np.allclose(tum[:, 1:4], T[keep, :3, 3], atol=1e-8)
    assert np.allclose(Rotation.from_quat(tum[:, 4:]).as_matrix(), T[keep, :3, :3], atol=1e-8)
    m = Map.load(out / "gt" / "map.papl")
    assert np.allclose(m.keyframes.timestamp, t[m.keyframes.frame_index])
    # the video holds only the kept frames, each shown at its true time (variable frame rate)
    frames, times = _video(out / "video.mp4")
    assert len(frames) == len(keep) and np.allclose(times, t, atol=1e-6)
    rec = open_recording(out / "video.mp4")
    assert rec.frame_count == len(keep)
    assert np.allclose([f.timestamp_s for f in rec], t, atol=1e-6)
    # the frames are the plain walk's frames (same noise), with the dropped ones left out
    pngs = sorted((out / "frames").glob("*.png"))
    assert [p.name for p in pngs] == [f"{k:06d}.png" for k in range(len(keep))]
    for k in (0, 31, len(keep) - 1):
        a = cv2.imread(str(pngs[k]))
        b = cv2.imread(str(tmp_path / "plain" / "frames" / f"{keep[k]:06d}.png"))
        assert np.array_equal(a, b), k
    assert np.allclose(np.loadtxt(out / "frames" / "timestamps.txt"), t)
    rec = open_recording(out / "frames")
    assert np.allclose([f.timestamp_s for f in rec], t)


# ---- photo set --------------------------------------------------------------------------------------


def test_photo_set_is_a_folder_at_1hz(tmp_path):
    cfg = with_variants(SynthConfig(**{**SMALL, "fps": 30.0}, seconds=8.0, seed=2), "photo-set")
    out = generate(cfg, tmp_path / "photos")
    assert not (out / "video.mp4").exists()
    pngs = sorted((out / "frames").glob("*.png"))
    assert [p.name for p in pngs] == [f"{k:06d}.png" for k in range(8)]
    t = np.loadtxt(out / "frames" / "timestamps.txt")
    assert np.allclose(t, np.arange(8.0)) and np.allclose(np.loadtxt(out / "timestamps.txt"), t)
    tum = np.loadtxt(out / "gt" / "trajectory.tum")
    assert np.allclose(tum[:, 0], t)
    _, T = camera_path(cfg, make_scene("corridor", 2))
    assert np.allclose(tum[:, 1:4], T[::30, :3, 3], atol=1e-8)
    baseline = np.linalg.norm(np.diff(tum[:, 1:4], axis=0), axis=1)
    assert np.median(baseline) > 0.5 * cfg.speed, "about a second of walking between photos"
    m = Map.load(out / "gt" / "map.papl")
    assert np.array_equal(m.keyframes.frame_index, np.arange(8)), "every photo is a keyframe"
    rec = open_recording(out / "frames")
    assert rec.kind == "images" and math.isclose(rec.fps, 1.0)
    assert np.allclose([f.timestamp_s for f in rec], t)
    assert json.loads((out / "scene.json").read_text())["recording"] == "frames"


def test_photo_set_and_video_replace_each_other_in_one_folder(tmp_path):
    out = tmp_path / "run"
    video = SynthConfig(**SMALL, seconds=2.0, write_frames=True)
    generate(video, out)
    generate(with_variants(video, "photo-set"), out)
    assert not (out / "video.mp4").exists() and len(list((out / "frames").glob("*.png"))) == 2
    generate(dataclasses.replace(video, write_frames=False), out)
    assert (out / "video.mp4").exists() and not (out / "frames").exists()


# ---- low-texture corridor ---------------------------------------------------------------------------


def test_low_texture_corridor_has_few_corners_but_the_same_geometry_and_edges():
    scene = make_scene("corridor", 0)
    low = low_texture(scene)
    assert low.name == scene.name and np.array_equal(low.quad_corners, scene.quad_corners)
    assert np.array_equal(low.segments, scene.segments) and np.array_equal(low.axes, scene.axes)
    cfg = SynthConfig(width=160, height=120, fps=10.0, seconds=10.0, supersample=2)
    cam = cfg.camera()
    t, T = camera_path(cfg, scene)
    post = _PostProcess(cfg, cam, t, T)
    fast = cv2.FastFeatureDetector_create(threshold=10)
    stats = {}
    for name, sc in (("normal", scene), ("low", low)):
        r = Renderer(sc, cam, cfg.supersample)
        corners = textured = on_edge = 0
        for i in range(0, cfg.n_frames, 12):
            img, depth = r.render(T[i], with_depth=True)
            gray = cv2.cvtColor(post.apply(i, img, None), cv2.COLOR_BGR2GRAY)
            corners += len(fast.detect(gray))
            mag = np.hypot(cv2.Sobel(gray, cv2.CV_32F, 1, 0), cv2.Sobel(gray, cv2.CV_32F, 0, 1))
            textured += float((mag > 16).mean())
            on_edge += edge_scores(cam, img, depth, T[i], sc)[0]
        stats[name] = corners, textured, on_edge
    (c0, g0, e0), (c1, g1, e1) = stats["normal"], stats["low"]
    assert c1 < 0.2 * c0, f"FAST corners {c1} vs {c0}"
    assert g1 < 0.4 * g0, f"textured pixels {g1:.2f} vs {g0:.2f}"
    assert e1 >= 0.8 * e0 > 0, f"GT segments on rendered edges {e1} vs {e0}: structure stays visible"


# ---- determinism, interface, bad values ---------------------------------------------------------------


def test_same_seed_same_output_other_seed_differs(tmp_path):
    cfg = with_variants(
        SynthConfig(**SMALL, seconds=4.0, seed=6), "rotation-start", "dropped-frames", "low-texture"
    )
    cfg = dataclasses.replace(cfg, pan_seconds=1.5, drop_fraction=0.25)
    a, b = generate(cfg, tmp_path / "a"), generate(cfg, tmp_path / "b")
    for name in ("timestamps.txt", "gt/trajectory.tum", "gt/segments.txt", "gt/axes.json", "camera.json"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name
    fa, fb = _video(a / "video.mp4")[0], _video(b / "video.mp4")[0]
    assert len(fa) == len(fb) == 30 and all(np.array_equal(x, y) for x, y in zip(fa, fb, strict=True))
    ia, ib = (json.loads((d / "scene.json").read_text()) for d in (a, b))
    assert ia["dropped_frames"] == ib["dropped_frames"]
    c = generate(dataclasses.replace(cfg, seed=7), tmp_path / "c")
    assert json.loads((c / "scene.json").read_text())["dropped_frames"] != ia["dropped_frames"]
    assert (c / "gt/trajectory.tum").read_bytes() != (a / "gt/trajectory.tum").read_bytes()


def test_hand_held_is_blur_exposure_and_noise_and_named_only_when_exactly_those():
    cfg = with_variants(SynthConfig(), "hand-held")
    assert (cfg.motion_blur, cfg.exposure_jitter, cfg.noise_sigma) == (0.5, 0.3, 2.0)
    assert cfg.variants == ["hand-held"] and cfg.motion == "walk" and cfg.frame_indices().size == cfg.n_frames
    assert with_variants(SynthConfig(), "low-texture", "hand-held").variants == ["low-texture", "hand-held"]
    # other strengths of the same effects are a plain walk with options, not the named variant
    assert dataclasses.replace(cfg, motion_blur=0.25).variants == []
    assert dataclasses.replace(SynthConfig(), motion_blur=0.5, exposure_jitter=0.3).variants == []


def test_hand_held_render_keeps_the_walk_and_changes_exposure(tmp_path):
    plain = SynthConfig(**SMALL, seconds=3.0, seed=2)
    a = generate(plain, tmp_path / "plain")
    b = generate(with_variants(plain, "hand-held"), tmp_path / "held")
    fa, _ = _video(a / "video.mp4")
    fb, _ = _video(b / "video.mp4")
    assert len(fa) == len(fb) == plain.n_frames
    assert (a / "gt/trajectory.tum").read_bytes() == (b / "gt/trajectory.tum").read_bytes(), "same walk"
    ratio = np.array([fb[i].mean() / fa[i].mean() for i in range(len(fa))])
    assert ratio.max() / ratio.min() > 1.1, "brightness varies over the walk"
    assert json.loads((b / "scene.json").read_text())["variants"] == ["hand-held"]


def test_plain_config_records_no_variant_fields():
    d = SynthConfig().to_dict()
    assert "motion" not in d and "photo_hz" not in d and SynthConfig(**d) == SynthConfig()
    cfg = with_variants(SynthConfig(), "photo-set")
    assert SynthConfig(**cfg.to_dict()) == cfg and cfg.to_dict()["photo_hz"] == 1.0


@pytest.mark.parametrize(
    "cfg",
    [
        with_variants(SynthConfig(), "rotation-start", "low-texture"),
        dataclasses.replace(with_variants(SynthConfig(), "rotation-only"), pan_seconds=4.0, pan_deg=90.0),
        dataclasses.replace(with_variants(SynthConfig(), "dropped-frames"), drop_fraction=0.2),
        with_variants(SynthConfig(), "photo-set"),
        dataclasses.replace(SynthConfig(), photo_hz=2.0, write_frames=True),
        dataclasses.replace(SynthConfig(), pan_deg=30.0),
        with_variants(SynthConfig(), "hand-held", "dropped-frames"),
        dataclasses.replace(with_variants(SynthConfig(), "hand-held"), motion_blur=0.25),
    ],
)
def test_variant_options_round_trip_through_the_command_line(cfg):
    args = build_parser().parse_args(shlex.split(cfg.command("d"))[1:])
    assert config_from_args(args) == cfg


def test_cli_variant_photo_set(tmp_path, capsys):
    out = tmp_path / "cli"
    argv = ["synth", "garage", "--out", str(out), "--width", "48", "--height", "32", "--seconds", "3"]
    assert main([*argv, "--variant", "photo-set,low-texture", "--supersample", "1"]) == 0
    said = capsys.readouterr().out
    assert "3 frames of garage (photo-set, low-texture)" in said and str(out / "frames") in said
    info = json.loads((out / "scene.json").read_text())
    assert info["variants"] == ["photo-set", "low-texture"]
    assert config_from_args(build_parser().parse_args(shlex.split(info["command"])[1:])) == SynthConfig(
        **info["config"]
    )


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--variant", "wobbly"], "unknown variant 'wobbly'; known variants: " + ", ".join(VARIANTS)),
        (["--variant", "rotation-start,rotation-only"], "do not combine"),
        (["--variant", "dropped-frames,photo-set"], "do not combine"),
        (["--drop-fraction", "0.7"], "drop fraction 0.7 is outside 0..0.5"),
        (["--photo-hz", "50"], "photo rate 50.0 Hz is outside 0..30"),
        (["--variant", "rotation-start", "--pan-seconds", "10"], "--pan-seconds < --seconds"),
        (["--pan-deg", "0"], "pan angle"),
        (["--pan-seconds", "-1"], "pan time"),
    ],
)
def test_bad_variant_values_are_one_line_and_exit_2(tmp_path, capsys, extra, message):
    assert main(["synth", "corridor", "--out", str(tmp_path / "o"), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("papl-map synth: error:") and message in err, err
    assert not (tmp_path / "o").exists(), "nothing is written for a bad option"


def test_with_variants_rejects_unknown_names():
    with pytest.raises(InputError, match="known variants"):
        with_variants(SynthConfig(), "rotation-start", "sideways")
