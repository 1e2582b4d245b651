"""The Map: one struct-of-arrays data model for camera, keyframes, points, lines and axes.

Saved as one versioned `.papl` file: an uncompressed zip holding `meta.json` and one `.npy`
per array, so numpy alone can read it and load/save run at disk speed. `Map.load` validates
shapes, dtypes, ids, references, finiteness and version, and refuses a bad file with one
`MapFormatError` line naming the file and the fault.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tokenize
import zipfile
import zlib
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any

import numpy as np

from papl_mapper.atomic import atomic_path
from papl_mapper.errors import MapFormatError

FORMAT_NAME = "papl-map"
FORMAT_VERSION = 1
SUFFIX = ".papl"


class LineState(IntEnum):
    """Which representation a line is optimised in (paper: the three-stage line optimisation)."""

    TEMPORARY_VP = 0  # anchored to its own vanishing direction in the reference keyframe
    ORTHONORMAL = 1  # free 4-DoF line, not yet associated with an axis
    ANCHORED = 2  # 3-parameter line on one or more principal axes


@dataclass
class Camera:
    """Pinhole camera with OpenCV distortion (k1, k2, p1, p2[, k3...]); pixel centres at integers."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(5))
    model: str = "pinhole"

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["distortion"] = [float(x) for x in np.asarray(self.distortion).ravel()]
        return d

    @classmethod
    def from_dict(cls, d: Any) -> Camera:
        """A camera from `to_dict`'s schema; ValueError naming the first field that is missing, of the
        wrong type, not finite or out of range (callers add the file name)."""
        if not isinstance(d, dict):
            raise ValueError(f"camera must be an object of fields, got {type(d).__name__}")
        unknown = sorted(set(d) - set(_CAMERA_FIELDS) - {"model", "distortion"})
        if unknown:
            raise ValueError(f"unknown camera field(s) {unknown}")
        values: dict[str, Any] = {}
        for name, kind in _CAMERA_FIELDS.items():
            if name not in d:
                raise ValueError(f"camera field {name!r} is missing")
            values[name] = _number(d[name], f"camera field {name!r}", integer=kind is int)
        if (
            values["width"] < 0
            or values["height"] < 0
            or values["width"] > 1 << 16
            or values["height"] > 1 << 16
        ):
            raise ValueError(f"camera size {values['width']}x{values['height']} is out of range (0..65536)")
        model = d.get("model", "pinhole")
        if model != "pinhole":
            raise ValueError(
                f"camera model {model!r} is not supported: papl-mapper maps pinhole cameras with OpenCV "
                "radial-tangential distortion (k1 k2 p1 p2 k3); undistort fisheye recordings first"
            )
        dist = d.get("distortion", [0.0] * 5)
        if not isinstance(dist, (list, tuple, np.ndarray)) or len(dist) not in _DISTORTION_LENGTHS:
            raise ValueError(f"camera field 'distortion' must be a list of {_DISTORTION_LENGTHS} numbers")
        values["distortion"] = np.array([_number(x, "camera field 'distortion'") for x in dist], np.float64)
        return cls(**values, model=model)


_CAMERA_FIELDS = {"width": int, "height": int, "fx": float, "fy": float, "cx": float, "cy": float}
_DISTORTION_LENGTHS = (0, 1, 2, 3, 4, 5, 8, 12, 14)  # OpenCV's lengths; shorter ones are padded


