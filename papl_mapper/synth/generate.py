"""Render a synthetic walkthrough to a folder: video, intrinsics, GT trajectory, segments, axes, map.

The layout (other stages read it):

    DIR/video.mp4            mp4v, exactly N frames        DIR/frames/000000.png ...  (write_frames)
    DIR/timestamps.txt       one float (s) per frame       DIR/camera.json            Camera.to_dict()
    DIR/gt/trajectory.tum    t tx ty tz qx qy qz qw, T_wc  DIR/gt/segments.txt        x1 y1 z1 x2 y2 z2 axis
    DIR/gt/axes.json         directions, vertical_index    DIR/gt/map.papl            the GT as a Map
    DIR/scene.json           scene, config, seed, path length, the command that regenerates DIR

Frames are numbered in recording order: frame k of video.mp4 is frames/NNNNNN.png with NNNNNN = k,
line k of timestamps.txt and of gt/trajectory.tum. The adversarial variants (VARIANTS) keep this:

- rotation-start / rotation-only (`motion`): the camera pans in place for `pan_seconds` first, then
  walks; or it only pans, back and forth, and never translates.
- dropped-frames (`drop_fraction`): frames of the walk are missing (seeded, some in runs of 2-4);
  the others keep their true times, so timestamps.txt has gaps, and video.mp4 holds only the kept
  frames with those times as presentation times (a variable-frame-rate MP4: frame times read
  through OpenCV's CAP_PROP_POS_MSEC are the true ones). scene.json lists the dropped walk frames.
- photo-set (`photo_hz`): frames of the walk at `photo_hz` written as DIR/frames/ only (no video).
- low-texture (`low_texture`): blank walls and ceilings, faint floors; same geometry and GT.

Whenever the recorded frames are not every frame of the walk (dropped-frames, photo-set), the
frames folder holds a copy of timestamps.txt, so `papl-map run DIR/frames` reads the true times.
Motion blur, exposure and noise of a recorded frame are those of the same frame of the full walk.

Every file is written under a temporary name and renamed, so an interrupted run never leaves a
half-written file under a final name.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shlex
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from papl_mapper import __version__
from papl_mapper.atomic import move_dir_into_place, move_into_place
from papl_mapper.errors import BackendUnavailableError, InputError
from papl_mapper.map import Axes, Camera, Keyframes, Lines, LineState, Map, Points
from papl_mapper.synth.markers import place_markers
from papl_mapper.synth.mp4 import retime_mp4
from papl_mapper.synth.path import look_around, pan_then_walk, walkthrough
from papl_mapper.synth.project import project, visible_points, visible_segments
from papl_mapper.synth.render import Renderer
from papl_mapper.synth.scenes import SCENES, Scene, low_texture, make_scene
from papl_mapper.trajectory_io import TUM_HEADER, format_tum

KEYFRAME_EVERY = 10  # GT map keyframes: every 10th frame
MAX_GT_POINTS = 2000
WHITE_LEVEL = 230.0  # 8-bit value of a white surface facing the light; lights saturate

ProgressCallback = Callable[[int, int, str], None]

MOTIONS = ("walk", "rotation-start", "rotation-only")
#: Named adversarial variants: the SynthConfig fields each one sets. They combine, except the two
#: motions with each other and dropped-frames with photo-set.
VARIANTS: dict[str, dict[str, object]] = {
    "rotation-start": {"motion": "rotation-start"},
    "rotation-only": {"motion": "rotation-only"},
    "dropped-frames": {"drop_fraction": 0.1},
    "photo-set": {"photo_hz": 1.0},
    "low-texture": {"low_texture": True},
    "hand-held": {"motion_blur": 0.5, "exposure_jitter": 0.3, "noise_sigma": 2.0},
}
#: Fields of the variants: left out of scene.json and the GT map's metadata while all are default,
#: so a plain walkthrough is written exactly as before they existed.
VARIANT_FIELDS = ("motion", "pan_seconds", "pan_deg", "drop_fraction", "photo_hz", "low_texture")
MARKER_FIELDS = ("markers", "marker_size", "marker_dictionary")


@dataclass
class SynthConfig:
    """Options of one synthetic walkthrough."""

    scene: str = "corridor"
    """Scene name: corridor, atlanta or garage."""
    width: int = 640
    """Image width in pixels."""
    height: int = 480
    """Image height in pixels."""
    fps: float = 30.0
    """Frames per second of the video."""
    seconds: float = 10.0
    """Length of the walkthrough in seconds; frames = round(seconds * fps)."""
    hfov_deg: float = 70.0
    """Horizontal field of view in degrees."""
    noise_sigma: float = 0.0
    """Standard deviation of Gaussian image noise in grey levels (0..255)."""
    motion_blur: float = 0.0
    """Shutter time as a fraction of the frame interval: blur along the image motion (0 = none)."""
    exposure_jitter: float = 0.0
    """RMS of slow exposure changes, in stops (0 = constant exposure)."""
    seed: int = 0
    """Seed of the scene textures, the path jitter, noise and exposure."""
    write_frames: bool = False
    """Also write every frame as frames/NNNNNN.png."""
    supersample: int = 2
    """Render at this multiple of the resolution and area-average down (anti-aliasing); 1..4."""
    speed: float = 1.0
    """Walking speed in metres per second."""
    msaa: bool = False
    """With supersampling, look textures up once per pixel (edges still anti-aliased): faster, a little
    softer (benchmarks/results/notes.md)."""
    motion: str = "walk"
    """walk; rotation-start: stand and pan in place for pan_seconds, then walk; rotation-only: stand
    at the start and pan back and forth the whole time (pure rotation, no translation)."""
    pan_seconds: float = 2.5
    """rotation-start: length of the pan before walking; rotation-only: time of one sweep."""
    pan_deg: float = 45.0
    """Angle of the pan (rotation-start) or of each sweep (rotation-only), in degrees."""
    drop_fraction: float = 0.0
    """Fraction of the walk's frames left out (seeded, some in runs of 2-4); 0 = none."""
    photo_hz: float = 0.0
    """Photo set: keep the walk's frames at this rate, written as frames/ without a video; 0 = video."""
    low_texture: bool = False
    """Blank walls and ceilings and faint floors (few points; structural edges still visible)."""
    markers: int = 0
    """ArUco markers (ids 0..markers-1) stuck on walls the walk sees face-on from 1-3 m; 0 = none."""
    marker_size: float = 0.2
    """Side of each marker's black square in metres."""
    marker_dictionary: str = "4X4_50"
    """ArUco dictionary of the markers (OpenCV's name without DICT_)."""

    @property
    def n_frames(self) -> int:
        """Frames of the walk at `fps` (the recording holds all of them unless frames are dropped or
        it is a photo set: see frame_indices)."""
        return int(round(self.seconds * self.fps))

    @property
    def variants(self) -> list[str]:
        """Names of the adversarial variants this config uses (see VARIANTS), in that order."""
        out = [self.motion] if self.motion != "walk" else []
        out += ["dropped-frames"] if self.drop_fraction > 0 else []
        out += ["photo-set"] if self.photo_hz > 0 else []
        out += ["low-texture"] if self.low_texture else []
        # camera effects, not a kind of walk: named only when they are exactly the variant's, so that the
        # command written to scene.json (explicit --blur, --exposure, --noise, then --variant) is this config
        held = VARIANTS["hand-held"]
        out += ["hand-held"] if all(getattr(self, k) == v for k, v in held.items()) else []
        return out

    def frame_indices(self) -> np.ndarray:
        """(K,) int64 indices into the walk's n_frames of the frames the recording holds, increasing."""
        n = self.n_frames
        if self.photo_hz > 0:
            step = self.fps / self.photo_hz
            idx = np.round(np.arange(math.ceil(n / step)) * step).astype(np.int64)
            return np.unique(idx[idx < n])
        if self.drop_fraction > 0:
            return np.flatnonzero(~drop_pattern(n, self.drop_fraction, self.seed)).astype(np.int64)
        return np.arange(n, dtype=np.int64)

    def to_dict(self) -> dict:
        """The fields as a dict; the variant fields only when one of them is not its default."""
        d = dataclasses.asdict(self)
        if all(d[k] == _DEFAULTS[k] for k in VARIANT_FIELDS):
            for k in VARIANT_FIELDS:
                del d[k]
        if self.markers == 0:  # scenes without markers keep the scene.json they always had
            for k in MARKER_FIELDS:
                del d[k]
        return d

    def validate(self) -> None:
        """InputError naming the first impossible option."""
        if self.scene not in SCENES:
            raise InputError(f"unknown scene {self.scene!r}; known scenes: {', '.join(SCENES)}")
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"resolution {self.width}x{self.height} is impossible; give positive sizes")
        if not (self.fps > 0 and math.isfinite(self.fps)):
            raise InputError(f"frame rate {self.fps} is impossible; give a positive --fps")
        if not (self.seconds > 0 and math.isfinite(self.seconds)) or self.n_frames < 1:
            raise InputError(
                f"{self.seconds} s at {self.fps} fps gives {self.n_frames} frames; give a longer --seconds"
            )
        if not 10 <= self.hfov_deg <= 150:
            raise InputError(f"horizontal field of view {self.hfov_deg} deg is outside 10..150")
        if self.noise_sigma < 0 or self.exposure_jitter < 0:
            raise InputError("noise and exposure jitter must not be negative")
        if not 0 <= self.motion_blur <= 1:
            raise InputError(f"motion blur {self.motion_blur} is outside 0..1 (a fraction of the frame time)")
        if self.supersample not in (1, 2, 3, 4):
            raise InputError(f"supersample {self.supersample} must be 1, 2, 3 or 4")
        if not 0 < self.speed <= 5:
            raise InputError(f"walking speed {self.speed} m/s is outside (0, 5]")
        if not 0 <= self.markers <= 20:
            raise InputError(f"--markers {self.markers} is outside 0..20")
        if not (0.02 <= self.marker_size <= 2 and math.isfinite(self.marker_size)):
            raise InputError(f"--marker-size {self.marker_size} m is outside 0.02..2")
        if not hasattr(cv2.aruco, f"DICT_{self.marker_dictionary}"):
            raise InputError(f"--marker-dictionary {self.marker_dictionary!r}: no such ArUco dictionary")
        self._validate_variants()

    def _validate_variants(self) -> None:
        if self.motion not in MOTIONS:
            raise InputError(f"unknown motion {self.motion!r}; known motions: {', '.join(MOTIONS)}")
        if not (self.pan_seconds > 0 and math.isfinite(self.pan_seconds)):
            raise InputError(f"pan time {self.pan_seconds} s is impossible; give a positive --pan-seconds")
        if not 0 < self.pan_deg <= 360:
            raise InputError(f"pan angle {self.pan_deg} deg is outside (0, 360]")
        n_pan = int(round(self.pan_seconds * self.fps))
        if self.motion == "rotation-start" and not 1 <= n_pan < self.n_frames:
            raise InputError(
                f"a {self.pan_seconds:g} s pan is {n_pan} of the {self.n_frames} frames; rotation-start "
                "needs at least one frame of pan and one of walking (--pan-seconds < --seconds)"
            )
        if not 0 <= self.drop_fraction <= 0.5:
            raise InputError(f"drop fraction {self.drop_fraction} is outside 0..0.5")
        if self.drop_fraction > 0 and self.n_frames < 3:
            raise InputError(f"{self.n_frames} frames are too few to drop any; give a longer --seconds")
        if not (0 <= self.photo_hz <= self.fps and math.isfinite(self.photo_hz)):
            raise InputError(f"photo rate {self.photo_hz} Hz is outside 0..{self.fps:g} (the --fps)")
        if self.photo_hz > 0 and self.drop_fraction > 0:
            raise InputError("dropped-frames and photo-set do not combine; choose one of them")

    def camera(self) -> Camera:
        """Pinhole camera, zero distortion, principal point at the image centre."""
        f = (self.width / 2) / math.tan(math.radians(self.hfov_deg) / 2)
        return Camera(self.width, self.height, f, f, (self.width - 1) / 2, (self.height - 1) / 2)

    def command(self, out_dir: str | os.PathLike) -> str:
        """The `papl-map synth` command line that regenerates this walkthrough into out_dir."""
        args = ["papl-map", "synth", self.scene, "--out", str(out_dir)]
        args += ["--width", str(self.width), "--height", str(self.height), "--fps", f"{self.fps:g}"]
        args += ["--seconds", f"{self.seconds:g}", "--hfov", f"{self.hfov_deg:g}"]
        args += ["--noise", f"{self.noise_sigma:g}", "--blur", f"{self.motion_blur:g}"]
        args += ["--exposure", f"{self.exposure_jitter:g}", "--seed", str(self.seed)]
        args += ["--supersample", str(self.supersample), "--speed", f"{self.speed:g}"]
        if self.msaa:
            args.append("--msaa")
        if self.write_frames:
            args.append("--frames")
        if self.variants:
            args += ["--variant", ",".join(self.variants)]
        for name, flag in (("pan_seconds", "--pan-seconds"), ("pan_deg", "--pan-deg")):
            if getattr(self, name) != _DEFAULTS[name]:
                args += [flag, f"{getattr(self, name):g}"]
        if self.drop_fraction > 0 and self.drop_fraction != VARIANTS["dropped-frames"]["drop_fraction"]:
            args += ["--drop-fraction", f"{self.drop_fraction:g}"]
        if self.photo_hz > 0 and self.photo_hz != VARIANTS["photo-set"]["photo_hz"]:
            args += ["--photo-hz", f"{self.photo_hz:g}"]
        if self.markers:
            args += ["--markers", str(self.markers), "--marker-size", f"{self.marker_size:g}"]
            args += ["--marker-dictionary", self.marker_dictionary]
        return shlex.join(args)


