"""Camera intrinsics from a file or a field-of-view guess, fitted to the recording, and undistortion.

Formats read: our camera.json (`Camera.to_dict`), OpenCV YAML/JSON/XML written by cv2.FileStorage
(`camera_matrix`, `distortion_coefficients`, optional `image_width`/`image_height`; YAML and JSON
are parsed in Python, only XML by OpenCV), the YAML of the datasets' own calibrations (EuRoC's
`sensor.yaml` and Kalibr's camchain: `intrinsics` fu fv cu cv, radial-tangential distortion,
`resolution`; ORB-SLAM settings: `Camera.fx` ... or `Camera1.fx` ...), COLMAP
`cameras.txt` (PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV) and KITTI `calib.txt`
(P0..P3 or P_rect_XX). Our pixel centres are integers; COLMAP puts the first pixel's centre at
(0.5, 0.5), so its principal point is shifted by -0.5 on reading.

Size policy (`fit_camera`): a camera whose size equals the recording's is used as is; one whose
aspect ratio matches (within 1 %) is scaled, because downscaled recordings are common; any other
size is an InputError, since intrinsics for another image shape are wrong for this video.
Observations are undistorted point-wise (`Undistorter`), never whole images.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from papl_mapper.errors import InputError
from papl_mapper.map import Camera

log = logging.getLogger(__name__)

DEFAULT_HFOV_DEG = 60.0
MAX_CAMERA_FILE_BYTES = 1 << 20  # calibration files are a few hundred bytes
ASPECT_TOLERANCE = 0.01


@dataclass
class CameraSource:
    """A camera for a recording and where it came from (`guessed` -> the report must say so)."""

    camera: Camera
    source: str  # file path, or "guess (hfov 60 deg)"
    guessed: bool = False
    scaled_from: tuple[int, int] | None = None  # (w, h) of the file's camera when it was scaled


def guess_camera(width: int, height: int, hfov_deg: float = DEFAULT_HFOV_DEG) -> Camera:
    """Square-pixel pinhole with the principal point at the image centre and the given horizontal FOV."""
    if not 1.0 <= hfov_deg < 179.0:
        raise InputError(f"horizontal field of view {hfov_deg} deg is out of range (1..179)")
    f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return Camera(int(width), int(height), f, f, (width - 1) / 2.0, (height - 1) / 2.0, np.zeros(5))


def scale_camera(camera: Camera, width: int, height: int) -> Camera:
    """The same camera for images resized to width x height (integer pixel centres preserved)."""
    sx, sy = width / camera.width, height / camera.height
    return replace(
        camera,
        width=int(width),
        height=int(height),
        fx=camera.fx * sx,
        fy=camera.fy * sy,
        cx=(camera.cx + 0.5) * sx - 0.5,
        cy=(camera.cy + 0.5) * sy - 0.5,
        distortion=np.array(camera.distortion, np.float64),
    )


def fit_camera(camera: Camera, width: int, height: int, name: str = "camera") -> Camera:
    """Return `camera` for a width x height image: as is, scaled if the aspect matches, else InputError."""
    if (camera.width, camera.height) == (width, height):
        return camera
    if camera.width <= 0 or camera.height <= 0:
        return replace(camera, width=int(width), height=int(height))
    aspect_cam = camera.width / camera.height
    aspect_img = width / height
    if abs(aspect_cam / aspect_img - 1.0) > ASPECT_TOLERANCE:
        raise InputError(
            f"{name}: intrinsics are for {camera.width}x{camera.height} images but the recording is "
            f"{width}x{height} (another aspect ratio); give the camera file of this video"
        )
    log.info("%s: scaling intrinsics from %dx%d to %dx%d", name, camera.width, camera.height, width, height)
    return scale_camera(camera, width, height)


def _K(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """The 3x3 intrinsic matrix of focal lengths and principal point (pixels)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _camera_from_K(K: np.ndarray, dist: np.ndarray | None, width: int, height: int, where: str) -> Camera:
    K = np.asarray(K, np.float64).reshape(3, 3)
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(
            f"{where}: camera matrix has non-positive or non-finite focal lengths "
            f"(fx {K[0, 0]:g}, fy {K[1, 1]:g})"
        )
    d = np.zeros(5) if dist is None else np.asarray(dist, np.float64).ravel()
    if not np.isfinite(d).all():
        raise InputError(f"{where}: distortion coefficients are not finite")
    if len(d) < 4 and len(d) > 0:
        d = np.concatenate([d, np.zeros(4 - len(d))])
    if len(d) == 0:
        d = np.zeros(5)
    return Camera(int(width), int(height), K[0, 0], K[1, 1], K[0, 2], K[1, 2], d)


