"""What `pipelines.run.run` writes into its output folder, and the checks made before any work.

The map, trajectories, config and summary are written under temporary names and renamed together
(`write_outputs`); then the extras `config.output` asks for: exports, eval.json, previews, report
(`write_extras`). manifest.json lists them all (`papl_mapper.outputs`).
"""

from __future__ import annotations

import contextlib
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from papl_mapper.atomic import atomic_path, check_output_dir
from papl_mapper.config import config_to_dict, dump_toml
from papl_mapper.errors import InputError
from papl_mapper.extras import require
from papl_mapper.map import Map, json_default
from papl_mapper.outputs import add_outputs, begin_run
from papl_mapper.pipelines.config import RunConfig, check_input
from papl_mapper.pipelines.summary import RunSummary
from papl_mapper.scale import check_config as check_scale_config
from papl_mapper.trajectory_io import Trajectory, write_tum

log = logging.getLogger(__name__)

OUTPUT_FILES = ("trajectory.tum", "keyframes.tum", "config.toml", "summary.json", "map.papl")
"""What a run writes into the output folder, in the order the files are renamed into place."""


@dataclass
class Extras:
    """The extra outputs a run wrote (absolute paths), for the caller to list."""

    exports: list[Path] = field(default_factory=list)
    evaluation: Any = None
    """`eval.Evaluation` against `config.output.gt`, or None."""
    previews: list[Path] | None = None
    """The preview PNGs (None: not rendered)."""
    turntable: Path | None = None
    report: Path | None = None

    def paths(self, out: Path) -> list[Path]:
        """Every file written, eval.json included."""
        ev = [out / "eval.json"] if self.evaluation is not None else []
        optional = [p for p in (self.turntable, self.report) if p is not None]
        return [*self.exports, *ev, *(self.previews or []), *optional]


def check_before_work(out: Path, cfg: RunConfig) -> None:
    """Every setting and path that can be checked before the first frame: the output folder, the frame
    range, the export formats, their targets and libraries, the previews' and report's libraries, the
    ground-truth folder, the scale settings."""
    from papl_mapper.exporters import check_available, check_target, suffix_of

    check_output_dir(out)
    check_input(cfg.input)
    for fmt in cfg.output.export:
        target = out / _export_name(fmt)
        if out.is_dir():
            check_target(target)
        else:
            check_available(suffix_of(target))
    # a missing extra fails now, not after the mapping: previews and the report's plots
    if cfg.output.render:
        from papl_mapper.gui.preview import RENDER_MODULES

        for module in RENDER_MODULES:
            require(module, "rendering previews")
    if cfg.output.report:
        require("matplotlib", "the report's plots")
    if cfg.output.gt is not None and not cfg.output.gt.is_dir():
        raise InputError(f"--gt {cfg.output.gt}: no such ground-truth folder")
    check_scale_config(cfg.scale)  # a bad --marker or --camera-height fails before any work


def _export_name(fmt: str) -> str:
    return f"map.{fmt.strip().lstrip('.')}"


#: What each tracking segment left out of the map gets in its folder (`SegmentMap.folder`).
SEGMENT_FILES = ("trajectory.tum", "keyframes.tum", "map.papl")


@dataclass
class SegmentMap:
    """A tracking segment the map could not be joined with, mapped on its own: its own frame and
    scale, frames `first`-`last` of the recording."""

    first: int
    last: int
    map: Map
    trajectory: Trajectory

    @property
    def folder(self) -> str:
        """Its folder in the output folder, e.g. segments/000000-000103."""
        return f"segments/{self.first:06d}-{self.last:06d}"

    def summary(self) -> dict[str, Any]:
        """Its row in summary.json's `segment_maps`."""
        counts = self.map.summary()
        return {
            "frames": [self.first, self.last],
            "folder": self.folder,
            "frames_posed": len(self.trajectory),
            **{k: counts[k] for k in ("keyframes", "points", "lines", "anchored_fraction")},
        }


