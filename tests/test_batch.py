"""`papl-map batch` on the local pool: manifests and their errors, names, failure isolation, Ctrl-C and
resume, and maps identical to `run`'s.

The recordings are the first 1.2 s of samples/tiny with 3 BA iterations and no focal check (as in
test_resume.py), given through a manifest: `a` (samples/tiny, with its camera and ground truth), `b`
(a copy of the same video under another name) and `bad` (random bytes named .mp4).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

from papl_mapper.cli import main
from papl_mapper.config import load_config
from papl_mapper.errors import InputError
from papl_mapper.pipelines.batch import frontend_key, probe, read_result
from papl_mapper.pipelines.batch_inputs import assign_names, collect
from papl_mapper.pipelines.config import RunConfig

from .conftest import default_sigint

TINY = Path(__file__).resolve().parents[1] / "samples" / "tiny"
DEMO = Path(__file__).resolve().parents[1] / "samples" / "demo"
FAST_SET = ["ba.max_iterations=3", "focal.enabled=false"]
FAST_END = 1.2
WAIT_S = 180.0  # generous: the machine is shared


def _needs_tiny() -> None:
    if not (TINY / "video.mp4").exists():
        pytest.skip("samples/tiny is not there")


def write_manifest(folder: Path, with_bad: bool = True) -> Path:
    """a (samples/tiny with camera and gt), b (a copy of it), bad (random bytes), FAST settings."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(TINY / "video.mp4", folder / "copy.mp4")
    (folder / "bad.mp4").write_bytes(np.random.default_rng(0).bytes(20000))
    sets = ", ".join(f'"{s}"' for s in FAST_SET)
    text = f'[defaults]\ncamera = "{TINY / "camera.json"}"\nend = {FAST_END}\nset = [{sets}]\n\n'
    text += f'[[recording]]\nname = "a"\npath = "{TINY / "video.mp4"}"\ngt = "{TINY / "gt"}"\n\n'
    text += '[[recording]]\nname = "b"\npath = "copy.mp4"\n\n'
    if with_bad:
        text += '[[recording]]\nname = "bad"\npath = "bad.mp4"\n'
    path = folder / "walks.toml"
    path.write_text(text)
    return path


def run_reference(out: Path) -> Path:
    """What `run` gives for recording a (the same call `papl-map run` makes)."""
    from papl_mapper.pipelines.run import run

    cfg = load_config(
        RunConfig, None, [*FAST_SET, f"input.camera={TINY / 'camera.json'}", f"input.end_s={FAST_END}"]
    )
    run(TINY / "video.mp4", out, cfg)
    return out


@pytest.fixture(scope="session")
def reference(tmp_path_factory) -> Path:
    _needs_tiny()
    return run_reference(tmp_path_factory.mktemp("batch_reference"))


def assert_same_as_run(out: Path, reference: Path) -> None:
    """Every array of map.papl, the trajectories and config.toml are identical to the reference's (the
    config's extras aside: the batch asks for a report, recording a has ground truth)."""
    a, b = np.load(out / "map.papl"), np.load(reference / "map.papl")
    assert set(a.files) == set(b.files)
    for k in a.files:
        if k != "meta.json":  # timings and the source's path
            x, y = a[k], b[k]
            assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), k
    for name in ("trajectory.tum", "keyframes.tum"):
        assert (out / name).read_bytes() == (reference / name).read_bytes(), name
    settings = [tomllib.loads((folder / "config.toml").read_text()) for folder in (out, reference)]
    for s in settings:
        s.pop("output")
    assert settings[0] == settings[1]


def _papl_map(*args: str) -> list[str]:
    return [sys.executable, "-m", "papl_mapper.cli", *args]


def _rows(out: Path) -> dict[str, dict]:
    doc = json.loads((out / "batch.json").read_text())
    return {r["name"]: r for r in doc["recordings"]}


# ---- a batch interrupted and resumed ----------------------------------------------------------------


