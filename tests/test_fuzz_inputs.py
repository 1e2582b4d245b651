"""Seeded mutation fuzzing of the map loader and the camera readers (issue #16): truncations, byte
flips, field swaps and lying .npy headers of valid files. Only the typed errors may come out, and no
case may allocate much more than the file it reads. Each test runs for a fixed time budget."""

from __future__ import annotations

import io
import json
import time
import tracemalloc
import zipfile
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from papl_mapper.errors import InputError, MapFormatError
from papl_mapper.frontend.camera import camera_for_recording
from papl_mapper.map import Map

TINY = Path(__file__).resolve().parents[1] / "samples" / "tiny"
BUDGET_S = 2.5  # per test; the cases run until it is spent (about a thousand map cases here)
MAX_PEAK_BYTES = 32 * 2**20  # the tiny map is 250 KB: a case allocating more has trusted a lie
ODD_VALUES = [None, True, -1, 0, 2**63, 1e308, float("nan"), "abc", "", [], [1, 2], {}, {"a": 1}, "1e-9"]


def _flip(data: bytes, rng: np.random.Generator) -> bytes:
    buf = bytearray(data)
    for _ in range(int(rng.integers(1, 8))):
        buf[int(rng.integers(len(buf)))] = int(rng.integers(256))
    return bytes(buf)


def _truncate(data: bytes, rng: np.random.Generator) -> bytes:
    return data[: int(rng.integers(len(data)))]


def _swap_fields(obj: dict, rng: np.random.Generator) -> dict:
    """Two fields swap values, or one gets an odd value of another type; nested objects too."""
    obj = json.loads(json.dumps(obj))
    node = obj
    while rng.random() < 0.5:
        nested = [k for k, v in node.items() if isinstance(v, dict) and v]
        if not nested:
            break
        node = node[nested[int(rng.integers(len(nested)))]]
    keys = list(node)
    if len(keys) >= 2 and rng.random() < 0.4:
        a, b = rng.choice(len(keys), 2, replace=False)
        node[keys[a]], node[keys[b]] = node[keys[b]], node[keys[a]]
    elif keys and rng.random() < 0.8:
        node[keys[int(rng.integers(len(keys)))]] = ODD_VALUES[int(rng.integers(len(ODD_VALUES)))]
    elif keys:
        del node[keys[int(rng.integers(len(keys)))]]
    return obj


def _lying_header(rng: np.random.Generator) -> bytes:
    """A .npy header with a random (often huge or mismatched) shape and dtype, and a little data."""
    ndim = int(rng.integers(0, 4))
    shape = tuple(int(x) for x in rng.choice([0, 1, 2, 3, 4, 5, 2**20, 2**31, 2**40, 2**62], ndim))
    descr = ["<f8", "<i8", "|u1", "|i1", "<f4", "|b1", "<c16", "|S4"][int(rng.integers(8))]
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": descr, "fortran_order": bool(rng.random() < 0.3), "shape": shape}
    )
    return buf.getvalue() + bytes(int(rng.integers(0, 64)))


def _mutate_map(good: bytes, rng: np.random.Generator) -> tuple[str, bytes]:
    kind = ["truncate", "flip", "meta", "npy", "deflate"][int(rng.integers(5))]
    if kind == "truncate":
        return kind, _truncate(good, rng)
    if kind == "flip":
        return kind, _flip(good, rng)
    out = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(good)) as zin:
        names = zin.namelist()
        target = names[int(rng.integers(1, len(names)))]
        method = zipfile.ZIP_DEFLATED if kind == "deflate" else zipfile.ZIP_STORED
        with zipfile.ZipFile(out, "w", method) as zout:
            for name in names:
                data = zin.read(name)
                if kind == "meta" and name == "meta.json":
                    data = json.dumps(_swap_fields(json.loads(data), rng)).encode()
                elif kind == "npy" and name == target:
                    data = _lying_header(rng)
                elif kind == "deflate" and name == target and rng.random() < 0.5:
                    data = data[:128] + bytes(
                        int(rng.integers(1, 9)) * 2**20
                    )  # zeros: a small bomb (up to 8 MB)
                zout.writestr(name, data)
    return kind, out.getvalue()


