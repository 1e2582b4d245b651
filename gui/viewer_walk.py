"""The walkthrough player's 2D panel: a keyframe's image from the recording, with overlays.

The map names its recording (`metadata["source_path"]`, written by `papl-map run`) and each
keyframe's frame index in it. A `FrameSource` decodes one frame by index (a video by seeking, an
image folder by its naturally sorted files) at the map camera's size; `keyframe_panel` draws the
segments detected in it (thin, dark) and the map's lines reprojected into it (coloured by axis),
so a user sees what the map explains and what it missed. A recording that is not where the map
says gives a panel that names where it looked, and the 3D view is unaffected.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from papl_mapper.errors import PaplError
from papl_mapper.map import Map

if TYPE_CHECKING:  # the frontend imports scipy: loaded with the first frame's panel, not before
    from papl_mapper.frontend.lines import SegmentDetector

log = logging.getLogger(__name__)

DETECTED_RGB = (20, 20, 20)  # detected segments: near black, under the map lines drawn over them
PANEL_BG = (40, 43, 52)


@dataclass
class Panel:
    """What the 2D panel shows for one keyframe: the picture and one line of text under it."""

    image: np.ndarray  # (H, W, 3) uint8 RGB
    caption: str
    has_frame: bool  # False when the recording could not be read (the image is a message card)
    n_detected: int = 0
    n_reprojected: int = 0


def recording_candidates(m: Map, run_dir: Path | None) -> list[Path]:
    """Where the map's recording may be: its recorded path, then that name beside the run folder."""
    src = m.metadata.get("source_path")
    out: list[Path] = []
    if src:
        out.append(Path(src))
    if run_dir is not None and run_dir.is_dir():
        summary = run_dir / "summary.json"
        if summary.is_file():
            import json

            try:
                path = json.loads(summary.read_text()).get("recording", {}).get("path")
            except (OSError, ValueError):
                path = None
            if path and Path(path) not in out:
                out.append(Path(path))
        if src:
            out.append(run_dir / Path(src).name)
    return out


class FrameSource:
    """Random access to a recording's frames by source index, resized to the map camera's size."""

    def __init__(self, path: Path, size: tuple[int, int]):
        self.path, self.size = path, size
        self._cap: cv2.VideoCapture | None = None
        self._next = -1  # index the capture returns on its next read
        self._files: list[Path] = []
        if path.is_dir():  # the frontend's own listing, so frame indices mean the same files
            from papl_mapper.frontend.video import open_recording

            try:
                self._files = list(open_recording(path, prefetch=0).image_files)
            except PaplError as exc:
                raise OSError(str(exc)) from exc
        else:
            cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
            if not cap.isOpened():
                raise OSError(f"{path}: not a readable video")
            self._cap, self._next = cap, 0

    def read(self, index: int) -> np.ndarray:
        """Frame `index` as (H, W, 3) uint8 RGB; raises OSError when it does not decode."""
        if self._files:
            if not 0 <= index < len(self._files):
                raise OSError(f"{self.path}: no frame {index} (it holds {len(self._files)} images)")
            bgr = cv2.imread(str(self._files[index]), cv2.IMREAD_COLOR)
        else:
            assert self._cap is not None
            if not (0 <= index - self._next < 30):  # a short gap reads through; a long one seeks
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, index)
                self._next = index
            bgr = None
            while self._next <= index:
                ok = self._cap.grab()
                self._next += 1
                if not ok:
                    break
                if self._next - 1 == index:
                    ok, bgr = self._cap.retrieve()
        if bgr is None:
            raise OSError(f"{self.path}: frame {index} does not decode")
        if (bgr.shape[1], bgr.shape[0]) != self.size:
            bgr = cv2.resize(bgr, self.size, interpolation=cv2.INTER_AREA)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()


def open_frames(
    m: Map, run_dir: Path | None, recording: Path | None = None
) -> tuple[FrameSource | None, str]:
    """The map's recording (or `recording`, where the user says it is now) opened for reading, or
    None and one line saying where it looked."""
    size = (int(m.camera.width), int(m.camera.height))
    places = [recording] if recording is not None else recording_candidates(m, run_dir)
    if not places:
        return None, "this map does not record its recording (made before the viewer, or by hand)"
    missing, faults = [], []
    for p in places:
        if not p.exists():
            missing.append(str(p))
            continue
        try:
            return FrameSource(p, size), ""
        except OSError as exc:
            faults.append(str(exc))
    if missing:
        faults.insert(0, "recording not found, looked for " + " and ".join(missing))
    return None, "; ".join(faults)


