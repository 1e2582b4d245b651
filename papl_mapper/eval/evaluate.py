"""`evaluate`: compare a map (and its trajectory) with a ground-truth folder.

Ground truth (the folder GT or GT/gt): `trajectory.tum` (required, T_wc of every frame),
`segments.txt` (`x1 y1 z1 x2 y2 z2 axis`), `axes.json`, and optionally `map.papl`, whose lines and
axes stand in where segments.txt or axes.json are absent. The estimate is aligned to the ground
truth by the Sim(3) of its trajectory (Umeyama, as `evo_ape -as`), which then carries the map's
lines and axes into the ground-truth frame for the line and axis metrics.

Line recall is given twice: against all ground-truth segments, and against the part of them the
recording shows (`visibility.py`: in front, inside the image, not hidden behind the synthetic scene's
quads, in at least `line_visible_min_frames` ground-truth frames of the evaluated time span).
Precision is always against all of the ground truth: an estimated line can only match a real one.
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from papl_mapper.atomic import atomic_path
from papl_mapper.errors import ConfigError, InputError
from papl_mapper.geometry.lines import line_angle_deg
from papl_mapper.geometry.se3 import rotation_alignment
from papl_mapper.geometry.similarity import umeyama
from papl_mapper.map import Map
from papl_mapper.trajectory_io import Trajectory, read_tum

from .axes import GtAxes, match_axes, read_axes
from .lines import Segments, covered_fraction, read_segments
from .trajectory import associate_trajectories, ate_errors, rmse, rpe
from .visibility import DEFAULT_MIN_FRAMES, recording_camera, scene_occluders, segment_visibility

log = logging.getLogger(__name__)

GT_LAYOUT = "gt/trajectory.tum, gt/segments.txt, gt/axes.json (gt/map.papl optional)"


@dataclass
class EvalConfig:
    """How the estimate is compared with the ground truth."""

    max_time_diff: float = 0.01
    """Largest timestamp difference (s) at which an estimated pose is paired with a ground-truth pose."""
    correct_scale: bool = True
    """Align with a Sim(3) (monocular maps are up to scale); false aligns with SE(3) only."""
    rpe_delta: int = 1
    """RPE compares pose pairs this many matched poses apart."""
    line_thresholds_rel: tuple[float, ...] = (0.005, 0.01, 0.02)
    """Line distance thresholds as fractions of the ground-truth scene's bounding-box diagonal."""
    sample_spacing_rel: float = 0.5
    """Sampling step along segments for the line metrics, as a fraction of the smallest threshold."""
    line_visible_min_frames: int = DEFAULT_MIN_FRAMES
    """Fewest ground-truth frames a part of a GT segment must be seen in to count as visible for
    `line_recall_visible`. 5 frames: no line can be triangulated from 1-2 views, and the mapper itself
    asks for 5 observations of a segment (lines.min_views); at 30 fps that is 1/6 s of video. Between
    1 and 10 frames the seen share of the GT length barely changes on the synthetic walks."""

    def check(self) -> None:
        """Raise ConfigError on impossible values."""
        if not self.max_time_diff >= 0:
            raise ConfigError(f"eval max_time_diff must be >= 0, got {self.max_time_diff}")
        if self.rpe_delta < 1:
            raise ConfigError(f"eval rpe_delta must be >= 1, got {self.rpe_delta}")
        if not self.line_thresholds_rel or min(self.line_thresholds_rel) <= 0:
            raise ConfigError(f"eval line_thresholds_rel must be positive, got {self.line_thresholds_rel}")
        if not self.sample_spacing_rel > 0:
            raise ConfigError(f"eval sample_spacing_rel must be > 0, got {self.sample_spacing_rel}")
        if self.line_visible_min_frames < 1:
            raise ConfigError(
                f"eval line_visible_min_frames must be >= 1, got {self.line_visible_min_frames}"
            )