def _fuzz(
    make: Callable[[np.random.Generator], object], check: Callable[[object], None], seed: int, budget_s: float
) -> dict:
    """`check(make(rng))` until the budget is spent: the number of cases, and the peak memory `check`
    allocated (traced, above what was held before it)."""
    rng = np.random.default_rng(seed)
    n, peak = 0, 0
    t0 = time.perf_counter()
    tracemalloc.start()
    try:
        while time.perf_counter() - t0 < budget_s:
            case = make(rng)
            tracemalloc.reset_peak()
            held = tracemalloc.get_traced_memory()[0]
            check(case)
            peak = max(peak, tracemalloc.get_traced_memory()[1] - held)
            n += 1
    finally:
        tracemalloc.stop()
    return {"cases": n, "peak_bytes": peak, "seconds": round(time.perf_counter() - t0, 2)}


def fuzz_map_loader(tmp: Path, seed: int = 0, budget_s: float = BUDGET_S) -> dict:
    good = (TINY / "gt" / "map.papl").read_bytes()
    path = tmp / "fuzz.papl"
    kinds: dict[str, int] = {}

    def make(rng: np.random.Generator) -> str:
        kind, data = _mutate_map(good, rng)
        path.write_bytes(data)
        return kind

    def check(kind: str) -> None:
        try:
            Map.load(path)
            kinds[f"{kind} loaded"] = kinds.get(f"{kind} loaded", 0) + 1
        except MapFormatError as exc:
            assert str(exc).startswith(str(path)) and "\n" not in str(exc), exc
            kinds[kind] = kinds.get(kind, 0) + 1

    stats = _fuzz(make, check, seed, budget_s)
    return {**stats, "kinds": kinds}


def _camera_files(tmp: Path) -> dict[str, bytes]:
    """One valid file per supported camera format, for the 640x480 tiny sample."""
    K = np.array([[457.0, 0, 319.5], [0, 457.0, 239.5], [0, 0, 1]])
    yaml = tmp / "opencv.yaml"
    fs = cv2.FileStorage(str(yaml), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", np.zeros((1, 5)))
    fs.release()
    return {
        "camera.json": (TINY / "camera.json").read_bytes(),
        "opencv.yaml": yaml.read_bytes(),
        "cameras.txt": b"# COLMAP\n1 OPENCV 640 480 457 457 320 240 0.01 0 0 0\n",
        "calib.txt": b"P0: 457 0 319.5 0 0 457 239.5 0 0 0 1 0\n",
    }


def fuzz_camera_readers(tmp: Path, seed: int = 0, budget_s: float = BUDGET_S) -> dict:
    files = _camera_files(tmp)
    names = sorted(files)

    def make(rng: np.random.Generator) -> Path:
        name = names[int(rng.integers(len(names)))]
        data = files[name]
        kind = int(rng.integers(3))
        if kind == 0:
            data = _truncate(data, rng)
        elif kind == 1:
            data = _flip(data, rng)
        elif name == "camera.json":
            data = json.dumps(_swap_fields(json.loads(data), rng)).encode()
        else:  # a token swapped for an odd one
            tokens = data.split(b" ")
            tokens[int(rng.integers(len(tokens)))] = str(
                ODD_VALUES[int(rng.integers(len(ODD_VALUES)))]
            ).encode()
            data = b" ".join(tokens)
        path = tmp / name
        path.write_bytes(data)
        return path

    def check(path: Path) -> None:
        try:
            camera_for_recording(path, 640, 480)
        except InputError as exc:
            assert str(path) in str(exc) and "\n" not in str(exc), exc

    return _fuzz(make, check, seed, budget_s)


def test_map_loader_fuzz(tmp_path: Path):
    stats = fuzz_map_loader(tmp_path)
    assert stats["cases"] > 50, stats
    assert stats["peak_bytes"] < MAX_PEAK_BYTES, stats


def test_camera_reader_fuzz(tmp_path: Path):
    stats = fuzz_camera_readers(tmp_path)
    assert stats["cases"] > 50, stats
    assert stats["peak_bytes"] < MAX_PEAK_BYTES, stats
