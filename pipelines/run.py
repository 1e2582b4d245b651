"""`papl-map run`: one recording to one anchored line map, as a short recipe over the stages.

frontend (tracks) -> keyframe registration with windowed BA -> points-only global BA -> track
completion, merging and retriangulation, and the points BA again -> line triangulation (temporary-VP
stage) -> upright rotation, axes and soft association -> full global BA over
points, anchored and orthonormal lines -> axis update and a second BA -> every frame's pose.
The frontend, registration, points BA and full BA are checkpointed in OUT/.checkpoint (see
`pipelines/checkpoint.py`), so `--resume` after an interruption continues after the latest of them.
`run` also owns the output folder: the checks before work, the outputs, log.txt, the extras and the
manifest (`pipelines/run_outputs.py`), so the command line and the Python API do the same.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import logging
import os
import time
import traceback
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from papl_mapper.pipelines import checkpoint as ckpt
from papl_mapper.pipelines.checkpoint import AxisInputs, StageStore
from papl_mapper.pipelines.config import RunConfig
from papl_mapper.pipelines.logfile import close_log, file_log
from papl_mapper.pipelines.run_outputs import (
    Extras,
    check_before_work,
    unmapped_trajectory,
    write_extras,
    write_outputs,
    write_unmapped,
)
from papl_mapper.pipelines.summary import MappingStats, RecordingInfo, RunSummary

from papl_mapper import __version__
from papl_mapper.backend import global_ba
from papl_mapper.backend.calibration import check_focal
from papl_mapper.config import config_to_dict
from papl_mapper.errors import OutputError, PaplError, UnmappableError
from papl_mapper.eval.trajectory import Trajectory
from papl_mapper.frontend import FrontendStats, process
from papl_mapper.frontend.camera import camera_for_recording
from papl_mapper.frontend.video import open_recording
from papl_mapper.geometry.se3 import invert
from papl_mapper.geometry.triangulation import observation_planes
from papl_mapper.map import Axes, Map
from papl_mapper.mapping.assemble import (
    assemble_map,
    cull_observations,
    drop_stray_lines,
    rotation_to_z,
    set_line_states,
    transform_map,
    vertical_in_world,
    vp_directions_w,
)
from papl_mapper.mapping.culling import CullStats, cull_keyframes
from papl_mapper.mapping.incremental import Registration, register_keyframes
from papl_mapper.mapping.lines import LineEstimates, triangulate_lines
from papl_mapper.mapping.pose_refine import FrameRefiner
from papl_mapper.mapping.rotation_only import fill_rotation_only
from papl_mapper.mapping.structure import find_structure, line_weights
from papl_mapper.mapping.track_completion import complete_tracks
from papl_mapper.mapping.tracking import track_pnp
from papl_mapper.mapping.windowed import WindowedRefiner
from papl_mapper.outputs import add_outputs
from papl_mapper.scale import scale_from_config
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)

ProgressCallback = Callable[[int, int, str], None]
ProgressFactory = Callable[[str], AbstractContextManager[ProgressCallback]]


@contextlib.contextmanager
def _silent(_: str) -> Iterator[ProgressCallback]:
    yield lambda done, total, message="": None


@dataclass
class RunResult:
    """What a run wrote: the map, its summary (summary.json) and the extras of `config.output`."""

    out_dir: Path
    map: Map
    summary: RunSummary
    extras: Extras = field(default_factory=Extras)


class RunInterrupted(KeyboardInterrupt):
    """Ctrl-C during `run`: the stage it stopped, and the latest checkpoint `--resume` continues from."""

    def __init__(self, stage: str, resume_from: str | None, checkpoint_dir: Path) -> None:
        super().__init__(stage)
        self.stage = stage
        self.resume_from = resume_from
        """A stage of `checkpoint.STAGES`, or None when no stage had finished."""
        self.checkpoint_dir = checkpoint_dir

    def message(self) -> str:
        """The one line saying which stage Ctrl-C stopped and where --resume continues."""
        if self.resume_from is None:
            then = "nothing was checkpointed yet, so --resume starts from the beginning"
        else:
            then = f"rerun with --resume to continue from the {ckpt.TITLES[self.resume_from]} checkpoint"
        out = self.checkpoint_dir.parent
        return f"interrupted in {self.stage}: the outputs in {out} are unchanged; {then}"


class ExtrasInterrupted(KeyboardInterrupt):
    """Ctrl-C after the map and its outputs were written, while exports, evaluation, previews or the
    report were: the folder holds the new map; some extras may be missing."""

    def __init__(self, out_dir: Path) -> None:
        super().__init__(str(out_dir))
        self.out_dir = out_dir


def _sha256(path: Path, limit: int = 1 << 30) -> str:
    """SHA-256 of a file (of its first GiB for larger ones, which the summary says)."""
    h = hashlib.sha256()
    if path.is_dir():
        for p in sorted(path.iterdir()):
            h.update(p.name.encode())
        return h.hexdigest()
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            h.update(chunk)
            if fh.tell() >= limit:
                break
    return h.hexdigest()


class _Timer:
    """Wall time per stage, in the order the stages ran; `current` names the running (or failed) stage."""

    def __init__(self) -> None:
        self.times: dict[str, float] = {}
        self.current: str | None = None

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        self.current = name
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.times[name] = round(self.times.get(name, 0.0) + time.perf_counter() - t0, 4)
        self.current = None  # only when the stage ended normally: an exception leaves its name


def run(
    recording: str | Path,
    out_dir: str | Path,
    config: RunConfig | None = None,
    *,
    resume: bool = False,
    progress: ProgressFactory | None = None,
) -> RunResult:
    """Map one recording into `out_dir`: map.papl, trajectory.tum, keyframes.tum, config.toml,
    summary.json, log.txt, the extras of `config.output` and manifest.json listing them.

    `config.input` says which frames, at what size, with which camera, so config.toml and the
    recording reproduce the run. Everything checkable is checked before the first frame. The log of
    an unfinished run stays beside the checkpoints (a resumed run appends to it) and replaces log.txt
    when the outputs are written, so log.txt always belongs to map.papl.
    """
    cfg = config or RunConfig()
    progress = progress or _silent
    recording, out = Path(recording), Path(out_dir)
    check_before_work(out, cfg)
    running_log = out / ".checkpoint" / "log.txt"
    try:
        running_log.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out}: cannot create the output folder ({exc.strerror or exc})") from exc
    handler = file_log(running_log, "a" if resume else "w")
    try:
        m, summary = _map_recording(recording, out, cfg, resume, progress)
    except RunInterrupted as exc:  # the running log keeps why the run stopped
        _log_only(handler, exc.message())
        raise
    except PaplError as exc:
        _log_only(handler, f"error: {exc}")
        raise
    except Exception:
        _log_only(handler, f"internal error:\n{traceback.format_exc()}")
        raise
    finally:
        close_log(handler)
    os.replace(running_log, out / "log.txt")
    add_outputs(out, [out / "log.txt"])
    handler = file_log(out / "log.txt", "a")  # exports, previews and the report log there too
    try:
        extras = write_extras(out, m, cfg, progress)
    except KeyboardInterrupt as exc:
        raise ExtrasInterrupted(out) from exc
    finally:
        close_log(handler)
    return RunResult(out, m, summary, extras)


def _log_only(handler: logging.Handler, message: str) -> None:
    """An ERROR record into the run's log file only (the caller tells the terminal its own way)."""
    handler.handle(log.makeRecord(log.name, logging.ERROR, __file__, 0, message, None, None))