def _number(value: Any, what: str, integer: bool = False) -> int | float:
    """`value` as a finite float (or an exact int); ValueError naming `what` otherwise."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    if not ok:
        raise ValueError(f"{what} must be a number, got {value!r:.40}")
    if not np.isfinite(value):
        raise ValueError(f"{what} is not finite ({value})")
    if integer:
        if float(value) != int(value):
            raise ValueError(f"{what} must be an integer, got {value}")
        return int(value)
    return float(value)


@dataclass
class Keyframes:
    """Keyframe poses. `T_wc` (N, 4, 4) maps camera coordinates to world coordinates."""

    ids: np.ndarray  # (N,) int64, unique
    frame_index: np.ndarray  # (N,) int64, index of the frame in the recording
    timestamp: np.ndarray  # (N,) float64, seconds
    T_wc: np.ndarray  # (N, 4, 4) float64

    @classmethod
    def empty(cls) -> Keyframes:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 4, 4)))

    def __len__(self) -> int:
        return len(self.ids)


@dataclass
class Points:
    """3D points with colours and their 2D observations (pixels, distorted image)."""

    ids: np.ndarray  # (P,) int64, unique
    xyz: np.ndarray  # (P, 3) float64, world
    color: np.ndarray  # (P, 3) uint8 RGB
    obs_ids: np.ndarray  # (K, 2) int64: point id, keyframe id
    obs_uv: np.ndarray  # (K, 2) float64 pixels

    @classmethod
    def empty(cls) -> Points:
        return cls(
            np.zeros(0, np.int64),
            np.zeros((0, 3)),
            np.zeros((0, 3), np.uint8),
            np.zeros((0, 2), np.int64),
            np.zeros((0, 2)),
        )

    def __len__(self) -> int:
        return len(self.ids)


@dataclass
class Lines:
    """3D line segments, their soft association to axes and their 2D observations.

    `axis_weights[m, a]` is the EM weight w_ma of line m on axis a (rows sum to <= 1).
    Anchored lines carry their reference keyframe and the inverse depth of the segment
    midpoint in it (the paper's three-parameter representation); others carry -1 and NaN.
    """

    ids: np.ndarray  # (M,) int64, unique
    endpoints_w: np.ndarray  # (M, 2, 3) float64, world
    axis_weights: np.ndarray  # (M, A) float64 in [0, 1]
    state: np.ndarray  # (M,) int8, LineState
    ref_keyframe_id: np.ndarray  # (M,) int64, -1 when none
    inverse_depth: np.ndarray  # (M,) float64, NaN when not anchored
    obs_ids: np.ndarray  # (L, 2) int64: line id, keyframe id
    obs_xy: np.ndarray  # (L, 4) float64: x1, y1, x2, y2 pixels

    @classmethod
    def empty(cls, n_axes: int = 0) -> Lines:
        return cls(
            np.zeros(0, np.int64),
            np.zeros((0, 2, 3)),
            np.zeros((0, n_axes)),
            np.zeros(0, np.int8),
            np.zeros(0, np.int64),
            np.zeros(0),
            np.zeros((0, 2), np.int64),
            np.zeros((0, 4)),
        )

    def __len__(self) -> int:
        return len(self.ids)

    def axis_of_line(self, min_weight: float = 0.5) -> np.ndarray:
        """(M,) the axis each anchored line belongs to most (weight >= min_weight), else -1."""
        if self.axis_weights.shape[1] == 0 or len(self) == 0:
            return np.full(len(self), -1, np.int64)
        best = np.argmax(self.axis_weights, axis=1)
        ok = (self.state == LineState.ANCHORED) & (
            self.axis_weights[np.arange(len(self)), best] >= min_weight
        )
        return np.where(ok, best, -1).astype(np.int64)

    def lengths(self) -> np.ndarray:
        """(M,) segment lengths."""
        return np.linalg.norm(self.endpoints_w[:, 1] - self.endpoints_w[:, 0], axis=1)


@dataclass
class Axes:
    """Principal axes: unit directions (A, 3) in the world frame, and which one is vertical."""

    directions: np.ndarray  # (A, 3) float64, unit
    vertical_index: int = -1  # -1 when no vertical axis is known

    @classmethod
    def empty(cls) -> Axes:
        return cls(np.zeros((0, 3)), -1)

    def __len__(self) -> int:
        return len(self.directions)

    def angles_deg(self) -> np.ndarray:
        """(A, A) unsigned angles between axis lines in degrees (0..90)."""
        c = np.clip(np.abs(self.directions @ self.directions.T), 0.0, 1.0)
        return np.degrees(np.arccos(c))


@dataclass
class Map:
    """Everything the mapper produces; exporters, previews and reports take only this."""

    camera: Camera
    keyframes: Keyframes = field(default_factory=Keyframes.empty)
    points: Points = field(default_factory=Points.empty)
    lines: Lines = field(default_factory=Lines.empty)
    axes: Axes = field(default_factory=Axes.empty)
    metadata: dict[str, Any] = field(default_factory=lambda: {"units": "arbitrary"})

    # ---- persistence -------------------------------------------------------------------

    def save(self, path: str | os.PathLike) -> Path:
        """Validate, then write atomically (temporary name in the same folder, then rename)."""
        self.validate()
        path = Path(path)
        meta = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "camera": self.camera.to_dict(),
            "vertical_index": int(self.axes.vertical_index),
            "metadata": self.metadata,
        }
        with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED) as zf:
            zf.writestr("meta.json", json.dumps(meta, indent=1, default=json_default))
            for name, arr in _arrays(self).items():
                with zf.open(f"{name}.npy", "w", force_zip64=True) as out:
                    np.lib.format.write_array(out, np.ascontiguousarray(arr), allow_pickle=False)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> Map:
        """Read and validate a `.papl` file; raise MapFormatError naming the file and the fault."""
        path = Path(path)
        if not path.exists():
            raise MapFormatError(f"{path}: no such map file")
        if path.is_dir():
            raise MapFormatError(f"{path}: is a folder, not a map file")
        try:
            with zipfile.ZipFile(path) as zf:
                meta = _read_meta(zf)
                arrays = _read_arrays(zf, path.stat().st_size)
        except MapFormatError as exc:
            raise MapFormatError(f"{path}: {exc}") from exc
        except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError) as exc:
            raise MapFormatError(f"{path}: corrupt or truncated map file ({exc})") from exc
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
            raise MapFormatError(f"{path}: corrupt metadata ({exc})") from exc
        except (ValueError, SyntaxError) as exc:
            raise MapFormatError(f"{path}: corrupt array data ({exc})") from exc
        except MemoryError as exc:
            raise MapFormatError(f"{path}: an array does not fit in memory") from exc
        try:
            camera = Camera.from_dict(meta["camera"])
            m = cls(
                camera=camera,
                keyframes=Keyframes(*(arrays[f"keyframes.{f}"] for f in _FIELDS["keyframes"])),
                points=Points(*(arrays[f"points.{f}"] for f in _FIELDS["points"])),
                lines=Lines(*(arrays[f"lines.{f}"] for f in _FIELDS["lines"])),
                axes=Axes(arrays["axes.directions"], meta["vertical_index"]),
                metadata=meta["metadata"],
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise MapFormatError(f"{path}: invalid metadata ({exc})") from exc
        try:
            m.validate()
        except MapFormatError as exc:
            raise MapFormatError(f"{path}: {exc}") from exc
        return m

    # ---- validation --------------------------------------------------------------------

    def validate(self) -> None:
        """Check shapes, dtypes, unique ids, references, finiteness and frames; raise on the first fault."""
        c = self.camera
        if not (c.width > 0 and c.height > 0 and c.fx > 0 and abs(c.fy) > 0):
            raise MapFormatError(f"camera has impossible intrinsics {c.width}x{c.height} f={c.fx},{c.fy}")
        if not np.all(np.isfinite([c.fx, c.fy, c.cx, c.cy])) or not np.all(np.isfinite(c.distortion)):
            raise MapFormatError("camera intrinsics are not finite")
        for name, (shape, kind) in _ARRAY_SPECS.items():
            arr = _get(self, name)
            if not isinstance(arr, np.ndarray):
                raise MapFormatError(f"{name} is {type(arr).__name__}, expected an array")
            if arr.dtype.kind not in kind:
                raise MapFormatError(f"{name} has dtype {arr.dtype}, expected kind {kind!r}")
            if arr.ndim != len(shape):
                raise MapFormatError(f"{name} has shape {arr.shape}, expected {shape}")
            for dim, want in zip(arr.shape, shape, strict=True):
                if isinstance(want, int) and dim != want:
                    raise MapFormatError(f"{name} has shape {arr.shape}, expected {shape}")
        sizes = {}
        for group in ("keyframes", "points", "lines"):
            n = len(_get(self, f"{group}.ids"))
            sizes[group] = n
            for f in _FIELDS[group]:
                if f.startswith("obs_"):
                    continue
                arr = _get(self, f"{group}.{f}")
                if len(arr) != n:
                    raise MapFormatError(f"{group}.{f} has {len(arr)} rows, {group}.ids has {n}")
            ids = _get(self, f"{group}.ids")
            if not _all_unique(ids):
                raise MapFormatError(f"{group}.ids are not unique")
        n_axes = len(self.axes.directions)
        if self.lines.axis_weights.shape[1] != n_axes:
            raise MapFormatError(
                f"lines.axis_weights has {self.lines.axis_weights.shape[1]} columns for {n_axes} axes"
            )
        for group, obs_len in (("points", "obs_uv"), ("lines", "obs_xy")):
            obs_ids = _get(self, f"{group}.obs_ids")
            if len(obs_ids) != len(_get(self, f"{group}.{obs_len}")):
                raise MapFormatError(f"{group}.obs_ids and {group}.{obs_len} differ in length")
            _check_refs(obs_ids[:, 0], self.__getattribute__(group).ids, f"{group}.obs_ids[:, 0]", group)
            _check_refs(obs_ids[:, 1], self.keyframes.ids, f"{group}.obs_ids[:, 1]", "keyframes")
        for name in _FINITE:
            arr = _get(self, name)
            bad = ~np.isfinite(arr.reshape(len(arr), -1)).all(axis=1) if arr.size else np.zeros(0, bool)
            if bad.any():
                ids = _bad_ids(self, name, bad)
                raise MapFormatError(f"{name} holds NaN or infinite values (ids {ids})")
        T = self.keyframes.T_wc
        if len(T):
            if not np.allclose(T[:, 3], [0, 0, 0, 1], atol=1e-9):
                raise MapFormatError("keyframes.T_wc: last row is not [0 0 0 1]")
            R = T[:, :3, :3]
            err = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
            det = np.linalg.det(R)
            bad = (err > 1e-6) | (det < 0)
            if bad.any():
                raise MapFormatError(
                    f"keyframes.T_wc: rotation not orthonormal (ids {self.keyframes.ids[bad][:5].tolist()})"
                )
        if n_axes:
            norms = np.linalg.norm(self.axes.directions, axis=1)
            if np.abs(norms - 1).max() > 1e-6:
                raise MapFormatError("axes.directions are not unit vectors")
        if not -1 <= self.axes.vertical_index < max(n_axes, 0) and not (
            n_axes == 0 and self.axes.vertical_index == -1
        ):
            raise MapFormatError(f"axes.vertical_index {self.axes.vertical_index} out of range")
        w = self.lines.axis_weights
        if w.size and (w.min() < -1e-9 or w.max() > 1 + 1e-9 or w.sum(axis=1).max() > 1 + 1e-6):
            raise MapFormatError("lines.axis_weights must lie in [0, 1] with rows summing to <= 1")
        st = self.lines.state
        if st.size and (st.min() < 0 or st.max() > max(LineState)):
            raise MapFormatError(f"lines.state holds unknown states {sorted(set(st.tolist()))}")
        anchored = st == LineState.ANCHORED
        inv = self.lines.inverse_depth[anchored]
        if inv.size and not np.isfinite(inv).all():
            raise MapFormatError("lines.inverse_depth is not finite for some anchored lines")
        refs = self.lines.ref_keyframe_id
        if refs.size:
            has_ref = refs >= 0
            _check_refs(refs[has_ref], self.keyframes.ids, "lines.ref_keyframe_id", "keyframes")

    # ---- summaries ---------------------------------------------------------------------

    def summary(self) -> dict[str, Any]:
        """Counts and axis facts for `papl-map info` and the report."""
        axis = self.lines.axis_of_line()
        n_axes = len(self.axes)
        per_axis = [int((axis == a).sum()) for a in range(n_axes)]
        out = {
            "keyframes": len(self.keyframes),
            "points": len(self.points),
            "point_observations": len(self.points.obs_ids),
            "lines": len(self.lines),
            "line_observations": len(self.lines.obs_ids),
            "lines_per_axis": per_axis,
            "unanchored_lines": int((axis < 0).sum()),
            "anchored_fraction": float((axis >= 0).mean()) if len(axis) else 0.0,
            "axes": self.axes.directions.tolist(),
            "vertical_index": int(self.axes.vertical_index),
            "axis_angles_deg": self.axes.angles_deg().round(3).tolist(),
            "units": self.metadata.get("units", "arbitrary"),
            "camera": self.camera.to_dict(),
        }
        if len(self.keyframes):
            c = self.keyframes.T_wc[:, :3, 3]
            out["trajectory_length"] = float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum())
            out["duration_s"] = float(self.keyframes.timestamp.max() - self.keyframes.timestamp.min())
        return out


def map_file(path: str | os.PathLike) -> Path:
    """The map file `path` names: itself, or a run folder's map.papl (MapFormatError when it has none)."""
    path = Path(path)
    if path.is_dir():
        if not (path / "map.papl").is_file():
            raise MapFormatError(f"{path}: a folder with no map.papl; give a .papl file or a run folder")
        return path / "map.papl"
    return path


# ---- array table (the on-disk layout) ------------------------------------------------------

_FIELDS = {
    "keyframes": ("ids", "frame_index", "timestamp", "T_wc"),
    "points": ("ids", "xyz", "color", "obs_ids", "obs_uv"),
    "lines": (
        "ids",
        "endpoints_w",
        "axis_weights",
        "state",
        "ref_keyframe_id",
        "inverse_depth",
        "obs_ids",
        "obs_xy",
    ),
}
# name -> (shape with None for free dims, accepted dtype kinds)
_ARRAY_SPECS: dict[str, tuple[tuple, str]] = {
    "keyframes.ids": ((None,), "iu"),
    "keyframes.frame_index": ((None,), "iu"),
    "keyframes.timestamp": ((None,), "f"),
    "keyframes.T_wc": ((None, 4, 4), "f"),
    "points.ids": ((None,), "iu"),
    "points.xyz": ((None, 3), "f"),
    "points.color": ((None, 3), "u"),
    "points.obs_ids": ((None, 2), "iu"),
    "points.obs_uv": ((None, 2), "f"),
    "lines.ids": ((None,), "iu"),
    "lines.endpoints_w": ((None, 2, 3), "f"),
    "lines.axis_weights": ((None, None), "f"),
    "lines.state": ((None,), "iu"),
    "lines.ref_keyframe_id": ((None,), "i"),
    "lines.inverse_depth": ((None,), "f"),
    "lines.obs_ids": ((None, 2), "iu"),
    "lines.obs_xy": ((None, 4), "f"),
    "axes.directions": ((None, 3), "f"),
}
_FINITE = (
    "keyframes.timestamp",
    "keyframes.T_wc",
    "points.xyz",
    "points.obs_uv",
    "lines.endpoints_w",
    "lines.axis_weights",
    "lines.obs_xy",
    "axes.directions",
)


def _get(m: Map, name: str) -> Any:
    group, attr = name.split(".")
    return getattr(getattr(m, group), attr)


def _arrays(m: Map) -> dict[str, np.ndarray]:
    return {name: _get(m, name) for name in _ARRAY_SPECS}


def _all_unique(ids: np.ndarray) -> bool:
    """True when no id repeats. Sorted ids take one O(n) pass; others a sort (np.unique hashes, slower)."""
    if len(ids) < 2 or bool(np.all(ids[1:] > ids[:-1])):
        return True
    s = np.sort(ids)
    return bool(np.all(s[1:] != s[:-1]))


def _check_refs(refs: np.ndarray, ids: np.ndarray, what: str, target: str) -> None:
    if refs.size == 0:
        return
    known = np.isin(refs, ids)
    if not known.all():
        missing = np.unique(refs[~known])[:5].tolist()
        raise MapFormatError(f"{what} refers to unknown {target} ids {missing}")


def _bad_ids(m: Map, name: str, bad: np.ndarray) -> list:
    group = name.split(".")[0]
    if group in ("keyframes", "points", "lines") and not name.endswith(("obs_uv", "obs_xy")):
        return _get(m, f"{group}.ids")[bad][:5].tolist()
    return np.flatnonzero(bad)[:5].tolist()


MAX_META_BYTES = 64 << 20
"""Largest meta.json read (the metadata holds the config and timings: kilobytes)."""
MAX_INFLATION = 20
"""Largest ratio of a member's declared size to its stored size: maps are written uncompressed, and
real arrays deflate little; a far higher ratio (a zip bomb) is refused before inflating."""


def _member(zf: zipfile.ZipFile, name: str, archive_bytes: int) -> zipfile.ZipInfo:
    """The zip entry `name`, refused when missing or when its declared size is not justified."""
    try:
        info = zf.getinfo(name)
    except KeyError:
        raise MapFormatError(f"{name} is missing") from None
    if (
        info.file_size > max(MAX_INFLATION * info.compress_size, 1 << 16)
        or info.compress_size > archive_bytes
    ):
        raise MapFormatError(
            f"{name} declares {info.file_size:,} bytes from {info.compress_size:,} stored "
            f"(more than {MAX_INFLATION}x, or more than the file holds)"
        )
    return info


def _read_meta(zf: zipfile.ZipFile) -> dict[str, Any]:
    """meta.json, schema-checked: format, version, camera object, integer vertical_index, metadata object."""
    if "meta.json" not in zf.namelist():
        raise MapFormatError("not a papl map (no meta.json inside)")
    info = _member(zf, "meta.json", 1 << 62)
    if info.file_size > MAX_META_BYTES:
        raise MapFormatError(f"meta.json is {info.file_size:,} bytes (at most {MAX_META_BYTES:,})")
    meta = json.loads(zf.read(info))
    if not isinstance(meta, dict):
        raise MapFormatError(f"not a papl map (meta.json holds a {type(meta).__name__}, not an object)")
    if meta.get("format") != FORMAT_NAME:
        raise MapFormatError(f"not a papl map (format {meta.get('format')!r:.40})")
    version = meta.get("version")
    if version != FORMAT_VERSION or isinstance(version, bool):
        raise MapFormatError(
            f"map format version {version!r:.20}, this papl-mapper reads version "
            f"{FORMAT_VERSION}; re-export it with a matching papl-mapper"
        )
    vi = meta.get("vertical_index", -1)
    if not isinstance(vi, int) or isinstance(vi, bool):
        raise MapFormatError(f"meta.json: vertical_index must be an integer, got {vi!r:.40}")
    metadata = meta.get("metadata", {})
    if not isinstance(metadata, dict):
        raise MapFormatError(f"meta.json: metadata must be an object, got {type(metadata).__name__}")
    if not isinstance(meta.get("camera"), dict):
        raise MapFormatError(f"meta.json: camera must be an object, got {type(meta.get('camera')).__name__}")
    return {**meta, "vertical_index": vi, "metadata": metadata}


def _read_arrays(zf: zipfile.ZipFile, archive_bytes: int) -> dict[str, np.ndarray]:
    """Every array of `_ARRAY_SPECS`. All headers are read and checked first (spec, byte count equal to
    the entry's size, rows agreeing across a group), so nothing is allocated for a lying header."""
    headers = {}
    names = set(zf.namelist())
    for name in _ARRAY_SPECS:
        if f"{name}.npy" not in names:
            raise MapFormatError(f"array {name!r} is missing")
        info = _member(zf, f"{name}.npy", archive_bytes)
        with zf.open(info) as fh:
            shape, fortran, dtype = _npy_header(fh)
            header_bytes = fh.tell()
        _check_header(name, shape, dtype)
        nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
        if header_bytes + nbytes != info.file_size:
            raise MapFormatError(
                f"array {name!r} declares shape {shape} ({nbytes:,} bytes) but its entry holds "
                f"{info.file_size - header_bytes:,}"
            )
        headers[name] = (info, shape, fortran, dtype)
    _check_rows({name: h[1] for name, h in headers.items()})
    arrays = {}
    for name, (info, shape, fortran, dtype) in headers.items():
        with zf.open(info) as fh:
            _npy_header(fh)
            arrays[name] = _read_npy_data(fh, shape, fortran, dtype)
    return arrays


def _check_header(name: str, shape: tuple, dtype: np.dtype) -> None:
    """The spec of `_ARRAY_SPECS` (dimensions, dtype kind) checked on a header, before any allocation."""
    want, kind = _ARRAY_SPECS[name]
    if dtype.hasobject or dtype.kind not in kind:
        raise MapFormatError(f"array {name!r} has dtype {dtype}, expected kind {kind!r}")
    if len(shape) != len(want) or any(
        isinstance(w, int) and d != w for d, w in zip(shape, want, strict=True)
    ):
        raise MapFormatError(f"array {name!r} has shape {shape}, expected {want}")


def _check_rows(shapes: dict[str, tuple]) -> None:
    """Rows of a group's per-item arrays equal its ids'; obs pairs agree; a weight column per axis."""
    for group, fields in _FIELDS.items():
        n = shapes[f"{group}.ids"][0]
        for f in fields:
            if not f.startswith("obs_") and shapes[f"{group}.{f}"][0] != n:
                raise MapFormatError(f"{group}.{f} has {shapes[f'{group}.{f}'][0]} rows, {group}.ids has {n}")
    for group, obs in (("points", "obs_uv"), ("lines", "obs_xy")):
        if shapes[f"{group}.obs_ids"][0] != shapes[f"{group}.{obs}"][0]:
            raise MapFormatError(f"{group}.obs_ids and {group}.{obs} differ in length")
    if shapes["lines.axis_weights"][1] != shapes["axes.directions"][0]:
        raise MapFormatError("lines.axis_weights has a column count other than the number of axes")


def _npy_header(fh: Any) -> tuple[tuple, bool, np.dtype]:
    """(shape, fortran_order, dtype) of a .npy stream, left at the start of its data."""
    version = np.lib.format.read_magic(fh)
    try:
        if version == (1, 0):
            return np.lib.format.read_array_header_1_0(fh)
        if version == (2, 0):
            return np.lib.format.read_array_header_2_0(fh)
    except (SyntaxError, TypeError, OverflowError, tokenize.TokenError) as exc:  # numpy parses it as Python
        raise ValueError(f"unreadable .npy header ({type(exc).__name__})") from exc
    raise ValueError(f"unsupported .npy version {version}")


def _read_npy_data(fh: Any, shape: tuple, fortran: bool, dtype: np.dtype) -> np.ndarray:
    """Read one .npy member's data straight into a fresh writable array (one copy, CRC checked by zip)."""
    arr = np.empty(shape[::-1] if fortran else shape, dtype=dtype)
    got = fh.readinto(memoryview(arr).cast("B")) if arr.size else 0
    if got != arr.nbytes:
        raise EOFError(f"array data truncated ({got} of {arr.nbytes} bytes)")
    if fh.read(1):
        raise ValueError("trailing bytes after array data")
    return arr.T if fortran else arr


def json_default(o: Any) -> Any:
    """`json.dumps(default=...)` for numpy arrays and scalars and paths."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"cannot store {type(o).__name__} as JSON")