@dataclass
class EvalResult:
    """Every metric of one evaluation; `to_dict()` is JSON-ready, `table()` is for people."""

    gt_dir: str
    trajectory_source: str
    n_gt_poses: int
    n_est_poses: int
    n_matched_poses: int
    alignment: str  # how the Sim(3) was found
    scale: float  # Sim(3) scale: ground-truth units per estimated unit
    sim3: np.ndarray  # (4, 4) [sR t; 0 1], estimate -> ground truth
    ate_rmse: float
    ate_mean: float
    ate_median: float
    ate_max: float
    gt_path_length: float  # ground-truth path length over the matched time span
    ate_rmse_rel_path: float  # ate_rmse / gt_path_length
    rpe_trans: float  # RMSE, ground-truth units
    rpe_rot_deg: float  # RMSE
    n_rpe_pairs: int
    ate_per_pose: tuple[np.ndarray, np.ndarray]  # (ground-truth timestamps, errors) of matched poses
    scene_diagonal: float | None = None  # ground-truth segments' bounding-box diagonal
    line_thresholds: dict[str, float] = field(default_factory=dict)  # key -> absolute tau (GT units)
    line_recall: dict[str, float | None] = field(default_factory=dict)
    line_precision: dict[str, float | None] = field(default_factory=dict)
    line_recall_by_axis: dict[str, dict[str, float]] = field(default_factory=dict)  # GT axis name -> recall
    # recall against the visible clip of the GT (same keys as line_recall); empty when not computable
    line_recall_visible: dict[str, float | None] = field(default_factory=dict)
    gt_visible_length: float | None = None  # GT length seen in >= line_visible_min_frames frames
    gt_visible_fraction: float | None = None  # gt_visible_length / gt_line_length
    line_visible_min_frames: int = DEFAULT_MIN_FRAMES
    line_visibility: str = ""  # how visibility was decided (frames, camera, occluders)
    n_gt_segments: int = 0
    n_est_lines: int = 0
    gt_line_length: float = 0.0
    est_line_length: float = 0.0  # after the Sim(3), ground-truth units
    axis_errors_deg: list[float] = field(default_factory=list)  # matched pairs, in ground-truth order
    axis_pairs: list[dict[str, Any]] = field(default_factory=list)
    unmatched_gt_axes: list[int] = field(default_factory=list)
    unmatched_est_axes: list[int] = field(default_factory=list)
    vertical_error_deg: float | None = None  # estimated vertical vs ground-truth vertical
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON types; NaN becomes null."""
        out: dict[str, Any] = {}
        for k, v in self.__dict__.items():
            if k == "ate_per_pose":
                v = {"timestamps": v[0], "errors": v[1]}
            out[k] = _plain(v)
        return out

    def table(self) -> str:
        """A readable multi-line summary."""

        def f(v: Any, unit: str = "") -> str:
            if v is None or (isinstance(v, float) and not math.isfinite(v)):
                return "n/a"
            return f"{v:.6g}{unit}"

        rows = [
            ("ground truth", self.gt_dir),
            ("estimate", self.trajectory_source),
            (
                "poses (gt / est / matched)",
                f"{self.n_gt_poses} / {self.n_est_poses} / {self.n_matched_poses}",
            ),
            ("alignment", self.alignment),
            ("scale (gt per est unit)", f(self.scale)),
            ("ATE RMSE", f(self.ate_rmse)),
            ("ATE mean / median / max", f"{f(self.ate_mean)} / {f(self.ate_median)} / {f(self.ate_max)}"),
            ("GT path length", f(self.gt_path_length)),
            ("ATE RMSE / path length", f(self.ate_rmse_rel_path)),
            (f"RPE translation ({self.n_rpe_pairs} pairs)", f(self.rpe_trans)),
            ("RPE rotation", f(self.rpe_rot_deg, " deg")),
        ]
        if self.line_thresholds:
            rows.append(
                (
                    "lines (gt / est)",
                    f"{self.n_gt_segments} / {self.n_est_lines}  "
                    f"(length {f(self.gt_line_length)} / {f(self.est_line_length)})",
                )
            )
            rows.append(("scene diagonal", f(self.scene_diagonal)))
            if self.gt_visible_fraction is not None:
                rows.append(
                    (
                        f"GT seen in >= {self.line_visible_min_frames} frames",
                        f"{f(self.gt_visible_fraction)} of the GT length ({f(self.gt_visible_length)})",
                    )
                )
            for key, tau in self.line_thresholds.items():
                vis = (
                    f" (of visible GT {f(self.line_recall_visible.get(key))})"
                    if self.line_recall_visible
                    else ""
                )
                rows.append(
                    (
                        f"lines @ {key} (tau {tau:.4g})",
                        f"recall {f(self.line_recall.get(key))}{vis}  "
                        f"precision {f(self.line_precision.get(key))}",
                    )
                )
        for name, rec in self.line_recall_by_axis.items():
            rows.append((f"  recall, {name} lines", "  ".join(f"{k}: {f(v)}" for k, v in rec.items())))
        for p in self.axis_pairs:
            rows.append((f"axis {p['gt_name']} (gt {p['gt']} <- est {p['est']})", f(p["error_deg"], " deg")))
        if self.vertical_error_deg is not None:
            rows.append(("vertical axis error", f(self.vertical_error_deg, " deg")))
        if self.unmatched_gt_axes or self.unmatched_est_axes:
            rows.append(
                (
                    "unmatched axes",
                    f"gt {self.unmatched_gt_axes or '-'}  est {self.unmatched_est_axes or '-'}",
                )
            )
        width = max(len(k) for k, _ in rows)
        text = "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
        if self.notes:
            text += "\n" + "\n".join(f"note: {n}" for n in self.notes)
        return text


@dataclass
class GroundTruth:
    """The contents of a ground-truth folder."""

    folder: Path
    trajectory: Trajectory
    segments: Segments | None
    axes: GtAxes | None
    notes: list[str] = field(default_factory=list)


def resolve_gt_dir(gt_dir: str | os.PathLike) -> Path:
    """The folder holding trajectory.tum: GT/gt when present, else GT itself."""
    gt_dir = Path(gt_dir)
    if not gt_dir.is_dir():
        raise InputError(f"{gt_dir}: no such ground-truth folder (it holds {GT_LAYOUT})")
    return gt_dir / "gt" if (gt_dir / "gt").is_dir() else gt_dir


def load_ground_truth(gt_dir: str | os.PathLike) -> GroundTruth:
    """Read a ground-truth folder; InputError when trajectory.tum is missing or any file is malformed."""
    folder = resolve_gt_dir(gt_dir)
    tum = folder / "trajectory.tum"
    if not tum.is_file():
        raise InputError(f"{tum}: ground-truth trajectory missing (a ground-truth folder holds {GT_LAYOUT})")
    traj = read_tum(tum)
    notes: list[str] = []
    gt_map: Map | None = None

    def the_map() -> Map | None:
        nonlocal gt_map
        if gt_map is None and (folder / "map.papl").is_file():
            gt_map = Map.load(folder / "map.papl")
        return gt_map

    segments: Segments | None = None
    if (folder / "segments.txt").is_file():
        segments = read_segments(folder / "segments.txt")
    elif the_map() is not None:
        m = the_map()
        segments = Segments(m.lines.endpoints_w.copy(), m.lines.axis_of_line())
        notes.append("segments.txt absent: ground-truth segments taken from gt/map.papl")
    else:
        notes.append("no segments.txt or map.papl in the ground truth: no line metrics")
    axes: GtAxes | None = None
    if (folder / "axes.json").is_file():
        axes = read_axes(folder / "axes.json")
    elif the_map() is not None and len(the_map().axes):
        m = the_map()
        axes = GtAxes(
            m.axes.directions.copy(), m.axes.vertical_index, [f"axis {i}" for i in range(len(m.axes))]
        )
        notes.append("axes.json absent: ground-truth axes taken from gt/map.papl")
    else:
        notes.append("no axes.json or map.papl axes in the ground truth: no axis metrics")
    return GroundTruth(folder, traj, segments, axes, notes)


def trajectory_of_map(m: Map) -> Trajectory:
    """The map's keyframe poses as a trajectory sorted by time."""
    if len(m.keyframes) == 0:
        raise InputError("the map has no keyframes and no trajectory file was given: nothing to align")
    order = np.argsort(m.keyframes.timestamp, kind="stable")
    return Trajectory(m.keyframes.timestamp[order], m.keyframes.T_wc[order], "map keyframes")


