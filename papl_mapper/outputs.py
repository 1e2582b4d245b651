"""The manifest of a run folder: the files one run wrote, so that a rerun retires the previous run's.

`manifest.json` lists paths relative to the folder. When a run's main outputs are renamed into place,
`begin_run` removes every file the previous manifest lists that the new run did not write, then writes
the new manifest; each later output (exports, previews, report) is added with `add_outputs`. The
folder thus always holds one run's files, even after an interrupted rerun. Nothing the manifest does
not list is ever removed, and nothing outside the folder.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable
from pathlib import Path

from papl_mapper.atomic import atomic_path

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
#: names an earlier papl-map run may have left; only warned about when no manifest lists them
_KNOWN_EXTRAS = ("map.*", "eval.json", "report.html", "previews")


def read_manifest(folder: Path) -> list[str]:
    """The relative paths the folder's manifest lists ([] without one, or with an unreadable one)."""
    path = Path(folder) / MANIFEST
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return []
    except (OSError, ValueError) as exc:
        log.warning("%s: unreadable manifest (%s); no earlier outputs are retired", path, exc)
        return []
    files = data.get("files") if isinstance(data, dict) else None
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        log.warning("%s: not a papl-map manifest; no earlier outputs are retired", path)
        return []
    return files


def _write(folder: Path, files: list[str]) -> None:
    with atomic_path(Path(folder) / MANIFEST) as tmp:
        tmp.write_text(json.dumps({"files": files}, indent=1) + "\n")


def _inside(folder: Path, rel: str) -> Path | None:
    """`folder / rel` when `rel` is a plain relative path that stays inside `folder`, else None."""
    if not rel or os.path.isabs(rel) or ".." in Path(rel).parts:
        return None
    return Path(folder) / rel


def begin_run(folder: Path, written: Iterable[str | os.PathLike]) -> list[str]:
    """Record `written` (paths inside `folder`) as the folder's run and retire what the previous run's
    manifest lists beyond it (files only; folders left empty by that go too). Returns the retired paths."""
    folder = Path(folder)
    files = [_relative(folder, p) for p in written]
    previous = read_manifest(folder)
    if not previous:
        _warn_unlisted(folder, files)
    retired = []
    for rel in sorted(set(previous) - set(files)):
        path = _inside(folder, rel)
        if path is None or not (path.is_file() or path.is_symlink()):
            continue
        path.unlink()
        retired.append(rel)
        parent = path.parent
        while parent != folder and parent.is_dir() and not any(parent.iterdir()):
            parent.rmdir()
            parent = parent.parent
    if retired:
        log.info("removed %d outputs of the previous run in %s: %s", len(retired), folder, ", ".join(retired))
    _write(folder, files)
    return retired


def add_outputs(folder: Path, written: Iterable[str | os.PathLike]) -> None:
    """Add files written after `begin_run` (exports, previews, report) to the folder's manifest."""
    folder = Path(folder)
    files = read_manifest(folder)
    new = [r for r in (_relative(folder, p) for p in written) if r not in files]
    if new:
        _write(folder, files + new)


def _relative(folder: Path, path: str | os.PathLike) -> str:
    """`path` (a file inside `folder`, e.g. folder / "map.ply") relative to `folder`, with / separators."""
    return Path(os.path.relpath(os.path.abspath(path), os.path.abspath(folder))).as_posix()


def _warn_unlisted(folder: Path, files: list[str]) -> None:
    """Without a manifest, say which earlier-looking outputs stay (they may come from another run)."""
    found = sorted({p.name for pattern in _KNOWN_EXTRAS for p in folder.glob(pattern)} - set(files))
    if found:
        log.warning(
            "%s holds %s from before (no %s lists them): they may belong to another run",
            folder,
            ", ".join(found),
            MANIFEST,
        )
