"""The recordings of a `papl-map batch`: from recording paths, folders of recordings and manifests.

An INPUT is a recording (a video file or a folder of images), a folder of recordings (every video
file below it, and every folder that holds images and no video), or a manifest:

TOML (paths relative to the manifest's folder; `[defaults]` applies to every entry)::

    [defaults]
    camera = "cameras/phone.json"
    set = ["ba.max_iterations=10"]

    [[recording]]
    path = "walks/monday.mp4"
    start = 2.0                      # seconds
    end = 60.0
    step = 1
    gt = "walks/monday_gt"           # ground-truth folder: eval.json and ATE in the index
    set = ["frontend.vp.use_vertical_prior=false"]
    name = "monday"                  # output folder (default: from the file name)

CSV: a header row naming the columns (`path` is required; the others are the same keys), one
recording per row, empty cells for "not given", several `set` overrides separated by ";", and
lines starting with "#" ignored.

A recording found in a folder or given directly uses `camera.json` beside it (unless --camera is
given) and the `gt/` folder beside it when that folder holds this one video and `gt/trajectory.tum`.
Every problem is an InputError of one line naming the manifest and its line.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import json
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from papl_mapper.errors import InputError
from papl_mapper.frontend.video import IMAGE_SUFFIXES

VIDEO_SUFFIXES = (
    ".mp4",
    ".m4v",
    ".mov",
    ".avi",
    ".mkv",
    ".webm",
    ".mpg",
    ".mpeg",
    ".wmv",
    ".flv",
    ".ts",
    ".mts",
    ".m2ts",
    ".3gp",
    ".ogv",
)
"""Suffixes of the files a folder input treats as recordings (a direct INPUT may be any file)."""

MANIFEST_SUFFIXES = (".toml", ".csv")

KEYS: dict[str, type | tuple[type, ...]] = {
    "path": str,
    "name": str,
    "camera": str,
    "gt": str,
    "start": (int, float),
    "end": (int, float),
    "step": int,
    "max_size": int,
    "preset": str,
    "config": str,
    "set": (list, str),
}
"""The keys of a manifest entry and their types; `path` is required."""

_PATH_KEYS = ("path", "camera", "gt", "config")


@dataclass
class Recording:
    """One recording of a batch and its per-recording options (paths absolute)."""

    path: Path
    origin: str
    """Where it was named: "walks.csv line 4", "argument samples/tiny/video.mp4", "folder samples"."""
    name: str | None = None
    """The output folder's name when the manifest gives one (else assigned by `assign_names`)."""
    camera: Path | None = None
    gt: Path | None = None
    start: float | None = None
    end: float | None = None
    step: int | None = None
    max_size: int | None = None
    preset: str | None = None
    config: Path | None = None
    set: list[str] = field(default_factory=list)

    def identity(self) -> str:
        """What makes two entries the same recording: the file and every option that changes the map."""
        d = {k: v for k, v in dataclasses.asdict(self).items() if k not in ("origin", "name")}
        return json.dumps(d, sort_keys=True, default=str)


def collect(
    inputs: list[str | Path], camera: Path | None = None, exclude: Path | None = None
) -> list[Recording]:
    """Every recording named by `inputs`, in order; InputError (one line) for any bad input.

    `camera` is the camera file for recordings without their own; `exclude` (the batch's output
    folder) is never searched for recordings.
    """
    if not inputs:
        raise InputError("no INPUT given: name recordings, folders of recordings or manifests")
    out: list[Recording] = []
    for item in inputs:
        p = Path(item)
        if not p.exists():
            raise InputError(
                f"{p}: no such file or folder; give a recording, a folder of recordings or a manifest"
            )
        if p.is_file() and p.suffix.lower() == ".toml":
            out += _toml_manifest(p)
        elif p.is_file() and p.suffix.lower() == ".csv":
            out += _csv_manifest(p)
        elif p.is_dir() and not _is_image_folder(p):
            found = _discover(p, exclude)
            if not found:
                raise InputError(
                    f"{p}: no recordings found (video files {', '.join(VIDEO_SUFFIXES[:4])}, ... "
                    "or folders of images)"
                )
            out += [_beside(r, f"folder {p}", camera) for r in found]
        else:
            out.append(_beside(p.resolve(), f"argument {p}", camera))
    for r in out:
        if r.camera is None and camera is not None:
            r.camera = camera.resolve()
    _check_duplicates(out)
    return out


def _beside(path: Path, origin: str, camera: Path | None) -> Recording:
    """A recording found on disk, with camera.json and gt/ beside it where they exist."""
    rec = Recording(path=path, origin=origin)
    folder = path if path.is_dir() else path.parent
    if camera is None and (folder / "camera.json").is_file():
        rec.camera = folder / "camera.json"
    videos = [p for p in folder.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES] if path.is_file() else []
    if (folder / "gt" / "trajectory.tum").is_file() and len(videos) <= 1:
        rec.gt = folder / "gt"
    return rec


