"""Issue #16: bad inputs and faults end in one error line naming the file, exit 2, no traceback, and
leave every other file as it was (checksums of the folder before and after)."""

from __future__ import annotations

import errno
import hashlib
import io
import json
import os
import signal
import socket
import stat
import subprocess
import sys
import time
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest

from papl_mapper.cli import main
from papl_mapper.errors import MapFormatError
from papl_mapper.map import Map

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "samples" / "tiny"
VIDEO = str(TINY / "video.mp4")
FAST = ["--end", "1.0", "--set", "ba.max_iterations=3", "--set", "focal.enabled=false"]


def snapshot(folder: Path) -> dict[str, str]:
    """Every entry under `folder`: its kind, and a checksum of regular files and link targets."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(folder):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = p.lstat()
            if stat.S_ISREG(st.st_mode):
                out[str(p.relative_to(folder))] = hashlib.sha256(p.read_bytes()).hexdigest()
            elif stat.S_ISLNK(st.st_mode):
                out[str(p.relative_to(folder))] = "link " + os.readlink(p)
            else:
                out[str(p.relative_to(folder))] = f"kind {stat.S_IFMT(st.st_mode)}"
    return out


def fails_cleanly(capsys, argv: list[str], names: str, code: int = 2) -> str:
    """Run the CLI; assert exit `code`, exactly one stderr line holding 'error:' and `names`, no traceback."""
    assert main(argv) == code
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if ": error: " in line]
    assert len(errors) == 1, err
    assert "Traceback" not in err
    assert names in errors[0], errors[0]
    return errors[0]


def untouched(folder: Path, before: dict[str, str], allowed: tuple[str, ...] = ()) -> None:
    """Nothing under `folder` changed but the paths in `allowed`, what they hold, and their parents."""
    after = snapshot(folder)
    changed = {k for k in set(before) | set(after) if before.get(k) != after.get(k)}

    def ok(k: str) -> bool:
        return any(k == a or k.startswith(a + os.sep) or a.startswith(k + os.sep) for a in allowed)

    assert {k for k in changed if not ok(k)} == set()


@pytest.fixture
def good_map(tmp_path: Path) -> Path:
    path = tmp_path / "good.papl"
    path.write_bytes((TINY / "gt" / "map.papl").read_bytes())
    return path


def rewrite_map(src: Path, dst: Path, meta=None, arrays: dict[str, bytes] | None = None, deflate=False):
    """A copy of the map `src` with meta.json changed by `meta(dict) -> object` and members replaced."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED if deflate else 0) as z:
        for name in zin.namelist():
            data = zin.read(name)
            if name == "meta.json" and meta is not None:
                data = json.dumps(meta(json.loads(data))).encode()
            if arrays and name in arrays:
                data = arrays[name]
            z.writestr(name, data)
    return dst


def camera_file(tmp_path: Path, name: str, **changes) -> Path:
    cam = json.loads((TINY / "camera.json").read_text())
    cam.update(changes)
    path = tmp_path / name
    path.write_text(json.dumps(cam))
    return path


# ---- row 1: the output-path policy ---------------------------------------------------------------


def test_export_through_a_link_writes_its_target_and_keeps_the_link(tmp_path, good_map, capsys):
    (tmp_path / "real.ply").write_text("old")
    (tmp_path / "link.ply").symlink_to("real.ply")
    assert main(["export", str(good_map), str(tmp_path / "link.ply")]) == 0
    assert (tmp_path / "link.ply").is_symlink()
    assert (tmp_path / "real.ply").read_bytes().startswith(b"ply\n")


