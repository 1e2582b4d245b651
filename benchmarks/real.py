"""papl-map against COLMAP and GLOMAP on the real sequences in ../shared/data/real.

Every folder of the data directory holding `images/` (with `timestamps.txt`), `groundtruth.tum`
and an intrinsics file (camera.json, KITTI calib.txt, ...) is one sequence; nothing is listed here,
so sequences added later are picked up. Each sequence is mapped three ways in the same run:

- papl-map: `.venv/bin/papl-map run SEQ/images --camera CAMFILE --out DIR` as a subprocess, wall
  clock timed; a failure (non-zero exit) is a row with its exit code and one-line error.
- COLMAP (pycolmap): SIFT extraction into a fresh database, a single PINHOLE camera with the file's
  intrinsics (principal point + 0.5 px: COLMAP puts the first pixel's centre at 0.5, OpenCV at 0),
  sequential matching for a video, exhaustive for a photo set (median frame interval above
  PHOTO_SET_INTERVAL_S), then `pycolmap.incremental_mapping` with focal length, principal point
  and extra parameters held fixed (bundle adjustment and absolute pose).
- GLOMAP: `pycolmap.global_mapping` on the same database, the same parameters held fixed.
  Extraction, matching and mapping are timed separately; a method's time is their sum (the
  extraction and matching are shared by COLMAP and GLOMAP and counted in both). The model with
  the most registered images is used.

Accuracy, the same for every method: the estimate's poses (papl-map's trajectory.tum, which
carries the recording's timestamps; for COLMAP each registered image's name mapped to its line of
images/timestamps.txt) are matched to groundtruth.tum by timestamp (nearest within 0.01 s, as evo),
aligned by Umeyama's Sim(3) with scale over the matched positions, and the ATE RMSE is taken over
those matched frames, i.e. over the frames the method posed (see "frames posed"), in metres
and as % of the ground-truth path length between the first and last image (the same length for
every method). The ratios papl/COLMAP and papl/GLOMAP divide papl-map's ATE (m) and wall time by
the peer's.

    .venv/bin/python benchmarks/real.py                          # everything (a few minutes)
    .venv/bin/python benchmarks/real.py --only kitti06_0000_0050,icl_lr_kt1_250_366
    .venv/bin/python benchmarks/real.py --skip-colmap            # papl-map only, peers from the JSON
    .venv/bin/python benchmarks/real.py --ablation points-only,orthonormal-lines,no-axis-management
    .venv/bin/python benchmarks/real.py --step 3                 # every 3rd image: real_step3.json
    .venv/bin/python benchmarks/real.py --step 3 --offset 1      # from the 2nd: real_step3_offset1.json
    .venv/bin/python benchmarks/real.py --repeat 3               # papl-map's wall: median of 3 runs
    .venv/bin/python benchmarks/real.py --shuffle 0,1,2          # photo sets out of order: real_shuffled.json
    .venv/bin/python benchmarks/real.py --ablation mapping.retry_lost=false   # any config key as a row

Every sequence's images are read once before the first method runs, so that all methods find them in
the page cache. Prints one table and writes benchmarks/results/real.json.
With --only, the entries of the other sequences already in the JSON are kept (each entry names the
commit it was measured at).
With --skip-colmap the COLMAP/GLOMAP records of a sequence are taken from the existing JSON when
its input fingerprint (images, timestamps, intrinsics, ground truth) is unchanged.
With --step N every method maps every N-th image (papl-map with `--step N`, the peers the same image
list): the wide baselines of dropped frames or a faster walk, on the same ground truth.
With --shuffle SEEDS each photo set is also mapped with its images in a random order per seed (a
folder of symlinks named in that order, without timestamps.txt, as a folder of photos whose names do
not follow the capture order; every method gets the same list); papl-map's frame times are mapped
back to the photos' own. Videos are not shuffled.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from machine import ROOT, git_commit, machine_info

from papl_mapper.eval.trajectory import (
    associate,
    associate_trajectories,
    ate_errors,
    rmse,
)
from papl_mapper.frontend.camera import read_camera_file
from papl_mapper.geometry.similarity import umeyama
from papl_mapper.trajectory_io import Trajectory, read_tum, write_tum

OUT = ROOT / "benchmarks" / "results" / "real.json"
DATA = ROOT.parent / "shared" / "data" / "real"
PAPL = ROOT / ".venv" / "bin" / "papl-map"
CAMERA_FILES = ("camera.json", "calib.txt", "cameras.txt", "camera.yaml", "camera.yml")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")
MAX_TIME_DIFF_S = 0.01  # timestamp association, as evo's default and papl-map eval
PHOTO_SET_INTERVAL_S = 0.5  # median frame interval above this: a photo set (exhaustive matching)
FOLDER_FPS = 30.0  # papl-map's frame rate for a folder without timestamps.txt
SEED = 0
METHODS = ("papl", "colmap", "glomap")
LABELS = {"papl": "papl-map", "colmap": "COLMAP", "glomap": "GLOMAP"}
ABLATION = ("points-only", "orthonormal-lines", "no-axis-management", "paper-anchors")
"""Presets for `--ablation`: lines off, lines unanchored, axes never updated, the paper's n + 2."""