def _is_image_folder(p: Path) -> bool:
    files = [c for c in p.iterdir() if c.is_file()]
    has_images = any(c.suffix.lower() in IMAGE_SUFFIXES for c in files)
    return has_images and not any(c.suffix.lower() in VIDEO_SUFFIXES for c in files)


def _discover(root: Path, exclude: Path | None) -> list[Path]:
    """Video files and image folders below `root` (hidden folders, gt/ folders and `exclude` skipped)."""
    found: list[Path] = []
    ex = exclude.resolve() if exclude is not None else None

    def walk(folder: Path) -> None:
        if ex is not None and folder.resolve() == ex:
            return
        children = sorted(folder.iterdir(), key=lambda c: c.name)
        for c in children:
            if c.is_file() and c.suffix.lower() in VIDEO_SUFFIXES:
                found.append(c.resolve())
        for c in children:
            if c.is_dir() and not c.name.startswith(".") and c.name != "gt":
                if _is_image_folder(c):
                    found.append(c.resolve())
                else:
                    walk(c)

    walk(root)
    return found


# ---- manifests ------------------------------------------------------------------------------------


def _entry(manifest: Path, where: str, data: dict[str, Any], defaults: dict[str, Any]) -> Recording:
    """One manifest entry (a TOML table or CSV row, already typed) checked and turned into a Recording."""
    merged = {**defaults, **data}
    if "path" not in merged or merged["path"] in ("", None):
        raise InputError(f"{manifest} {where}: no path; every recording needs one")
    rec = Recording(path=Path(), origin=f"{manifest} {where}")
    base = manifest.parent
    for key, value in merged.items():
        if key not in KEYS:
            raise InputError(f"{manifest} {where}: unknown key {key!r}; known: {', '.join(KEYS)}")
        if not isinstance(value, KEYS[key]) or isinstance(value, bool):
            raise InputError(f"{manifest} {where}: {key} = {value!r}: expected {_type_name(KEYS[key])}")
        if key in _PATH_KEYS:
            path = Path(value).expanduser()
            path = (base / path if not path.is_absolute() else path).resolve()
            if not path.exists():
                raise InputError(f"{manifest} {where}: {key} {value}: no such file or folder ({path})")
            value = path
        elif key == "set":
            items = value.split(";") if isinstance(value, str) else value
            if not all(isinstance(s, str) for s in items):
                raise InputError(f"{manifest} {where}: set must list strings key=value")
            value = [s.strip() for s in items if s.strip()]
            for s in value:
                if "=" not in s:
                    raise InputError(f"{manifest} {where}: set {s!r}: expected key=value")
        elif key in ("start", "end"):
            value = float(value)
            if value < 0:
                raise InputError(f"{manifest} {where}: {key} {value:g} s is negative")
        elif key == "step" and value < 1:
            raise InputError(f"{manifest} {where}: step {value} must be >= 1")
        elif key == "max_size" and value < 16:
            raise InputError(f"{manifest} {where}: max_size {value} is too small (>= 16 pixels)")
        elif key == "name":
            value = value.strip()
            if not value or _safe_name(value) != value:
                raise InputError(
                    f"{manifest} {where}: name {value!r}: use letters, digits, '.', '_' and '-' only"
                )
        setattr(rec, key, value)
    if rec.start is not None and rec.end is not None and rec.end < rec.start:
        raise InputError(f"{manifest} {where}: end {rec.end:g} s is before start {rec.start:g} s")
    return rec


def _type_name(t: type | tuple[type, ...]) -> str:
    names = {int: "an integer", float: "a number", str: "a string", list: "a list"}
    ts = t if isinstance(t, tuple) else (t,)
    if ts == (int, float):
        return "a number"
    return " or ".join(names.get(x, x.__name__) for x in ts)


def _toml_manifest(path: Path) -> list[Recording]:
    try:
        text = path.read_text(encoding="utf-8")
        data = tomllib.loads(text)
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the manifest ({exc})") from exc
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: not valid TOML ({exc})") from exc
    unknown = sorted(set(data) - {"defaults", "recording"})
    if unknown:
        raise InputError(
            f"{path} line {_line_of(text, unknown[0])}: unknown table {unknown[0]!r}; "
            "a manifest holds [defaults] and [[recording]] tables"
        )
    defaults = data.get("defaults", {})
    if not isinstance(defaults, dict):
        raise InputError(f"{path} line {_line_of(text, 'defaults')}: defaults must be a table")
    if "path" in defaults or "name" in defaults:
        raise InputError(f"{path} line {_line_of(text, 'defaults')}: [defaults] cannot give a path or name")
    entries = data.get("recording", [])
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise InputError(f"{path} line {_line_of(text, 'recording')}: recording must be [[recording]] tables")
    if not entries:
        raise InputError(f"{path}: empty manifest: no [[recording]] tables")
    headers = [i + 1 for i, ln in enumerate(text.splitlines()) if re.match(r"\s*\[\[\s*recording\s*\]\]", ln)]
    out = []
    for i, e in enumerate(entries):
        where = f"line {headers[i]}" if i < len(headers) else f"recording {i + 1}"
        out.append(_entry(path, where, e, defaults))
    return out