@pytest.fixture(scope="module")
def batch(tmp_path_factory) -> dict:
    """`papl-map batch walks.toml --workers 1`, SIGINT once b has its frontend checkpoint, then the same
    command with --workers 2. Returns the folders and what each step gave."""
    _needs_tiny()
    root = tmp_path_factory.mktemp("batch")
    manifest = write_manifest(root / "in")
    out = root / "out"
    args = _papl_map("-q", "batch", str(manifest), "--out", str(out), "--report")
    proc = subprocess.Popen(
        [*args, "--workers", "1"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=default_sigint,
    )
    deadline = time.monotonic() + WAIT_S
    while not list((out / "b" / ".checkpoint").glob("frontend-*")):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "b did not reach its frontend checkpoint"
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)
    first_out, first_err = proc.communicate(timeout=WAIT_S)
    interrupted = {"code": proc.returncode, "out": first_out, "err": first_err, "rows": _rows(out)}
    a_map = out / "a" / "map.papl"
    a_before = (a_map.stat().st_mtime_ns, (out / ".batch" / "a" / "attempts").read_text())
    proc = subprocess.run([*args, "--workers", "2"], capture_output=True, text=True, timeout=WAIT_S)
    a_after = (a_map.stat().st_mtime_ns, (out / ".batch" / "a" / "attempts").read_text())
    resumed = {"code": proc.returncode, "out": proc.stdout, "err": proc.stderr, "rows": _rows(out)}
    return {
        "root": root,
        "out": out,
        "manifest": manifest,
        "interrupted": interrupted,
        "resumed": resumed,
        "a_unchanged": a_before == a_after,
    }


def test_sigint_stops_the_batch_and_keeps_what_finished(batch):
    first = batch["interrupted"]
    assert first["code"] == 130, first["err"]
    assert first["err"].strip().count("\n") == 0 and "rerun the same command" in first["err"], first["err"]
    rows = first["rows"]
    assert rows["a"]["status"] == "ok"
    assert rows["b"]["status"] == "interrupted", rows["b"]
    assert rows["bad"]["status"] == "pending"


def test_resumed_batch_skips_finished_and_continues_the_half_finished(batch):
    second = batch["resumed"]
    rows = second["rows"]
    assert batch["a_unchanged"]  # a was not recomputed: same map file, no new attempt
    assert rows["a"]["reused"] is True
    assert rows["b"]["status"] == "ok" and rows["b"]["resumed_from"] in (
        "frontend",
        "registration",
        "ba_points",
    )
    out = batch["out"]
    assert "resumed: frontend tracks from" in (out / "b" / "log.txt").read_text()


def test_a_bad_recording_fails_alone_with_its_error(batch):
    second = batch["resumed"]
    assert second["code"] == 1  # one failed
    bad = second["rows"]["bad"]
    assert bad["status"] == "failed"
    assert "bad.mp4" in bad["error"] and "\n" not in bad["error"]
    assert f"bad: failed: {bad['error']}" in second["out"]
    assert "1 failed (bad)" in second["out"]
    assert second["err"] == ""  # no traceback, no FFmpeg noise from the driver
    doc = json.loads((batch["out"] / "batch.json").read_text())
    assert doc["finished"] is True and doc["totals"]["ok"] == 2 and doc["totals"]["failed"] == 1


def test_batch_outputs_are_what_run_writes(batch, reference):
    out = batch["out"]
    for name in ("a", "b"):
        assert_same_as_run(out / name, reference)
        for f in ("map.papl", "trajectory.tum", "keyframes.tum", "config.toml", "summary.json", "log.txt"):
            assert (out / name / f).exists()
        assert (out / name / "report.html").exists()
    assert (out / "a" / "eval.json").exists() and not (out / "b" / "eval.json").exists()
    assert _rows(out)["a"]["ate_rmse"] is not None
    # the key the batch skips by names the frontend checkpoint run() wrote (same fields, same hash)
    from papl_mapper.pipelines.batch import Job

    job = Job.from_dict(json.loads((out / ".batch" / "a" / "job.json").read_text()))
    import hashlib

    digest = hashlib.sha256(frontend_key(job, job.config(), probe(job)).encode()).hexdigest()[:16]
    assert (out / "a" / ".checkpoint" / f"frontend-{digest}").is_dir()


def test_index_links_each_report_and_shows_the_error(batch):
    out = batch["out"]
    page = (out / "index.html").read_text()
    assert 'href="a/report.html"' in page and 'href="b/report.html"' in page
    assert "not a video" in page  # bad's error line
    assert "<script" not in page and "http://" not in page and "https://" not in page
    assert "recordings per minute" in page