def write_outputs(
    out: Path,
    m: Map,
    traj: Trajectory,
    cfg: RunConfig,
    summary: RunSummary,
    segments: list[SegmentMap] = (),
) -> None:
    """Every output is written under a temporary name first, then all are renamed (the map last), so an
    interruption while writing leaves the previous run's outputs, not a mix of two runs (only a Ctrl-C
    landing between two of the renames, a window of microseconds, could still mix them). Each segment
    left out of the map gets its map and trajectories in its own folder."""
    names = [f"{seg.folder}/{name}" for seg in segments for name in SEGMENT_FILES] + list(OUTPUT_FILES)
    for seg in segments:
        (out / seg.folder).mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as stack:
        # contexts close in reverse: the map, entered first, is renamed last
        tmp = {name: stack.enter_context(atomic_path(out / name)) for name in reversed(names)}
        m.save(tmp["map.papl"])
        _write_text(tmp["summary.json"], json.dumps(summary.to_dict(), indent=1, default=json_default))
        _write_text(tmp["config.toml"], dump_toml(config_to_dict(cfg)))
        write_tum(tmp["keyframes.tum"], Trajectory(m.keyframes.timestamp, m.keyframes.T_wc, "keyframes"))
        write_tum(tmp["trajectory.tum"], traj)
        for seg in segments:
            seg.map.save(tmp[f"{seg.folder}/map.papl"])
            kf = seg.map.keyframes
            write_tum(tmp[f"{seg.folder}/keyframes.tum"], Trajectory(kf.timestamp, kf.T_wc, "keyframes"))
            write_tum(tmp[f"{seg.folder}/trajectory.tum"], seg.trajectory)
    begin_run(out, [out / name for name in names])


def write_unmapped(out: Path, traj: Trajectory, cfg: RunConfig, summary: RunSummary) -> None:
    """What a recording that cannot be mapped still gives: the poses found (orientations of a camera
    turning in place), the config and the summary saying why; no map, no structure."""
    names = ("trajectory.tum", "config.toml", "summary.json")
    with contextlib.ExitStack() as stack:
        tmp = {name: stack.enter_context(atomic_path(out / name)) for name in names}
        write_tum(tmp["trajectory.tum"], traj)
        _write_text(tmp["config.toml"], dump_toml(config_to_dict(cfg)))
        _write_text(tmp["summary.json"], json.dumps(summary.to_dict(), indent=1, default=json_default))
    begin_run(out, [out / name for name in names])


def write_extras(out: Path, m: Map, cfg: RunConfig, progress: Any, segments: list[SegmentMap] = ()) -> Extras:
    """The exports, eval.json, previews and report.html of `cfg.output`, each added to the manifest as
    it is written; `progress(title)` is the previews' progress context (see `pipelines.run`). The
    segments mapped on their own get the exports too, in their folders."""
    done = Extras()
    o = cfg.output
    for fmt in o.export:
        from papl_mapper.exporters import export

        for folder, mp in [(out, m), *((out / seg.folder, seg.map) for seg in segments)]:
            paths = export(mp, folder / _export_name(fmt))
            add_outputs(out, paths)
            done.exports += paths
    if o.gt is not None:
        from papl_mapper.eval import evaluate

        done.evaluation = evaluate(o.gt, m, out / "trajectory.tum")
        with atomic_path(out / "eval.json") as tmp:
            tmp.write_text(json.dumps(done.evaluation.to_dict(), indent=1))
        add_outputs(out, [out / "eval.json"])
    rendered = None
    if o.render:
        from papl_mapper.gui.preview import render_views

        with progress("previews") as cb:
            rendered = render_views(m, out / "previews", progress=cb)
        done.previews, done.turntable = list(rendered.paths), rendered.turntable or None
        add_outputs(out, done.previews + ([done.turntable] if done.turntable else []))
    if o.report:
        from papl_mapper.gui.report import write_report

        done.report = write_report(out, out / "report.html", gt_dir=o.gt, previews=rendered)
        add_outputs(out, [done.report])
    return done


def unmapped_trajectory(timestamps: np.ndarray, T_cw_frames: dict[int, np.ndarray]) -> Trajectory:
    """The poses an unmappable recording still has (world-to-camera per frame) as a trajectory."""
    from papl_mapper.geometry.se3 import invert

    frames = np.array(sorted(T_cw_frames), np.int64)
    T_wc = np.array([invert(T_cw_frames[int(f)]) for f in frames]).reshape(-1, 4, 4)
    return Trajectory(timestamps[frames].astype(np.float64), T_wc, "trajectory")


def _write_text(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
