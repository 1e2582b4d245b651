"""Decoding of recordings: video files through OpenCV's FFmpeg backend, and image folders.

`open_recording` checks the input once (it decodes the first two frames) and returns a `Recording`
that can be iterated any number of times; each pass decodes in a background thread into a
bounded queue so decoding overlaps processing.

Bad input is handled per frame. A frame that does not decode (an image file that is corrupt,
truncated, empty or of another size than the folder's images; a video frame whose data is
damaged while later frames decode) is skipped, and the pass goes on: the frames that decode
keep their own index and timestamp (a skipped frame leaves a gap, it shifts nothing), and the
skipped ones are listed in `Recording.bad_frames` with a one-line reason each. A video whose
stream ends before its announced length yields what is readable; where it stopped is logged
and kept on the Recording (`stopped_early`, `stop_message`). `open_recording` raises
InputError when no frame, or only one frame beside bad ones, decodes.
"""

from __future__ import annotations

import itertools
import logging
import queue
import re
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from papl_mapper.errors import InputError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")
_END = object()
_MAX_BAD_RUN = 1000  # failed grabs in a row after which a video stream counts as ended (length unknown)
_REFERENCE_IMAGES = 3  # decodable images of a folder whose most common size is the folder's size
_TIME_TOL_S = 1e-6  # time-range bounds are met within a microsecond (clock times carry 2e-7 s rounding)


@dataclass
class Frame:
    """One decoded frame: its index in the source, its time, and the (possibly downscaled) image."""

    index: int  # index of the frame in the source (before the step is applied)
    timestamp_s: float
    image: np.ndarray  # (H, W, 3) uint8 BGR or (H, W) uint8 gray


@dataclass(frozen=True)
class BadFrame:
    """A frame of the selection that could not be decoded and was skipped.

    `index` is the frame's index in the source (the index it would have had as a Frame),
    `name` the image file's name (folders) or "frame <index> at <t> s" (videos), `timestamp_s`
    its time (from timestamps.txt / fps for folders; estimated from the previous frame for a
    video frame, whose data gave none), `reason` one line such as "truncated PNG".
    `str(bad)` is "<name> (<reason>)".
    """

    index: int
    name: str
    timestamp_s: float
    reason: str

    def __str__(self) -> str:
        return f"{self.name} ({self.reason})"


def describe_bad_frames(bad: list[BadFrame], limit: int = 5) -> str:
    """One line: '3 frames could not be decoded and were skipped: a.png (empty file), ...'.

    At most `limit` frames are named, then "and <k> more"; "" when `bad` is empty.
    """
    if not bad:
        return ""
    verb = "frame could not be decoded and was" if len(bad) == 1 else "frames could not be decoded and were"
    return f"{len(bad)} {verb} skipped: {_list_bad(bad, limit)}"


def _list_bad(bad: list[BadFrame], limit: int) -> str:
    more = f" and {len(bad) - limit} more" if len(bad) > limit else ""
    return ", ".join(str(b) for b in bad[:limit]) + more