def test_output_folder_of_another_batch_is_refused(batch, tmp_path, capsys):
    other = tmp_path / "other.mp4"
    shutil.copy(TINY / "video.mp4", other)
    # a batch whose recording "a" is another file, into the folder that holds a = samples/tiny
    manifest = tmp_path / "m.csv"
    manifest.write_text(f"name,path,camera\na,{other},{TINY / 'camera.json'}\n")
    before = (batch["out"] / "batch.json").read_bytes()
    assert main(["batch", str(manifest), "--out", str(batch["out"])]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "holds another batch" in err, err
    assert (batch["out"] / "batch.json").read_bytes() == before


# ---- worker deaths ----------------------------------------------------------------------------------


def test_worker_over_the_memory_limit_is_stopped_and_marked(tmp_path, capsys):
    _needs_tiny()
    code = main(
        [
            "-q",
            "batch",
            str(TINY / "video.mp4"),
            "--out",
            str(tmp_path / "out"),
            "--memory-limit",
            "0.05",
            *("--end", str(FAST_END)),
        ]
    )
    assert code == 1
    row = _rows(tmp_path / "out")["video"]
    assert row["status"] == "failed" and "over the limit of 0.05 GiB (--memory-limit)" in row["error"]
    assert "video: failed: its worker was stopped at" in capsys.readouterr().out


def test_killed_worker_is_one_failed_recording(tmp_path):
    _needs_tiny()
    out = tmp_path / "out"
    args = _papl_map("-q", "batch", str(TINY / "video.mp4"), "--out", str(out), "--end", str(FAST_END))
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    attempts = out / ".batch" / "video" / "attempts"
    deadline = time.monotonic() + WAIT_S
    while not (attempts.exists() and attempts.read_text().strip()):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.02)
    os.kill(int(attempts.read_text().split()[-1]), signal.SIGKILL)  # the worker process the job runs in
    stdout, stderr = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 1, stderr
    row = _rows(out)["video"]
    assert row["status"] == "failed" and row["error"].startswith("its worker died of SIGKILL"), row
    assert read_result(out / ".batch" / "video")[1]["status"] == "failed"


# ---- inputs, manifests, names -----------------------------------------------------------------------


def test_manifests_toml_and_csv(tmp_path):
    _needs_tiny()
    toml = write_manifest(tmp_path)
    recs = collect([toml])
    assert [r.name for r in recs] == ["a", "b", "bad"]
    a, b, _ = recs
    assert a.path == TINY / "video.mp4" and a.gt == TINY / "gt" and a.end == FAST_END
    assert b.path == tmp_path / "copy.mp4" and b.camera == TINY / "camera.json" and b.set == FAST_SET
    csv = tmp_path / "walks.csv"
    csv.write_text(
        "# walks of Monday\npath,start,end,step,set,gt\n"
        f"copy.mp4,0.5,2,2,{';'.join(FAST_SET)},{TINY / 'gt'}\n"
        "bad.mp4,,,,,\n"
    )
    r1, r2 = collect([csv])
    assert (r1.start, r1.end, r1.step, r1.set, r1.gt) == (0.5, 2.0, 2, FAST_SET, TINY / "gt")
    assert r2.path == tmp_path / "bad.mp4" and r2.start is None and r2.origin.endswith("line 4")


BAD_MANIFESTS = {
    "empty.toml": ("# nothing\n", "empty manifest"),
    "empty.csv": ("path,end\n", "empty manifest"),
    "missing.toml": ('[[recording]]\npath = "x.mp4"\n\n[[recording]]\npath = "nope.mp4"\n', "line 4: path"),
    "missing.csv": ("path\nx.mp4\nnope.mp4\n", "line 3: path nope.mp4: no such file"),
    "key.toml": ('[[recording]]\npath = "x.mp4"\nstrat = 2\n', "line 1: unknown key 'strat'"),
    "type.toml": (
        '[[recording]]\npath = "x.mp4"\nstep = "two"\n',
        "line 1: step = 'two': expected an integer",
    ),
    "column.csv": ("path,strat\nx.mp4,2\n", "line 1: unknown column 'strat'"),
    "number.csv": ("path,end\nx.mp4,soon\n", "line 2: end 'soon': expected a number"),
    "range.csv": ("path,start,end\nx.mp4,5,2\n", "line 2: end 2 s is before start 5 s"),
    "dup.csv": ("path,end\nx.mp4,2\nx.mp4,2\n", "duplicate recording"),
    "names.csv": ("path,name\nx.mp4,n\ny.mp4,n\n", "line 3: name 'n' is already used by"),
    "set.csv": ("path,set\nx.mp4,ba.nope=1\n", "line 2: unknown config key 'ba.nope'"),
    "preset.toml": ('[[recording]]\npath = "x.mp4"\npreset = "fast"\n', "line 1: unknown preset 'fast'"),
    "syntax.toml": ("[[recording]\n", "not valid TOML"),
}