def evaluate(
    gt_dir: Path,
    result: Map,
    trajectory_tum: Path | None = None,
    config: EvalConfig | None = None,
) -> EvalResult:
    """Align `result` to the ground truth by its trajectory's Sim(3) and measure trajectory, lines, axes.

    Axes are compared after the rotation that best maps the estimated camera orientations onto
    the ground truth's (see `orientation_alignment`).

    `trajectory_tum` is the estimate's trajectory (every frame); None uses the map's keyframes.
    """
    config = config or EvalConfig()
    config.check()
    gt = load_ground_truth(gt_dir)
    notes = list(gt.notes)
    est = read_tum(trajectory_tum) if trajectory_tum is not None else trajectory_of_map(result)
    source = str(trajectory_tum) if trajectory_tum is not None else "map keyframes"
    i_ref, i_est = associate_trajectories(gt.trajectory, est, config.max_time_diff)
    if len(i_ref) == 0:
        raise InputError(
            f"{source}: no timestamp lies within {config.max_time_diff} s of one in "
            f"{gt.folder / 'trajectory.tum'} (estimate {_span(est)}, ground truth {_span(gt.trajectory)}); "
            "check that both use the same clock"
        )
    if len(i_ref) < 3:
        raise InputError(
            f"{source}: only {len(i_ref)} poses match ground-truth timestamps; a Sim(3) alignment needs 3"
        )
    ref_m, est_m = gt.trajectory.subset(i_ref), est.subset(i_est)
    sim = umeyama(
        est_m.positions,
        ref_m.positions,
        with_scale=config.correct_scale,
        R_x=est_m.T_wc[:, :3, :3],
        R_y=ref_m.T_wc[:, :3, :3],
    )
    if sim.method != "Umeyama":
        notes.append(f"alignment: {sim.method}; evo refuses such trajectories")
    aligned = sim.apply_poses(est_m.T_wc)
    err = ate_errors(ref_m.positions, aligned[:, :3, 3])
    lo, hi = int(i_ref.min()), int(i_ref.max())
    path_len = gt.trajectory.subset(np.arange(lo, hi + 1)).path_length()
    rpe_t, rpe_r = rpe(ref_m.T_wc, aligned, config.rpe_delta)
    res = EvalResult(
        gt_dir=str(gt.folder),
        trajectory_source=source,
        n_gt_poses=len(gt.trajectory),
        n_est_poses=len(est),
        n_matched_poses=len(i_ref),
        alignment=("Sim(3), " if config.correct_scale else "SE(3), ") + sim.method,
        scale=sim.scale,
        sim3=sim.matrix,
        ate_rmse=rmse(err),
        ate_mean=float(err.mean()),
        ate_median=float(np.median(err)),
        ate_max=float(err.max()),
        gt_path_length=path_len,
        ate_rmse_rel_path=rmse(err) / path_len if path_len > 0 else float("nan"),
        rpe_trans=rmse(rpe_t),
        rpe_rot_deg=rmse(rpe_r),
        n_rpe_pairs=len(rpe_t),
        ate_per_pose=(ref_m.timestamps.copy(), err),
        n_est_lines=len(result.lines),
        notes=notes,
    )
    if gt.segments is not None:
        names = gt.axes.names if gt.axes is not None else []
        est_w = sim.apply(result.lines.endpoints_w)
        _line_part(res, gt.segments, est_w, config, names)
        if res.line_thresholds:
            _visible_line_part(res, gt, gt.trajectory.T_wc[lo : hi + 1], est_w, config)
    if gt.axes is not None:
        _axis_part(res, gt.axes, result, orientation_alignment(est_m.T_wc, ref_m.T_wc))
    return res


