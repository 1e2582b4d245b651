"""Stage checkpoints of `papl-map run` in OUT/.checkpoint, so an interrupted run can resume.

Every finished stage is one folder `<stage>-<hash of its key>/`, written under a temporary name and
renamed, so it is complete or absent. It holds the stage's data files and `stage.json` (the full key,
statistics, timings). A stage's key hashes the previous stage's key and the RunConfig fields the stage
reads, so changing a later stage's settings keeps the earlier checkpoints while changing an earlier one
invalidates everything after it. A checkpoint that is stale or cannot be read is logged and ignored.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from papl_mapper import __version__
from papl_mapper.atomic import move_dir_into_place
from papl_mapper.axes.update import AxisState
from papl_mapper.config import config_to_dict
from papl_mapper.errors import OutputError
from papl_mapper.map import Map, json_default
from papl_mapper.mapping.incremental import Registration
from papl_mapper.mapping.revisit import Revisit
from papl_mapper.mapping.structure import AxisInputs
from papl_mapper.pipelines.config import RunConfig
from papl_mapper.pipelines.summary import MappingStats
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)

FORMAT_VERSION = 2
"""Bumped when a checkpoint's layout changes, so older checkpoints are ignored instead of misread."""

STAGES = ("frontend", "registration", "ba_points", "ba_full")
"""Checkpointed stages in the order they run; each one's key chains the previous one's."""

TITLES = {
    "frontend": "frontend tracks",
    "registration": "registration",
    "ba_points": "points BA",
    "ba_full": "full BA",
}

# RunConfig fields a stage does not read. Everything else is part of its key, so a field added to
# RunConfig later invalidates every checkpoint until it is listed here (safe, never stale).
# input, frontend and hfov_deg act through the tracks and the camera, which the frontend key holds.
_UPSTREAM = {"input", "frontend", "hfov_deg"}
_LATER_ONLY = {"output", "focal", "scale", "stray_line_margin"}
_LINES_AND_AXES = {"lines", "axes", "variant", "lines_from_all_frames"}
NOT_READ: dict[str, set[str]] = {
    "registration": _UPSTREAM
    | _LATER_ONLY
    | _LINES_AND_AXES
    | {"cull", "rotations", "completion", "max_line_error_px"},
    "ba_points": _UPSTREAM | _LATER_ONLY | _LINES_AND_AXES,
    "ba_full": _UPSTREAM | _LATER_ONLY,
}

_REGISTRATION_FIELDS = {
    "frames",
    "T_cw",
    "points_w",
    "point_angle",
    "T_cw_frames",
    "lost",
    "left_out",
    "revisits",
    "init_frames",
}
_REVISIT_FIELDS = {
    "frame",
    "T_cw",
    "pairs",
    "old_frame",
    "drift",
    "scale",
    "path",
    "old_parallax_deg",
    "angle_deg",
    "tracked_T_cw",
    "fused",
}

T = TypeVar("T")


def _digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def frontend_key(input_sha256: str, config: RunConfig, camera: dict[str, Any]) -> str:
    """The frontend's key (JSON text): the input's SHA-256, the frontend config and seed, the camera
    fitted to the recording (`Camera.to_dict`), the frame range and the checkpoint format."""
    i = config.input
    return json.dumps(
        {
            "input": input_sha256,
            "frontend": config_to_dict(config.frontend),
            "seed": config.seed,
            "camera": camera,
            "range": [i.start_s, i.end_s, i.step, i.max_size],
            "format": FORMAT_VERSION,
        },
        sort_keys=True,
        default=str,
    )


def stage_key(previous: str, stage: str, config: RunConfig) -> str:
    """The key of `stage`: the previous stage's key and the config fields `stage` reads (JSON text)."""
    cfg = {k: v for k, v in config_to_dict(config).items() if k not in NOT_READ[stage]}
    return json.dumps(
        {
            "stage": stage,
            "previous": _digest(previous),
            "config": cfg,
            "format": FORMAT_VERSION,
            "software": __version__,
        },
        sort_keys=True,
        default=str,
    )


