"""The registry of formats by file suffix, and `export(map, path)` that dispatches and writes atomically.

Each format module publishes `FORMATS = {suffix: function}`, a pure function `(Map, ExportOptions)
-> bytes` (or `dict[file name, bytes]` for a folder format like COLMAP text). `export` alone deals
with paths: it picks the longest matching suffix, writes to a temporary file in the same folder and
renames it over the target, so an existing output is replaced whole or not at all.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from papl_mapper.atomic import atomic_path, check_output_dir, output_target
from papl_mapper.errors import ConfigError, InputError, OutputError
from papl_mapper.extras import require
from papl_mapper.map import Map

from . import colmap, drawing, dxf, gltf, obj, ply, trajectory, tubes, usd
from .scene import ExportOptions

log = logging.getLogger(__name__)

Exporter = Callable[[Map, ExportOptions], "bytes | dict[str, bytes]"]

#: suffix (with its dot, lower case) -> pure export function
REGISTRY: dict[str, Exporter] = {}
for _module in (ply, gltf, usd, dxf, obj, tubes, trajectory, colmap, drawing):
    REGISTRY.update(_module.FORMATS)
#: suffixes whose export is a folder of files (dict name -> bytes)
FOLDER_FORMATS = frozenset(colmap.FORMATS)
#: suffix -> (module, feature): the optional library a format needs (modules publish `REQUIRES`)
REQUIRES: dict[str, tuple[str, str]] = {}
for _module in (usd, dxf, drawing):
    REQUIRES.update(_module.REQUIRES)


def supported_suffixes() -> list[str]:
    """Every suffix `export` understands, longest first (the order they are matched in)."""
    return sorted(REGISTRY, key=lambda s: (-len(s), s))


def suffix_of(path: str | os.PathLike, format: str | None = None) -> str:
    """The registry key for `path` (or for an explicit format name such as 'ply' or '.tubes.glb')."""
    if format:
        key = format.lower() if format.startswith(".") else "." + format.lower()
        if key not in REGISTRY:
            raise InputError(
                f"unknown export format {format!r}; supported: {', '.join(supported_suffixes())}"
            )
        return key
    name = Path(path).name.lower()
    view = _VIEW_NAME.search(name)
    if view:
        return f".{view['kind']}.{view['ext']}"
    for s in supported_suffixes():
        if name.endswith(s) and len(name) > len(s):
            return s
    raise InputError(
        f"{path}: unknown export suffix {Path(path).suffix or '(none)'!r}; "
        f"supported: {', '.join(supported_suffixes())}"
    )


#: plan.dxf, site.plan.svg, elevation-2.dxf, map.elevation-1.svg: the CAD views by file name
_VIEW_NAME = re.compile(r"(?:^|[._-])(?P<kind>plan|elevation)(?:-(?P<axis>\d+))?\.(?P<ext>dxf|svg)$")


def check_available(key: str) -> None:
    """BackendUnavailableError naming the extra when the format `key` needs a library not installed."""
    if key in REQUIRES:
        require(*REQUIRES[key])


def check_target(path: str | os.PathLike, format: str | None = None) -> str:
    """Refuse an export target before any work: unknown suffix, a format whose library (an extra) is not
    installed, or a name the output-path policy (`atomic.output_target`) would not write. Returns the
    format's registry key."""
    key = suffix_of(path, format)
    check_available(key)
    if key in FOLDER_FORMATS:
        check_output_dir(path)
    else:
        output_target(path)
    return key


def view_options(path: str | os.PathLike, options: ExportOptions) -> ExportOptions:
    """`options` with `elevation_axis` from a file name such as elevation-2.svg (1 when it names none)."""
    view = _VIEW_NAME.search(Path(path).name.lower())
    if view and view["kind"] == "elevation" and view["axis"]:
        return dataclasses.replace(options, elevation_axis=int(view["axis"]))
    return options


def export(
    m: Map,
    path: str | os.PathLike,
    options: ExportOptions | None = None,
    format: str | None = None,
    **overrides: Any,
) -> list[Path]:
    """Export `m` to `path` in the format its suffix names; return the files written.

    `overrides` are ExportOptions fields (e.g. parts=("lines",), ascii=True).
    """
    options = options or ExportOptions()
    if overrides:
        unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(ExportOptions)})
        if unknown:
            known = sorted(f.name for f in dataclasses.fields(ExportOptions))
            raise ConfigError(f"unknown export option(s) {unknown}; known: {known}")
        options = dataclasses.replace(options, **overrides)
    path = Path(path)
    key = suffix_of(path, format)
    data = REGISTRY[key](m, view_options(path, options))
    if isinstance(data, dict):
        check_output_dir(path)
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{path}: cannot create the output folder ({exc.strerror or exc})") from exc
        return [write_atomic(path / name, blob) for name, blob in data.items()]
    return [write_atomic(path, data)]


def write_atomic(path: Path, data: bytes) -> Path:
    """Write `data` to `path` through `atomic_path` (its output-path policy), flushed to disk."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    log.debug("wrote %s (%s bytes)", path, f"{len(data):,}")
    return path