@dataclass
class Sequence:
    name: str
    folder: Path
    images: Path
    names: list[str]  # image file names in name (natural) order, as papl-map reads them
    timestamps: np.ndarray  # one per image
    camera_file: Path
    gt: Trajectory
    width: int
    height: int
    step: int = 1  # every step-th image of the folder (papl-map --step; the peers get the same images)
    shuffle: int | None = None  # the seed of the image order (`shuffled`); None: name order
    offset: int = 0  # the first image of a thinned sequence (`every_nth`)

    @property
    def label(self) -> str:
        label = self.name if self.shuffle is None else f"{self.name}_shuffle{self.shuffle}"
        return label + (f"_offset{self.offset}" if self.offset else "")

    @property
    def median_interval_s(self) -> float:
        stamps = np.sort(self.timestamps)
        return float(np.median(np.diff(stamps))) if len(stamps) > 1 else float("nan")

    @property
    def matching(self) -> str:
        return "exhaustive" if self.median_interval_s > PHOTO_SET_INTERVAL_S else "sequential"

    def gt_path_length_m(self) -> float:
        """Ground-truth path length between the ground-truth poses matched to the first and last image."""
        i_img, i_gt = associate(np.sort(self.timestamps), self.gt.timestamps, MAX_TIME_DIFF_S)
        if len(i_gt) < 2:
            return float("nan")
        return self.gt.subset(np.arange(i_gt.min(), i_gt.max() + 1)).path_length()

    def fingerprint(self) -> str:
        """sha256 over image names and sizes, timestamps, intrinsics and ground truth files."""
        h = hashlib.sha256()
        for n in self.names:
            h.update(f"{n}:{(self.images / n).stat().st_size};".encode())
        stamps = self.folder / "images" / "timestamps.txt"  # the folder's own, also for a shuffled list
        for p in (stamps, self.camera_file, self.folder / "groundtruth.tum"):
            h.update(p.read_bytes())
        return h.hexdigest()


def _natural_key(name: str) -> list[object]:
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", name)]