@dataclass
class Resumed:
    """The checkpoint a run continued from: stage, folder and the stage timings recorded in it."""

    stage: str
    path: Path
    timings_s: dict[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {"stage": self.stage, "checkpoint": str(self.path), "timings_s_before": self.timings_s}


class StageStore:
    """Reads and writes the stage checkpoints of one output folder (`folder` None: checkpoints off).

    `load` only returns checkpoints while every earlier stage of this run came from a checkpoint too:
    once a stage is recomputed, later stages are recomputed from its fresh result.
    """

    def __init__(self, folder: Path | None, frontend_key: str = "", resume: bool = False) -> None:
        self.folder = folder
        self.resume = resume and folder is not None
        self.keys: dict[str, str] = {"frontend": frontend_key}
        self.latest: str | None = None
        """The latest stage whose result this run holds from a valid checkpoint (loaded or written)."""
        self.resumed: Resumed | None = None
        self.written: dict[str, dict[str, float]] = {}
        """Checkpoints written by this run: write time (s) and size (bytes) per stage."""
        self._recomputed = False

    @classmethod
    def off(cls) -> StageStore:
        return cls(None)

    def chain(self, config: RunConfig) -> dict[str, str]:
        """Set the keys of the stages after the frontend from the frontend key and `config`; return all."""
        for prev, stage in zip(STAGES, STAGES[1:], strict=False):
            self.keys[stage] = stage_key(self.keys[prev], stage, config)
        return self.keys

    def may_load(self, stage: str) -> bool:
        """Whether `load` may find a checkpoint of `stage` (resuming, nothing recomputed yet, its folder
        there; `load` still checks it): what only a recomputed stage needs need not start."""
        return self.resume and not self._recomputed and stage in self.keys and self.path(stage).is_dir()

    def path(self, stage: str) -> Path:
        assert self.folder is not None
        return self.folder / f"{stage}-{_digest(self.keys[stage])[:16]}"

    def load(self, stage: str, read: Callable[[Path, dict[str, Any]], T]) -> T | None:
        """`read(folder, stage.json)` of this stage's valid checkpoint, or None (stale/unreadable: logged)."""
        if not self.resume or self._recomputed or stage not in self.keys:
            return None
        path = self.path(stage)
        if not path.is_dir():
            others = sorted(p.name for p in self.folder.glob(f"{stage}-*") if p.is_dir())
            if others:
                log.info(
                    "ignored: %s checkpoint %s was made from other input or settings",
                    TITLES[stage],
                    ", ".join(others),
                )
            return None
        try:
            meta = json.loads((path / "stage.json").read_text())
            if meta.get("key") != self.keys[stage]:
                raise ValueError("its key does not match its folder name")
            value = read(path, meta)
        except Exception as exc:  # noqa: BLE001 - any fault in a checkpoint means: recompute, never trust
            log.warning("ignored: unreadable %s checkpoint %s (%s); recomputing", TITLES[stage], path, exc)
            return None
        self.latest = stage
        self.resumed = Resumed(stage, path, dict(meta.get("timings_s", {})))
        log.info("resumed: %s from %s", TITLES[stage], path)
        return value

    def skip(self, stage: str) -> None:
        """`stage` was recomputed but is not checkpointed: later stages recompute, and resume before it."""
        self._recomputed = True

    def save(
        self,
        stage: str,
        write: Callable[[Path], None],
        stats: dict[str, Any] | None = None,
        timings_s: dict[str, float] | None = None,
    ) -> Path | None:
        """Write this stage's checkpoint atomically: `write(folder)` fills it, stage.json goes last.

        Later stages now recompute. A write that fails (disk full) is logged; the run goes on without it.
        Checkpoints of other input or settings stay until `prune` (a run that fails keeps them).
        """
        self._recomputed = True
        if self.folder is None or stage not in self.keys:
            return None
        final = self.path(stage)
        t0 = time.perf_counter()
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            with _staging(self.folder, stage) as tmp:
                write(tmp)
                meta = {"stage": stage, "key": self.keys[stage], "stats": stats or {}}
                meta["timings_s"] = dict(timings_s or {})
                (tmp / "stage.json").write_text(json.dumps(meta, indent=1, default=json_default))
                move_dir_into_place(tmp, final)
        except (OSError, OutputError) as exc:
            log.warning("could not write the %s checkpoint in %s (%s)", TITLES[stage], self.folder, exc)
            return None
        size = sum(p.stat().st_size for p in final.iterdir())
        self.written[stage] = {"write_s": round(time.perf_counter() - t0, 4), "bytes": size}
        self.latest = stage
        log.debug("checkpoint: %s in %s (%.1f MiB)", TITLES[stage], final, size / 2**20)
        return final

    def prune(self) -> None:
        """Remove the checkpoints of other input or settings for every stage this run checkpointed:
        called once the run's outputs are written, so a run that fails leaves the previous ones."""
        if self.folder is None:
            return
        for stage in self.written:
            final = self.path(stage)
            for old in self.folder.glob(f"{stage}-*"):
                if old != final and old.is_dir():
                    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def _staging(folder: Path, stage: str) -> Iterator[Path]:
    """A fresh temporary folder beside the checkpoints, removed unless it was renamed away."""
    for stale in folder.glob(f".{stage}-*.tmp"):
        shutil.rmtree(stale, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{stage}-", suffix=".tmp", dir=folder))
    try:
        os.chmod(tmp, folder.stat().st_mode & 0o777)  # mkdtemp's 0700 -> as open as its parent
        yield tmp
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


# ---- frontend ---------------------------------------------------------------------------------


def write_tracks(folder: Path, tracks: Tracks) -> None:
    tracks.save(folder / "tracks.npz")


def read_tracks(folder: Path, meta: dict[str, Any]) -> tuple[Tracks, dict[str, Any]]:
    """The tracks and the frontend's statistics."""
    return Tracks.load(folder / "tracks.npz"), dict(meta.get("stats", {}))


# ---- registration -----------------------------------------------------------------------------


def registration_storable() -> bool:
    """Whether this module stores every field of Registration and Revisit (else no checkpoint)."""
    reg = {f.name for f in dataclasses.fields(Registration)}
    rv = {f.name for f in dataclasses.fields(Revisit)}
    return reg == _REGISTRATION_FIELDS and rv == _REVISIT_FIELDS


def _dict_arrays(d: dict[int, Any], shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    ids = np.fromiter(d, np.int64, len(d))  # insertion order, which later stages may iterate in
    values = np.array([np.asarray(v, np.float64) for v in d.values()], np.float64).reshape(-1, *shape)
    return ids, values


def write_registration(folder: Path, reg: Registration, tracks: Tracks) -> None:
    """Registration and the tracks' point ids as registration left them (revisits rename tracks);
    each segment left out of the map in a file of its own."""
    np.savez(
        folder / "registration.npz",
        **_registration_arrays(reg),
        point_track=tracks.point_track,
        n_left_out=np.int64(len(reg.left_out)),
    )
    for k, seg in enumerate(reg.left_out):
        np.savez(folder / f"registration_left_out_{k}.npz", **_registration_arrays(seg))


def _registration_arrays(reg: Registration) -> dict[str, np.ndarray]:
    """One Registration's fields as arrays (not its left-out segments)."""
    kf_ids, kf_T = _dict_arrays(reg.T_cw, (4, 4))
    fr_ids, fr_T = _dict_arrays(reg.T_cw_frames, (4, 4))
    pt_ids, pt_xyz = _dict_arrays(reg.points_w, (3,))
    ang_ids, ang = _dict_arrays(reg.point_angle, ())
    rv = reg.revisits
    pairs = [np.asarray(r.pairs, np.int64).reshape(-1, 2) for r in rv]
    fused = [np.asarray(r.fused, np.int64).reshape(-1, 2) for r in rv]
    return dict(
        frames=np.asarray(reg.frames, np.int64),
        kf_ids=kf_ids,
        kf_T_cw=kf_T,
        frame_ids=fr_ids,
        frame_T_cw=fr_T,
        point_ids=pt_ids,
        point_xyz=pt_xyz,
        angle_ids=ang_ids,
        angle_deg=ang,
        lost=np.asarray(reg.lost, np.int64),
        init_frames=np.asarray(reg.init_frames, np.int64),
        revisit_frame=np.array([r.frame for r in rv], np.int64),
        revisit_T_cw=np.array([r.T_cw for r in rv], np.float64).reshape(-1, 4, 4),
        revisit_old_frame=np.array([r.old_frame for r in rv], np.int64),
        revisit_drift=np.array([r.drift for r in rv], np.float64),
        revisit_scale=np.array([r.scale for r in rv], np.float64),
        revisit_path=np.array([r.path for r in rv], np.float64),
        revisit_old_parallax_deg=np.array([r.old_parallax_deg for r in rv], np.float64),
        revisit_angle_deg=np.array([r.angle_deg for r in rv], np.float64),
        revisit_tracked_T_cw=np.array(
            [np.full((4, 4), np.nan) if r.tracked_T_cw is None else r.tracked_T_cw for r in rv], np.float64
        ).reshape(-1, 4, 4),
        revisit_n_pairs=np.array([len(p) for p in pairs], np.int64),
        revisit_pairs=np.concatenate(pairs) if pairs else np.zeros((0, 2), np.int64),
        revisit_n_fused=np.array([len(p) for p in fused], np.int64),
        revisit_fused=np.concatenate(fused) if fused else np.zeros((0, 2), np.int64),
    )


def _check_point_track(point_track: np.ndarray, tracks: Tracks) -> np.ndarray:
    """A checkpoint's (Kp,) point track ids, refused when they do not fit these tracks."""
    if point_track.shape != tracks.point_track.shape:
        raise ValueError(f"point_track has {point_track.shape} rows, the tracks {tracks.point_track.shape}")
    return point_track


def read_registration(folder: Path, meta: dict[str, Any], tracks: Tracks) -> tuple[Registration, np.ndarray]:
    """The Registration and the (Kp,) point ids to put into `tracks` (checked against its length)."""
    with np.load(folder / "registration.npz", allow_pickle=False) as z:
        a = {k: z[k] for k in z.files}
    _check_point_track(a["point_track"], tracks)
    reg = _registration_from(a)
    for k in range(int(a.get("n_left_out", 0))):
        with np.load(folder / f"registration_left_out_{k}.npz", allow_pickle=False) as z:
            reg.left_out.append(_registration_from({key: z[key] for key in z.files}))
    return reg, a["point_track"]


def _registration_from(a: dict[str, np.ndarray]) -> Registration:
    """One Registration from `_registration_arrays`' arrays (older checkpoints lack later fields)."""

    def as_dict(ids: np.ndarray, values: np.ndarray) -> dict[int, np.ndarray]:
        if len(ids) != len(values):
            raise ValueError("ids and values differ in length")
        return {int(i): v for i, v in zip(ids.tolist(), values, strict=True)}

    bounds = np.concatenate([[0], np.cumsum(a["revisit_n_pairs"])])
    n_rv = len(a["revisit_frame"])
    fused_bounds = np.concatenate([[0], np.cumsum(a.get("revisit_n_fused", np.zeros(n_rv, np.int64)))])
    fused = a.get("revisit_fused", np.zeros((0, 2), np.int64))

    def newer(key: str, shape: tuple[int, ...] = ()) -> np.ndarray:
        """A revisit field later formats added; unknown (NaN) in an older checkpoint."""
        return a.get(key, np.full((n_rv, *shape), np.nan))

    tracked = newer("revisit_tracked_T_cw", (4, 4))
    path, old_parallax, angle = (newer(f"revisit_{k}") for k in ("path", "old_parallax_deg", "angle_deg"))
    revisits = [
        Revisit(
            frame=int(a["revisit_frame"][i]),
            T_cw=a["revisit_T_cw"][i],
            pairs=a["revisit_pairs"][bounds[i] : bounds[i + 1]],
            old_frame=int(a["revisit_old_frame"][i]),
            drift=float(a["revisit_drift"][i]),
            scale=float(a["revisit_scale"][i]),
            path=float(path[i]),
            old_parallax_deg=float(old_parallax[i]),
            angle_deg=float(angle[i]),
            tracked_T_cw=None if np.isnan(tracked[i]).any() else tracked[i],
            fused=fused[fused_bounds[i] : fused_bounds[i + 1]],
        )
        for i in range(n_rv)
    ]
    reg = Registration(
        frames=a["frames"].tolist(),
        T_cw=as_dict(a["kf_ids"], a["kf_T_cw"]),
        points_w=as_dict(a["point_ids"], a["point_xyz"]),
        point_angle={int(i): float(v) for i, v in zip(a["angle_ids"], a["angle_deg"], strict=True)},
        T_cw_frames=as_dict(a["frame_ids"], a["frame_T_cw"]),
        lost=a["lost"].tolist(),
        revisits=revisits,
        init_frames=(int(a["init_frames"][0]), int(a["init_frames"][1])),
    )
    if set(reg.frames) - set(reg.T_cw) or len(reg.frames) != len(reg.T_cw):
        raise ValueError("keyframes and keyframe poses disagree")
    return reg


# ---- points BA and full BA --------------------------------------------------------------------


def write_map(
    folder: Path,
    m: Map,
    point_track: np.ndarray,
    axis_inputs: AxisInputs | None = None,
    line_track: np.ndarray | None = None,
) -> None:
    """The stage's map, the point (and segment) track ids as track completion left them, and the
    axis-update inputs."""
    m.save(folder / "map.papl")
    np.save(folder / "point_track.npy", point_track)
    if line_track is not None:
        np.save(folder / "line_track.npy", line_track)
    if axis_inputs is not None:
        s = axis_inputs.state
        np.savez(
            folder / "axes.npz",
            axes_w=axis_inputs.axes_w,
            serial=s.serial,
            age=s.age,
            jumps=s.jumps,
            state_ints=np.array([s.vertical_index, s.next_serial], np.int64),
            obs_dirs_w=axis_inputs.obs_dirs_w,
            obs_line=axis_inputs.obs_line,
            line_track=axis_inputs.line_track,
            obs_normals_w=axis_inputs.obs_normals_w,
            obs_length_px=axis_inputs.obs_length_px,
        )


def read_map(
    folder: Path, meta: dict[str, Any], tracks: Tracks
) -> tuple[Map, MappingStats, AxisInputs | None, np.ndarray]:
    """The map, the statistics so far, the axis-update inputs (None when the stage had none) and the
    (Kp,) point ids to put into `tracks` (checked against its length); segment ids the stage renamed
    are put into `tracks` here."""
    m = Map.load(folder / "map.papl")
    stats = MappingStats.from_dict(meta["stats"])
    point_track = _check_point_track(np.load(folder / "point_track.npy", allow_pickle=False), tracks)
    if (folder / "line_track.npy").exists():
        line_track = np.load(folder / "line_track.npy", allow_pickle=False)
        if line_track.shape != tracks.line_track.shape:
            raise ValueError(f"line_track has {line_track.shape} rows, the tracks {tracks.line_track.shape}")
        tracks.line_track[:] = line_track
    path = folder / "axes.npz"
    if not path.exists():
        return m, stats, None, point_track
    with np.load(path, allow_pickle=False) as z:
        a = {k: z[k] for k in z.files}
    vertical, next_serial = (int(v) for v in a["state_ints"])
    state = AxisState(a["serial"], a["age"], a["jumps"], vertical, next_serial)
    if (
        len(a["obs_dirs_w"]) != len(a["obs_line"])
        or len(state) != len(a["axes_w"])
        or a["obs_normals_w"].shape != a["obs_dirs_w"].shape
        or len(a["obs_length_px"]) != len(a["obs_line"])
    ):
        raise ValueError("axes.npz: arrays of different lengths")
    axis_inputs = AxisInputs(
        a["axes_w"],
        state,
        a["obs_dirs_w"],
        a["obs_line"],
        a["line_track"],
        a["obs_normals_w"],
        a["obs_length_px"],
    )
    return m, stats, axis_inputs, point_track