@dataclass
class Recording:
    """A video file or image folder opened for decoding, with the frame selection applied.

    `width`/`height` are the size of the yielded images (after `max_size`); `scale_xy` maps
    source pixels to them (use `papl_mapper.frontend.camera.scale_camera` on a source camera).
    `stopped_early`/`stop_message` are set by a pass that ended before the stream's announced end.

    `bad_frames: list[BadFrame]` lists the frames of the selection (range and step applied)
    that did not decode and were skipped, in source order; each pass starts it afresh and
    appends as it goes, so after a complete pass it is that pass's whole list (empty right after
    `open_recording`). `bad_frames_message()` is the one-line summary for a log or report.
    A video's stream ending early is not a bad frame: that is `stopped_early`.
    """

    path: Path
    kind: str  # "video" or "images"
    source_width: int
    source_height: int
    width: int
    height: int
    fps: float  # frames per second of the source (nominal)
    frame_count: int  # frames announced by the container or files in the folder (0 if unknown)
    step: int = 1
    start_s: float | None = None
    end_s: float | None = None
    gray: bool = False
    prefetch: int = 8
    image_files: list[Path] = field(default_factory=list)
    image_timestamps: np.ndarray | None = None  # (N,) seconds for image folders, None -> index / fps
    stopped_early: bool = False
    stopped_at_frame: int | None = None  # source index of the last frame decoded in a pass that ended early
    stop_message: str = ""
    decoded_frames: int = 0  # frames yielded by the last complete pass
    bad_frames: list[BadFrame] = field(default_factory=list)  # skipped frames of the current/last pass

    @property
    def time_origin_s(self) -> float:
        """The time start_s and end_s count from: the first image's timestamp in a folder with timestamps
        (TUM and KITTI write clock times), 0 for a video and a folder without."""
        if self.kind == "images" and self.image_timestamps is not None and len(self.image_timestamps):
            return float(self.image_timestamps[0])
        return 0.0

    @property
    def scale_xy(self) -> tuple[float, float]:
        return self.width / self.source_width, self.height / self.source_height

    @property
    def size(self) -> tuple[int, int]:
        return self.width, self.height

    def bad_frames_message(self, limit: int = 5) -> str:
        """One line naming the skipped frames ("" when none): see `describe_bad_frames`."""
        return describe_bad_frames(self.bad_frames, limit)

    def expected_frames(self) -> int:
        """Frames a pass will yield if the stream is intact (0 when the container does not say)."""
        if self.frame_count <= 0:
            return 0
        indices = np.arange(self.frame_count)
        if self.kind == "images" and self.image_timestamps is not None:
            times = self.image_timestamps
        else:
            times = indices / self.fps
        times = times - self.time_origin_s
        keep = np.ones(self.frame_count, bool)
        if self.start_s is not None:
            keep &= times >= self.start_s - _TIME_TOL_S
        if self.end_s is not None:
            keep &= times <= self.end_s + _TIME_TOL_S
        kept = indices[keep]
        if len(kept) == 0:
            return 0
        return len(kept[:: self.step])

    def __iter__(self) -> Iterator[Frame]:
        """Decode in a background thread (bounded queue); stop the thread if the consumer stops."""
        q: queue.Queue = queue.Queue(maxsize=max(1, self.prefetch))
        stop = threading.Event()
        main = threading.main_thread()

        def put(item: object) -> bool:
            # a consumer that never closes this generator still lets the interpreter exit: it stops
            # the main thread first, then joins this (non-daemon) thread
            while not stop.is_set() and main.is_alive():
                try:
                    q.put(item, timeout=0.1)
                    return True
                except queue.Full:
                    continue
            return False

        def worker() -> None:
            try:
                for frame in self._decode():
                    if not put(frame):
                        return
            except BaseException as exc:  # handed to the consumer, re-raised there
                put(exc)
                return
            put(_END)

        # not a daemon: a daemon thread still inside OpenCV when the interpreter exits is unwound
        # through C++ and aborts the process ("terminate called without an active exception")
        thread = threading.Thread(target=worker, name=f"decode-{self.path.name}")
        try:
            thread.start()  # Ctrl-C can land in start(), after the thread runs: the finally stops it
            while True:
                item = q.get()
                if item is _END:
                    return
                if isinstance(item, BaseException):
                    raise item
                yield item
        finally:
            stop.set()  # the thread leaves at its next frame
            if thread.is_alive():
                thread.join()

    def frames(self) -> Iterator[Frame]:
        """Decode in the calling thread (no prefetch); same frames as iterating the Recording."""
        return self._decode()

    # -- decoding -----------------------------------------------------------------------------

    def _prepare(self, image: np.ndarray) -> np.ndarray:
        if image.ndim == 3 and image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
        if image.ndim == 2 and not self.gray:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        if image.shape[1] != self.width or image.shape[0] != self.height:
            image = cv2.resize(image, (self.width, self.height), interpolation=cv2.INTER_AREA)
        if self.gray and image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        return image

    def _in_range(self, t: float) -> int:
        """-1 before the time range, 0 inside, 1 after it (t on the recording's clock)."""
        t = t - self.time_origin_s
        if self.start_s is not None and t < self.start_s - _TIME_TOL_S:
            return -1
        if self.end_s is not None and t > self.end_s + _TIME_TOL_S:
            return 1
        return 0

    def _skip(self, index: int, name: str, t: float, reason: str) -> None:
        self.bad_frames.append(BadFrame(index, name, t, reason))
        log.debug("%s: skipped %s (%s)", self.path, name, reason)

    def _decode(self) -> Iterator[Frame]:
        self.stopped_early, self.stopped_at_frame, self.stop_message = False, None, ""
        self.bad_frames = []
        source = self._decode_video() if self.kind == "video" else self._decode_images()
        n = 0
        for frame in source:
            n += 1
            yield frame
        self.decoded_frames = n

    def _decode_video(self) -> Iterator[Frame]:
        cap = cv2.VideoCapture(str(self.path), cv2.CAP_FFMPEG)
        if not cap.isOpened():
            raise InputError(f"{self.path}: the video could not be reopened for decoding")
        try:
            index = -1  # source index of the latest frame, grabbed or failed
            last_grab = -1  # source index of the latest frame grabbed
            last_t = 0.0
            last_ok = None
            kept = 0
            failed = 0  # failed grabs in a row
            pending: list[BadFrame] = []  # failed frames that count as bad once a later frame grabs
            while True:
                if not cap.grab():
                    # a damaged packet fails one grab and the next frame grabs again; at the end of
                    # the stream every grab fails (cheaply), so try as long as frames may remain
                    failed += 1
                    remaining = self.frame_count - (last_grab + 1)
                    if failed > (max(30, remaining) if self.frame_count > 0 else _MAX_BAD_RUN):
                        break
                    index += 1
                    t = last_t + (index - last_grab) / self.fps if last_grab >= 0 else index / self.fps
                    where = self._in_range(t)
                    if where > 0:
                        break
                    if where == 0:
                        if kept % self.step == 0:
                            pending.append(
                                BadFrame(index, f"frame {index} at {t:.3f} s", t, "its data does not decode")
                            )
                        kept += 1
                    continue
                index += 1
                last_grab, failed = index, 0
                for bad in pending:
                    self._skip(bad.index, bad.name, bad.timestamp_s, bad.reason)
                pending.clear()
                t = last_t = _video_time(cap, index, self.fps)
                where = self._in_range(t)
                if where > 0:
                    return
                if where < 0:
                    continue
                if kept % self.step:
                    kept += 1
                    continue
                kept += 1
                ok, image = cap.retrieve()
                name = f"frame {index} at {t:.3f} s"
                if not ok or image is None:
                    self._skip(index, name, t, "grabbed but could not be converted to an image")
                    continue
                if image.shape[:2] != (self.source_height, self.source_width):
                    self._skip(
                        index,
                        name,
                        t,
                        f"{image.shape[1]}x{image.shape[0]}, not the stream's "
                        f"{self.source_width}x{self.source_height}",
                    )
                    continue
                last_ok = index
                yield Frame(index, t, self._prepare(image))
            announced = self.frame_count
            # containers may count one frame more than FFmpeg delivers; more missing is a truncation
            if announced > 0 and last_grab + 1 < announced - 1 and self.end_s is None:
                self._mark_stop(
                    last_ok if last_ok is not None else last_grab,
                    f"the stream ended after {last_grab + 1} of {announced} announced frames "
                    "(truncated or corrupt)",
                )
        finally:
            cap.release()

    def _decode_images(self) -> Iterator[Frame]:
        kept = 0
        flags = cv2.IMREAD_GRAYSCALE if self.gray else cv2.IMREAD_COLOR
        for index, path in enumerate(self.image_files):
            t = float(self.image_timestamps[index]) if self.image_timestamps is not None else index / self.fps
            where = self._in_range(t)
            if where > 0:
                return
            if where < 0:
                continue
            if kept % self.step:
                kept += 1
                continue
            kept += 1
            image, reason = _read_image(path, flags)
            if image is not None and image.shape[:2] != (self.source_height, self.source_width):
                size = f"{self.source_width}x{self.source_height}"
                image, reason = None, f"{image.shape[1]}x{image.shape[0]}, not the folder's {size}"
            if image is None:
                self._skip(index, path.name, t, reason)
                continue
            yield Frame(index, t, self._prepare(image))

    def _mark_stop(self, last_index: int, message: str) -> None:
        self.stopped_early = True
        self.stopped_at_frame = last_index
        self.stop_message = message
        log.warning("%s: %s; kept the frames up to index %d", self.path, message, last_index)