def discover(data: Path) -> list[Sequence]:
    """Every sub-folder of `data` with images/timestamps.txt, groundtruth.tum and an intrinsics file."""
    seqs = []
    for folder in sorted(p for p in data.iterdir() if p.is_dir()):
        images = folder / "images"
        cams = [folder / c for c in CAMERA_FILES if (folder / c).is_file()]
        if (
            not (images / "timestamps.txt").is_file()
            or not (folder / "groundtruth.tum").is_file()
            or not cams
        ):
            print(
                f"skipping {folder}: needs images/timestamps.txt, groundtruth.tum and one of {CAMERA_FILES}"
            )
            continue
        names = sorted(
            (p.name for p in images.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
            key=_natural_key,
        )
        stamps = [
            float(ln.split()[0])
            for ln in (images / "timestamps.txt").read_text().splitlines()
            if ln.strip() and not ln.lstrip().startswith("#")
        ]
        if len(stamps) != len(names):
            print(f"skipping {folder}: {len(stamps)} timestamps for {len(names)} images")
            continue
        h, w = cv2.imread(str(images / names[0]), cv2.IMREAD_UNCHANGED).shape[:2]
        seqs.append(
            Sequence(
                folder.name,
                folder,
                images,
                names,
                np.asarray(stamps),
                cams[0],
                read_tum(folder / "groundtruth.tum"),
                w,
                h,
            )
        )
    return seqs


def every_nth(seq: Sequence, step: int, offset: int = 0, root: Path | None = None) -> Sequence:
    """The sequence thinned to every step-th image from the first, as `papl-map run --step` reads it
    (wider baselines, as dropped frames or a faster walk give); from image `offset` > 0, a folder of
    symlinks to those images with their timestamps.txt under `root`, mapped as it is."""
    if step == 1 and offset == 0:
        return seq
    names, stamps = seq.names[offset::step], seq.timestamps[offset::step]
    if offset == 0:
        return dataclasses.replace(seq, names=names, timestamps=stamps, step=step)
    images = root / f"{seq.name}_step{step}_offset{offset}" / "images"
    _link_images(images, names, [seq.images / n for n in names])
    lines = [f"{t!r} {n}\n" for t, n in zip(stamps.tolist(), names, strict=True)]
    (images / "timestamps.txt").write_text("".join(lines))
    return dataclasses.replace(seq, images=images, names=names, timestamps=stamps, step=step, offset=offset)


def _link_images(images: Path, names: list[str], sources: list[Path]) -> None:
    """A fresh folder `images` of symbolic links `names` to the image files `sources`."""
    if images.exists():
        shutil.rmtree(images)
    images.mkdir(parents=True)
    for name, src in zip(names, sources, strict=True):
        (images / name).symlink_to(src.resolve())


def shuffled(seq: Sequence, seed: int, root: Path) -> Sequence:
    """The sequence with its images in a random order: a folder of symlinks `NNNN_<name>` under `root`
    in that order and without timestamps.txt (papl-map then times frame k at k / 30 s)."""
    order = np.random.default_rng(seed).permutation(len(seq.names))
    images = root / f"{seq.name}_shuffle{seed}" / "images"
    names = [f"{k:04d}_{seq.names[i]}" for k, i in enumerate(order)]
    _link_images(images, names, [seq.images / seq.names[i] for i in order])
    stamps = seq.timestamps[order]
    return dataclasses.replace(seq, images=images, names=names, timestamps=stamps, shuffle=seed)


def _retimed(seq: Sequence, est: Trajectory) -> Trajectory:
    """papl-map's trajectory of a shuffled folder (frame k at k / 30 s) at the photos' own times."""
    k = np.rint(est.timestamps * FOLDER_FPS).astype(int)
    t = seq.timestamps[k]
    order = np.argsort(t)
    return Trajectory(t[order], est.T_wc[order])


def accuracy(seq: Sequence, est: Trajectory) -> dict:
    """ATE after Sim(3) (Umeyama with scale) over the estimate's poses matched to the ground truth."""
    i_ref, i_est = associate_trajectories(seq.gt, est, MAX_TIME_DIFF_S)
    out: dict = {"frames_matched_gt": len(i_ref)}
    if len(i_ref) < 3:
        out["ate_error"] = f"only {len(i_ref)} poses match ground-truth timestamps"
        return out
    ref_m, est_m = seq.gt.subset(i_ref), est.subset(i_est)
    try:
        sim = umeyama(
            est_m.positions,
            ref_m.positions,
            with_scale=True,
            R_x=est_m.T_wc[:, :3, :3],
            R_y=ref_m.T_wc[:, :3, :3],
        )
    except Exception as exc:  # noqa: BLE001 - a degenerate estimate is a result, not the end
        out["ate_error"] = f"{type(exc).__name__}: {exc}"
        return out
    err = ate_errors(ref_m.positions, sim.apply(est_m.positions))
    path = seq.gt_path_length_m()
    out.update(
        ate_rmse_m=rmse(err),
        ate_max_m=float(err.max()),
        ate_rmse_pct_path=100.0 * rmse(err) / path if path > 0 else float("nan"),
        sim3_scale=sim.scale,
        alignment=sim.method,
    )
    return out


def _warm_cache(seq: Sequence) -> None:
    """Read every input file once before anything is timed, so that no method pays the disk reads the
    methods after it are spared (papl-map runs first)."""
    for name in seq.names:
        (seq.images / name).read_bytes()


def _warm_imports() -> None:
    """Import papl-map's pipeline once in a throw-away process before anything is timed: the first
    process after a while reads its libraries (OpenCV, gtsam, scipy) from disk, ~0.7 s that a second run
    and the peers, imported once in this process, do not pay."""
    subprocess.run(
        [str(PAPL.parent / "python"), "-c", "import papl_mapper.pipelines.run"], cwd=ROOT, check=False
    )


def _loadavg() -> float:
    return round(os.getloadavg()[0], 2)


def _one_line_error(stderr: str) -> str:
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    return lines[-1] if lines else "(no message)"


def run_papl(seq: Sequence, out: Path, timeout_s: float, preset: str = "full") -> dict:
    """`papl-map run --preset` (or `--set`, for a preset of the form KEY=VALUE) as a subprocess, wall
    clock timed; a failure is recorded, not raised."""
    if out.exists():
        shutil.rmtree(out)
    cmd = [str(PAPL), "run", str(seq.images), "--camera", str(seq.camera_file), "--out", str(out)]
    if preset != "full":
        cmd += ["--set", preset] if "=" in preset else ["--preset", preset]
    cmd += ["--step", str(seq.step)] if seq.step > 1 and not seq.offset else []
    rec: dict = {"command": " ".join(cmd), "loadavg_1m_at_start": _loadavg(), "frames_total": len(seq.names)}
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, cwd=ROOT)
    except subprocess.TimeoutExpired:
        rec.update(wall_s=time.perf_counter() - t0, status="failed", error=f"timed out after {timeout_s:g} s")
        return rec
    rec["wall_s"] = time.perf_counter() - t0
    rec["exit_code"] = proc.returncode
    if proc.returncode != 0:
        rec.update(status="failed", error=_one_line_error(proc.stderr))
        return rec
    traj_path = out / "trajectory.tum"
    try:
        est = read_tum(traj_path)
    except Exception as exc:  # noqa: BLE001 - an unreadable output is a failure row
        rec.update(status="failed", error=f"{type(exc).__name__}: {exc}")
        return rec
    rec.update(status="ok", frames_posed=len(est), trajectory=str(traj_path))
    rec.update(accuracy(seq, est if seq.shuffle is None else _retimed(seq, est)))
    try:
        summary = json.loads((out / "summary.json").read_text())
        counts = summary.get("counts", {})
        rec["map"] = {k: counts.get(k) for k in ("keyframes", "points", "lines", "anchored_fraction")}
        rec["stage_s"] = summary.get("timings_s")
    except (OSError, ValueError):
        pass
    return rec