@pytest.mark.parametrize("kind", ["fifo", "socket", "device", "folder"])
def test_export_refuses_to_replace_what_is_not_a_regular_file(kind, tmp_path, good_map, capsys):
    target = tmp_path / "out.ply"
    if kind == "fifo":
        os.mkfifo(target)
    elif kind == "socket":
        target = tmp_path / "s.ply"  # short: AF_UNIX paths are limited to ~100 bytes
        sock = socket.socket(socket.AF_UNIX)
        try:
            sock.bind(str(target))
        except OSError:
            pytest.skip("cannot bind a unix socket here")
    elif kind == "device":
        try:
            os.mknod(target, 0o600 | stat.S_IFCHR, os.makedev(1, 3))  # a copy of /dev/null
        except (PermissionError, OSError):
            pytest.skip("mknod needs root")
    else:
        target.mkdir()
    before = snapshot(tmp_path)
    line = fails_cleanly(capsys, ["export", str(good_map), str(target)], str(target))
    assert {"fifo": "FIFO", "socket": "socket", "device": "device", "folder": "folder"}[kind] in line
    untouched(tmp_path, before)


# ---- row 2: tracebacks instead of one line -------------------------------------------------------


def test_run_out_is_an_existing_file(tmp_path, capsys):
    (tmp_path / "afile").write_text("mine")
    before = snapshot(tmp_path)
    fails_cleanly(
        capsys, ["run", VIDEO, "--out", str(tmp_path / "afile")], "afile: exists and is not a folder"
    )
    untouched(tmp_path, before)


def test_run_out_on_a_read_only_folder(tmp_path, capsys, monkeypatch):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    if os.geteuid() == 0:  # root passes permission bits: deny the way a read-only mount does
        import papl_mapper.atomic as atomic

        real = atomic.os.access
        monkeypatch.setattr(atomic.os, "access", lambda p, m: False if Path(p) == ro else real(p, m))
    before = snapshot(tmp_path)
    fails_cleanly(capsys, ["run", VIDEO, "--out", str(ro / "x")], f"cannot write in {ro}")
    untouched(tmp_path, before)


def test_disk_full_while_writing_the_map(tmp_path, good_map, capsys, monkeypatch):
    import papl_mapper.map as map_module

    out = tmp_path / "run"
    out.mkdir()
    (out / "map.papl").write_bytes(good_map.read_bytes())
    (out / "trajectory.tum").write_text("0 0 0 0 0 0 0 1\n")

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(map_module.np.lib.format, "write_array", full)
    before = snapshot(out)
    cmd = ["-q", "run", VIDEO, "--camera", str(TINY / "camera.json"), "--out", str(out), *FAST]
    line = fails_cleanly(capsys, cmd, "map.papl: could not write the file (No space left on device)")
    assert str(out) in line
    # the previous outputs are whole; only the checkpoints and the running log are new
    untouched(out, before, allowed=(".checkpoint",))


def test_config_is_a_folder(tmp_path, capsys):
    (tmp_path / "adir").mkdir()
    before = snapshot(tmp_path)
    cmd = ["run", VIDEO, "--out", str(tmp_path / "o"), "--config", str(tmp_path / "adir")]
    fails_cleanly(capsys, cmd, "adir: is a folder")
    untouched(tmp_path, before)


CAMERA_FILES = {
    "list.json": ("[1, 2]", "must hold an object"),
    "broken.yaml": ("%YAML:1.0\ncamera_matrix: [1, 2\n  foo: : :\n", "not a readable OpenCV YAML"),
    "width.json": (None, "camera field 'width' must be a number"),
    "fx.json": (None, "camera field 'fx' must be a number"),
    "fisheye.json": (None, "camera model 'fisheye' is not supported"),
    "tiny_f.json": (None, "implausible focal length 1e-09"),
    "k1.json": (None, "implausible distortion"),
    "short_k.json": (None, "camera field 'distortion'"),
}