def orientation_alignment(T_est: np.ndarray, T_ref: np.ndarray) -> np.ndarray:
    """Rotation est world -> ref world from matched camera orientations (chordal L2 mean).

    Axes are directions in the frame the camera orientations live in; aligning them with the
    positions' Sim(3) would carry its rotation error, which is large about the direction of a
    short, nearly straight path. Orientations fix all three rotation angles at every pose.
    """
    return rotation_alignment(T_est[:, :3, :3], T_ref[:, :3, :3])


def _line_part(
    res: EvalResult, gt: Segments, est_w: np.ndarray, config: EvalConfig, names: list[str]
) -> None:
    keep = gt.lengths() > 0
    if not keep.any():
        res.notes.append("the ground-truth segments have no length: no line metrics")
        return
    ends = gt.endpoints[keep]
    diag = float(np.linalg.norm(ends.reshape(-1, 3).max(axis=0) - ends.reshape(-1, 3).min(axis=0)))
    rel = np.asarray(config.line_thresholds_rel, np.float64)
    taus = rel * diag
    spacing = config.sample_spacing_rel * float(taus.min())
    recall, gt_len, by_label = covered_fraction(ends, est_w, taus, spacing, gt.axis[keep])
    precision, est_len, _ = covered_fraction(est_w, ends, taus, spacing)
    if len(est_w) == 0:
        recall = np.zeros(len(taus))
        by_label = {a: np.zeros(len(taus)) for a in by_label}
    keys = [f"{100 * r:g}%" for r in rel]
    res.line_recall_by_axis = {
        (names[a] if 0 <= a < len(names) else f"axis {a}") if a >= 0 else "non-structural": {
            k: float(v) for k, v in zip(keys, vals, strict=True)
        }
        for a, vals in sorted(by_label.items())
    }
    res.scene_diagonal = diag
    res.n_gt_segments = int(keep.sum())
    res.gt_line_length = gt_len
    res.est_line_length = est_len
    res.line_thresholds = {k: float(t) for k, t in zip(keys, taus, strict=True)}
    res.line_recall = {k: _num(v) for k, v in zip(keys, recall, strict=True)}
    res.line_precision = {k: _num(v) for k, v in zip(keys, precision, strict=True)}
    if est_len == 0:
        res.notes.append("the map has no line segments: line precision is undefined")