def _map_recording(
    recording: Path, out: Path, cfg: RunConfig, resume: bool, progress: ProgressFactory
) -> tuple[Map, RunSummary]:
    """The stages, then the outputs (see `run`); RunInterrupted on Ctrl-C."""
    timer = _Timer()
    timer.current = "reading the input"
    store: StageStore | None = None
    try:
        i = cfg.input
        rec = open_recording(recording, i.step, i.start_s, i.end_s, i.max_size)
        cam_src = camera_for_recording(i.camera, rec.width, rec.height, cfg.hfov_deg)
        sha = _sha256(recording)
        store = StageStore(out / ".checkpoint", ckpt.frontend_key(sha, cfg, cam_src.camera.to_dict()), resume)
        loaded = store.load("frontend", ckpt.read_tracks)
        if loaded is None:
            fstats = FrontendStats()
            with timer.stage("frontend"), progress("frontend") as cb:
                tracks = process(rec, cam_src.camera, cfg.frontend, progress=cb, stats=fstats, seed=cfg.seed)
            frontend_stats = dataclasses.asdict(fstats)
            with timer.stage("checkpoints"):
                store.save("frontend", functools.partial(ckpt.write_tracks, tracks=tracks), frontend_stats)
        else:
            tracks, frontend_stats = loaded
        try:
            m, stats = map_tracks(tracks, cfg, timer, progress, store)
        except UnmappableError as exc:
            summary = RunSummary(
                recording=RecordingInfo(str(recording), sha, int(len(tracks))),
                frontend=frontend_stats,
                status="unmapped",
                error=str(exc),
                frames_posed=len(exc.T_cw_frames),
            )
            write_unmapped(out, unmapped_trajectory(tracks.timestamp, exc.T_cw_frames), cfg, summary)
            raise
        focal_check = None
        if cfg.focal.enabled:
            with timer.stage("focal_check"):
                focal = check_focal(m, cfg.focal, cfg.seed)
            guessed = " (the camera was guessed from hfov_deg)" if cam_src.guessed else ""
            (log.warning if focal.warn else log.info)("%s%s", focal.message, guessed)
            focal_check = focal.summary()
        m.metadata.update(
            {
                "units": "arbitrary",
                "software": f"papl-mapper {__version__}",
                "source": recording.name,
                "source_path": str(recording),
                "source_sha256": sha,
                "camera_source": cam_src.source,
                "camera_guessed": bool(cam_src.guessed),
                "variant": config_to_dict(cfg.variant),
                "timings_s": timer.times,
            }
        )
        with timer.stage("trajectory"):
            traj = frame_trajectory(tracks, m, cfg)
        with timer.stage("scale"):
            m, traj = scale_from_config(m, traj, cfg.scale, rec.frames)
        summary = RunSummary(
            recording=RecordingInfo(
                str(recording),
                sha,
                int(len(tracks)),
                fps=float(rec.fps),
                width=int(rec.width),
                height=int(rec.height),
                stopped_early=bool(rec.stopped_early),
                stop_message=rec.stop_message,
            ),
            frontend=frontend_stats,
            camera={**cam_src.camera.to_dict(), "source": cam_src.source, "guessed": bool(cam_src.guessed)},
            counts=m.summary(),
            frames_lost=int(len(tracks) - len(traj)),
            mapping=stats,
            focal_check=focal_check,
            timings_s=timer.times,
            resumed=store.resumed.as_dict() if store.resumed else None,
            checkpoints_written=store.written,
            per_frame=_per_frame(tracks),
        )
        timer.current = "writing outputs"
        write_outputs(out, m, traj, cfg, summary)
        store.prune()
    except KeyboardInterrupt as exc:
        latest = store.latest if store is not None else None
        raise RunInterrupted(timer.current or "between stages", latest, out / ".checkpoint") from exc
    return m, summary