def read_colmap_cameras(path: Path, camera_id: int | None = None) -> Camera:
    """First camera (or `camera_id`) of a COLMAP cameras.txt, principal point moved to integer centres."""
    rows = []
    for lineno, raw in enumerate(path.read_text().splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        tok = line.split()
        if len(tok) < 5:
            raise InputError(f"{path}: line {lineno} is not 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'")
        rows.append((lineno, tok))
    if not rows:
        raise InputError(f"{path}: no camera in this COLMAP cameras.txt")
    if camera_id is not None:
        rows = [r for r in rows if r[1][0] == str(camera_id)]
        if not rows:
            raise InputError(f"{path}: no camera with id {camera_id}")
    elif len(rows) > 1:
        log.warning("%s: %d cameras; using the first (id %s)", path, len(rows), rows[0][1][0])
    lineno, tok = rows[0]
    model = tok[1].upper()
    try:
        w, h = int(tok[2]), int(tok[3])
        p = [float(x) for x in tok[4:]]
    except ValueError as exc:
        raise InputError(f"{path}: line {lineno}: {exc}") from exc
    need = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8}
    if model not in need:
        raise InputError(f"{path}: camera model {model} is not supported (use one of {sorted(need)})")
    if len(p) != need[model]:
        raise InputError(f"{path}: line {lineno}: {model} takes {need[model]} parameters, got {len(p)}")
    dist = np.zeros(5)
    if model == "SIMPLE_PINHOLE":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    elif model == "PINHOLE":
        fx, fy, cx, cy = p
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        dist[0] = p[3]
    elif model == "RADIAL":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        dist[0], dist[1] = p[3], p[4]
    else:  # OPENCV
        fx, fy, cx, cy = p[:4]
        dist[:4] = p[4:8]
    return _camera_from_K(_K(fx, fy, cx - 0.5, cy - 0.5), dist, w, h, str(path))


def read_kitti_calib(path: Path, key: str | None = None) -> Camera:
    """K of one projection matrix of a KITTI calib.txt (P0 by default, else P2, P_rect_00, P_rect_02).

    KITTI files carry no image size: the camera has width = height = 0 and `fit_camera` adopts
    the recording's size.
    """
    mats: dict[str, np.ndarray] = {}
    for raw in path.read_text().splitlines():
        if ":" not in raw:
            continue
        name, _, values = raw.partition(":")
        try:
            nums = np.array([float(v) for v in values.split()], np.float64)
        except ValueError:
            continue
        if len(nums) == 12:
            mats[name.strip()] = nums.reshape(3, 4)
    if not mats:
        raise InputError(f"{path}: no 3x4 projection matrix (P0: ... 12 numbers) in this KITTI calib file")
    order = [key] if key else ["P0", "P2", "P_rect_00", "P_rect_02", *sorted(mats)]
    for k in order:
        if k in mats:
            return _camera_from_K(mats[k][:, :3], None, 0, 0, f"{path} {k}")
    raise InputError(f"{path}: no matrix {key!r}; the file has {sorted(mats)}")


def _read_opencv_storage(path: Path) -> Camera:
    try:
        return _read_opencv_nodes(path)
    except (cv2.error, SystemError, ValueError, TypeError) as exc:  # OpenCV's parser raises these
        cause = exc.__cause__ or exc.__context__ or exc  # SystemError wraps the cv2.error that says why
        reason = (str(cause).strip().splitlines() or [type(cause).__name__])[-1][:160]
        raise InputError(f"{path}: not a readable OpenCV XML camera file ({reason})") from exc


def _read_opencv_nodes(path: Path) -> Camera:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        if not fs.isOpened():
            raise InputError(f"{path}: not an OpenCV XML file")
        K = None
        for name in ("camera_matrix", "cameraMatrix", "K", "intrinsics"):
            node = fs.getNode(name)
            if not node.empty():
                K = _node_array(node)
                break
        if K is None or np.size(K) != 9:
            raise InputError(f"{path}: no 3x3 'camera_matrix' in this OpenCV file")
        dist = None
        for name in ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D"):
            node = fs.getNode(name)
            if not node.empty():
                dist = _node_array(node)
                break
        w = h = 0
        for wname, hname in (("image_width", "image_height"), ("width", "height")):
            if not fs.getNode(wname).empty() and not fs.getNode(hname).empty():
                w, h = int(fs.getNode(wname).real()), int(fs.getNode(hname).real())
                break
        return _camera_from_K(K, dist, w, h, str(path))
    finally:
        fs.release()