def run_papl_median(seq: Sequence, out: Path, timeout_s: float, repeat: int) -> dict:
    """`run_papl` `repeat` times: the record of the run with the median wall time, with every run's
    wall time in `walls_s` (a 4-13 s job's wall time moves by a quarter between runs on a shared
    machine; its outputs do not)."""
    runs = [run_papl(seq, out, timeout_s) for _ in range(max(1, repeat))]
    rec = sorted(runs, key=lambda r: r.get("wall_s", math.inf))[(len(runs) - 1) // 2]
    return {**rec, "walls_s": [r.get("wall_s") for r in runs]} if repeat > 1 else rec


def _colmap_camera(seq: Sequence) -> tuple[str, str]:
    """COLMAP camera model and parameter string from the sequence's intrinsics file."""
    cam = read_camera_file(seq.camera_file)
    if cam.width and (cam.width, cam.height) != (seq.width, seq.height):
        raise ValueError(f"{seq.camera_file}: {cam.width}x{cam.height}, images are {seq.width}x{seq.height}")
    # COLMAP's pixel centres are at +0.5 from OpenCV's (its first pixel spans 0..1).
    k = [cam.fx, cam.fy, cam.cx + 0.5, cam.cy + 0.5]
    dist = np.asarray(cam.distortion, np.float64).reshape(-1)
    if not np.any(dist):
        return "PINHOLE", ",".join(f"{v:.10g}" for v in k)
    d = np.zeros(8)
    d[: min(len(dist), 8)] = dist[:8]  # OpenCV order k1 k2 p1 p2 k3 k4 k5 k6, as FULL_OPENCV
    return "FULL_OPENCV", ",".join(f"{v:.10g}" for v in [*k, *d])


def colmap_options() -> dict:
    """The pycolmap option objects used (everything not set here is pycolmap 4.2's default)."""
    import pycolmap

    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    sequential = pycolmap.SequentialPairingOptions()
    exhaustive = pycolmap.ExhaustivePairingOptions()
    verification = pycolmap.TwoViewGeometryOptions()
    inc = pycolmap.IncrementalPipelineOptions()
    inc.ba_refine_focal_length = False
    inc.ba_refine_principal_point = False
    inc.ba_refine_extra_params = False
    inc.mapper.abs_pose_refine_focal_length = False
    inc.mapper.abs_pose_refine_extra_params = False
    inc.random_seed = SEED
    glo = pycolmap.GlobalPipelineOptions()
    glo.mapper.bundle_adjustment.refine_focal_length = False
    glo.mapper.bundle_adjustment.refine_principal_point = False
    glo.mapper.bundle_adjustment.refine_extra_params = False
    glo.mapper.global_positioning.use_gpu = False
    glo.mapper.bundle_adjustment.ceres.use_gpu = False
    glo.random_seed = SEED
    return {
        "extraction": extraction,
        "matching": matching,
        "sequential": sequential,
        "exhaustive": exhaustive,
        "verification": verification,
        "incremental": inc,
        "global": glo,
    }


def options_record() -> dict:
    """What is set on top of pycolmap's defaults, for the JSON."""
    import pycolmap

    return {
        "pycolmap_version": pycolmap.__version__,
        "camera": "ImageReaderOptions(camera_model='PINHOLE', camera_params='fx,fy,cx+0.5,cy+0.5'), "
        "CameraMode.SINGLE, image_names = the images in name order",
        "extraction": "SIFT, FeatureExtractionOptions defaults (max_num_features 8192), use_gpu False, "
        "Device.cpu",
        "matching": "FeatureMatchingOptions defaults (SIFT brute force, ratio 0.8, cross-check), "
        "use_gpu False; match_sequential (SequentialPairingOptions defaults: overlap 10, quadratic_overlap, "
        "no loop detection) for videos, match_exhaustive for photo sets (median frame interval > "
        f"{PHOTO_SET_INTERVAL_S} s); TwoViewGeometryOptions defaults",
        "incremental": "IncrementalPipelineOptions: ba_refine_focal_length, ba_refine_principal_point, "
        "ba_refine_extra_params False; mapper.abs_pose_refine_focal_length, "
        f"mapper.abs_pose_refine_extra_params False; random_seed {SEED}; otherwise defaults",
        "global": "GlobalPipelineOptions: mapper.bundle_adjustment.refine_focal_length, "
        "refine_principal_point, refine_extra_params False; mapper.global_positioning.use_gpu, "
        f"mapper.bundle_adjustment.ceres.use_gpu False; random_seed {SEED}; otherwise defaults",
        "model": "the reconstruction with the most registered images",
    }


def _trajectory_of(seq: Sequence, rec) -> Trajectory:
    stamp = dict(zip(seq.names, seq.timestamps, strict=True))
    rows = []
    for img in rec.images.values():
        if img.has_pose and img.name in stamp:
            T_cw = np.eye(4)
            T_cw[:3] = img.cam_from_world().matrix()
            rows.append((stamp[img.name], np.linalg.inv(T_cw)))
    rows.sort(key=lambda r: r[0])
    return Trajectory(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]).reshape(-1, 4, 4))