def _read_image(path: Path, flags: int) -> tuple[np.ndarray | None, str]:
    """The decoded image and "", or None and a one-line reason why it does not decode."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        return None, f"unreadable: {exc.strerror or exc}"
    if not data:
        return None, "empty file"
    fmt = _image_format(data)
    if fmt == "JPEG" and not _jpeg_complete(data):
        return None, "truncated JPEG"  # some libjpeg builds fill the missing part with grey
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error:
        image = None
    if image is not None and image.size:
        return image, ""
    if fmt is None:
        kind = path.suffix.lstrip(".").upper() or "an image"
        return None, f"not a {kind} file (unrecognised content)"
    if fmt == "PNG" and not _png_complete(data):
        return None, "truncated PNG"
    return None, f"corrupt or truncated {fmt}"


def _image_format(data: bytes) -> str | None:
    """The image format the bytes start like, or None."""
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        return "PNG"
    if data.startswith(b"\xff\xd8\xff"):
        return "JPEG"
    if data.startswith((b"II*\x00", b"MM\x00*")):
        return "TIFF"
    if data.startswith(b"BM"):
        return "BMP"
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return "WebP"
    if len(data) > 2 and data[0:1] == b"P" and data[1:2] in b"123456" and data[2:3].isspace():
        return "PNM"
    return None


def _png_complete(data: bytes) -> bool:
    """True when the PNG's chunks run whole up to IEND."""
    i = 8
    while i + 12 <= len(data):
        end = i + 12 + int.from_bytes(data[i : i + 4], "big")
        if end > len(data):
            return False
        if data[i + 4 : i + 8] == b"IEND":
            return True
        i = end
    return False