def map_tracks(
    tracks: Tracks,
    cfg: RunConfig,
    timer: _Timer | None = None,
    progress: ProgressFactory | None = None,
    store: StageStore | None = None,
) -> tuple[Map, MappingStats]:
    """Everything after the frontend: tracks -> optimised, upright Map and statistics.

    With a `store`, registration, points BA and full BA are checkpointed, and a resumed run continues
    after the latest valid checkpoint (`tracks.point_track` is restored as registration
    and track completion left it).
    """
    timer = timer or _Timer()
    progress = progress or _silent
    store = store or StageStore.off()

    store.chain(cfg)
    loaded = store.load("registration", functools.partial(ckpt.read_registration, tracks=tracks))
    if loaded is None:
        with timer.stage("registration"), progress("keyframes") as cb:
            refine = WindowedRefiner(tracks, cfg.ba, cfg.local_ba_window, cfg.max_point_error_px)
            reg = register_keyframes(
                tracks, cfg.mapping, cb, refine if cfg.mapping.refine_every > 0 else None, cfg.seed
            )
        _save(store, timer, "registration", ckpt.write_registration, reg=reg, tracks=tracks)
    else:
        reg, point_track = loaded
        tracks.point_track[:] = point_track  # in place, like the loop closures that renamed them
    read_map = functools.partial(ckpt.read_map, tracks=tracks)
    full = store.load("ba_full", read_map)
    points = store.load("ba_points", read_map) if full is None else None
    if full is not None:
        m, stats, axis_inputs, point_track = full
        tracks.point_track[:] = point_track  # as track completion renamed them
    else:
        if points is not None:
            m, stats, _, point_track = points
            tracks.point_track[:] = point_track
        else:
            m, stats = _points_ba(tracks, reg, cfg, timer, progress)
            _save(store, timer, "ba_points", ckpt.write_map, m=m, point_track=tracks.point_track, stats=stats)
        up = vertical_in_world(tracks, _poses(m))
        if up is None:
            log.warning("no vertical vanishing direction: the map keeps the first camera's orientation")
        else:
            transform_map(m, rotation_to_z(up))
        if cfg.variant.lines == "none":
            return m, stats
        m, axis_inputs = _lines_and_axes(tracks, m, up is not None, cfg, timer)
        with timer.stage("ba_full"):
            m, stats.ba = _ba(m, cfg, progress, "BA (points + lines)")
        if cfg.completion.enabled and cfg.completion.after_full_ba:
            # as after the points BA: the better poses confirm more observations; the BA after it also
            # re-applies the error limits to the lines the first full BA placed
            stats.completion_full_ba = _complete(tracks, m, cfg, timer)
            with timer.stage("ba_full"):
                m, stats.ba = _ba(m, cfg, progress, "BA (points + lines, completed tracks)")
        _save(
            store,
            timer,
            "ba_full",
            ckpt.write_map,
            m=m,
            point_track=tracks.point_track,
            axis_inputs=axis_inputs,
            stats=stats,
        )
    if axis_inputs is not None and cfg.variant.axis_management:
        from papl_mapper.axes import remap_weights, update_axes

        ai = axis_inputs
        with timer.stage("axis_update"):
            upd = update_axes(ai.axes_w, m.axes.directions, ai.state, cfg.axes)
            w = remap_weights(m.lines.axis_weights, upd.index_map, len(upd.axes))
            stats.axis_update = upd.messages()
            m.axes = upd.to_map_axes()
            fresh = line_weights(
                ai.obs_dirs_w,
                ai.obs_line,
                len(ai.line_track),
                m.axes.directions,
                cfg.axes,
                cfg.variant.association == "hard",
            )
            order = np.searchsorted(ai.line_track, m.lines.ids)
            m.lines.axis_weights = np.where(fresh[order].sum(1, keepdims=True) > 0, fresh[order], w)
            set_line_states(m)
        if upd.adopted or upd.deleted or upd.merged:
            with timer.stage("ba_full"):
                m, stats.ba = _ba(m, cfg, progress, "BA (after axis update)")
    dropped = drop_stray_lines(m, cfg.stray_line_margin)
    if dropped:
        log.info("%d lines reaching outside the points' extent dropped after BA", dropped)
    if len(m.axes) and m.axes.vertical_index >= 0:
        transform_map(m, rotation_to_z(_up(m.axes)))
    return m, stats


