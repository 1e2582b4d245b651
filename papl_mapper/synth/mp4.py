"""Give the frames of a constant-rate MP4 their own presentation times (a variable-frame-rate video).

OpenCV's VideoWriter writes every frame one frame interval after the last. A recording with
dropped frames has gaps instead: `retime_mp4` rewrites the track's time-to-sample table (`stts`)
so that frame k is shown `gaps[k]` intervals after frame k - 1, and updates the durations. The
samples themselves are untouched; decoders (FFmpeg, so OpenCV's CAP_PROP_POS_MSEC) then report the
true times. Only the layout FFmpeg's MP4 muxer writes for OpenCV is handled: one track, 32-bit
(version 0) headers, one stts entry, and the moov box after the media data, so growing the table
moves no sample.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from pathlib import Path

from papl_mapper.errors import BackendUnavailableError

_Box = tuple[bytes, int, int, int]  # type, offset, header size, size


def _boxes(buf: bytes | bytearray, start: int, end: int) -> list[_Box]:
    out = []
    off = start
    while off + 8 <= end:
        size, kind = struct.unpack_from(">I4s", buf, off)
        hdr = 8
        if size == 1:
            (size,) = struct.unpack_from(">Q", buf, off + 8)
            hdr = 16
        elif size == 0:
            size = end - off
        if size < hdr or off + size > end:
            raise ValueError(f"box {kind!r} at byte {off} has a bad size {size}")
        out.append((kind, off, hdr, size))
        off += size
    return out


def _path(buf: bytes | bytearray, names: Sequence[bytes]) -> list[_Box]:
    """The chain of boxes along `names` from the top level; ValueError unless each is unique."""
    chain: list[_Box] = []
    start, end = 0, len(buf)
    for name in names:
        hits = [b for b in _boxes(buf, start, end) if b[0] == name]
        if len(hits) != 1:
            raise ValueError(f"{len(hits)} {name.decode()} boxes where one is expected")
        chain.append(hits[0])
        _, off, hdr, size = hits[0]
        start, end = off + hdr, off + size
    return chain


def _payload(buf: bytearray, box: _Box, version: int = 0) -> int:
    """Offset of a full box's fields after version/flags; ValueError for another version."""
    kind, off, hdr, _ = box
    if buf[off + hdr] != version:
        raise ValueError(f"{kind.decode()} version {buf[off + hdr]} (only {version} is handled)")
    return off + hdr + 4


def retime_mp4(path: str | Path, gaps: Sequence[int]) -> None:
    """Rewrite the MP4 at `path` in place so frame k follows frame k - 1 by gaps[k] frame intervals.

    `gaps` has one positive integer per frame; gaps[-1] is the last frame's own duration (1 for one
    interval). Raises BackendUnavailableError when the file is not the layout described above.
    """
    path = Path(path)
    gaps = [int(g) for g in gaps]
    if not gaps or min(gaps) < 1:
        raise ValueError("gaps must be positive frame counts, one per frame")
    buf = bytearray(path.read_bytes())
    try:
        top = [b[0] for b in _boxes(buf, 0, len(buf))]
        if b"mdat" not in top or top.index(b"moov") < top.index(b"mdat"):
            raise ValueError("the moov box is not after the media data")
        if sum(1 for b in _boxes(buf, *_inner(_path(buf, [b"moov"])[0])) if b[0] == b"trak") != 1:
            raise ValueError("not exactly one track")
        trak = [b"moov", b"trak"]
        stbl_chain = _path(buf, [*trak, b"mdia", b"minf", b"stbl", b"stts"])
        stts = stbl_chain[-1]
        p = _payload(buf, stts)
        entries, count, delta = struct.unpack_from(">III", buf, p)
        if entries != 1 or count != len(gaps):
            raise ValueError(f"stts holds {entries} entries for {count} samples, not one for {len(gaps)}")
        runs: list[list[int]] = []
        for g in gaps:
            if runs and runs[-1][1] == g * delta:
                runs[-1][0] += 1
            else:
                runs.append([1, g * delta])
        media_duration = sum(g * delta for g in gaps)
        mdhd = _payload(buf, _path(buf, [*trak, b"mdia", b"mdhd"])[-1])
        (media_scale,) = struct.unpack_from(">I", buf, mdhd + 8)
        mvhd = _payload(buf, _path(buf, [b"moov", b"mvhd"])[-1])
        (movie_scale,) = struct.unpack_from(">I", buf, mvhd + 8)
        movie_duration = -(-media_duration * movie_scale // media_scale)  # rounded up, as FFmpeg does
        if media_duration >= 2**32 or movie_duration >= 2**32:
            raise ValueError("the duration does not fit a version 0 header")
        tkhd = _payload(buf, _path(buf, [*trak, b"tkhd"])[-1])
        elst = None
        if any(b[0] == b"edts" for b in _boxes(buf, *_inner(_path(buf, trak)[-1]))):
            elst = _payload(buf, _path(buf, [*trak, b"edts", b"elst"])[-1])
            if struct.unpack_from(">I", buf, elst)[0] != 1:
                raise ValueError("the edit list holds more than one edit")
        if any(hdr != 8 for _, _, hdr, _ in stbl_chain):
            raise ValueError("a 64-bit box size on the way to stts")
    except (ValueError, struct.error) as exc:
        raise BackendUnavailableError(f"{path}: cannot give the video its frame times ({exc})") from exc
    struct.pack_into(">I", buf, mdhd + 12, media_duration)
    struct.pack_into(">I", buf, mvhd + 12, movie_duration)
    struct.pack_into(">I", buf, tkhd + 16, movie_duration)
    if elst is not None:
        struct.pack_into(">I", buf, elst + 4, movie_duration)  # the one edit spans the whole track
    table = struct.pack(">I", len(runs)) + b"".join(struct.pack(">II", c, d) for c, d in runs)
    new_stts = struct.pack(">I4sI", 12 + len(table), b"stts", 0) + table
    grow = len(new_stts) - stts[3]
    for _, off, _, size in stbl_chain[:-1]:  # moov, trak, mdia, minf, stbl grow by the same amount
        struct.pack_into(">I", buf, off, size + grow)
    buf[stts[1] : stts[1] + stts[3]] = new_stts
    path.write_bytes(bytes(buf))


def _inner(box: _Box) -> tuple[int, int]:
    _, off, hdr, size = box
    return off + hdr, off + size