@pytest.mark.parametrize("name", sorted(CAMERA_FILES))
def test_bad_camera_files(name, tmp_path, capsys):
    text, message = CAMERA_FILES[name]
    if text is not None:
        (tmp_path / name).write_text(text)
    else:
        changes = {
            "width.json": {"width": "abc"},
            "fx.json": {"fx": "abc"},
            "fisheye.json": {"model": "fisheye"},
            "tiny_f.json": {"fx": 1e-9, "fy": 1e-9},
            "k1.json": {"distortion": [1e6, 0, 0, 0, 0]},
            "short_k.json": {"distortion": "k1"},
        }[name]
        camera_file(tmp_path, name, **changes)
    out = tmp_path / "o"
    before = snapshot(tmp_path)
    line = fails_cleanly(capsys, ["run", VIDEO, "--out", str(out), "--camera", str(tmp_path / name)], name)
    assert message in line
    # only the running log is new, and it keeps the error
    untouched(tmp_path, before, allowed=("o/.checkpoint/log.txt",))
    assert message in (out / ".checkpoint" / "log.txt").read_text()
    assert not (out / "map.papl").exists()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--set", "ba.point_sigma_px=-1"], "'ba.point_sigma_px': -1.0 is negative"),
        (["--set", "ba.point_sigma_px=0"], "standard deviation must be > 0"),
        (["--set", "max_point_error_px=nan"], "'max_point_error_px': nan is not a finite number"),
        (["--set", "hfov_deg=inf"], "'hfov_deg': inf is not a finite number"),
        (["--end", "nan"], "--end nan"),
        (["--start", "-5"], "--start -5.0"),
        (["--start", "2", "--end", "1"], "is not after --start"),
        (["--step", "0"], "--step 0"),
        (["--camera-height", "nan"], "--camera-height nan"),
        (["--export", "ply,xyz"], "unknown export suffix '.xyz'"),
        (["--gt", "/nonexistent/gt"], "--gt /nonexistent/gt: no such ground-truth folder"),
    ],
)
def test_run_options_refused_before_the_first_frame(argv, message, tmp_path, capsys):
    before = snapshot(tmp_path)
    t0 = time.perf_counter()
    fails_cleanly(capsys, ["run", VIDEO, "--out", str(tmp_path / "o"), *argv], message)
    untouched(tmp_path, before)  # not even the output folder was created
    assert not (tmp_path / "o").exists()
    assert time.perf_counter() - t0 < 30  # no mapping happened (it takes longer; generous on a busy box)


def test_synth_seconds_nan(tmp_path, capsys):
    before = snapshot(tmp_path)
    fails_cleanly(
        capsys, ["synth", "corridor", "--seconds", "nan", "--out", str(tmp_path / "s")], "--seconds nan"
    )
    untouched(tmp_path, before)


META_FAULTS = {
    "vertical_index_str": (lambda m: {**m, "vertical_index": "abc"}, "vertical_index must be an integer"),
    "vertical_index_bool": (lambda m: {**m, "vertical_index": True}, "vertical_index must be an integer"),
    "camera_fx_str": (lambda m: {**m, "camera": {**m["camera"], "fx": "abc"}}, "'fx' must be a number"),
    "camera_str": (lambda m: {**m, "camera": "xyz"}, "camera must be an object"),
    "camera_missing": (lambda m: {k: v for k, v in m.items() if k != "camera"}, "camera must be an object"),
    "camera_width_float": (lambda m: {**m, "camera": {**m["camera"], "width": 640.5}}, "must be an integer"),
    "camera_fisheye": (lambda m: {**m, "camera": {**m["camera"], "model": "fisheye"}}, "not supported"),
    "list": (lambda m: [m], "holds a list"),
    "metadata_list": (lambda m: {**m, "metadata": [1]}, "metadata must be an object"),
    "version_str": (lambda m: {**m, "version": "1"}, "map format version '1'"),
}


@pytest.mark.parametrize("case", sorted(META_FAULTS))
def test_map_meta_faults(case, tmp_path, good_map, capsys):
    change, message = META_FAULTS[case]
    bad = rewrite_map(good_map, tmp_path / "bad.papl", meta=change)
    before = snapshot(tmp_path)
    line = fails_cleanly(capsys, ["info", str(bad)], "bad.papl")
    assert message in line
    untouched(tmp_path, before)


def _npy_header(shape: tuple, descr: str = "<f8") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def test_npy_header_declaring_a_huge_shape(tmp_path, good_map, capsys):
    bad = rewrite_map(good_map, tmp_path / "huge.papl", arrays={"points.xyz.npy": _npy_header((2**40, 3))})
    line = fails_cleanly(capsys, ["info", str(bad)], "huge.papl")
    assert "declares shape (1099511627776, 3)" in line