_DEFAULTS = {f.name: f.default for f in dataclasses.fields(SynthConfig)}


def with_variants(config: SynthConfig, *names: str) -> SynthConfig:
    """A copy of config with the named adversarial variants (VARIANTS) switched on.

    InputError for an unknown name, both motions, or dropped-frames with photo-set.
    """
    fields: dict[str, object] = {}
    for name in names:
        if name not in VARIANTS:
            raise InputError(f"unknown variant {name!r}; known variants: {', '.join(VARIANTS)}")
        fields.update(VARIANTS[name])
    if {"rotation-start", "rotation-only"} <= set(names):
        raise InputError("rotation-start and rotation-only do not combine; choose one of them")
    if {"dropped-frames", "photo-set"} <= set(names):
        raise InputError("dropped-frames and photo-set do not combine; choose one of them")
    return dataclasses.replace(config, **fields)


def drop_pattern(n: int, fraction: float, seed: int = 0) -> np.ndarray:
    """(n,) bool, True for the frames a recording with dropped frames misses.

    round(fraction * n) frames in separate runs (a kept frame between any two): one run each of 2,
    3 and 4 frames first (as far as the count allows), then runs of 1 to 4 (mostly 1). The first and
    the last frame are always kept. Seeded.
    """
    rng = np.random.default_rng([seed, 43])
    target = int(round(fraction * n))
    drop = np.zeros(n, bool)
    forced = [2, 3, 4]
    while int(drop.sum()) < target:
        want = forced[0] if forced else int(rng.choice([1, 1, 1, 2, 3, 4]))
        length = min(want, target - int(drop.sum()))
        free = np.array([], np.int64)
        while length >= 1:
            if n - length - 1 >= 1:  # starts 1 .. n - 1 - length keep the first and last frame
                # a run at s needs frames s - 1 .. s + length free (no merging with another run)
                busy = np.convolve(drop.astype(np.int64), np.ones(length + 2, np.int64), "valid")
                free = np.flatnonzero(busy == 0) + 1
            if len(free):
                break
            length -= 1
        if not len(free):
            break  # no room left for another separate run
        start = int(rng.choice(free))
        drop[start : start + length] = True
        if forced:
            forced.pop(0)
    return drop