def _save(store: StageStore, timer: _Timer, stage: str, write: Callable[..., None], **kw: Any) -> None:
    """Checkpoint one stage (its write time adds to the "checkpoints" timing)."""
    stats = kw.pop("stats", None)
    stats = stats.as_dict() if stats is not None else None
    if stage == "registration" and not ckpt.registration_storable():
        log.warning("registration is not checkpointed: Registration has fields the checkpoint does not know")
        store.skip(stage)
        return
    with timer.stage("checkpoints") if store.folder else contextlib.nullcontext():
        store.save(stage, functools.partial(write, **kw), stats, dict(timer.times))


def _points_ba(
    tracks: Tracks, reg: Registration, cfg: RunConfig, timer: _Timer, progress: ProgressFactory
) -> tuple[Map, MappingStats]:
    """Keyframe culling, the points-only map and its global BA, with the statistics so far."""
    n_registered = len(reg.frames)
    cull_stats = CullStats()
    with timer.stage("culling"):
        reg = cull_keyframes(tracks, reg, cfg.cull, cull_stats)
    T_wc = {f: np.linalg.inv(T) for f, T in reg.T_cw.items()}
    stats = MappingStats(
        frames_unregistered=len(reg.lost),
        keyframes_registered=n_registered,
        culling=cull_stats.as_dict(),
        revisits=[
            {
                "frame": rv.frame,
                "old_frame": rv.old_frame,
                "tracks_fused": len(rv.pairs),
                "correction": round(rv.drift, 4),
                "scale": round(rv.scale, 4),
            }
            for rv in reg.revisits
        ],
    )
    m = assemble_map(tracks, T_wc, reg.points_w, LineEstimates.empty())
    with timer.stage("ba_points"):
        m, stats.ba_points = _ba(m, cfg, progress, "BA (points)")
    if cfg.completion.enabled:
        stats.completion = _complete(tracks, m, cfg, timer)
        with timer.stage("ba_points"):
            m, stats.ba_points = _ba(m, cfg, progress, "BA (points, completed tracks)")
    return m, stats