def _visible_line_part(
    res: EvalResult, gt: GroundTruth, T_wc: np.ndarray, est_w: np.ndarray, config: EvalConfig
) -> None:
    """Recall against the GT seen in >= line_visible_min_frames of the GT frames T_wc (F, 4, 4)."""
    res.line_visible_min_frames = config.line_visible_min_frames
    camera, cam_src = recording_camera(gt.folder)
    if camera is None:
        res.notes.append(f"{cam_src}: no recall against the visible ground truth")
        return
    keep = gt.segments.lengths() > 0
    ends = gt.segments.endpoints[keep]
    quads, occ_src = scene_occluders(gt.folder, gt.segments.endpoints)
    taus = np.array(list(res.line_thresholds.values()))
    spacing = config.sample_spacing_rel * float(taus.min())
    vis = segment_visibility(ends, camera, T_wc, spacing, quads, gt.segments.axis[keep])
    parts, _ = vis.parts(config.line_visible_min_frames)
    visible_len = float(vis.visible_length(config.line_visible_min_frames).sum())
    res.gt_visible_length = visible_len
    res.gt_visible_fraction = visible_len / res.gt_line_length if res.gt_line_length > 0 else None
    res.line_visibility = (
        f"GT seen in >= {config.line_visible_min_frames} of {len(T_wc)} GT frames; camera {cam_src}; "
        + (f"occluders {occ_src}" if quads is not None else occ_src)
    )
    if quads is None:
        res.notes.append(occ_src)
    if visible_len <= 0:
        res.notes.append("no ground-truth segment is visible: no recall against the visible ground truth")
        return
    if len(est_w) == 0:
        recall = np.zeros(len(taus))
    else:
        recall, _, _ = covered_fraction(parts, est_w, taus, spacing)
    res.line_recall_visible = {k: _num(v) for k, v in zip(res.line_thresholds, recall, strict=True)}


def _axis_part(res: EvalResult, gt: GtAxes, m: Map, R: np.ndarray) -> None:
    est = m.axes.directions @ R.T
    match = match_axes(gt.directions, est)
    res.axis_errors_deg = [float(e) for e in match.errors_deg]
    res.axis_pairs = [
        {"gt": g, "est": e, "gt_name": gt.names[g], "error_deg": float(err)}
        for (g, e), err in zip(match.pairs, match.errors_deg, strict=True)
    ]
    res.unmatched_gt_axes = match.unmatched_gt
    res.unmatched_est_axes = match.unmatched_est
    if gt.vertical_index >= 0 and m.axes.vertical_index >= 0:
        res.vertical_error_deg = float(
            line_angle_deg(gt.directions[gt.vertical_index], est[m.axes.vertical_index])
        )
    if len(est) == 0:
        res.notes.append("the map has no principal axes: no axis errors")


def resolve_result(result: str | os.PathLike) -> tuple[Map, Path | None]:
    """(map, trajectory file or None) of a run folder (map.papl, trajectory.tum/keyframes.tum) or a .papl."""
    path = Path(result)
    if path.is_dir():
        map_path = path / "map.papl"
        if not map_path.is_file():
            raise InputError(f"{path}: run folder has no map.papl; give a run folder or a .papl map file")
        for name in ("trajectory.tum", "keyframes.tum"):
            if (path / name).is_file():
                return Map.load(map_path), path / name
        return Map.load(map_path), None
    if not path.exists():
        raise InputError(f"{path}: no such run folder or map file")
    return Map.load(path), None


def write_json(result: EvalResult, path: str | os.PathLike) -> Path:
    """Write `result.to_dict()` as JSON atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(result.to_dict(), indent=1) + "\n")
    return path


def _span(t: Trajectory) -> str:
    return f"{t.timestamps[0]:.6f}..{t.timestamps[-1]:.6f} s" if len(t) else "empty"


def _num(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def _plain(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (np.floating, float)):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    return v