def _node_array(node: cv2.FileNode) -> np.ndarray | None:
    """A matrix node (opencv-matrix) or a plain sequence of numbers as an array."""
    if node.isSeq():
        return np.array([node.at(i).real() for i in range(node.size())], np.float64)
    mat = node.mat()
    return None if mat is None else np.asarray(mat, np.float64)


_RADTAN = ("radial-tangential", "radtan", "plumb_bob", "none")
"""Kalibr's / EuRoC's names of OpenCV's k1 k2 p1 p2 distortion (our model)."""


def _read_dataset_yaml(path: Path, data: dict) -> Camera:
    """EuRoC's sensor.yaml or one camera of a Kalibr camchain: `intrinsics` [fu, fv, cu, cv],
    `distortion_coefficients` (or `distortion_coeffs`) k1 k2 p1 p2 and `resolution` [w, h]."""
    model = str(data.get("camera_model", "pinhole")).lower()
    dist_model = str(data.get("distortion_model", "radial-tangential")).lower()
    if model != "pinhole" or dist_model not in _RADTAN:
        raise InputError(
            f"{path}: camera model {model} with {dist_model} distortion is not supported (a pinhole "
            "camera with radial-tangential distortion is; undistort the images first)"
        )
    try:
        fu, fv, cu, cv = (float(v) for v in data["intrinsics"])
        w, h = (_size(v) for v in data.get("resolution", (0, 0)))
        dist = _first(data, ("distortion_coefficients", "distortion_coeffs"))
        dist_arr = None if dist is None else np.array(dist, float).ravel()
    except (TypeError, ValueError) as exc:
        raise InputError(f"{path}: not a valid EuRoC / Kalibr camera file ({exc})") from exc
    return _camera_from_K(_K(fu, fv, cu, cv), dist_arr, w, h, str(path))


