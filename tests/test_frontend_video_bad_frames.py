"""Decoding goes on past bad frames: they are skipped, counted and named; the others keep
their own index and timestamp."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from papl_mapper.errors import InputError
from papl_mapper.frontend.video import BadFrame, open_recording

W, H = 64, 48
N = 12
FPS = 30
STAMPS = np.round(100.0 + 0.05 * np.arange(N) + 0.003 * np.sin(np.arange(N)), 6)  # not index / fps


def _image(i: int) -> np.ndarray:
    """Random texture (seeded by i), the index written as a grey patch in the corner."""
    img = np.random.default_rng(i).integers(0, 256, (H, W, 3), dtype=np.uint8)
    img[:8, :8] = 10 * i
    return img


def _png(i: int, size: tuple[int, int] = (W, H)) -> bytes:
    img = _image(i) if size == (W, H) else cv2.resize(_image(i), size)
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return buf.tobytes()


def _folder(path, bad: dict[int, bytes], suffix: str = ".png", encode=_png):
    path.mkdir()
    for i in range(N):
        (path / f"{i:06d}{suffix}").write_bytes(bad.get(i, encode(i)))
    (path / "timestamps.txt").write_text("\n".join(f"{t:.6f}" for t in STAMPS))
    return path


def _broken() -> dict[int, bytes]:
    """Garbage bytes, a PNG cut in half, an empty file and a PNG of another size."""
    garbage = np.random.default_rng(99).integers(0, 256, 3000, dtype=np.uint8).tobytes()
    half = _png(5)
    return {3: garbage, 5: half[: len(half) // 2], 7: b"", 9: _png(9, (48, 32))}


def test_folder_skips_bad_images_and_keeps_indices_and_timestamps(tmp_path, caplog):
    rec = open_recording(_folder(tmp_path / "seq", _broken()))
    assert (rec.width, rec.height, rec.frame_count) == (W, H, N)
    assert rec.bad_frames == []  # filled by a decoding pass
    with caplog.at_level(logging.WARNING):
        frames = list(rec)
    good = [0, 1, 2, 4, 6, 8, 10, 11]
    assert [f.index for f in frames] == good
    np.testing.assert_array_equal([f.timestamp_s for f in frames], STAMPS[good])
    for f in frames:
        np.testing.assert_array_equal(f.image, _image(f.index))  # lossless: the very pixels
    assert rec.bad_frames == [
        BadFrame(3, "000003.png", STAMPS[3], "not a PNG file (unrecognised content)"),
        BadFrame(5, "000005.png", STAMPS[5], "truncated PNG"),
        BadFrame(7, "000007.png", STAMPS[7], "empty file"),
        BadFrame(9, "000009.png", STAMPS[9], "48x32, not the folder's 64x48"),
    ]
    message = rec.bad_frames_message()
    assert message.startswith("4 frames could not be decoded and were skipped: 000003.png (not a PNG")
    assert "000005.png (truncated PNG)" in message and "\n" not in message
    assert rec.bad_frames_message(limit=2).endswith("and 2 more")
    assert not rec.stopped_early and rec.decoded_frames == len(good)
    # the caller logs the one summary line (INFO lines may show where an earlier test set the level)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    # a second pass, in the calling thread, gives the same frames and a fresh list
    assert [f.index for f in rec.frames()] == good and len(rec.bad_frames) == 4


def test_folder_step_only_checks_selected_frames(tmp_path):
    rec = open_recording(_folder(tmp_path / "seq", _broken()), step=3)
    assert [f.index for f in rec] == [0, 6]
    assert [(b.index, b.reason) for b in rec.bad_frames] == [
        (3, "not a PNG file (unrecognised content)"),
        (9, "48x32, not the folder's 64x48"),
    ]


def test_odd_sized_first_image_does_not_set_the_folder_size(tmp_path):
    rec = open_recording(_folder(tmp_path / "seq", {0: _png(0, (48, 32))}))
    assert (rec.width, rec.height) == (W, H)
    assert [f.index for f in rec] == list(range(1, N))
    assert [str(b) for b in rec.bad_frames] == ["000000.png (48x32, not the folder's 64x48)"]


def test_truncated_jpeg_is_named(tmp_path):
    def jpg(i: int) -> bytes:
        return cv2.imencode(".jpg", _image(i))[1].tobytes()

    data = jpg(4)
    rec = open_recording(_folder(tmp_path / "seq", {4: data[: len(data) * 2 // 3]}, ".jpg", jpg))
    assert [f.index for f in rec] == [i for i in range(N) if i != 4]
    assert [str(b) for b in rec.bad_frames] == ["000004.jpg (truncated JPEG)"]


def test_all_bad_folder_is_one_line_input_error(tmp_path):
    folder = tmp_path / "broken"
    folder.mkdir()
    broken = _broken()
    for i in (3, 5, 7):
        (folder / f"{i:06d}.png").write_bytes(broken[i])
    with pytest.raises(InputError) as err:
        open_recording(folder)
    msg = str(err.value)
    assert "\n" not in msg and str(folder) in msg
    assert "none of its 3 images decodes" in msg and "000007.png (empty file)" in msg


def test_one_decodable_frame_among_bad_ones_is_an_input_error(tmp_path):
    folder = tmp_path / "seq"
    folder.mkdir()
    (folder / "a.png").write_bytes(_png(0))
    (folder / "b.png").write_bytes(b"")
    (folder / "c.png").write_bytes(_png(2)[:100])
    with pytest.raises(InputError, match=r"only 1 of the 3 selected frames decodes") as err:
        open_recording(folder)
    assert "\n" not in str(err.value) and "c.png (truncated PNG)" in str(err.value)


# -- videos -----------------------------------------------------------------------------------

VN = 45
VW, VH = 320, 240


def _frame(i: int) -> np.ndarray:
    """Frame i shows its index as a grey level (decoded back within codec noise) and a bar."""
    img = np.full((VH, VW, 3), 4 * i, np.uint8)
    cv2.rectangle(img, (10 + 2 * i, 60), (60 + 2 * i, 180), (255, 255, 255), -1)
    return img


def _write(path, fourcc: str) -> None:
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), FPS, (VW, VH))
    assert w.isOpened()
    for i in range(VN):
        w.write(_frame(i))
    w.release()


def _level(img: np.ndarray) -> float:
    return float(np.median(img[: img.shape[0] // 5, :, 1]))


def _avi_frames(data: bytes) -> list[tuple[int, int]]:
    """(offset, size) of each video chunk's payload in an AVI's movi list, in stream order."""
    i = data.index(b"movi") + 4
    out = []
    while i + 8 <= len(data) and data[i : i + 4] != b"idx1":
        size = int.from_bytes(data[i + 4 : i + 8], "little")
        if data[i + 2 : i + 4] in (b"dc", b"db"):
            out.append((i + 8, size))
        i += 8 + size + (size & 1)
    return out


def test_video_still_decodes_every_frame(tmp_path):
    path = tmp_path / "walk.mp4"
    _write(path, "mp4v")
    rec = open_recording(path)
    frames = list(rec)
    assert [f.index for f in frames] == list(range(VN))
    np.testing.assert_allclose([f.timestamp_s for f in frames], np.arange(VN) / FPS, atol=1e-3)
    np.testing.assert_allclose([_level(f.image) for f in frames], 4 * np.arange(VN), atol=3)
    assert rec.bad_frames == [] and rec.bad_frames_message() == ""
    assert not rec.stopped_early and rec.decoded_frames == VN


@pytest.mark.parametrize("bad", [0, 20])
def test_video_frame_that_does_not_decode_is_skipped(tmp_path, bad):
    full = tmp_path / "full.avi"
    _write(full, "MJPG")
    data = bytearray(full.read_bytes())
    chunks = _avi_frames(bytes(data))
    assert len(chunks) == VN
    offset, size = chunks[bad]
    data[offset : offset + size] = np.random.default_rng(bad).integers(0, 256, size, dtype=np.uint8).tobytes()
    damaged = tmp_path / "damaged.avi"
    damaged.write_bytes(bytes(data))
    rec = open_recording(damaged)
    frames = list(rec)
    good = [i for i in range(VN) if i != bad]
    assert [f.index for f in frames] == good  # later frames keep their index
    np.testing.assert_allclose([f.timestamp_s for f in frames], np.array(good) / FPS, atol=1e-3)
    np.testing.assert_allclose([_level(f.image) for f in frames], 4 * np.array(good), atol=3)
    assert [(b.index, b.reason) for b in rec.bad_frames] == [(bad, "its data does not decode")]
    assert rec.bad_frames[0].timestamp_s == pytest.approx(bad / FPS, abs=1e-3)
    where = f"frame {bad} at {bad / FPS:.3f} s"
    assert (
        rec.bad_frames_message()
        == f"1 frame could not be decoded and was skipped: {where} (its data does not decode)"
    )
    assert not rec.stopped_early


def test_truncated_video_is_a_stream_end_not_bad_frames(tmp_path):
    full = tmp_path / "full.avi"
    _write(full, "MJPG")
    data = full.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) // 2])
    rec = open_recording(cut)
    frames = list(rec)
    assert [f.index for f in frames] == list(range(len(frames))) and 5 < len(frames) < VN
    assert rec.stopped_early and "announced" in rec.stop_message
    assert rec.bad_frames == []
