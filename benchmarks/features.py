"""Which keypoints bridge a wide baseline: verified matches of neighbouring images, their precision, time.

For each real sequence in ../shared/data/real (every --step-th image), each detector's keypoints are
matched between neighbours (Lowe ratio 0.8) and verified by an essential matrix (USAC, 2 px); the
table gives the verified matches (minimum and median over the pairs), the median Sampson distance of
the inliers to their essential matrix (px: how precisely the keypoints are placed), and the
milliseconds per image for detection and per pair for matching plus verification. `product` is the
frontend's own detector and matcher (`frontend.features`: SIFT with RootSIFT and ORB descriptors).
Writes benchmarks/results/features.json.

    .venv/bin/python benchmarks/features.py
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
from machine import machine_info

from papl_mapper.frontend.camera import read_camera_file
from papl_mapper.frontend.features import FeatureConfig, SiftDetector, match_pair
from papl_mapper.geometry.two_view import sampson_px

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "real"
OUT = ROOT / "benchmarks" / "results" / "features.json"


def _klt_corners_orb(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The frontend's keyframe descriptors: fixed-size ORB on Shi-Tomasi corners."""
    c = cv2.goodFeaturesToTrack(gray, 400, 0.01, 15, blockSize=3).reshape(-1, 2)
    kps, desc = cv2.ORB_create(edgeThreshold=15, patchSize=15).compute(
        gray, [cv2.KeyPoint(float(x), float(y), 15.0) for x, y in c]
    )
    return np.array([k.pt for k in kps], np.float32), desc


def _detector(det: cv2.Feature2D):
    def run(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        kps, desc = det.detectAndCompute(gray, None)
        return np.array([k.pt for k in kps], np.float32), desc

    return run


def _product(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    uv, root_sift, _ = SiftDetector(FeatureConfig()).detect(gray)
    return uv.astype(np.float32), root_sift


DETECTORS = {
    "product": (_product, None),
    "orb_on_klt_corners": (_klt_corners_orb, cv2.NORM_HAMMING),
    "orb_1500_fast20": (_detector(cv2.ORB_create(1500)), cv2.NORM_HAMMING),
    "orb_1500_fast5": (_detector(cv2.ORB_create(1500, fastThreshold=5)), cv2.NORM_HAMMING),
    "sift_1500": (_detector(cv2.SIFT_create(1500)), cv2.NORM_L2),
}


def _verified(a, b, norm, K) -> tuple[int, float]:
    """Verified matches of two images and the median Sampson distance of the inliers (px)."""
    if norm is None:
        m, _ = match_pair(a[1], b[1], 0.8)
        pa, pb = a[0][m[:, 0]], b[0][m[:, 1]]
    else:
        knn = cv2.BFMatcher(norm).knnMatch(a[1], b[1], k=2)
        m = [p[0] for p in knn if len(p) == 2 and p[0].distance < 0.8 * p[1].distance]
        pa = a[0][[x.queryIdx for x in m]]
        pb = b[0][[x.trainIdx for x in m]]
    if len(pa) < 8:
        return 0, float("nan")
    cv2.setRNGSeed(0)
    E, mask = cv2.findEssentialMat(pa, pb, K, cv2.USAC_FAST, 0.999, 2.0)
    if mask is None or E is None:
        return 0, float("nan")
    ok = mask.ravel().astype(bool)
    return int(ok.sum()), float(np.median(sampson_px(E[:3], pa[ok], pb[ok], K)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--step", type=int, default=1)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    rows = []
    print(
        f"{'sequence':24} {'detector':20} {'min':>5} {'median':>6} {'sampson px':>10} "
        f"{'detect ms':>9} {'match ms':>8}"
    )
    for seq in sorted(p for p in args.data.iterdir() if (p / "images").is_dir()):
        cam_file = next((seq / n for n in ("camera.json", "calib.txt") if (seq / n).exists()), None)
        K = read_camera_file(cam_file).K
        images = sorted(p for p in (seq / "images").iterdir() if p.suffix in (".png", ".jpg"))[:: args.step]
        grays = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in images[:30]]
        for name, (detect, norm) in DETECTORS.items():
            t0 = time.perf_counter()
            feats = [detect(g) for g in grays]
            t1 = time.perf_counter()
            pairs = [_verified(feats[i], feats[i + 1], norm, K) for i in range(len(feats) - 1)]
            t2 = time.perf_counter()
            verified = [v for v, _ in pairs]
            row = {
                "sequence": seq.name,
                "detector": name,
                "verified_min": min(verified),
                "verified_median": float(np.median(verified)),
                "inlier_sampson_px_median": float(np.nanmedian([e for _, e in pairs])),
                "detect_ms_per_image": 1000 * (t1 - t0) / len(feats),
                "match_verify_ms_per_pair": 1000 * (t2 - t1) / len(verified),
            }
            rows.append(row)
            print(
                f"{seq.name:24} {name:20} {row['verified_min']:5d} {row['verified_median']:6.0f} "
                f"{row['inlier_sampson_px_median']:10.3f} "
                f"{row['detect_ms_per_image']:9.1f} {row['match_verify_ms_per_pair']:8.1f}"
            )
    args.out.write_text(
        json.dumps({"benchmark": "features", "rows": rows, "machine": machine_info()}, indent=1)
    )
    print("wrote", args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