# ---- row 5: header injection ---------------------------------------------------------------------


def test_units_with_a_newline_cannot_inject_headers(tmp_path, good_map, capsys):
    plyfile = pytest.importorskip("plyfile")

    def evil(m):
        m["metadata"]["units"] = "m\nend_header\nelement evil 1"
        return m

    bad = rewrite_map(good_map, tmp_path / "units.papl", meta=evil)
    outs = [tmp_path / f"u.{s}" for s in ("ply", "obj", "tum", "dxf", "tubes.ply")]
    assert main(["export", str(bad), *map(str, outs)]) == 0
    for out in outs:
        text = out.read_bytes()
        assert b"\nelement evil" not in text and b"\nend_header\nelement" not in text, out
    assert len(plyfile.PlyData.read(str(tmp_path / "u.ply"))["vertex"]) > 0
    obj_comments = [ln for ln in (tmp_path / "u.obj").read_text().splitlines() if "evil" in ln]
    assert all(ln.startswith("#") for ln in obj_comments)


def test_config_strings_cannot_inject_toml(tmp_path):
    import tomllib

    from papl_mapper.config import dump_toml

    value = 'x"\nseed = 5\n[frontend]\\'
    assert tomllib.loads(dump_toml({"title": value, "seed": 0})) == {"title": value, "seed": 0}


# ---- row 6: size limits in the map loader --------------------------------------------------------


def test_deflate_bomb_is_refused_before_inflating(tmp_path, good_map, capsys):
    buf = io.BytesIO()
    np.save(buf, np.zeros((30_000_000, 3), np.uint8))  # 90 MB of zeros, ~90 KB deflated
    bomb = rewrite_map(
        good_map, tmp_path / "bomb.papl", arrays={"points.color.npy": buf.getvalue()}, deflate=True
    )
    assert bomb.stat().st_size < 1_000_000
    tracemalloc.start()
    try:
        with pytest.raises(MapFormatError, match="declares 90,000,128 bytes"):
            Map.load(bomb)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20 * 2**20
    fails_cleanly(capsys, ["info", str(bomb)], "bomb.papl")


@pytest.mark.parametrize(
    ("member", "header", "message"),
    [
        ("points.color.npy", _npy_header((10**9, 3), "|u1"), "declares shape"),  # rows beyond the entry
        ("points.xyz.npy", _npy_header((5, 3, 1)), "has shape (5, 3, 1)"),  # wrong rank
        ("points.xyz.npy", _npy_header((5, 3), "|O"), "dtype object"),  # pickled objects
    ],
)
def test_lying_npy_headers(member, header, message, tmp_path, good_map):
    bad = rewrite_map(good_map, tmp_path / "bad.papl", arrays={member: header})
    with pytest.raises(MapFormatError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Map.load(bad)


def test_rows_that_disagree_across_a_group_are_refused_before_allocating(tmp_path, good_map):
    m = Map.load(good_map)
    buf = io.BytesIO()
    np.save(buf, np.zeros((len(m.points) + 1, 3), np.uint8))
    bad = rewrite_map(good_map, tmp_path / "rows.papl", arrays={"points.color.npy": buf.getvalue()})
    with pytest.raises(MapFormatError, match="points.color has"):
        Map.load(bad)


# ---- row 8: several outputs at once --------------------------------------------------------------


def test_multi_export_checks_every_target_before_writing_any(tmp_path, good_map, capsys):
    out = tmp_path / "m8"
    out.mkdir()
    (out / "a.ply").write_text("OLD")
    (out / "b.obj").mkdir()
    before = snapshot(tmp_path)
    targets = [str(out / n) for n in ("a.ply", "b.obj", "c.dxf", "d.tum")]
    fails_cleanly(capsys, ["export", str(good_map), *targets], "b.obj: is a folder")
    untouched(tmp_path, before)


def test_multi_export_reports_each_failed_write_and_writes_the_rest(tmp_path, good_map, capsys, monkeypatch):
    import papl_mapper.exporters.registry as registry

    real = registry.write_atomic

    def full_for_obj(path, data):
        if str(path).endswith(".obj"):
            with registry.atomic_path(path) as tmp:
                tmp.write_bytes(data[:10])
                raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, data)

    monkeypatch.setattr(registry, "write_atomic", full_for_obj)
    (tmp_path / "b.obj").write_text("OLD")
    targets = [str(tmp_path / n) for n in ("a.ply", "b.obj", "c.tum")]
    line = fails_cleanly(capsys, ["export", str(good_map), *targets], "1 of 3 outputs not written")
    assert "b.obj: could not write the file (No space left on device)" in line
    assert (tmp_path / "a.ply").exists() and (tmp_path / "c.tum").exists()
    assert (tmp_path / "b.obj").read_text() == "OLD"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.ply", "b.obj", "c.tum", "good.papl"]


