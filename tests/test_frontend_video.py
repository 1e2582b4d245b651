"""Decoding: videos and image folders, frame selection, timestamps, scaling, bad inputs."""

from __future__ import annotations

import logging
import subprocess
import sys
import threading

import cv2
import numpy as np
import pytest

from papl_mapper.errors import InputError
from papl_mapper.frontend.video import open_recording, read_timestamps

FPS = 30
N = 45
W, H = 320, 240


def _frame(i: int) -> np.ndarray:
    """Frame i shows its index as a grey level (decoded back within codec noise) and a bar."""
    img = np.full((H, W, 3), 4 * i, np.uint8)
    cv2.rectangle(img, (10 + 2 * i, 60), (60 + 2 * i, 180), (255, 255, 255), -1)
    return img


def _write(path, fourcc: str, n: int = N) -> None:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), FPS, (W, H))
    assert w.isOpened()
    for i in range(n):
        w.write(_frame(i))
    w.release()


def _level(img: np.ndarray) -> float:
    """Grey level of the background area (frame index * 4)."""
    g = img if img.ndim == 2 else img[..., 1]
    return float(np.median(g[: g.shape[0] // 5, :]))


@pytest.fixture(scope="module")
def mp4(tmp_path_factory):
    path = tmp_path_factory.mktemp("video") / "walk.mp4"
    _write(path, "mp4v")
    return path


def test_video_all_frames_with_true_timestamps(mp4):
    rec = open_recording(mp4)
    assert (rec.width, rec.height, rec.fps, rec.frame_count) == (W, H, FPS, N)
    frames = list(rec)
    assert [f.index for f in frames] == list(range(N))
    t = np.array([f.timestamp_s for f in frames])
    np.testing.assert_allclose(t, np.arange(N) / FPS, atol=1e-3)
    levels = np.array([_level(f.image) for f in frames])
    np.testing.assert_allclose(levels, 4 * np.arange(N), atol=3)
    assert not rec.stopped_early
    assert rec.decoded_frames == N == rec.expected_frames()


def test_video_step_time_range_and_max_size(mp4):
    rec = open_recording(mp4, step=3, start_s=0.5, end_s=1.2, max_size=160, gray=True)
    frames = list(rec)
    idx = [f.index for f in frames]
    assert idx == list(range(15, 37, 3))  # 0.5 s = frame 15, 1.2 s = frame 36
    assert len(idx) == rec.expected_frames()
    assert frames[0].image.shape == (120, 160)
    assert rec.scale_xy == (0.5, 0.5)
    assert abs(_level(frames[0].image) - 60) <= 3


def test_iteration_can_stop_early_and_restart(mp4):
    rec = open_recording(mp4, prefetch=2)
    for k, _ in enumerate(rec):
        if k == 3:
            break
    assert len(list(rec)) == N


def test_ctrl_c_inside_the_decoder_thread_start_still_stops_the_thread(mp4, monkeypatch):
    """Ctrl-C can land in Thread.start() once the new thread runs (start waits for it): the decoder
    thread must still stop, else it is inside OpenCV when the interpreter exits and aborts it."""
    start, started = threading.Thread.start, []

    def interrupted_start(self: threading.Thread) -> None:
        start(self)
        started.append(self)
        raise KeyboardInterrupt

    monkeypatch.setattr(threading.Thread, "start", interrupted_start)
    with pytest.raises(KeyboardInterrupt):
        next(iter(open_recording(mp4, prefetch=2)))
    monkeypatch.undo()
    [decoder] = started
    decoder.join(timeout=5.0)
    assert decoder.name.startswith("decode-") and not decoder.is_alive() and not decoder.daemon


def test_a_decoder_never_closed_lets_the_interpreter_exit(mp4):
    """A recording iterator left open at exit (kept in a cycle): the interpreter stops the thread and
    exits cleanly instead of waiting for it forever or aborting inside OpenCV."""
    code = (
        "import sys\nfrom papl_mapper.frontend.video import open_recording\n"
        "it = iter(open_recording(sys.argv[1], prefetch=2))\nnext(it)\ncycle = [it]\ncycle.append(cycle)\n"
    )
    done = subprocess.run([sys.executable, "-c", code, str(mp4)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr


def test_image_folder_natural_order_and_timestamps_file(tmp_path):
    for i in range(12):
        cv2.imwrite(str(tmp_path / f"frame{i}.png"), _frame(i))
    stamps = 100.0 + 0.05 * np.arange(12)
    (tmp_path / "timestamps.txt").write_text("# t\n" + "\n".join(f"{t:.6f}" for t in stamps))
    rec = open_recording(tmp_path, step=2)
    frames = list(rec)
    assert [f.index for f in frames] == [0, 2, 4, 6, 8, 10]  # frame10 sorts after frame9
    np.testing.assert_allclose([f.timestamp_s for f in frames], stamps[::2])
    np.testing.assert_allclose([_level(f.image) for f in frames], 4 * np.arange(0, 12, 2), atol=1)
    assert rec.fps == pytest.approx(20.0)


def test_time_range_counts_from_the_first_image_of_a_folder_with_clock_timestamps(tmp_path):
    """TUM and KITTI folders carry clock times (1.3e9 s): --start/--end count from the first frame, as
    for a video; the frames keep their clock timestamps (they are matched to the ground truth)."""
    for i in range(12):
        cv2.imwrite(str(tmp_path / f"frame{i}.png"), _frame(i))
    stamps = 1305031102.0 + 0.05 * np.arange(12)
    (tmp_path / "timestamps.txt").write_text("\n".join(f"{t:.6f}" for t in stamps))
    rec = open_recording(tmp_path, start_s=0.1, end_s=0.3)
    frames = list(rec)
    assert [f.index for f in frames] == [2, 3, 4, 5, 6]
    assert rec.expected_frames() == 5
    np.testing.assert_allclose([f.timestamp_s for f in frames], stamps[2:7])


@pytest.mark.parametrize(
    "names, times",
    [
        # TUM RGB-D: clock seconds with a fraction
        (
            [f"{1305031102.175304 + 0.0333 * i:.6f}" for i in range(6)],
            1305031102.175304 + 0.0333 * np.arange(6),
        ),
        # EuRoC / ROS exports: clock nanoseconds
        (
            [str(1403636579763555584 + 50_000_000 * i) for i in range(6)],
            1403636579.763555 + 0.05 * np.arange(6),
        ),
    ],
)
def test_image_names_that_are_clock_times_time_the_frames(tmp_path, names, times):
    """A dataset's folder without timestamps.txt keeps its own clock (its ground truth is matched by
    time), not index / 30 fps."""
    for i, name in enumerate(names):
        cv2.imwrite(str(tmp_path / f"{name}.png"), _frame(i))
    frames = list(open_recording(tmp_path))
    np.testing.assert_allclose([f.timestamp_s for f in frames], times, rtol=0, atol=2e-6)


@pytest.mark.parametrize(
    "names",
    [
        [f"{i:06d}" for i in range(6)],  # frame numbers (KITTI): not times
        [f"20231205123045{i:03d}" for i in range(6)],  # a date and milliseconds in digits: not Unix time
        ["1305031102.8", "1305031102.9", "1305031102.10"],  # unpadded: .10 sorts after .9, time goes back
        [f"{1305031102.5 + 0.1 * i:.6f}" for i in range(5)] + ["frame"],  # not every name a time
    ],
)
def test_image_names_that_are_not_clock_times_leave_the_frame_rate(tmp_path, names):
    for i, name in enumerate(names):
        cv2.imwrite(str(tmp_path / f"{name}.png"), _frame(i))
    frames = list(open_recording(tmp_path))
    np.testing.assert_allclose([f.timestamp_s for f in frames], np.arange(len(names)) / 30.0)


@pytest.mark.parametrize("n_times", [6, 5])
def test_kitti_times_beside_the_image_folder(tmp_path, n_times):
    """KITTI's layout (sequences/06/image_0/000000.png, sequences/06/times.txt): its times when they
    fit the images one to one, else the frame rate."""
    images = tmp_path / "06" / "image_0"
    images.mkdir(parents=True)
    for i in range(6):
        cv2.imwrite(str(images / f"{i:06d}.png"), _frame(i))
    times = 0.103798 * np.arange(n_times)
    (tmp_path / "06" / "times.txt").write_text("".join(f"{t:.6e}\n" for t in times))
    frames = list(open_recording(images))
    expected = times if n_times == 6 else np.arange(6) / 30.0
    np.testing.assert_allclose([f.timestamp_s for f in frames], expected, atol=1e-9)


def test_timestamps_by_file_name(tmp_path):
    p = tmp_path / "rgb.txt"
    p.write_text("0.2 b.png\n0.1 a.png\n")
    np.testing.assert_allclose(read_timestamps(p, ["a.png", "b.png"]), [0.1, 0.2])
    with pytest.raises(InputError, match="no timestamp for c.png"):
        read_timestamps(p, ["a.png", "c.png"])


def test_truncated_stream_decodes_what_is_readable(tmp_path, caplog):
    full = tmp_path / "full.avi"
    _write(full, "MJPG")
    data = full.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) // 2])
    rec = open_recording(cut)
    with caplog.at_level(logging.WARNING):
        frames = list(rec)
    assert 5 < len(frames) < N
    assert rec.stopped_early and rec.stopped_at_frame == frames[-1].index
    assert "announced" in rec.stop_message
    assert "cut.avi" in caplog.text
    np.testing.assert_allclose([_level(f.image) for f in frames], 4 * np.arange(len(frames)), atol=3)


def test_bad_inputs(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        open_recording(tmp_path / "missing.mp4")
    text = tmp_path / "notes.mp4"
    text.write_text("this is not a video\n" * 100)
    with pytest.raises(InputError, match="notes.mp4"):
        open_recording(text)
    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    with pytest.raises(InputError, match="empty"):
        open_recording(empty)
    zero = tmp_path / "zero.avi"
    _write(zero, "MJPG", n=0)
    with pytest.raises(InputError, match="zero.avi"):
        open_recording(zero)
    folder = tmp_path / "nothing"
    folder.mkdir()
    with pytest.raises(InputError, match="no images"):
        open_recording(folder)


def test_time_range_without_frames_is_an_input_error(mp4):
    with pytest.raises(InputError, match="time range"):
        open_recording(mp4, start_s=100.0)
