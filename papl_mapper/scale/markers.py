"""Scale from fiducial markers of known size: ArUco corners detected in the keyframes, triangulated
from the keyframe poses, the scale the known side length over the triangulated one.

A spec reads `aruco:DICT:ID=SIZE_M` (e.g. `aruco:4X4_50:7=0.2`, the side of the black square in
metres). Views at a grazing angle to the marker's plane (judged from each view's planar pose of the
square, which needs no scale) and views whose corners reproject badly are left out before the final
triangulation; a square of free pose and side is then fitted to the detections of the kept views
(known shape: it holds the depth that independently triangulated corners leave loose when the views
line up with the marker). The uncertainty is the larger of the fit's own and a jackknife over the
views.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from papl_mapper.errors import InputError
from papl_mapper.geometry import triangulate_points
from papl_mapper.geometry.se3 import project_points
from papl_mapper.map import Map

from .estimate import ScaleEstimate

log = logging.getLogger(__name__)

#: ArUco dictionary names as users write them (upper case, without DICT_) -> OpenCV's constant
DICTIONARIES: dict[str, int] = {
    n[5:].upper(): getattr(cv2.aruco, n) for n in dir(cv2.aruco) if n.startswith("DICT_")
}


@dataclass(frozen=True)
class MarkerSpec:
    """One fiducial marker: its ArUco dictionary, id and side length in metres."""

    dictionary: str  # e.g. "4X4_50"
    marker_id: int
    size_m: float

    @property
    def label(self) -> str:
        return f"marker aruco:{self.dictionary}:{self.marker_id}={self.size_m:g}"


def parse_marker_spec(text: str) -> MarkerSpec:
    """`aruco:DICT:ID=SIZE_M` -> MarkerSpec; InputError naming --marker and the fault."""
    where = f"--marker {text!r}"
    kind, sep, rest = text.partition(":")
    if not sep or kind.lower() != "aruco":
        raise InputError(f"{where}: expected aruco:DICT:ID=SIZE_M, e.g. aruco:4X4_50:7=0.2")
    name, sep, rest = rest.partition(":")
    if not sep:
        raise InputError(f"{where}: expected aruco:DICT:ID=SIZE_M, e.g. aruco:4X4_50:7=0.2")
    key = name.upper().removeprefix("DICT_")
    if key not in DICTIONARIES:
        raise InputError(
            f"{where}: unknown ArUco dictionary {name!r}; known: {', '.join(sorted(DICTIONARIES))}"
        )
    id_text, sep, size_text = rest.partition("=")
    try:
        marker_id = int(id_text)
        size = float(size_text)
    except ValueError:
        raise InputError(f"{where}: ID must be an integer and SIZE_M a number of metres") from None
    if not sep or not (math.isfinite(size) and size > 0):
        raise InputError(f"{where}: SIZE_M must be a positive side length in metres")
    n_ids = cv2.aruco.getPredefinedDictionary(DICTIONARIES[key]).bytesList.shape[0]
    if not 0 <= marker_id < n_ids:
        raise InputError(f"{where}: dictionary {key} has ids 0..{n_ids - 1}, not {marker_id}")
    return MarkerSpec(key, marker_id, size)


def keyframe_images(frames: Iterable, m: Map) -> Iterator[tuple[int, np.ndarray]]:
    """(keyframe row, image) for every frame (objects with .index and .image) that is a keyframe."""
    row_of = {int(f): k for k, f in enumerate(m.keyframes.frame_index)}
    for frame in frames:
        k = row_of.get(int(frame.index))
        if k is not None:
            yield k, frame.image


def detect_markers(
    images: Iterable[tuple[int, np.ndarray]], specs: list[MarkerSpec]
) -> dict[MarkerSpec, list[tuple[int, np.ndarray]]]:
    """For each spec, the (keyframe row, corners (4, 2) pixels) of every image it is detected in."""
    detectors = {}
    for name in {s.dictionary for s in specs}:
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        detectors[name] = cv2.aruco.ArucoDetector(
            cv2.aruco.getPredefinedDictionary(DICTIONARIES[name]), params
        )
    found: dict[MarkerSpec, list[tuple[int, np.ndarray]]] = {s: [] for s in specs}
    for row, image in images:
        gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        for name, det in detectors.items():
            corners, ids, _ = det.detectMarkers(gray)
            if ids is None:
                continue
            for c, i in zip(corners, ids.ravel().tolist(), strict=True):
                for s in specs:
                    if s.dictionary == name and s.marker_id == i:
                        found[s].append((row, c.reshape(4, 2).astype(np.float64)))
    return found


def view_angles_deg(corners_px: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(V,) the angle between each view's ray to the marker and the marker's normal, from the planar
    pose of its four corners (V, 4, 2) alone (IPPE, independent of the map's scale)."""
    square = np.array([[-0.5, 0.5, 0], [0.5, 0.5, 0], [0.5, -0.5, 0], [-0.5, -0.5, 0]], np.float64)
    out = np.full(len(corners_px), 90.0)
    for i, c in enumerate(corners_px):
        ok, rvec, tvec = cv2.solvePnP(square, c.reshape(4, 1, 2), K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        if ok:
            normal = cv2.Rodrigues(rvec)[0][:, 2]
            ray = tvec.ravel() / np.linalg.norm(tvec)
            out[i] = math.degrees(math.acos(min(1.0, abs(float(normal @ ray)))))
    return out


def _triangulate(m: Map, rows: np.ndarray, corners_px: np.ndarray) -> tuple[np.ndarray, bool]:
    """(4, 3) marker corners from views `rows` (V,) with undistorted pixels (V, 4, 2)."""
    K = m.camera.K
    T = np.repeat(m.keyframes.T_wc[rows], 4, axis=0)
    X, ok = triangulate_points(np.tile(np.arange(4), len(rows)), T, K, corners_px.reshape(-1, 2), 4, 0.5)
    return X, bool(ok.all())


def fit_square(
    X0: np.ndarray, T_wc: np.ndarray, K: np.ndarray, corners_px: np.ndarray
) -> tuple[float, np.ndarray, float]:
    """(side, corners (4, 3), relative sigma of the side): the square of free pose and side whose
    corners reproject closest to the detections (V, 4, 2) in the views T_wc (V, 4, 4), from the
    triangulated corners X0 (4, 3). The known shape holds the depth that four independently
    triangulated corners leave loose when the views line up with the marker."""
    from scipy.optimize import least_squares

    x = (X0[1] - X0[0]) + (X0[2] - X0[3])
    y = (X0[0] - X0[3]) + (X0[1] - X0[2])
    x /= np.linalg.norm(x)
    y -= (y @ x) * x
    y /= np.linalg.norm(y)
    R0 = np.stack([x, y, np.cross(x, y)], axis=1)
    unit = np.array([[-0.5, 0.5, 0], [0.5, 0.5, 0], [0.5, -0.5, 0], [-0.5, -0.5, 0]])  # TL, TR, BR, BL

    def corners(p: np.ndarray) -> np.ndarray:
        R = cv2.Rodrigues(p[3:6])[0] @ R0
        return p[:3] + math.exp(p[6]) * unit @ R.T

    def residuals(p: np.ndarray) -> np.ndarray:
        uv, _ = project_points(K, T_wc[:, None], corners(p)[None])
        return (uv - corners_px).ravel()

    side0 = float(_side_ratios(X0).mean())
    p0 = np.concatenate([X0.mean(axis=0), np.zeros(3), [math.log(side0)]])
    res = least_squares(residuals, p0, method="lm", x_scale=np.r_[np.full(3, side0), np.ones(3), 1.0])
    dof = max(res.fun.size - 7, 1)
    J = res.jac
    try:
        cov = np.linalg.inv(J.T @ J) * float(res.fun @ res.fun) / dof
        rel = math.sqrt(max(float(cov[6, 6]), 0.0))
    except np.linalg.LinAlgError:
        rel = float("inf")
    return math.exp(res.x[6]), corners(res.x), rel


def _side_ratios(X: np.ndarray) -> np.ndarray:
    """(6,) the four sides and the two diagonals over sqrt(2): each an estimate of the side length."""
    sides = np.linalg.norm(X - np.roll(X, -1, axis=0), axis=1)
    diag = np.linalg.norm(X[[2, 3]] - X[[0, 1]], axis=1) / math.sqrt(2)
    return np.concatenate([sides, diag])


def marker_scale(
    m: Map,
    spec: MarkerSpec,
    detections: list[tuple[int, np.ndarray]],
    max_view_angle_deg: float = 75.0,
    max_reprojection_px: float = 2.0,
    min_side_px: float = 20.0,
) -> ScaleEstimate:
    """Scale from one marker's detections; InputError when it is unseen, seen once, or only grazing."""
    n_kf = len(m.keyframes)
    if not detections:
        raise InputError(f"{spec.label}: never detected in the {n_kf} keyframes; check the dictionary and id")
    rows = np.array([r for r, _ in detections], np.int64)
    if len(np.unique(rows)) < 2:
        raise InputError(
            f"{spec.label}: seen in one keyframe only; it needs two or more views from different places"
        )
    cam = m.camera
    raw = np.stack([c for _, c in detections])  # (V, 4, 2)
    px = cv2.undistortPoints(raw.reshape(-1, 1, 2), cam.K, np.asarray(cam.distortion), P=cam.K).reshape(
        raw.shape
    )
    angle = view_angles_deg(px, cam.K)
    facing = angle <= max_view_angle_deg
    if facing.sum() < 2:
        raise InputError(
            f"{spec.label}: seen only at grazing angles ({int((~facing).sum())} of {len(rows)} views more "
            f"than {max_view_angle_deg:g} degrees off its normal); film it more face-on"
        )
    big = np.linalg.norm(px - np.roll(px, -1, axis=1), axis=2).min(axis=1) >= min_side_px
    keep = facing & big
    if keep.sum() < 2:
        raise InputError(
            f"{spec.label}: seen face-on in {int(facing.sum())} views, but in all but {int(keep.sum())} "
            f"its sides are under {min_side_px:g} pixels; film it from closer"
        )
    # a map that drifts places far-apart views of one marker inconsistently: drop the worst view
    # until every view reprojects the triangulated corners within max_reprojection_px
    while True:
        X, ok = _triangulate(m, rows[keep], px[keep])
        if not ok:
            raise InputError(f"{spec.label}: its views have too little parallax to triangulate its corners")
        uv, _ = project_points(cam.K, m.keyframes.T_wc[rows][:, None], X[None])  # (V, 4, 2)
        err = np.where(keep, np.linalg.norm(uv - px, axis=2).max(axis=1), -1.0)
        worst = int(np.argmax(err))
        if err[worst] <= max_reprojection_px:
            break
        if keep.sum() <= 2:
            raise InputError(
                f"{spec.label}: its corners do not agree between views (reprojection {err[worst]:.1f} px)"
            )
        keep[worst] = False
    rows, px = rows[keep], px[keep]
    T = m.keyframes.T_wc[rows]
    side, X, rel_fit = fit_square(X, T, cam.K, px)
    rel_jack = 0.0
    if len(rows) >= 4:  # how much the side moves when one view is left out: pose errors show here
        sub = np.array(
            [fit_square(X, np.delete(T, i, 0), cam.K, np.delete(px, i, 0))[0] for i in range(len(rows))]
        )
        rel_jack = math.sqrt((len(sub) - 1) / len(sub) * float(((sub - sub.mean()) ** 2).sum())) / side
    scale, rel = spec.size_m / side, max(rel_fit, rel_jack)
    log.info(
        "%s: %d views (%d left out), side %.6g map units", spec.label, len(rows), int((~keep).sum()), side
    )
    return ScaleEstimate(
        scale,
        rel,
        "marker",
        f"ArUco {spec.dictionary} id {spec.marker_id} ({spec.size_m:g} m) in {len(rows)} keyframes",
        {
            "dictionary": spec.dictionary,
            "id": spec.marker_id,
            "size_m": spec.size_m,
            "views": int(len(rows)),
            "views_left_out": int((~keep).sum()),
            "corners_w": X.tolist(),
        },
    )