def _complete(tracks: Tracks, m: Map, cfg: RunConfig, timer: _Timer) -> dict[str, int]:
    """Track completion, merging and retriangulation on the BA poses of `m`; its points are replaced
    in place (keyframes and lines kept) for the BA that follows. Returns the statistics."""
    with timer.stage("completion"):
        points_w, done = complete_tracks(tracks, m, cfg.completion)
        m.points = assemble_map(tracks, _poses(m), points_w, LineEstimates.empty()).points
    log.info(
        "tracks: %d merged, %d completed (%d keyframe observations), %d retriangulated",
        done.merged,
        done.completed,
        done.observations_added,
        done.retriangulated,
    )
    return done.as_dict()


def _lines_and_axes(
    tracks: Tracks, m: Map, upright: bool, cfg: RunConfig, timer: _Timer
) -> tuple[Map, AxisInputs | None]:
    """Line triangulation on the upright points map, then axes and soft association: the map for the
    full BA and what the axis update after it needs (None without axes: orthonormal lines)."""
    with timer.stage("lines"):
        # every registered frame's segments, not only the keyframes': more views, longer baselines
        T_by_frame = frame_poses(tracks, m, cfg) if cfg.lines_from_all_frames else _poses(m)
        sel = np.isin(tracks.line_frame, list(T_by_frame))
        frames, labels = tracks.line_frame[sel], tracks.line_vp[sel]
        T_obs = np.stack([T_by_frame[int(f)] for f in frames]) if sel.any() else np.zeros((0, 4, 4))
        vp_w = vp_directions_w(tracks, frames, labels, T_obs)
        est = triangulate_lines(
            tracks.line_track[sel], T_obs, tracks.line_xy[sel], vp_w, tracks.camera.K, cfg.lines, cfg.seed
        )
    log.info("%d lines triangulated, %d from vanishing directions", len(est.track), int(est.from_vp.sum()))
    with timer.stage("axes"):
        m_points = m
        if cfg.variant.lines == "orthonormal" or not upright:
            axis_inputs = None
            m = assemble_map(tracks, _poses(m_points), _points(m_points), est)
        else:
            obs_line = np.searchsorted(est.track, tracks.line_track[sel])
            known = np.isin(tracks.line_track[sel], est.track)
            obs_dirs, obs_line = vp_w[known], obs_line[known]
            d = est.endpoints_w[:, 1] - est.endpoints_w[:, 0]
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            xy = tracks.line_xy[sel][known]
            structure = find_structure(
                d,
                est.from_vp,
                obs_dirs,
                obs_line,
                np.array([0.0, 0.0, 1.0]),
                cfg.axes,
                hard=cfg.variant.association == "hard",
                obs_normals_w=observation_planes(T_obs[known], tracks.camera.K, xy)[:, :3],
                obs_weight=np.linalg.norm(xy[:, 2:] - xy[:, :2], axis=1),
                min_support_fraction=cfg.axis_min_support_fraction,
            )
            m = assemble_map(
                tracks, _poses(m_points), _points(m_points), est, structure.axes, structure.weights
            )
            axis_inputs = AxisInputs(
                structure.axes.directions, structure.state, obs_dirs, obs_line, est.track
            )
        m.metadata = dict(m_points.metadata)
    return m, axis_inputs


