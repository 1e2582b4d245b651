"""The Map file: round trip, validation of every rule, clear errors for bad files."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from papl_mapper.errors import MapFormatError
from papl_mapper.map import FORMAT_VERSION, LineState, Map
from tests.conftest import make_map


def _assert_equal_maps(a: Map, b: Map) -> None:
    for group in ("keyframes", "points", "lines"):
        for name, arr in vars(getattr(a, group)).items():
            np.testing.assert_array_equal(arr, getattr(getattr(b, group), name), err_msg=f"{group}.{name}")
            assert arr.dtype == getattr(getattr(b, group), name).dtype
    np.testing.assert_array_equal(a.axes.directions, b.axes.directions)
    assert a.axes.vertical_index == b.axes.vertical_index
    assert a.camera.to_dict() == b.camera.to_dict()
    assert a.metadata == b.metadata


def test_round_trip_is_exact(tmp_path, small_map):
    small_map.metadata["config"] = {"seed": 3, "name": "x"}
    path = small_map.save(tmp_path / "m.papl")
    _assert_equal_maps(small_map, Map.load(path))


def test_empty_map_round_trips(tmp_path, small_map):
    from papl_mapper.map import Map as M

    m = M(small_map.camera)
    back = M.load(m.save(tmp_path / "e.papl"))
    assert len(back.lines) == 0 and len(back.keyframes) == 0


def test_file_is_readable_with_numpy_alone(tmp_path, small_map):
    path = small_map.save(tmp_path / "m.papl")
    with np.load(path) as npz:
        np.testing.assert_array_equal(npz["lines.endpoints_w"], small_map.lines.endpoints_w)
    with zipfile.ZipFile(path) as zf:
        assert json.loads(zf.read("meta.json"))["version"] == FORMAT_VERSION


def test_summary_counts(small_map):
    s = small_map.summary()
    axis = small_map.lines.axis_of_line()
    assert sum(s["lines_per_axis"]) + s["unanchored_lines"] == len(small_map.lines)
    assert s["lines_per_axis"] == [int((axis == a).sum()) for a in range(3)]
    assert s["axis_angles_deg"][0][1] == pytest.approx(90.0)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda m: m.lines.endpoints_w.__setitem__((3, 0, 1), np.nan), "NaN"),
        (lambda m: m.points.xyz.__setitem__((0, 0), np.inf), "NaN or infinite"),
        (lambda m: setattr(m.points, "ids", np.zeros(len(m.points.ids), np.int64)), "not unique"),
        (lambda m: m.lines.obs_ids.__setitem__((0, 1), 999999), "unknown keyframes"),
        (lambda m: m.points.obs_ids.__setitem__((0, 0), -5), "unknown points"),
        (lambda m: setattr(m.lines, "axis_weights", m.lines.axis_weights[:, :2]), "columns"),
        (lambda m: m.keyframes.T_wc.__setitem__((1, 0, 0), 2.0), "orthonormal"),
        (lambda m: m.axes.directions.__setitem__((0, 0), 0.5), "unit"),
        (lambda m: setattr(m.axes, "vertical_index", 7), "vertical_index"),
        (lambda m: setattr(m.points, "xyz", m.points.xyz[:, :2]), "shape"),
        (lambda m: setattr(m.lines, "state", np.full(len(m.lines), 9, np.int8)), "unknown states"),
        (lambda m: setattr(m.keyframes, "timestamp", m.keyframes.timestamp[:2]), "rows"),
    ],
)
def test_validation_refuses_bad_maps(tmp_path, mutate, message):
    m = make_map()
    mutate(m)
    with pytest.raises(MapFormatError, match=message):
        m.validate()
    with pytest.raises(MapFormatError):
        m.save(tmp_path / "bad.papl")
    assert not list(tmp_path.iterdir()), "a refused save leaves no file behind"


def test_nan_inverse_depth_only_refused_for_anchored_lines(small_map):
    anchored = np.flatnonzero(small_map.lines.state == LineState.ANCHORED)
    small_map.validate()  # unanchored lines carry NaN inverse depth legitimately
    small_map.lines.inverse_depth[anchored[0]] = np.nan
    with pytest.raises(MapFormatError, match="inverse_depth"):
        small_map.validate()


def test_truncated_file_is_refused(tmp_path, small_map):
    path = small_map.save(tmp_path / "m.papl")
    data = path.read_bytes()
    for cut in (10, len(data) // 2, len(data) - 30):
        bad = tmp_path / f"cut{cut}.papl"
        bad.write_bytes(data[:cut])
        with pytest.raises(MapFormatError, match=str(bad.name)):
            Map.load(bad)


def test_corrupt_bytes_are_refused(tmp_path, small_map):
    path = small_map.save(tmp_path / "m.papl")
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("lines.endpoints_w.npy")
    data = bytearray(path.read_bytes())
    pos = info.header_offset + 30 + len(info.filename) + 200  # inside the array payload
    data[pos] ^= 0xFF
    bad = tmp_path / "flip.papl"
    bad.write_bytes(bytes(data))
    with pytest.raises(MapFormatError, match="corrupt"):
        Map.load(bad)


def test_wrong_version_and_foreign_files_are_refused(tmp_path, small_map):
    path = small_map.save(tmp_path / "m.papl")
    newer = tmp_path / "v99.papl"
    with zipfile.ZipFile(path) as src, zipfile.ZipFile(newer, "w") as dst:
        for item in src.infolist():
            payload = src.read(item)
            if item.filename == "meta.json":
                meta = json.loads(payload)
                meta["version"] = 99
                payload = json.dumps(meta).encode()
            dst.writestr(item, payload)
    with pytest.raises(MapFormatError, match="version 99"):
        Map.load(newer)
    text = tmp_path / "notes.papl"
    text.write_text("hello")
    with pytest.raises(MapFormatError, match="corrupt or truncated"):
        Map.load(text)
    with pytest.raises(MapFormatError, match="no such map"):
        Map.load(tmp_path / "missing.papl")


def test_failed_save_keeps_the_previous_file(tmp_path, small_map):
    path = small_map.save(tmp_path / "m.papl")
    before = path.read_bytes()
    small_map.points.xyz[0, 0] = np.nan
    with pytest.raises(MapFormatError):
        small_map.save(path)
    assert path.read_bytes() == before


def test_saved_map_is_readable_by_others(tmp_path, small_map):
    """Outputs get the mode a plain open() would give, not mkstemp's owner-only 0600."""
    import os

    old = os.umask(0o022)
    try:
        path = small_map.save(tmp_path / "m.papl")
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o644
