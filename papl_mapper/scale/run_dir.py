"""Scaling a finished run folder: map, trajectories, summary and the exports beside them, atomically.

Everything is written under temporary names first and renamed only when all are ready (the map
last), so a failure leaves the unscaled outputs as they were.
"""

from __future__ import annotations

import contextlib
import json
import logging
from pathlib import Path

from papl_mapper.atomic import atomic_path
from papl_mapper.errors import InputError
from papl_mapper.map import Map, json_default
from papl_mapper.trajectory_io import read_tum, write_tum

from .apply import scale_map, scale_trajectory
from .estimate import ScaleEstimate

TRAJECTORIES = ("trajectory.tum", "keyframes.tum")


def run_map_path(run_dir: Path) -> Path:
    """The run folder's map.papl; InputError when `run_dir` is not a finished run."""
    path = run_dir / "map.papl"
    if not run_dir.is_dir():
        raise InputError(f"{run_dir}: no such run folder")
    if not path.exists():
        raise InputError(f"{run_dir}: holds no map.papl; is it the --out folder of a finished papl-map run?")
    return path


def map_exports(run_dir: Path) -> list[Path]:
    """The export files `papl-map run --export` wrote beside the map (map.<suffix>, not map.papl)."""
    from papl_mapper.exporters import REGISTRY

    out = []
    for p in sorted(run_dir.glob("map.*")):
        suffix = p.name[len("map") :].lower()
        if suffix != ".papl" and suffix in REGISTRY and not p.name.startswith("."):
            out.append(p)
    return out


def rescale_run(run_dir: str | Path, estimate: ScaleEstimate, m: Map | None = None) -> tuple[Map, list[Path]]:
    """Apply `estimate` to the run in `run_dir`; return the scaled map and the files rewritten."""
    from papl_mapper.exporters import FOLDER_FORMATS, REGISTRY, ExportOptions, suffix_of

    run_dir = Path(run_dir)
    map_path = run_map_path(run_dir)
    m = m if m is not None else Map.load(map_path)
    scaled = scale_map(m, estimate)
    trajectories = {name: read_tum(run_dir / name) for name in TRAJECTORIES if (run_dir / name).exists()}
    blobs: dict[Path, bytes] = {}  # every export rebuilt before anything is written
    for p in map_exports(run_dir):
        data = REGISTRY[suffix_of(p)](scaled, ExportOptions())
        if suffix_of(p) in FOLDER_FORMATS:
            blobs.update({p / name: blob for name, blob in data.items()})
        else:
            blobs[p] = data
    summary_path = run_dir / "summary.json"
    summary = None
    if summary_path.exists():
        try:
            summary = json.loads(summary_path.read_text())
        except json.JSONDecodeError as exc:
            raise InputError(f"{summary_path}: not valid JSON ({exc})") from exc
        summary["counts"] = scaled.summary()
        summary["scale"] = scaled.metadata["scale"]
    written = []
    with contextlib.ExitStack() as stack:
        # contexts close in reverse: the map, entered first, is renamed last
        tmp_map = stack.enter_context(atomic_path(map_path))
        tmp = {p: stack.enter_context(atomic_path(p)) for p in blobs}
        tmp_traj = {name: stack.enter_context(atomic_path(run_dir / name)) for name in trajectories}
        tmp_summary = stack.enter_context(atomic_path(summary_path)) if summary is not None else None
        scaled.save(tmp_map)
        for p, blob in blobs.items():
            tmp[p].write_bytes(blob)
        for name, traj in trajectories.items():
            write_tum(tmp_traj[name], scale_trajectory(traj, estimate.scale))
        if tmp_summary is not None:
            tmp_summary.write_text(json.dumps(summary, indent=1, default=json_default))
        written = [map_path, *blobs, *(run_dir / n for n in trajectories)]
        written += [summary_path] if summary is not None else []
    logging.getLogger(__name__).info("%s: scaled by %.6g (%s)", run_dir, estimate.scale, estimate.description)
    return scaled, written