def camera_path(config: SynthConfig, scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (n_frames,) and poses T_wc of the whole walk of `config` at its fps."""
    n, fps, seed, speed = config.n_frames, config.fps, config.seed, config.speed
    if config.motion == "rotation-start":
        return pan_then_walk(scene, n, fps, seed, speed, config.pan_seconds, config.pan_deg)
    if config.motion == "rotation-only":
        return look_around(scene, n, fps, seed, speed, config.pan_seconds, config.pan_deg)
    return walkthrough(scene, n, fps, seed, speed)


def generate(
    config: SynthConfig, out_dir: str | os.PathLike, progress: ProgressCallback | None = None
) -> Path:
    """Render the walkthrough of `config` into out_dir (created if missing) and return out_dir."""
    config.validate()
    out = Path(out_dir)
    _prepare_dir(out)
    photos = config.photo_hz > 0  # a photo set: frames only, no video
    write_frames = config.write_frames or photos
    if write_frames and (out / "frames").exists() and not _only_our_frames(out / "frames"):
        raise InputError(
            f"{out / 'frames'}: holds files other than frames; move them or choose another --out"
        )
    scene = make_scene(config.scene, config.seed)
    if config.low_texture:
        scene = low_texture(scene)
    camera = config.camera()
    n = config.n_frames
    timestamps, T_wc = camera_path(config, scene)  # every frame of the walk
    keep = config.frame_indices()  # the frames the recording holds
    markers: list[dict] = []
    if config.markers:  # quads added after the path: the walk is the same with or without them
        scene, markers = place_markers(
            scene,
            camera,
            T_wc[keep],
            config.markers,
            config.marker_size,
            config.marker_dictionary,
            config.seed,
        )
    renderer = Renderer(scene, camera, config.supersample, msaa=config.msaa)
    post = _PostProcess(config, camera, timestamps, T_wc)
    tmp_video = None if photos else out / ".video.tmp.mp4"
    frames_tmp = out / ".frames.tmp" if write_frames else None
    if frames_tmp is not None:
        shutil.rmtree(frames_tmp, ignore_errors=True)
        frames_tmp.mkdir()
    writer = None
    if tmp_video is not None:
        writer = cv2.VideoWriter(
            str(tmp_video), cv2.VideoWriter_fourcc(*"mp4v"), config.fps, (camera.width, camera.height)
        )
        if not writer.isOpened():
            raise BackendUnavailableError(
                f"{tmp_video}: OpenCV cannot open an mp4v video writer (no FFmpeg?)"
            )
    try:
        for k, i in enumerate(keep.tolist()):
            img, depth = renderer.render(T_wc[i], with_depth=post.needs_depth)
            frame = post.apply(i, img, depth)
            if writer is not None:
                writer.write(frame)
            if frames_tmp is not None:
                cv2.imwrite(str(frames_tmp / f"{k:06d}.png"), frame)
            if progress is not None:
                progress(k + 1, len(keep), "frames")
    except BaseException:
        if writer is not None:
            writer.release()
            tmp_video.unlink(missing_ok=True)
        if frames_tmp is not None:
            shutil.rmtree(frames_tmp, ignore_errors=True)
        raise
    if writer is not None:
        writer.release()
    subset = len(keep) < n
    rec_t, rec_T = timestamps[keep], T_wc[keep]
    stamps = "".join(f"{t:.9f}\n" for t in rec_t)
    # everything is staged under temporary names, then renamed in one quick run at the end
    staged = [] if tmp_video is None else [(tmp_video, out / "video.mp4")]
    try:
        if tmp_video is not None and subset:
            retime_mp4(tmp_video, np.append(np.diff(keep), 1))  # the kept frames at their true times
        if frames_tmp is not None and subset:
            (frames_tmp / "timestamps.txt").write_text(stamps)  # image folders read their times here
        (out / "gt").mkdir(exist_ok=True)
        staged.append(_stage_text(out / "timestamps.txt", stamps))
        staged.append(_stage_text(out / "camera.json", json.dumps(camera.to_dict(), indent=2) + "\n"))
        gt_header = f"{TUM_HEADER} (T_wc, camera to world, metres)"
        staged.append(_stage_text(out / "gt" / "trajectory.tum", format_tum(rec_t, rec_T, gt_header)))
        staged.append(_stage_text(out / "gt" / "segments.txt", segments_txt(scene)))
        axes = {"directions": scene.axes.tolist(), "vertical_index": 0, "names": scene.axis_names}
        staged.append(_stage_text(out / "gt" / "axes.json", json.dumps(axes, indent=2) + "\n"))
        if markers:
            staged.append(_stage_text(out / "gt" / "markers.json", json.dumps(markers, indent=2) + "\n"))
        tmp_map = out / "gt" / ".map.tmp.papl"
        every = 1 if photos else KEYFRAME_EVERY  # in a photo set every image is a keyframe
        gt_map(scene, camera, rec_t, rec_T, config, keyframe_every=every).save(tmp_map)
        staged.append((tmp_map, out / "gt" / "map.papl"))
    except BaseException:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
        if frames_tmp is not None:
            shutil.rmtree(frames_tmp, ignore_errors=True)
        raise
    for tmp, final in staged:
        move_into_place(tmp, final)
    if not markers:
        (out / "gt" / "markers.json").unlink(missing_ok=True)  # the markers of an earlier run
    if photos:
        (out / "video.mp4").unlink(missing_ok=True)  # the video of an earlier run
    if frames_tmp is not None:
        move_dir_into_place(frames_tmp, out / "frames")  # over the frames of an earlier run
    elif _only_our_frames(out / "frames"):
        shutil.rmtree(out / "frames", ignore_errors=True)  # frames of an earlier run
    length = float(np.linalg.norm(np.diff(T_wc[:, :3, 3], axis=0), axis=1).sum())
    info = {
        "scene": config.scene,
        "seed": config.seed,
        "frames": len(keep),
        "path_length_m": round(length, 4),
        "config": config.to_dict(),
        "command": config.command(out_dir),
        "software_version": __version__,
        "segments": int(len(scene.segments)),
        "axes": scene.axis_names,
    }
    if config.variants:
        info["variants"] = config.variants
        info["recording"] = "frames" if photos else "video.mp4"
        info["walk_frames"] = n
    if config.drop_fraction > 0:
        info["dropped_frames"] = np.setdiff1d(np.arange(n), keep).tolist()
    tmp, final = _stage_text(out / "scene.json", json.dumps(info, indent=2) + "\n")
    move_into_place(tmp, final)
    return out


def _prepare_dir(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder; choose another --out")
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".probe.", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise InputError(f"{out}: cannot write there ({exc.strerror}); choose a writable --out") from exc


def _only_our_frames(folder: Path) -> bool:
    """Whether `folder` exists and holds nothing but NNNNNN.png frames and the timestamps.txt that
    variants write beside them (safe to replace)."""
    if not folder.is_dir():
        return False
    return all(
        p.is_file()
        and ((p.suffix == ".png" and p.stem.isdigit() and len(p.stem) == 6) or p.name == "timestamps.txt")
        for p in folder.iterdir()
    )


def _stage_text(path: Path, text: str) -> tuple[Path, Path]:
    """Write text under a temporary name beside `path`; return (temporary, final) for the rename."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    return tmp, path


def segments_txt(scene: Scene) -> str:
    """`x1 y1 z1 x2 y2 z2 axis` lines; axis -1 marks non-structural segments."""
    rows = [
        " ".join(f"{x:.6f}" for x in seg.ravel()) + f" {int(a)}"
        for seg, a in zip(scene.segments, scene.segment_axis, strict=True)
    ]
    return "# x1 y1 z1 x2 y2 z2 axis (world, metres; axis -1 = non-structural)\n" + "\n".join(rows) + "\n"


def gt_map(
    scene: Scene,
    camera: Camera,
    timestamps: np.ndarray,
    T_wc: np.ndarray,
    config: SynthConfig,
    keyframe_every: int = KEYFRAME_EVERY,
) -> Map:
    """The ground truth as a Map: keyframes every 10th frame (`keyframe_every`) of the recording,
    corner points, GT segments, axes."""
    kf_frames = np.arange(0, len(T_wc), keyframe_every)
    kf_T = T_wc[kf_frames]
    kf_ids = np.arange(len(kf_frames), dtype=np.int64)
    keyframes = Keyframes(
        kf_ids, kf_frames.astype(np.int64), timestamps[kf_frames].astype(float), kf_T.copy()
    )
    pts = scene.corner_points()
    if len(pts) > MAX_GT_POINTS:
        pts = pts[np.random.default_rng(config.seed).choice(len(pts), MAX_GT_POINTS, replace=False)]
    p_obs, p_uv, l_obs, l_xy = [], [], [], []
    for k, T in zip(kf_ids, kf_T, strict=True):
        idx, uv = visible_points(scene, camera, T, pts)
        p_obs.append(np.column_stack([idx, np.full(len(idx), k)]))
        p_uv.append(uv)
        sidx, xy = visible_segments(scene, camera, T, scene.segments)
        l_obs.append(np.column_stack([sidx, np.full(len(sidx), k)]))
        l_xy.append(xy)
    points = Points(
        np.arange(len(pts), dtype=np.int64),
        pts.astype(float),
        np.full((len(pts), 3), 255, np.uint8),
        np.concatenate(p_obs).astype(np.int64).reshape(-1, 2),
        np.concatenate(p_uv).reshape(-1, 2),
    )
    M = len(scene.segments)
    axis = scene.segment_axis
    weights = np.zeros((M, len(scene.axes)))
    weights[axis >= 0, axis[axis >= 0]] = 1.0
    ref, inv_depth = _reference_keyframes(camera, kf_T, scene.segments.mean(axis=1))
    anchored = axis >= 0
    lines = Lines(
        np.arange(M, dtype=np.int64),
        scene.segments.copy(),
        weights,
        np.where(anchored, LineState.ANCHORED, LineState.ORTHONORMAL).astype(np.int8),
        np.where(anchored, ref, -1).astype(np.int64),
        np.where(anchored, inv_depth, np.nan),
        np.concatenate(l_obs).astype(np.int64).reshape(-1, 2),
        np.concatenate(l_xy).reshape(-1, 4),
    )
    metadata = {
        "units": "m",
        "source": "papl-map synth (ground truth)",
        "scene": scene.name,
        "axis_names": scene.axis_names,
        "config": config.to_dict(),
        "software_version": __version__,
    }
    return Map(camera, keyframes, points, lines, Axes(scene.axes.copy(), 0), metadata)


def _reference_keyframes(camera: Camera, kf_T: np.ndarray, mids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per segment midpoint: the keyframe seeing it nearest inside the image (else the nearest in
    front, else the nearest at all) and the midpoint's inverse depth (inverse distance if behind)."""
    best = np.full(len(mids), -1, np.int64)
    score = np.full(len(mids), np.inf)
    inv = np.full(len(mids), np.nan)
    for k, T in enumerate(kf_T):
        uv, z = project(camera, T, mids)
        dist = np.linalg.norm(mids - T[:3, 3], axis=1)
        inside = (
            (z > 0.1)
            & (np.abs(uv[:, 0] - camera.cx) < camera.width / 2)
            & (np.abs(uv[:, 1] - camera.cy) < camera.height / 2)
        )
        s = np.where(inside, z, np.where(z > 0.1, 1e3 + z, 1e6 + dist))
        better = s < score
        best[better] = k
        score[better] = s[better]
        inv[better] = np.where(z[better] > 0.1, 1 / np.maximum(z[better], 1e-9), 1 / dist[better])
    return best, inv


class _PostProcess:
    """Motion blur along the image motion, exposure changes and noise: seeded per frame."""

    def __init__(self, config: SynthConfig, camera: Camera, timestamps: np.ndarray, T_wc: np.ndarray):
        self.c = config
        self.camera = camera
        self.T_wc = T_wc
        rng = np.random.default_rng([config.seed, 23])
        k = 3
        f = rng.uniform(0.05, 0.3, k)
        ph = rng.uniform(0, 2 * math.pi, k)
        wave = np.sin(2 * math.pi * f[None] * timestamps[:, None] + ph[None]).sum(1) * math.sqrt(2.0 / k)
        self.gain = (2.0 ** (config.exposure_jitter * wave)).astype(np.float32)
        self.needs_depth = config.motion_blur > 0

    def apply(self, i: int, img: np.ndarray, depth: np.ndarray | None) -> np.ndarray:
        """float32 BGR in [0, 1.5] -> uint8 BGR frame."""
        if self.c.motion_blur > 0 and depth is not None:
            img = self._blur(i, img, depth)
        gain = float(WHITE_LEVEL * self.gain[i])
        if self.c.noise_sigma > 0:
            rng = np.random.default_rng([self.c.seed, 31, i])
            noise = rng.standard_normal(img.shape, dtype=np.float32)
            # one pass: round and saturate gain * img + sigma * noise to 8 bits
            return cv2.addWeighted(img, gain, noise, float(self.c.noise_sigma), 0.0, dtype=cv2.CV_8U)
        return cv2.convertScaleAbs(img, alpha=gain)  # img >= 0: rounds and saturates

    def image_motion(self, i: int, depth: np.ndarray) -> np.ndarray:
        """Median image motion (dx, dy) in pixels per frame at frame i (from depth and the next pose)."""
        j = min(i + 1, len(self.T_wc) - 1)
        if j == i:
            j = max(i - 1, 0)
        cam = self.camera
        gy, gx = np.mgrid[8 : cam.height : 16, 8 : cam.width : 16]
        z = depth[gy, gx].ravel()
        ok = np.isfinite(z)
        if not ok.any():
            return np.zeros(2)
        uv = np.column_stack([gx.ravel(), gy.ravel()])[ok].astype(float)
        Xc = (
            np.column_stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy, np.ones(len(uv))])
            * z[ok, None]
        )
        Xw = Xc @ self.T_wc[i][:3, :3].T + self.T_wc[i][:3, 3]
        uv2, z2 = project(cam, self.T_wc[j], Xw)
        good = z2 > 0.05
        if not good.any():
            return np.zeros(2)
        flow = np.median(uv2[good] - uv[good], axis=0)
        return flow if j > i else -flow

    def _blur(self, i: int, img: np.ndarray, depth: np.ndarray) -> np.ndarray:
        d = self.image_motion(i, depth) * self.c.motion_blur
        length = float(np.hypot(*d))
        if length < 0.5:
            return img
        r = int(math.ceil(length / 2)) + 1
        size = 2 * r + 1
        kernel = np.zeros((size * 4, size * 4), np.float32)  # drawn at 4x, then area-averaged
        c = np.array([size * 2, size * 2], float)
        p0 = np.round((c - d * 2) * 16).astype(int)
        p1 = np.round((c + d * 2) * 16).astype(int)
        cv2.line(kernel, tuple(p0), tuple(p1), 1.0, thickness=4, lineType=cv2.LINE_AA, shift=4)
        kernel = cv2.resize(kernel, (size, size), interpolation=cv2.INTER_AREA)
        kernel /= kernel.sum()
        return cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REFLECT)