# ---- row 4 and row 9: reruns, SIGTERM, info, a failed run ------------------------------------------


def test_rerun_retires_the_previous_runs_outputs_and_nothing_else(tmp_path, capsys):
    out = tmp_path / "run"
    cam = ["--camera", str(TINY / "camera.json")]
    assert main(["-q", "run", VIDEO, "--out", str(out), *cam, *FAST, "--export", "ply,glb"]) == 0
    first = json.loads((out / "manifest.json").read_text())["files"]
    assert {"map.papl", "map.ply", "map.glb", "log.txt"} <= set(first)
    (out / "notes.txt").write_text("mine")
    (out / "map.obj").write_text("mine too: no manifest lists it")
    checkpoints = sorted(p.name for p in (out / ".checkpoint").iterdir() if p.is_dir())
    # a rerun that fails on bad input changes no output and keeps the checkpoints
    before = snapshot(out)
    bad = camera_file(tmp_path, "bad.json", fx=1e-9, fy=1e-9)
    fails_cleanly(capsys, ["run", VIDEO, "--out", str(out), "--camera", str(bad), *FAST], "bad.json")
    untouched(out, before, allowed=(".checkpoint/log.txt",))
    assert sorted(p.name for p in (out / ".checkpoint").iterdir() if p.is_dir()) == checkpoints
    assert "implausible focal length" in (out / ".checkpoint" / "log.txt").read_text()
    # a finished rerun without exports leaves no stale export
    assert main(["-q", "run", VIDEO, "--out", str(out), *cam, *FAST]) == 0
    names = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
    assert names == sorted(
        ["config.toml", "keyframes.tum", "log.txt", "manifest.json", "map.obj", "map.papl", "notes.txt"]
        + ["summary.json", "trajectory.tum"]
    )
    assert (out / "notes.txt").read_text() == "mine"
    # info accepts the run folder as export, render and report do
    assert main(["info", str(out)]) == 0


def test_sigterm_stops_a_run_with_one_line(tmp_path):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "papl_mapper.cli", "run", VIDEO, "--out", str(out)]
    cmd += ["--camera", str(TINY / "camera.json"), "--set", "focal.enabled=false"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    deadline = time.monotonic() + 120
    while not list((out / ".checkpoint").glob("frontend-*")) and time.monotonic() < deadline:
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    assert "Traceback" not in err
    assert "SIGTERM" in err.strip().splitlines()[-1]
    assert not (out / "map.papl").exists()


def test_a_log_file_on_a_full_disk_is_dropped_quietly(tmp_path, capsys):
    import logging

    from papl_mapper.pipelines.logfile import close_log, file_log

    handler = file_log(tmp_path / "log.txt", "w")

    class Full(io.StringIO):
        def write(self, s):
            raise OSError(errno.ENOSPC, "No space left on device")

        def flush(self):
            raise OSError(errno.ENOSPC, "No space left on device")

    handler.stream = Full()
    try:
        log = logging.getLogger("papl_mapper.test")
        for _ in range(3):  # straight to the handler: other tests' handlers on the logger stay out
            handler.handle(log.makeRecord(log.name, logging.WARNING, __file__, 0, "disk full", None, None))
    finally:
        close_log(handler)  # no OSError from the final flush either
    err = capsys.readouterr().err
    assert "Logging error" not in err and "Traceback" not in err