def reproject_lines(
    m: Map, endpoints_w: np.ndarray, kf_row: int, near: float = 1e-3
) -> tuple[np.ndarray, np.ndarray]:
    """Segments (k, 4) in keyframe `kf_row`'s pixels (distortion applied) and their rows in `endpoints_w`,
    for the segments in front of the camera after clipping at depth `near` and inside the image."""
    c = m.camera
    T_cw = np.linalg.inv(m.keyframes.T_wc[kf_row])
    X = endpoints_w.astype(np.float64) @ T_cw[:3, :3].T + T_cw[:3, 3]  # (M, 2, 3)
    z1, z2 = X[:, 0, 2], X[:, 1, 2]
    front = (z1 > near) | (z2 > near)
    rows = np.flatnonzero(front)
    X = X[rows]
    z1, z2 = X[:, 0, 2], X[:, 1, 2]
    s = np.clip((near - z1) / np.where(z2 - z1 == 0, 1, z2 - z1), 0, 1)  # clip the part behind `near`
    a = np.where((z1 < near)[:, None], X[:, 0] + s[:, None] * (X[:, 1] - X[:, 0]), X[:, 0])
    b = np.where((z2 < near)[:, None], X[:, 1] + (1 - s)[:, None] * (X[:, 0] - X[:, 1]), X[:, 1])
    if len(rows) == 0:
        return np.zeros((0, 4)), rows
    pts = np.concatenate([a, b])
    uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), c.K, np.asarray(c.distortion, np.float64))
    uv = uv.reshape(2, -1, 2)
    segs = np.concatenate([uv[0], uv[1]], axis=1)  # (k, 4)
    inside = _touches_image(segs, c.width, c.height)
    return segs[inside], rows[inside]


def _touches_image(segs: np.ndarray, w: int, h: int) -> np.ndarray:
    lo = np.minimum(segs[:, :2], segs[:, 2:])
    hi = np.maximum(segs[:, :2], segs[:, 2:])
    finite = np.isfinite(segs).all(axis=1)
    return finite & (hi[:, 0] >= 0) & (lo[:, 0] <= w - 1) & (hi[:, 1] >= 0) & (lo[:, 1] <= h - 1)


def keyframe_panel(
    m: Map,
    kf_row: int,
    frames: FrameSource | None,
    why_no_frames: str,
    endpoints_w: np.ndarray,
    line_rgb: np.ndarray,
    detector: SegmentDetector | None,
    max_reprojected: int = 20_000,
) -> Panel:
    """The 2D panel for keyframe row `kf_row`: the frame, detected segments and reprojected map lines."""
    kf_id = int(m.keyframes.ids[kf_row])
    fi = int(m.keyframes.frame_index[kf_row])
    size = (int(m.camera.width), int(m.camera.height))
    if frames is None:
        return Panel(_message_card(size, why_no_frames), why_no_frames, False)
    try:
        rgb = frames.read(fi)
    except OSError as exc:
        return Panel(_message_card(size, str(exc)), str(exc), False)
    canvas = np.ascontiguousarray((0.75 * rgb + 0.25 * 255).astype(np.uint8))  # lighter: overlays read
    n_det = 0
    if detector is not None:
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        det = detector.detect(gray)
        n_det = len(det)
        for x1, y1, x2, y2 in det:
            p, q = (round(x1), round(y1)), (round(x2), round(y2))
            cv2.line(canvas, p, q, DETECTED_RGB, 2, cv2.LINE_AA)
    segs, rows = reproject_lines(m, endpoints_w, kf_row)
    if len(segs) > max_reprojected:
        keep = np.random.default_rng(0).choice(len(segs), max_reprojected, replace=False)
        segs, rows = segs[keep], rows[keep]
    thick = max(2, round(min(size) / 240))
    for (x1, y1, x2, y2), r in zip(segs, rows, strict=True):
        col = tuple(int(v) for v in line_rgb[r])
        cv2.line(canvas, (round(x1), round(y1)), (round(x2), round(y2)), col, thick, cv2.LINE_AA)
    caption = (
        f"keyframe {kf_id} (frame {fi}): {n_det} segments detected (dark), "
        f"{len(segs)} map lines reprojected (axis colours)"
    )
    return Panel(canvas, caption, True, n_det, len(segs))


def detector_for(run_dir: Path | None) -> SegmentDetector:
    """The run's own segment detector settings (its config.toml) when readable, else the defaults."""
    from papl_mapper.frontend.lines import LineConfig, SegmentDetector

    cfg = LineConfig()
    if run_dir is not None and (run_dir / "config.toml").is_file():
        from papl_mapper.config import load_config
        from papl_mapper.pipelines.config import RunConfig

        try:
            cfg = load_config(RunConfig, run_dir / "config.toml").frontend.lines
        except PaplError as exc:
            log.info("segment detector: using defaults, the run's config.toml does not load (%s)", exc)
    return SegmentDetector(cfg)


def _message_card(size: tuple[int, int], text: str) -> np.ndarray:
    """A dark card of `size` with `text` wrapped across it (the 2D panel when there is no frame)."""
    w, h = size
    img = np.full((h, w, 3), PANEL_BG, np.uint8)
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, max(0.6, w / 900)
    lines, cur = [], ""
    for word in text.split():
        trial = f"{cur} {word}".strip()
        if cur and cv2.getTextSize(trial, font, scale, 1)[0][0] > 0.92 * w:
            lines.append(cur)
            cur = word
        else:
            cur = trial
    lines.append(cur)
    step = int(cv2.getTextSize("Ag", font, scale, 1)[0][1] * 2.0)
    y = max(step, (h - step * len(lines)) // 2)
    for line in lines:
        cv2.putText(img, line, (int(0.04 * w), y), font, scale, (235, 235, 235), 1, cv2.LINE_AA)
        y += step
    return img