def _line_of(text: str, key: str) -> int:
    """The first line mentioning `key` as a table or key (1-based; 1 when not found)."""
    pat = re.compile(rf"^\s*(\[+\s*{re.escape(key)}\s*\]+|{re.escape(key)}\s*=)")
    for i, ln in enumerate(text.splitlines()):
        if pat.match(ln):
            return i + 1
    return 1


def _csv_manifest(path: Path) -> list[Recording]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the manifest ({exc})") from exc
    lines = [
        (i + 1, ln)
        for i, ln in enumerate(text.splitlines())
        if ln.strip() and not ln.lstrip().startswith("#")
    ]
    if not lines:
        raise InputError(f"{path}: empty manifest: no header row and no recordings")
    try:
        rows = list(csv.reader([ln for _, ln in lines]))
    except csv.Error as exc:
        raise InputError(f"{path}: not valid CSV ({exc})") from exc
    header_line, header = lines[0][0], [h.strip().lower() for h in rows[0]]
    for h in header:
        if h not in KEYS:
            raise InputError(
                f"{path} line {header_line}: unknown column {h!r}; the header names columns of "
                f"{', '.join(KEYS)} (path required)"
            )
    if "path" not in header:
        raise InputError(f"{path} line {header_line}: the header has no path column")
    if len(set(header)) != len(header):
        raise InputError(f"{path} line {header_line}: a column is named twice")
    if len(rows) == 1:
        raise InputError(f"{path}: empty manifest: a header and no recordings")
    out = []
    for (line, _), row in zip(lines[1:], rows[1:], strict=True):
        where = f"line {line}"
        if len(row) > len(header):
            raise InputError(f"{path} {where}: {len(row)} cells, the header names {len(header)} columns")
        data: dict[str, Any] = {}
        for h, cell in zip(header, row, strict=False):
            cell = cell.strip()
            if cell:
                data[h] = _csv_value(path, where, h, cell)
        out.append(_entry(path, where, data, {}))
    return out


def _csv_value(path: Path, where: str, key: str, cell: str) -> Any:
    t = KEYS[key]
    try:
        if t is int:
            return int(cell)
        if t == (int, float):
            return float(cell)
    except ValueError as exc:
        raise InputError(f"{path} {where}: {key} {cell!r}: expected {_type_name(t)}") from exc
    return cell


# ---- names and duplicates ---------------------------------------------------------------------------


def _check_duplicates(recs: list[Recording]) -> None:
    seen: dict[str, Recording] = {}
    names: dict[str, Recording] = {}
    for r in recs:
        ident = r.identity()
        if ident in seen:
            raise InputError(
                f"duplicate recording {r.path}: given by {seen[ident].origin} and by {r.origin} "
                "with the same options"
            )
        seen[ident] = r
        if r.name is not None:
            if r.name in names:
                raise InputError(f"{r.origin}: name {r.name!r} is already used by {names[r.name].origin}")
            names[r.name] = r


def _safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-.")


def assign_names(recs: list[Recording], previous: dict[str, str] | None = None) -> list[str]:
    """A stable, unique output folder name for each recording.

    A manifest's `name` wins; then the name an earlier run of this batch gave the same recording
    (`previous`: identity -> name); then the file name (the folder name for image folders), with
    parent folder names put in front of names that collide ("tiny-video", "demo-video"), and a short
    hash of the options after those that still collide (the same file with two time ranges).
    """
    previous = previous or {}
    names: list[str | None] = [r.name or previous.get(r.identity()) for r in recs]
    taken = {n for n in names if n}
    todo = [i for i, n in enumerate(names) if n is None]
    parts = {i: [_safe_name(p) or "x" for p in reversed(_stem_parts(recs[i].path))] for i in todo}
    depth = dict.fromkeys(todo, 1)
    while todo:
        cand = {i: "-".join(reversed(parts[i][: depth[i]])) for i in todo}
        groups: dict[str, list[int]] = {}
        for i, c in cand.items():
            groups.setdefault(c, []).append(i)
        nxt = []
        for i in todo:
            c = cand[i]
            same_file = len({recs[j].path for j in groups[c]}) == 1  # parent folders cannot tell them apart
            if len(groups[c]) == 1 and c not in taken:
                names[i] = c
                taken.add(c)
            elif depth[i] < len(parts[i]) and not (same_file and len(groups[c]) > 1):
                depth[i] += 1
                nxt.append(i)
            else:
                h = hashlib.sha256(recs[i].identity().encode()).hexdigest()[:6]
                name = f"{c}-{h}"
                while name in taken:
                    h = hashlib.sha256(h.encode()).hexdigest()[:6]
                    name = f"{c}-{h}"
                names[i] = name
                taken.add(name)
        todo = nxt
    return [str(n) for n in names]


def _stem_parts(path: Path) -> list[str]:
    """['samples', 'tiny', 'video'] for /.../samples/tiny/video.mp4 (the stem last, 3 parents at most)."""
    stem = path.name if path.is_dir() else path.stem
    parents = [p for p in path.parent.parts if p != path.anchor][-3:]
    return [*parents, stem]
