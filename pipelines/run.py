"""`papl-map run`: one recording to one anchored line map, as a short recipe over the stages.

frontend (tracks) -> keyframe registration with windowed BA -> points-only global BA -> rotation
check (a second BA from averaged rotations where the first one's miss the pairwise ones) -> reverse
check (the recording registered backwards, in a worker process beside the forward registration,
`pipelines/registration.py`: a second start where the tracks favour it) -> track completion,
merging and retriangulation, and the points BA again -> line triangulation (temporary-VP stage) ->
upright rotation, axes and soft association -> full global BA over points, anchored and orthonormal
lines -> axis update and a second BA -> every frame's pose.
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
import time
import traceback
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from papl_mapper import __version__
from papl_mapper.atomic import move_into_place
from papl_mapper.backend.calibration import check_focal
from papl_mapper.errors import OutputError, PaplError, UnmappableError
from papl_mapper.frontend import FrontendStats, process
from papl_mapper.frontend.camera import camera_for_recording
from papl_mapper.frontend.video import open_recording
from papl_mapper.map import Map
from papl_mapper.mapping import frames
from papl_mapper.mapping.adjust import adjust, cull
from papl_mapper.mapping.assemble import (
    assemble_map,
    drop_stray_lines,
    upright_by_axes,
    upright_by_vanishing_points,
)
from papl_mapper.mapping.culling import CullStats, cull_keyframes
from papl_mapper.mapping.frames import keyframe_poses
from papl_mapper.mapping.incremental import Registration
from papl_mapper.mapping.line_completion import complete_map_lines
from papl_mapper.mapping.lines import LineEstimates
from papl_mapper.mapping.reverse_start import reverse_checked
from papl_mapper.mapping.rotation_averaging import rotation_checked
from papl_mapper.mapping.structure import structured_map, triangulate_map_lines, update_structure
from papl_mapper.mapping.track_completion import complete_map
from papl_mapper.outputs import add_outputs
from papl_mapper.pipelines import checkpoint as ckpt
from papl_mapper.pipelines.checkpoint import StageStore
from papl_mapper.pipelines.config import RunConfig
from papl_mapper.pipelines.logfile import close_log, file_log
from papl_mapper.pipelines.registration import BackwardRegistration, register_tracks
from papl_mapper.pipelines.run_outputs import (
    Extras,
    SegmentMap,
    check_before_work,
    unmapped_trajectory,
    write_extras,
    write_outputs,
    write_unmapped,
)
from papl_mapper.pipelines.summary import (
    MappingStats,
    RecordingInfo,
    RunSummary,
    per_frame_counts,
    revisit_row,
)
from papl_mapper.scale import scale_from_config
from papl_mapper.tracks import Tracks
from papl_mapper.trajectory_io import Trajectory

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
        m, summary, segments = _map_recording(recording, out, cfg, resume, progress)
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
    move_into_place(running_log, out / "log.txt")
    add_outputs(out, [out / "log.txt"])
    handler = file_log(out / "log.txt", "a")  # exports, previews and the report log there too
    try:
        extras = write_extras(out, m, cfg, progress, segments)
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
) -> tuple[Map, RunSummary, list[SegmentMap]]:
    """The stages, then the outputs (see `run`); RunInterrupted on Ctrl-C."""
    timer = _Timer()
    timer.current = "reading the input"
    store: StageStore | None = None
    backward = BackwardRegistration(cfg)  # forked before any thread starts: the fork copies none
    if cfg.output.render or cfg.output.report:  # the previews' backend probe runs beside the mapping
        from papl_mapper.gui.preview import start_offscreen_probe

        start_offscreen_probe()
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
        store.chain(cfg)
        if not (store.may_load("ba_points") or store.may_load("ba_full")):  # else no backward start
            backward.submit(tracks)  # before the forward registration renames tracks
        try:
            reg = register(tracks, cfg, timer, progress, store)
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
        m, stats = build_map(tracks, reg, cfg, timer, progress, store, backward)
        # the focal check of the map as it is now, in the worker beside the frames' poses
        focal_wait = backward.aside(check_focal, m, cfg.focal, cfg.seed) if cfg.focal.enabled else None
        m.metadata.update(
            {
                "units": "arbitrary",
                "software": f"papl-mapper {__version__}",
                "source": recording.name,
                "source_path": str(recording),
                "source_sha256": sha,
                "camera_source": cam_src.source,
                "camera_guessed": bool(cam_src.guessed),
                "variant": {  # the ablation switches, as maps have recorded them
                    "lines": cfg.variant.lines,
                    "association": cfg.axes.association,
                    "axis_management": cfg.axes.update,
                },
                "timings_s": timer.times,
            }
        )
        with timer.stage("trajectory"):
            traj = frame_trajectory(tracks, m, cfg)
        focal_check = None
        if focal_wait is not None:
            with timer.stage("focal_check"):
                focal = focal_wait()
            guessed = " (the camera was guessed from hfov_deg)" if cam_src.guessed else ""
            (log.warning if focal.warn else log.info)("%s%s", focal.message, guessed)
            focal_check = focal.summary()
        backward.close()
        with timer.stage("scale"):
            m, traj = scale_from_config(m, traj, cfg.scale, rec.frames)
        segments = segment_maps(tracks, reg, cfg, timer, progress)
        for seg in segments:
            seg.map.metadata.update({k: m.metadata[k] for k in ("software", "source", "source_sha256")})
            seg.map.metadata.update(units="arbitrary", segment_frames=[seg.first, seg.last])
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
            per_frame=per_frame_counts(tracks),
            segment_maps=[seg.summary() for seg in segments],
        )
        _warn_partial(summary.frames_lost, len(tracks), cam_src.guessed, stats.segments_left_out, segments)
        timer.current = "writing outputs"
        write_outputs(out, m, traj, cfg, summary, segments)
        store.prune()
    except KeyboardInterrupt as exc:
        latest = store.latest if store is not None else None
        raise RunInterrupted(timer.current or "between stages", latest, out / ".checkpoint") from exc
    finally:
        backward.close()
    return m, summary, segments


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
    with BackwardRegistration(cfg) as backward:
        backward.submit(tracks)  # before the forward registration renames tracks
        reg = register(tracks, cfg, timer, progress, store)
        return build_map(tracks, reg, cfg, timer, progress, store, backward)


def register(
    tracks: Tracks, cfg: RunConfig, timer: _Timer, progress: ProgressFactory, store: StageStore
) -> Registration:
    """Registration (`register_keyframes` with the windowed BA), or its checkpoint when resumed."""
    store.chain(cfg)
    loaded = store.load("registration", functools.partial(ckpt.read_registration, tracks=tracks))
    if loaded is not None:
        reg, point_track = loaded
        tracks.point_track[:] = point_track  # in place, like the loop closures that renamed them
        return reg
    with timer.stage("registration"), progress("keyframes") as cb:
        reg = register_tracks(tracks, cfg, cb)
    _save(store, timer, "registration", ckpt.write_registration, reg=reg, tracks=tracks)
    return reg


def build_map(
    tracks: Tracks,
    reg: Registration,
    cfg: RunConfig,
    timer: _Timer,
    progress: ProgressFactory,
    store: StageStore,
    backward: BackwardRegistration | None = None,
) -> tuple[Map, MappingStats]:
    """Everything after registration: the registered keyframes -> optimised, upright Map and
    statistics; the points BA and full BA checkpointed in `store` and resumed from it. `backward`:
    the backward registration of the tracks (`cfg.reverse`), submitted before the forward one; without
    it, the tracks as they are now are registered backwards here."""
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
            m, stats = _points_ba(tracks, reg, cfg, timer, progress, backward)
            _save(store, timer, "ba_points", ckpt.write_map, m=m, point_track=tracks.point_track, stats=stats)
        upright = upright_by_vanishing_points(tracks, m)
        if not upright:
            log.warning("no vertical vanishing direction: the map keeps the first camera's orientation")
        if cfg.variant.lines == "none":
            _cull_after_ba(m, cfg, stats)
            return m, stats
        with timer.stage("lines"):
            # every registered frame's segments, not only the keyframes': more views, longer baselines
            poses = frame_poses(tracks, m, cfg) if cfg.lines_from_all_frames else keyframe_poses(m)
            lines = triangulate_map_lines(tracks, poses, cfg.lines, cfg.seed)
        with timer.stage("axes"):
            anchored = cfg.variant.lines == "anchored"
            m, axis_inputs = structured_map(
                tracks, m, lines, upright, cfg.axes, anchored, cfg.ba.line_sigma_px, cfg.lines
            )
        with timer.stage("ba_full"):
            m, stats.ba = _ba(m, cfg, progress, "BA (points + lines)")
        if cfg.completion.enabled and cfg.completion.after_full_ba:
            # as after the points BA: the better poses confirm more observations; the BA after it also
            # re-applies the error limits to the lines the first full BA placed
            with timer.stage("completion"):
                stats.completion_full_ba = complete_map(tracks, m, cfg.completion).as_dict()
                if cfg.completion.lines:
                    stats.line_completion = complete_map_lines(tracks, m, cfg.completion, axis_inputs)
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
            line_track=tracks.line_track,
            stats=stats,
        )
    if axis_inputs is not None and cfg.axes.update:
        with timer.stage("axis_update"):
            changed, stats.axis_update = update_structure(m, axis_inputs, cfg.axes, cfg.ba.line_sigma_px)
        if changed:
            with timer.stage("ba_full"):
                m, stats.ba = _ba(m, cfg, progress, "BA (after axis update)")
    _cull_after_ba(m, cfg, stats)
    dropped = drop_stray_lines(m, cfg.stray_line_margin)
    if dropped:
        log.info("%d lines reaching outside the points' extent dropped after BA", dropped)
    upright_by_axes(m)
    return m, stats


def segment_maps(
    tracks: Tracks, reg: Registration, cfg: RunConfig, timer: _Timer, progress: ProgressFactory
) -> list[SegmentMap]:
    """Each tracking segment left out of the map (`reg.left_out`), mapped on its own by the stages
    after registration, with the poses of its frames: what was posed is not lost. Not checkpointed (a
    resumed run maps them again from the registration's); the track ids the stages rename are put
    back after each, so the map and its trajectory keep theirs."""
    out: list[SegmentMap] = []
    # the backward registration covers the whole recording, whose main map holds none of the segment's frames
    segment_cfg = dataclasses.replace(cfg, reverse=dataclasses.replace(cfg.reverse, enabled=False))
    for seg, (a, b) in zip(reg.left_out, reg.segments_left_out, strict=True):
        first, last = int(tracks.frame_index[a]), int(tracks.frame_index[b])
        log.info(
            "mapping the tracking segment of frames %d-%d on its own (its own frame and scale)", first, last
        )
        point_track, line_track = tracks.point_track.copy(), tracks.line_track.copy()
        try:
            with timer.stage("segments"):
                m, _ = build_map(tracks, seg, segment_cfg, _Timer(), progress, StageStore.off())
                traj = frame_trajectory(tracks, m, cfg)
        except Exception as exc:  # noqa: BLE001 - a segment's own map is extra: it must not cost the map
            log.warning("tracking segment of frames %d-%d: no map of its own (%s)", first, last, exc)
            log.debug("the segment's stages failed:", exc_info=True)
            continue
        finally:
            tracks.point_track[:] = point_track
            tracks.line_track[:] = line_track
        inside = (traj.timestamps >= tracks.timestamp[a]) & (traj.timestamps <= tracks.timestamp[b])
        out.append(SegmentMap(first, last, m, traj.subset(np.flatnonzero(inside))))
    return out


def _cull_after_ba(m: Map, cfg: RunConfig, stats: MappingStats) -> None:
    """The error limits every BA starts from, applied to the map the last one left (in place): an
    observation it moved beyond them (a free line thrown by a step the points paid for) is dropped, and
    a line or point left without views with it, so the exported map fits what it says it saw."""
    stats.culled_after_ba = cull(
        m, cfg.ba, cfg.max_point_error_px, cfg.max_line_error_px, "after the last BA"
    )


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
    tracks: Tracks,
    reg: Registration,
    cfg: RunConfig,
    timer: _Timer,
    progress: ProgressFactory,
    backward: BackwardRegistration | None,
) -> tuple[Map, MappingStats]:
    """Keyframe culling, the points-only map and its global BA, with the statistics so far."""
    n_registered = len(reg.frames)
    cull_stats = CullStats()
    with timer.stage("culling"):
        reg = cull_keyframes(tracks, reg, cfg.cull, cull_stats)
    stats = MappingStats(
        frames_unregistered=len(reg.lost),
        segments_left_out=[
            [int(tracks.frame_index[a]), int(tracks.frame_index[b])] for a, b in reg.segments_left_out
        ],
        keyframes_registered=n_registered,
        culling=cull_stats.as_dict(),
        revisits=[revisit_row(rv) for rv in reg.revisits],
    )
    T_wc = {f: np.linalg.inv(T) for f, T in reg.T_cw.items()}
    m = assemble_map(tracks, T_wc, reg.points_w, LineEstimates.empty())
    with timer.stage("ba_points"):
        m, stats.ba_points = _ba(m, cfg, progress, "BA (points)")
    if cfg.rotations.enabled:
        with timer.stage("rotation_check"), progress("BA (points, averaged rotations)") as cb:
            m, check = rotation_checked(
                m, cfg.ba, cfg.rotations, cfg.max_point_error_px, _costs(cb), cfg.seed
            )
            stats.rotation_check = check.as_dict()
    if cfg.reverse.enabled:
        with timer.stage("reverse_check"):
            if backward is None:
                backward = BackwardRegistration(cfg, worker=False)
            if not backward.submitted:  # a checkpoint that was to be resumed from did not load
                backward.submit(tracks)
            with progress("keyframes (backward)") as cb:
                back = backward.result(cb)
            with progress("BA (points, backward start)") as cb:
                m, reverse = reverse_checked(
                    m,
                    tracks,
                    back.poses,
                    cfg.ba,
                    cfg.max_point_error_px,
                    cfg.reverse,
                    _costs(cb),
                    backward.ba_aside,
                )
            stats.reverse_check = reverse.as_dict() | back.summary()
        if reverse.kept == "backward":
            with timer.stage("ba_points"):
                m, stats.ba_points = _ba(m, cfg, progress, "BA (points, backward start)")
    if cfg.completion.enabled:
        with timer.stage("completion"):
            stats.completion = complete_map(tracks, m, cfg.completion).as_dict()
        with timer.stage("ba_points"):
            m, stats.ba_points = _ba(m, cfg, progress, "BA (points, completed tracks)")
    return m, stats


def _costs(cb: ProgressCallback) -> Callable[[int, int, float], None]:
    """A BA's per-iteration report (iteration, of, cost) as a progress bar's message."""
    return lambda i, n, cost: cb(i, n, f"cost {cost:.6g}")


def _ba(m: Map, cfg: RunConfig, progress: ProgressFactory, title: str) -> tuple[Map, dict[str, Any]]:
    """A global BA with its outliers culled first, with a progress bar per LM iteration."""
    with progress(title) as cb:
        return adjust(m, cfg.ba, cfg.max_point_error_px, cfg.max_line_error_px, title, cb)


def frame_poses(tracks: Tracks, m: Map, cfg: RunConfig) -> dict[int, np.ndarray]:
    """T_wc of every frame that has one (`mapping.frames.frame_poses` with the run's settings)."""
    return frames.frame_poses(tracks, m, cfg.mapping.pnp, cfg.mapping.rotation_only, cfg.seed)


def frame_trajectory(tracks: Tracks, m: Map, cfg: RunConfig) -> Trajectory:
    """Every frame's pose as a trajectory (`mapping.frames.frame_trajectory` with the run's settings)."""
    return frames.frame_trajectory(tracks, m, cfg.mapping.pnp, cfg.mapping.rotation_only, cfg.seed)


__all__ = [
    "ExtrasInterrupted",
    "RunConfig",
    "RunInterrupted",
    "RunResult",
    "frame_trajectory",
    "map_tracks",
    "run",
]


#: Above this fraction of frames without a pose the run warns that the map is partial.
PARTIAL_WARN_FRACTION = 0.2


def _warn_partial(
    lost: int,
    frames: int,
    guessed_camera: bool,
    left_out: list[list[int]] = (),
    segments: list[SegmentMap] = (),
) -> None:
    """A warning, not silence, when much of the recording has no pose: the map covers only part of it,
    which a wrong camera file (intrinsics, distortion) causes as often as the recording itself. Tracking
    segments mapped on their own but not joined (`left_out`, recording frame ranges) are named, with
    the folders their own maps went to (`segments`)."""
    if frames == 0 or lost <= PARTIAL_WARN_FRACTION * frames:
        return
    cause = (
        "the guessed intrinsics (give --camera)"
        if guessed_camera
        else "the camera file (intrinsics, distortion)"
    )
    apart = ""
    if left_out:
        ranges = ", ".join(f"{a}-{b}" for a, b in left_out)
        apart = (
            f"; frames {ranges} were mapped as separate tracking segments that share too little with "
            "the map to join it (a blind stretch between them)"
        )
        if segments:
            folders = ", ".join(seg.folder for seg in segments)
            apart += f", each written with its own map, frame and scale to {folders}"
    log.warning(
        "%d of %d frames (%.0f%%) have no pose%s: the map covers only part of the recording; check %s, "
        "or the frames without a pose in summary.json's per_frame (too little texture or motion blur)",
        lost,
        frames,
        100.0 * lost / frames,
        apart,
        cause,
    )
