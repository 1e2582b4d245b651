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
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from papl_mapper.atomic import output_mode
from papl_mapper.errors import ConfigError, InputError
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
        if path.exists() and not path.is_dir():
            raise InputError(f"{path}: exists and is not a folder; the {key} export writes a folder of files")
        try:
            path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"{path}: cannot create the output folder ({exc.strerror or exc})") from exc
        return [write_atomic(path / name, blob) for name, blob in data.items()]
    return [write_atomic(path, data)]


def write_atomic(path: Path, data: bytes) -> Path:
    """Write `data` to a temporary file beside `path`, flush it, then rename it over `path`."""
    parent = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise InputError(f"{path}: is a folder; give a file name")
    if not parent.is_dir():
        raise InputError(f"{path}: the folder {parent} does not exist; create it first")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=parent)
    except OSError as exc:
        raise InputError(f"{path}: cannot write in {parent} ({exc.strerror or exc})") from exc
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, output_mode(path))
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise InputError(f"{path}: could not write the file ({exc.strerror or exc})") from exc
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    log.debug("wrote %s (%s bytes)", path, f"{len(data):,}")
    return path