def _ba(m: Map, cfg: RunConfig, progress: ProgressFactory, title: str) -> tuple[Map, dict[str, Any]]:
    """Outliers culled, then global BA with a progress bar per LM iteration; the map and statistics."""
    culled = cull_observations(m, cfg.max_point_error_px, cfg.max_line_error_px, cfg.ba.min_views, 1)
    log.info("%s: culled %s", title, ", ".join(f"{v} {k}" for k, v in culled.items() if v) or "nothing")
    with progress(title) as cb:
        res = global_ba(m, cfg.ba, progress=lambda i, n, cost: cb(i, n, f"cost {cost:.6g}"))
    log.info(
        "%s: cost %.6g -> %.6g in %d iterations (%.2f s); rms %s px",
        title,
        res.initial_cost,
        res.final_cost,
        res.iterations,
        res.time_s,
        ", ".join(f"{k} {v:.3f}" for k, v in res.final_rms_px.items()),
    )
    if res.dropped:
        log.info(
            "%s: left out %s", title, ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in res.dropped.items())
        )
    res.map.metadata = dict(m.metadata)
    stats = {
        "initial_cost": res.initial_cost,
        "final_cost": res.final_cost,
        "iterations": res.iterations,
        "converged": res.converged,
        "time_s": round(res.time_s, 3),
        "rms": {k: {"before": res.initial_rms_px.get(k), "after": v} for k, v in res.final_rms_px.items()},
        "culled_observations": sum(v for k, v in culled.items() if k.endswith("observations")),
        "problem": {
            "variables": res.n_variables,
            "observations": res.n_observations,
            "line_parameters": res.line_params,
            "culled_before": culled,
            "left_out": res.dropped,
        },
    }
    return res.map, stats


def _up(axes: Axes) -> np.ndarray:
    v = axes.directions[axes.vertical_index]
    return v if v[2] >= 0 else -v


def _poses(m: Map) -> dict[int, np.ndarray]:
    return {int(k): T for k, T in zip(m.keyframes.ids, m.keyframes.T_wc, strict=True)}


def _points(m: Map) -> dict[int, np.ndarray]:
    return {int(i): x for i, x in zip(m.points.ids, m.points.xyz, strict=True)}


def frame_poses(tracks: Tracks, m: Map, cfg: RunConfig) -> dict[int, np.ndarray]:
    """T_wc of every frame that has one: keyframes from the map, the others by PnP on its points."""
    K = tracks.camera.K
    kf = _poses(m)
    pid = m.points.ids
    out: dict[int, np.ndarray] = {}
    last = None
    # the map's lines and axes refine each PnP pose (points alone drift in rotation where few)
    refiner = FrameRefiner.from_map(tracks, m, cfg.mapping.pnp.refine)
    for f in range(len(tracks)):
        if f in kf:
            T_wc = kf[f]
        else:
            ids, uv = tracks.points_in(f)
            idx = np.minimum(np.searchsorted(pid, ids), max(len(pid) - 1, 0))
            known = pid[idx] == ids if len(pid) else np.zeros(len(ids), bool)
            guess = np.linalg.inv(last) if last is not None else None
            X, uv = m.points.xyz[idx[known]], uv[known]
            res = track_pnp(X, uv, K, guess, cfg.mapping.pnp, seed=cfg.seed)
            if not res.ok:
                continue
            T_cw, _ = refiner.refine(f, res.T_cw, X[res.inliers], uv[res.inliers])
            T_wc = np.linalg.inv(T_cw)
        last = out[f] = T_wc
    # frames that turn in place where nothing is mapped (a pan at the start) keep an orientation
    turned = fill_rotation_only(tracks, {f: invert(T) for f, T in out.items()}, cfg.mapping.rotation_only)
    out.update({f: invert(T) for f, T in turned.items()})
    return dict(sorted(out.items()))


def frame_trajectory(tracks: Tracks, m: Map, cfg: RunConfig) -> Trajectory:
    """A pose for every frame that has one (see `frame_poses`), as a timestamped trajectory."""
    poses = frame_poses(tracks, m, cfg)
    frames = np.array(sorted(poses), np.int64)
    T = np.array([poses[int(f)] for f in frames]).reshape(-1, 4, 4)
    return Trajectory(tracks.timestamp[frames].astype(np.float64), T, "trajectory")


def _per_frame(tracks: Tracks) -> dict[str, list[int]]:
    n = len(tracks)
    return {
        "frame": tracks.frame_index.astype(int).tolist(),
        "points": np.bincount(tracks.point_frame, minlength=n).astype(int).tolist(),
        "lines": np.bincount(tracks.line_frame, minlength=n).astype(int).tolist(),
    }


__all__ = [
    "ExtrasInterrupted",
    "RunConfig",
    "RunInterrupted",
    "RunResult",
    "frame_trajectory",
    "map_tracks",
    "run",
]