@pytest.mark.parametrize("name", list(BAD_MANIFESTS))
def test_bad_manifest_is_one_line_naming_it(name, tmp_path, capsys):
    text, expected = BAD_MANIFESTS[name]
    (tmp_path / "x.mp4").write_bytes(b"not read")
    (tmp_path / "y.mp4").write_bytes(b"not read")
    manifest = tmp_path / name
    manifest.write_text(text)
    out = tmp_path / "out"
    assert main(["batch", str(manifest), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert str(manifest) in err and expected in err, err
    assert not out.exists()  # nothing started


def test_bad_inputs_and_output_folders(tmp_path, capsys):
    _needs_tiny()
    run_out = tmp_path / "run_out"
    run_out.mkdir()
    (run_out / "summary.json").write_text("{}")
    cases = [
        ([str(tmp_path / "nope.mp4")], tmp_path / "o1", "no such file or folder"),
        ([str(tmp_path / "empty")], tmp_path / "o2", "no recordings found"),
        ([str(TINY / "video.mp4"), str(TINY / "video.mp4")], tmp_path / "o3", "duplicate recording"),
        ([str(TINY / "video.mp4")], run_out, "holds the outputs of a `papl-map run`"),
    ]
    (tmp_path / "empty").mkdir()
    for inputs, out, expected in cases:
        assert main(["batch", *inputs, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and expected in err, err


def test_folder_input_finds_videos_cameras_and_ground_truth(tmp_path):
    _needs_tiny()
    recs = collect([TINY.parent])  # samples/: demo/video.mp4 and tiny/video.mp4
    by_parent = {r.path.parent.name: r for r in recs}
    assert {"tiny"} <= set(by_parent)
    assert by_parent["tiny"].camera == TINY / "camera.json" and by_parent["tiny"].gt == TINY / "gt"
    if (DEMO / "video.mp4").exists():
        assert assign_names(recs) == [f"{r.path.parent.name}-video" for r in recs]


def test_names_are_unique_and_stable(tmp_path):
    _needs_tiny()
    recs = collect([TINY / "video.mp4"])
    assert assign_names(recs) == ["video"]
    csv = tmp_path / "m.csv"
    shutil.copy(TINY / "video.mp4", tmp_path / "video.mp4")
    csv.write_text(f"path,end\n{TINY / 'video.mp4'},1\n{TINY / 'video.mp4'},2\nvideo.mp4,1\n")
    recs = collect([csv])
    names = assign_names(recs)
    assert len(set(names)) == 3
    assert names[0].startswith("tiny-video-") and names[1].startswith("tiny-video-")
    assert names[2] == f"{tmp_path.name}-video"
    # an earlier run's names are kept, whatever else the batch now holds
    prev = {recs[2].identity(): "mine"}
    assert assign_names(recs, prev)[2] == "mine"
    with pytest.raises(InputError, match=r"line 2: name '\.\.'"):
        bad = tmp_path / "n.csv"
        bad.write_text(f"path,name\n{TINY / 'video.mp4'},..\n")
        collect([bad])


def test_a_jobs_memory_counts_its_child_processes() -> None:
    """--memory-limit watches the job with the worker process its run starts beside it."""
    from papl_mapper.pipelines.batch import _rss

    child = subprocess.Popen(
        [sys.executable, "-c", "import sys; b = bytearray(200 * 2**20); sys.stdin.read()"],
        stdin=subprocess.PIPE,
    )
    try:
        for _ in range(100):  # until the child holds its 200 MiB
            if _rss(child.pid) > 200 * 2**20:
                break
            time.sleep(0.05)
        alone = _rss(child.pid)
        assert alone > 200 * 2**20
        me = _rss_self_only()
        assert _rss(os.getpid()) >= 0.9 * (alone + me)
    finally:
        child.stdin.close()
        child.wait()


def _rss_self_only() -> int:
    with open("/proc/self/status") as fh:
        return next(int(ln.split()[1]) * 1024 for ln in fh if ln.startswith("VmRSS:"))