def _model_record(seq: Sequence, models: dict, out: Path) -> dict:
    if not models:
        return {"status": "no model", "frames_posed": 0, "frames_total": len(seq.names), "models": 0}
    best = max(models.values(), key=lambda r: r.num_reg_images())
    est = _trajectory_of(seq, best)
    write_tum(out, est)
    cam = next(iter(best.cameras.values()))
    rec = {
        "status": "ok",
        "frames_posed": len(est),
        "frames_total": len(seq.names),
        "models": len(models),
        "points3d": best.num_points3D(),
        "camera_after": {"model": str(cam.model.name), "params": [float(v) for v in cam.params]},
        "trajectory": str(out),
    }
    rec.update(accuracy(seq, est))
    return rec


def run_colmap(seq: Sequence, out: Path) -> dict[str, dict]:
    """COLMAP incremental and GLOMAP on one database; {"colmap": record, "glomap": record}."""
    import pycolmap

    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    db = out / "database.db"
    opts = colmap_options()
    model, params = _colmap_camera(seq)
    reader = pycolmap.ImageReaderOptions(camera_model=model, camera_params=params)
    shared: dict = {"loadavg_1m_at_start": _loadavg(), "camera_model": model, "camera_params": params}
    t0 = time.perf_counter()
    pycolmap.extract_features(
        db,
        seq.images,
        image_names=seq.names,
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=opts["extraction"],
        device=pycolmap.Device.cpu,
    )
    shared["extract_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    match = pycolmap.match_sequential if seq.matching == "sequential" else pycolmap.match_exhaustive
    match(
        db,
        matching_options=opts["matching"],
        pairing_options=opts[seq.matching],
        verification_options=opts["verification"],
        device=pycolmap.Device.cpu,
    )
    shared["match_s"] = time.perf_counter() - t0
    shared["matching"] = seq.matching
    result = {}
    for method, fn, key, sub in (
        ("colmap", pycolmap.incremental_mapping, "incremental", "sparse"),
        ("glomap", pycolmap.global_mapping, "global", "global"),
    ):
        (out / sub).mkdir()
        rec = dict(shared)
        rec["loadavg_1m_at_map_start"] = _loadavg()
        t0 = time.perf_counter()
        try:
            models = fn(db, seq.images, out / sub, options=opts[key])
            rec["map_s"] = time.perf_counter() - t0
            rec.update(_model_record(seq, models, out / f"{method}.tum"))
        except Exception as exc:  # noqa: BLE001 - a failed peer is a row of the table, not the end
            rec["map_s"] = time.perf_counter() - t0
            rec.update(status="failed", error=f"{type(exc).__name__}: {exc}", frames_total=len(seq.names))
        rec["wall_s"] = rec["extract_s"] + rec["match_s"] + rec["map_s"]
        result[method] = rec
    return result


def ratios(entry: dict) -> dict:
    """papl/peer ATE (m) and wall-time ratios; None where either side has no figure."""
    out = {}
    papl = entry.get("papl", {})
    for peer in ("colmap", "glomap"):
        other = entry.get(peer, {})
        for fig, key in (("ate", "ate_rmse_m"), ("time", "wall_s")):
            a, b = papl.get(key), other.get(key)
            ok = a is not None and b is not None and np.isfinite(a) and np.isfinite(b) and b > 0
            if fig == "ate" and (papl.get("status") != "ok" or other.get("status") != "ok"):
                ok = False
            out[f"papl_over_{peer}_{fig}"] = a / b if ok else None
    return out


def _f(v, fmt: str, width: int) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-".rjust(width)
    return format(v, fmt).rjust(width)


def print_table(entries: dict[str, dict]) -> None:
    w = max([24, *map(len, entries)])
    header = (
        f"{'sequence':{w}} {'method':8} {'posed':>7} {'ATE m':>8} {'ATE %path':>9} {'wall s':>7} "
        f"{'extract':>7} {'match':>6} {'map':>6}  {'ATE ratio':>9} {'time ratio':>10}  note"
    )
    print(header)
    print("-" * len(header))
    for name, e in entries.items():
        r = e.get("ratios", {})
        for method in METHODS:
            rec = e.get(method)
            if rec is None:
                continue
            posed = f"{rec.get('frames_posed', 0)}/{rec.get('frames_total', e.get('frames_total', '?'))}"
            if method == "papl":
                ratio_ate = ratio_t = ""
                extract = match = mapping = None
            else:
                ratio_ate = _f(r.get(f"papl_over_{method}_ate"), ".2f", 9)
                ratio_t = _f(r.get(f"papl_over_{method}_time"), ".2f", 10)
                extract, match, mapping = rec.get("extract_s"), rec.get("match_s"), rec.get("map_s")
            note = ""
            if rec.get("status") not in ("ok", None):
                note = rec.get("status", "")
                if rec.get("error"):
                    note += f" ({'exit ' + str(rec['exit_code']) + ': ' if 'exit_code' in rec else ''}"
                    note += f"{rec['error'][:90]})"
            elif rec.get("ate_error"):
                note = rec["ate_error"][:90]
            if rec.get("reused_from_commit"):
                note = (note + " " if note else "") + f"[reused, {rec['reused_from_commit'][:8]}]"
            print(
                f"{name:{w}} {LABELS[method]:8} {posed:>7} {_f(rec.get('ate_rmse_m'), '.4f', 8)} "
                f"{_f(rec.get('ate_rmse_pct_path'), '.3f', 9)} {_f(rec.get('wall_s'), '.1f', 7)} "
                f"{_f(extract, '.1f', 7)} {_f(match, '.1f', 6)} {_f(mapping, '.1f', 6)}  "
                f"{ratio_ate:>9} {ratio_t:>10}  {note}"
            )
    print(
        "ATE: RMSE after Sim(3) Umeyama alignment with scale, over the frames each method posed that match "
        f"a ground-truth timestamp (within {MAX_TIME_DIFF_S} s); %path of the GT path between first and last "
        "image. Ratios: papl-map / peer (ATE in m; wall time, peer = extraction + matching + mapping)."
    )


def print_ablation(entries: dict[str, dict]) -> None:
    """ATE (m) of papl-map's full method and of each ablation preset, per sequence, one run."""
    presets = sorted({p for e in entries.values() for p in e.get("papl_ablation", {})})
    w = max([24, *map(len, entries)])
    pw = max([18, *map(len, presets)])
    print()
    print(f"{'sequence':{w}} {'full':>9} " + " ".join(f"{p:>{pw}}" for p in presets))
    for name, e in entries.items():
        cells = [_f(e["papl"].get("ate_rmse_m"), ".4f", 9)]
        for p in presets:
            rec = e.get("papl_ablation", {}).get(p, {})
            cells.append(_f(rec.get("ate_rmse_m") if rec.get("status") == "ok" else None, ".4f", pw))
        print(f"{name:{w}} " + " ".join(cells))
    print(
        "ATE RMSE (m) after Sim(3); presets as `papl-map run --preset` (see `papl-map run --help`), "
        "KEY=VALUE as `--set`."
    )


def _finite(v):
    """The document with NaN/inf as null and numpy scalars as Python numbers (strict JSON)."""
    if isinstance(v, dict):
        return {k: _finite(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_finite(x) for x in v]
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not np.isfinite(v):
        return None
    return v


def _dirty_files() -> list[str]:
    try:
        out = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return []
    return [ln[3:] for ln in out.splitlines() if ln.strip()]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--data", type=Path, default=DATA, help="folder of sequences (default ../shared/data/real)"
    )
    ap.add_argument("--only", default="", help="comma-separated sequence names (folder names)")
    ap.add_argument("--skip-colmap", action="store_true", help="reuse COLMAP/GLOMAP records from --out")
    ap.add_argument("--out-dir", type=Path, default=Path("/tmp/papl_real"), help="scratch outputs")
    ap.add_argument("--out", type=Path, default=OUT, help="results JSON")
    ap.add_argument("--papl-timeout", type=float, default=3600.0, help="seconds per papl-map run")
    ap.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="run papl-map (the full method) this many times per sequence and keep the median wall "
        "time (its outputs are the same every run); the peers run once",
    )
    ap.add_argument("--verbose", action="store_true", help="keep COLMAP's log output")
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument(
        "--step",
        type=int,
        default=1,
        help="map every STEP-th image (all methods); results go to real_step<STEP>.json unless --out",
    )
    ap.add_argument(
        "--offset",
        type=int,
        default=0,
        help="with --step: start at this image (a folder of links to those images is mapped); results go "
        "to real_step<STEP>_offset<OFFSET>.json unless --out",
    )
    ap.add_argument(
        "--ablation",
        default="",
        help="papl-map presets (or config overrides KEY=VALUE) also run on every sequence, "
        f"comma-separated (e.g. {','.join(ABLATION)})",
    )
    ap.add_argument(
        "--shuffle",
        default="",
        help="comma-separated seeds: map each photo set with its images in that random order (all "
        "methods); results go to real_shuffled.json unless --out",
    )
    args = ap.parse_args()
    if not args.data.is_dir():
        print(f"{args.data}: no such folder; the real sequences live in ../shared/data/real")
        return 2
    if args.step < 1:
        print(f"--step {args.step}: must be 1 or more")
        return 2
    if args.offset and (args.offset >= args.step or args.offset < 0):
        print(f"--offset {args.offset}: must be between 0 and --step - 1")
        return 2
    if args.step > 1 and args.out == OUT:
        suffix = f"_offset{args.offset}" if args.offset else ""
        args.out = OUT.with_name(f"real_step{args.step}{suffix}.json")
    seeds = [int(v) for v in args.shuffle.split(",") if v.strip()]
    if seeds and args.out == OUT:
        args.out = OUT.with_name("real_shuffled.json")
    seqs = [every_nth(s, args.step, args.offset, args.out_dir) for s in discover(args.data)]
    if args.only:
        wanted = [s.strip() for s in args.only.split(",") if s.strip()]
        unknown = sorted(set(wanted) - {s.name for s in seqs})
        if unknown:
            print(f"unknown sequence(s) {', '.join(unknown)}; have {', '.join(s.name for s in seqs)}")
            return 2
        seqs = [s for s in seqs if s.name in wanted]
    if seeds:
        videos = [s.name for s in seqs if s.matching != "exhaustive"]
        if videos:
            print(f"--shuffle: not shuffling the videos {', '.join(videos)} (photo sets only)")
        seqs = [shuffled(s, k, args.out_dir) for s in seqs if s.matching == "exhaustive" for k in seeds]
    previous: dict = {}
    if args.out.is_file():
        try:
            previous = json.loads(args.out.read_text()).get("sequences", {})
        except ValueError:
            print(f"{args.out}: not valid JSON; not reusing it")
    if not args.skip_colmap and not args.verbose:
        import pycolmap

        pycolmap.logging.minloglevel = 2  # errors only
    _warm_imports()
    commit = git_commit()
    dirty = _dirty_files()  # papl-map runs from this working tree, uncommitted changes included
    machine_start = machine_info()
    entries: dict[str, dict] = {}
    for seq in seqs:
        fp = seq.fingerprint()
        entry: dict = {
            "folder": str(seq.folder),
            "camera_file": seq.camera_file.name,
            "frames_total": len(seq.names),
            "step": seq.step,
            **({"offset": seq.offset} if seq.offset else {}),
            **({"shuffle_seed": seq.shuffle, "image_order": seq.names} if seq.shuffle is not None else {}),
            "image_size_px": [seq.width, seq.height],
            "median_frame_interval_s": seq.median_interval_s,
            "matching": seq.matching,
            "gt_path_length_m": seq.gt_path_length_m(),
            "fingerprint_sha256": fp,
            "commit": commit,
        }
        print(f"{seq.label}: {len(seq.names)} images, {seq.matching} matching for the peers", flush=True)
        _warm_cache(seq)
        scratch = args.out_dir / seq.label
        entry["papl"] = run_papl_median(seq, scratch / "papl", args.papl_timeout, args.repeat)
        for preset in filter(None, args.ablation.split(",")):
            rec = run_papl(seq, scratch / f"papl-{preset}", args.papl_timeout, preset)
            entry.setdefault("papl_ablation", {})[preset] = rec
        if args.skip_colmap:
            old = previous.get(seq.label, {})
            for peer in ("colmap", "glomap"):
                if old.get(peer) and old.get("fingerprint_sha256") == fp:
                    entry[peer] = {
                        **old[peer],
                        "reused_from_commit": old[peer].get("commit", old.get("commit")),
                    }
                else:
                    entry[peer] = {"status": "not run (--skip-colmap, no earlier result for these inputs)"}
        else:
            try:
                peers = run_colmap(seq, args.out_dir / seq.label / "colmap")
            except Exception as exc:  # noqa: BLE001 - extraction/matching failure: rows, not the end
                err = {
                    "status": "failed",
                    "error": f"{type(exc).__name__}: {exc}",
                    "frames_total": len(seq.names),
                }
                peers = {"colmap": dict(err), "glomap": dict(err)}
            for peer, rec in peers.items():
                entry[peer] = {**rec, "commit": commit}
        entry["ratios"] = ratios(entry)
        entries[seq.label] = entry
    print()
    print_table(entries)
    if args.ablation:
        print_ablation(entries)
    machine = {**machine_start, "loadavg_1m_at_end": _loadavg()}
    if git_commit() != commit:  # the checkout moved on while the benchmark ran
        machine["git_commit_at_end"] = git_commit()
    print(f"load average (1 min): {machine['loadavg_1m']} at start, {machine['loadavg_1m_at_end']} at end")
    if args.no_write:
        return 0
    kept = {k: v for k, v in previous.items() if k not in entries and (args.data / k).is_dir()}
    doc = {
        "benchmark": "real",
        "description": "papl-map vs COLMAP (incremental) and GLOMAP (global) via pycolmap on the real "
        "sequences: frames posed, ATE after Sim(3) over the frames each method posed, wall time, ratios",
        "ate_definition": f"RMSE of camera-centre errors after Umeyama Sim(3) (with scale) over the "
        f"estimate's poses matched to groundtruth.tum by nearest timestamp within {MAX_TIME_DIFF_S} s "
        "(evo's rule): over the frames the method posed. %path: of the ground-truth path length between "
        "the ground-truth poses matched to the first and last image (same for every method).",
        "time_definition": "papl-map: wall clock of the `papl-map run` subprocess (with --repeat N, the "
        "median of N runs, all in walls_s). COLMAP/GLOMAP: "
        "extract_s + match_s (shared by both) + map_s, each the wall clock of its pycolmap call.",
        "command": " ".join([sys.executable, *sys.argv]),
        "colmap_options": options_record(),
        "sequences": {**kept, **entries},
        "uncommitted_files_at_start": dirty,
        "machine": machine,
        "commit": commit,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(_finite(doc), indent=1, allow_nan=False) + "\n")
    print("wrote", args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