def _jpeg_complete(data: bytes) -> bool:
    """False when the JPEG ends before its end-of-image marker (segments are walked to the first
    scan of the main image, so an embedded thumbnail's marker does not count). Anything the walk
    does not understand is left to the decoder (True)."""
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return True
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0xD9:
            return True
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
            i += 2
            continue
        length = int.from_bytes(data[i + 2 : i + 4], "big")
        if marker == 0xDA:  # start of scan: the entropy-coded data cannot hold FF D9
            return data.find(b"\xff\xd9", i + 2 + length) >= 0
        i += 2 + length
    return False


def _video_time(cap: cv2.VideoCapture, index: int, fps: float) -> float:
    """The frame's presentation time from the container, or index / fps when it gives none."""
    ms = cap.get(cv2.CAP_PROP_POS_MSEC)
    if ms is not None and np.isfinite(ms) and (ms > 0 or index == 0):
        return ms / 1000.0
    return index / fps if fps > 0 else float(index)


def _natural_key(path: Path) -> list[object]:
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", path.name)]


def read_timestamps(path: Path, names: list[str] | None = None) -> np.ndarray:
    """Timestamps in seconds from a text file: one number per line (frame order), or lines
    `<time> <file name>` / `<file name> <time>` (TUM style), matched to `names` when given.
    Lines starting with '#' are comments. Raises InputError naming the file and the bad line.
    """
    by_name: dict[str, float] = {}
    ordered: list[float] = []
    for lineno, raw in enumerate(Path(path).read_text().splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        tokens = line.replace(",", " ").split()
        numbers, others = [], []
        for tok in tokens:
            try:
                numbers.append(float(tok))
            except ValueError:
                others.append(tok)
        if not numbers:
            raise InputError(f"{path}: line {lineno} holds no timestamp: {line!r}")
        if others:
            by_name[Path(others[0]).name] = numbers[0]
        else:
            # "index time" pairs keep the last number; a lone number is the time
            ordered.append(numbers[-1])
    if by_name and names is not None:
        missing = [n for n in names if n not in by_name]
        if missing:
            raise InputError(f"{path}: no timestamp for {missing[0]} (and {len(missing) - 1} more images)")
        return np.array([by_name[n] for n in names], np.float64)
    values = np.array(ordered or list(by_name.values()), np.float64)
    if names is not None and len(values) != len(names):
        raise InputError(f"{path}: {len(values)} timestamps for {len(names)} images; give one per image")
    return values


def _fit_size(width: int, height: int, max_size: int | None) -> tuple[int, int]:
    if max_size is None or max(width, height) <= max_size:
        return width, height
    s = max_size / max(width, height)
    return max(1, round(width * s)), max(1, round(height * s))


def open_recording(
    path: str | Path,
    step: int = 1,
    start_s: float | None = None,
    end_s: float | None = None,
    max_size: int | None = None,
    *,
    gray: bool = False,
    fps: float | None = None,
    timestamps: str | Path | None = None,
    prefetch: int = 8,
) -> Recording:
    """Open a video file or an image folder; check it decodes at least one frame.

    step keeps every step-th frame of the time range [start_s, end_s]; max_size bounds the
    longer image side (downscaled with INTER_AREA). For image folders, `fps` (default 30)
    gives timestamps unless a timestamps file is given, `timestamps.txt` lies in the folder, the
    image names are clock times (`name_timestamps`), or KITTI's `times.txt` lies beside the folder.
    Frames that do not decode are skipped during decoding (`Recording.bad_frames`).
    Raises InputError for a missing path, a file that is not a video, no decodable frame, or
    bad frames leaving fewer than 2 that decode.
    """
    path = Path(path)
    if step < 1:
        raise InputError(f"{path}: frame step must be >= 1, got {step}")
    if start_s is not None and end_s is not None and end_s < start_s:
        raise InputError(f"{path}: time range end {end_s} s is before its start {start_s} s")
    if max_size is not None and max_size < 16:
        raise InputError(f"{path}: max_size {max_size} is too small (>= 16 pixels)")
    if not path.exists():
        raise InputError(f"{path}: no such file or folder; give a video file or a folder of images")
    common = dict(step=step, start_s=start_s, end_s=end_s, gray=gray, prefetch=prefetch)
    if path.is_dir():
        rec = _open_folder(path, fps, timestamps, max_size, common)
    else:
        rec = _open_video(path, max_size, common)
    good = list(itertools.islice(rec.frames(), 2))  # scans the whole selection when < 2 decode
    if rec.bad_frames and len(good) < 2:
        n, listed = len(good) + len(rec.bad_frames), _list_bad(rec.bad_frames, 3)
        if good:
            raise InputError(f"{path}: only 1 of the {n} selected frames decodes (2 are needed): {listed}")
        raise InputError(f"{path}: none of the {n} selected frames decodes: {listed}")
    rec.bad_frames = []
    if not good:
        span = f"{start_s or 0:g} s to " + ("the end" if end_s is None else f"{end_s:g} s")
        where = "" if start_s is None and end_s is None else f" in the time range {span} from the first frame"
        raise InputError(f"{path}: no decodable frame{where}; check the file and the time range")
    log.info(
        "%s: %s %dx%d (source %dx%d), %.3g fps, %d frames announced",
        path,
        rec.kind,
        rec.width,
        rec.height,
        rec.source_width,
        rec.source_height,
        rec.fps,
        rec.frame_count,
    )
    return rec


def _open_video(path: Path, max_size: int | None, common: dict) -> Recording:
    if path.stat().st_size == 0:
        raise InputError(f"{path}: the file is empty; give a video file")
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    try:
        if not cap.isOpened():
            raise InputError(f"{path}: not a video FFmpeg can read (unknown format, or corrupt header)")
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        ok, image = cap.read()
        for _ in range(max(30, count) if count > 0 else _MAX_BAD_RUN):  # damaged first frames
            if ok and image is not None:
                break
            ok, image = cap.read()
        if not ok or image is None:
            raise InputError(f"{path}: no decodable frame; the stream is empty or corrupt")
        h, w = image.shape[:2]
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        if not np.isfinite(fps) or fps <= 0 or fps > 1000:
            log.warning("%s: the container gives no frame rate; assuming 30 fps", path)
            fps = 30.0
    finally:
        cap.release()
    width, height = _fit_size(w, h, max_size)
    return Recording(path, "video", w, h, width, height, fps, max(count, 0), **common)


def _open_folder(
    path: Path, fps: float | None, timestamps: str | Path | None, max_size: int | None, common: dict
) -> Recording:
    files = sorted(
        (p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key
    )
    if not files:
        raise InputError(f"{path}: the folder holds no images ({', '.join(IMAGE_SUFFIXES)})")
    ts_path = Path(timestamps) if timestamps is not None else path / "timestamps.txt"
    stamps = None
    if ts_path.exists():
        stamps = read_timestamps(ts_path, [f.name for f in files])
        if not _increasing(stamps):
            raise InputError(f"{ts_path}: timestamps must increase with the sorted image names")
    elif timestamps is not None:
        raise InputError(f"{ts_path}: timestamps file not found")
    elif (stamps := name_timestamps(files)) is not None:
        log.info("%s: no timestamps.txt; the image names are the frames' times", path)
    else:
        stamps = _kitti_times(path, files)
    w, h = _folder_size(path, files, cv2.IMREAD_GRAYSCALE if common["gray"] else cv2.IMREAD_COLOR)
    if fps is None:
        fps = float(1.0 / np.median(np.diff(stamps))) if stamps is not None and len(stamps) > 1 else 30.0
    width, height = _fit_size(w, h, max_size)
    n = len(files)
    return Recording(
        path, "images", w, h, width, height, fps, n, image_files=files, image_timestamps=stamps, **common
    )


_UNIX_SECONDS = re.compile(r"1\d{9}\.\d+")
"""A name that is a Unix time in seconds with a fraction, 2001-2033 (TUM RGB-D: 1305031102.175304.png);
a date written as digits (20231205123045.123) is not one."""
_UNIX_NANOSECONDS = re.compile(r"1\d{18}")
"""A name that is a Unix time in nanoseconds, 2001-2033 (EuRoC, ROS bag exports:
1403636579763555584.png); a date written as digits (20231205123045123) is not one."""


def name_timestamps(files: list[Path]) -> np.ndarray | None:
    """The frames' times in seconds when every image name is a Unix time, as the datasets name them
    (TUM's seconds, EuRoC's nanoseconds) and they increase in the folder's order; None otherwise: a
    frame number (000123.png) or a date in digits is not one, and such a folder is timed by its frame
    rate."""
    stems = [f.stem for f in files]
    if all(_UNIX_SECONDS.fullmatch(s) for s in stems):
        t = np.array([float(s) for s in stems])
    elif all(_UNIX_NANOSECONDS.fullmatch(s) for s in stems):
        t = np.array([int(s) // 1000 for s in stems], np.float64) * 1e-6  # microseconds: float64-exact
    else:
        return None
    return t if _increasing(t) else None


def _increasing(stamps: np.ndarray) -> bool:
    """Whether the times increase strictly, frame after frame."""
    return len(stamps) < 2 or bool(np.all(np.diff(stamps) > 0))


def _kitti_times(path: Path, files: list[Path]) -> np.ndarray | None:
    """The frames' times from `times.txt` beside the folder, as KITTI lays a sequence out
    (sequences/06/image_0/000000.png, sequences/06/times.txt): one time per image, increasing; None
    when there is none or it does not fit the images (it was not written for this folder)."""
    times = path.parent / "times.txt"
    if not times.is_file():
        return None
    try:
        stamps = read_timestamps(times, [f.name for f in files])
    except InputError as exc:
        log.info("%s: not used for the frames' times (%s)", times, exc)
        return None
    if not _increasing(stamps):
        log.info("%s: not used for the frames' times (they do not increase)", times)
        return None
    log.info("%s: no timestamps.txt; the frames' times are those of %s", path, times)
    return stamps


def _folder_size(path: Path, files: list[Path], flags: int) -> tuple[int, int]:
    """(width, height) most common among the folder's first decodable images (the first on a tie),
    so one odd or broken image at the start does not set the size; InputError if none decodes."""
    sizes: list[tuple[int, int]] = []
    bad: list[BadFrame] = []
    for index, file in enumerate(files):
        image, reason = _read_image(file, flags)
        if image is None:
            bad.append(BadFrame(index, file.name, float("nan"), reason))
            continue
        sizes.append((image.shape[1], image.shape[0]))
        if len(sizes) == _REFERENCE_IMAGES:
            break
    if not sizes:
        raise InputError(f"{path}: none of its {len(files)} images decodes: {_list_bad(bad, 3)}")
    return max(sizes, key=lambda wh: (sizes.count(wh), -sizes.index(wh)))