def _read_orbslam_yaml(path: Path, data: dict) -> Camera:
    """An ORB-SLAM2 (`Camera.fx` ...) or ORB-SLAM3 (`Camera1.fx` ..., `Camera.type`) settings file."""
    prefix = "Camera1." if "Camera1.fx" in data else "Camera."
    kind = str(data.get("Camera.type", "PinHole")).lower()
    if kind != "pinhole":
        raise InputError(f"{path}: camera type {kind} is not supported (a pinhole camera is)")
    try:
        f = {k: float(data[prefix + k]) for k in ("fx", "fy", "cx", "cy")}
        dist = [float(data.get(prefix + k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")]
        w = _size(data.get("Camera.width", data.get(prefix + "width", 0)))
        h = _size(data.get("Camera.height", data.get(prefix + "height", 0)))
    except KeyError as exc:
        raise InputError(f"{path}: ORB-SLAM settings without {exc.args[0]}") from exc
    except (TypeError, ValueError) as exc:
        raise InputError(f"{path}: not a valid ORB-SLAM settings file ({exc})") from exc
    return _camera_from_K(_K(f["fx"], f["fy"], f["cx"], f["cy"]), np.array(dist), w, h, str(path))


def _read_mapping(path: Path, data: dict) -> Camera:
    """camera.json (`fx` ...), a mapping with a 3x3 `camera_matrix` (plain JSON, OpenCV JSON/YAML), or
    a dataset's own calibration (EuRoC / Kalibr `intrinsics`, ORB-SLAM `Camera.fx`)."""
    if "Camera.fx" in data or "Camera1.fx" in data:
        return _read_orbslam_yaml(path, data)
    if "fx" not in data and "camera_matrix" not in data and isinstance(data.get("cam0"), dict):
        log.info("%s: a Kalibr camchain, its cam0 used", path)
        data = data["cam0"]
    intrinsics = data.get("intrinsics")
    if isinstance(intrinsics, list) and len(intrinsics) == 4:
        return _read_dataset_yaml(path, data)
    if "fx" in data:
        try:
            keys = ("width", "height", "fx", "fy", "cx", "cy", "distortion", "model")
            cam = Camera.from_dict({k: data[k] for k in keys if k in data})
        except (TypeError, ValueError) as exc:
            raise InputError(f"{path}: not a valid camera.json: {exc}") from exc
        return _camera_from_K(cam.K, cam.distortion, cam.width, cam.height, str(path))
    K = _first(data, ("camera_matrix", "cameraMatrix", "K", "intrinsics"))
    if K is None:
        raise InputError(f"{path}: neither 'fx' nor 'camera_matrix' in this camera file")
    dist = _first(data, ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D", "distortion"))
    try:
        w = _size(_first(data, ("image_width", "width")) or 0)
        h = _size(_first(data, ("image_height", "height")) or 0)
        dist_arr = None if dist is None else np.array(dist, float).ravel()
        K_arr = np.array(K, np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{path}: not a valid camera file ({exc})") from exc
    if K_arr.size != 9:
        raise InputError(f"{path}: camera_matrix is not 3x3 (it has {K_arr.size} numbers)")
    return _camera_from_K(K_arr, dist_arr, w, h, str(path))


def _first(data: dict, names: tuple[str, ...]) -> object:
    """The value of the first of `names` in `data` (an opencv-matrix mapping as its `data` list)."""
    for name in names:
        if name in data:
            value = data[name]
            return value["data"] if isinstance(value, dict) and "data" in value else value
    return None


def _read_opencv_yaml(path: Path, text: str) -> Camera:
    """An OpenCV FileStorage YAML file, parsed by PyYAML's safe loader rather than OpenCV's parser:
    OpenCV 5.0's parser corrupted the heap on mutated files (tests/test_fuzz_inputs.py found it)."""
    import yaml

    class Loader(yaml.SafeLoader):
        """Safe YAML plus OpenCV's `!!opencv-matrix` tags, read as plain mappings."""

    for tag in ("opencv-matrix", "opencv-nd-matrix"):
        Loader.add_constructor(
            f"tag:yaml.org,2002:{tag}", lambda loader, node: loader.construct_mapping(node)
        )
    lines = text.splitlines()
    if lines and lines[0].startswith("%YAML"):  # OpenCV writes "%YAML:1.0", which YAML itself refuses
        lines = lines[1:]
    try:
        data = yaml.load("\n".join(lines), Loader)  # noqa: S506 - a SafeLoader subclass
    except (yaml.YAMLError, ValueError, TypeError, RecursionError) as exc:
        reason = " ".join(str(exc).split())[:160]
        raise InputError(f"{path}: not a readable OpenCV YAML camera file ({reason})") from exc
    if not isinstance(data, dict):
        raise InputError(f"{path}: an OpenCV YAML camera file must hold a mapping, not {type(data).__name__}")
    return _read_mapping(path, data)


def _size(value: object) -> int:
    """An image width or height from a camera file: a whole number in 0..65536, else ValueError."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value):
        raise ValueError(f"image size {value!r:.40} is not a whole number")
    if not 0 <= value <= 1 << 16:
        raise ValueError(f"image size {value} is out of range (0..65536)")
    return int(value)


def read_camera_file(path: str | Path) -> Camera:
    """Intrinsics from any supported file, chosen by content (see module doc). Size 0x0 = unknown."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: camera file not found")
    if path.stat().st_size > MAX_CAMERA_FILE_BYTES:
        raise InputError(f"{path}: {path.stat().st_size:,} bytes is too large for a camera file")
    suffix = path.suffix.lower()
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a text camera file") from exc
    except OSError as exc:
        raise InputError(f"{path}: cannot read the camera file ({exc.strerror or exc})") from exc
    if suffix == ".json" or text.lstrip().startswith("{"):
        try:
            data = json.loads(text)
        except (json.JSONDecodeError, RecursionError) as exc:
            raise InputError(f"{path}: not valid JSON ({exc})") from exc
        if not isinstance(data, dict):
            raise InputError(f"{path}: a JSON camera file must hold an object, not a {type(data).__name__}")
        return _read_mapping(path, data)
    if suffix in (".yml", ".yaml") or text.lstrip().startswith("%YAML"):
        return _read_opencv_yaml(path, text)
    if suffix == ".xml":
        return _read_opencv_storage(path)
    stripped = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if stripped and any(ln.split(":")[0].strip().startswith("P") and ":" in ln for ln in stripped):
        return read_kitti_calib(path)
    if stripped and len(stripped[0].split()) >= 5 and stripped[0].split()[1].replace("_", "").isalpha():
        return read_colmap_cameras(path)
    raise InputError(
        f"{path}: unrecognised camera file; use camera.json, OpenCV YAML/JSON, COLMAP cameras.txt "
        "or KITTI calib.txt"
    )


def camera_for_recording(
    path: str | Path | None, width: int, height: int, hfov_deg: float = DEFAULT_HFOV_DEG
) -> CameraSource:
    """The camera of a width x height recording: from a file (fitted, see `fit_camera`), or guessed."""
    if path is None:
        cam = guess_camera(width, height, hfov_deg)
        log.warning(
            "no camera file given: guessing intrinsics from a %.0f deg horizontal field of view "
            "(fx = %.1f px); give --camera for a metric-quality map",
            hfov_deg,
            cam.fx,
        )
        return CameraSource(cam, f"guess (hfov {hfov_deg:g} deg)", guessed=True)
    cam = read_camera_file(path)
    original = (cam.width, cam.height)
    fitted = fit_camera(cam, width, height, str(path))
    check_intrinsics(fitted, str(path))
    check_distortion(fitted, str(path))
    scaled = original if original != (width, height) and cam.width > 0 else None
    return CameraSource(fitted, str(path), guessed=False, scaled_from=scaled)


def check_intrinsics(camera: Camera, name: str) -> None:
    """InputError when the focal lengths give a field of view outside 1..179 deg (the range `guess_camera`
    accepts): a wrong file, or one for another image size."""
    for f, size, axis in ((camera.fx, camera.width, "horizontal"), (camera.fy, camera.height, "vertical")):
        fov = math.degrees(2 * math.atan2(size / 2.0, abs(f)))
        if not 1.0 <= fov < 179.0:
            raise InputError(
                f"{name}: implausible focal length {f:g} px for {camera.width}x{camera.height} images "
                f"({axis} field of view {fov:.4g} deg, expected 1..179); check the camera file"
            )


MAX_CORNER_STRETCH = 2.5
"""Largest factor by which undistortion may move the image corners away from the centre (barrel
distortion): wide-angle lenses reach about 1.5 within the pinhole-plus-radial model; beyond, it is a
wrong file."""
MAX_CORNER_SQUEEZE = 1.5
"""Largest factor by which undistortion may move the image corners towards the centre (pincushion
distortion): lenses stay within a few percent; a third of the radius is already a wrong file."""


def check_distortion(camera: Camera, name: str) -> None:
    """InputError when the radial distortion folds the image (not monotonic out to its corners) or
    stretches its corners by more than `MAX_CORNER_STRETCH`: coefficients from another model or order."""
    d = np.zeros(5)
    dist = np.asarray(camera.distortion, np.float64).ravel()[:5]
    d[: len(dist)] = dist
    k1, k2, k3 = d[0], d[1], d[4]
    if not (k1 or k2 or k3) or camera.width <= 0:
        return
    corners = np.array(
        [[0, 0], [camera.width - 1, 0], [0, camera.height - 1], [camera.width - 1, camera.height - 1]]
    )
    rc = float(np.max(np.linalg.norm((corners - [camera.cx, camera.cy]) / [camera.fx, camera.fy], axis=1)))
    r = np.linspace(0.0, MAX_CORNER_STRETCH * rc, 4001)
    with np.errstate(over="ignore", invalid="ignore"):  # absurd coefficients overflow: then not rising
        rd = r * (1 + k1 * r**2 + k2 * r**4 + k3 * r**6)
        rising = np.diff(rd) > 0
    branch = len(rising) if rising.all() else int(np.argmin(rising))  # monotonic part from the centre
    if branch == 0 or rd[branch] < rc:
        raise InputError(
            f"{name}: implausible distortion (k1 {k1:g}, k2 {k2:g}, k3 {k3:g}): it folds the image back "
            f"before its corners, or moves them more than {MAX_CORNER_STRETCH:g} times further out; check "
            "the coefficients and their order (k1 k2 p1 p2 k3)"
        )
    ru = float(np.interp(rc, rd[: branch + 1], r[: branch + 1]))
    if ru < rc / MAX_CORNER_SQUEEZE:
        raise InputError(
            f"{name}: implausible distortion (k1 {k1:g}, k2 {k2:g}, k3 {k3:g}): the image corners undistort "
            f"to {ru / rc:.3f} times their radius, squeezing the view; check the coefficients and their "
            "order (k1 k2 p1 p2 k3)"
        )


class Undistorter:
    """Maps distorted pixels of `camera` to undistorted pixels of the same K (zero distortion)."""

    def __init__(self, camera: Camera):
        self.camera = camera
        self.K = camera.K
        self.dist = np.asarray(camera.distortion, np.float64).ravel()
        self.identity = not np.any(self.dist)

    @property
    def undistorted_camera(self) -> Camera:
        return replace(self.camera, distortion=np.zeros(5))

    def points(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) distorted pixels -> (N, 2) float64 undistorted pixels."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        if self.identity or len(uv) == 0:
            return uv.copy()
        out = cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, self.dist, P=self.K)
        return out.reshape(-1, 2).astype(np.float64)

    def segments(self, xy: np.ndarray) -> np.ndarray:
        """(S, 4) distorted endpoints x1 y1 x2 y2 -> (S, 4) float64 undistorted endpoints."""
        xy = np.asarray(xy, np.float64).reshape(-1, 4)
        return self.points(xy.reshape(-1, 2)).reshape(-1, 4)
