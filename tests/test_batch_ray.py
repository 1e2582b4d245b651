"""`papl-map batch --ray=ADDRESS` on a one-machine Ray cluster this module starts on 127.0.0.1 (and stops):
the same three recordings as test_batch.py (a, b, and a corrupt one), one worker killed mid-job
(Ray retries it and the retry resumes from its checkpoint), maps identical to `run`'s."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time

import pytest

from papl_mapper.cli import main
from tests import test_batch
from tests.test_batch import TINY, WAIT_S, _needs_tiny, _rows, assert_same_as_run, write_manifest

reference = test_batch.reference  # the session fixture: one `run` of a for both test modules

ray = pytest.importorskip("ray", reason="Ray is not installed (pip install '.[ray]'; scripts/setup.sh does)")


@pytest.fixture(scope="module")
def head(tmp_path_factory):
    from papl_mapper.pipelines.batch_ray import LocalRayHead

    # a ~/.ray/auth_token left by an earlier local `ray.init()` makes Ray 2.60 clients authenticate
    # against this token-less head and fail ("Unauthenticated"): head and clients get a clean HOME
    home = os.environ.get("HOME")
    os.environ["HOME"] = str(tmp_path_factory.mktemp("ray_home"))
    h = LocalRayHead(num_cpus=2)
    h.start()
    try:
        yield h
    finally:
        h.stop()
        if home is None:
            os.environ.pop("HOME", None)
        else:
            os.environ["HOME"] = home
    assert not h.session_pids()


def test_ray_batch_retries_a_killed_worker_and_isolates_the_bad_file(head, reference, tmp_path):
    _needs_tiny()
    manifest = write_manifest(tmp_path / "in")
    out = tmp_path / "out"
    args = [sys.executable, "-m", "papl_mapper.cli", "-q", "batch", f"--ray={head.address}", str(manifest)]
    proc = subprocess.Popen(
        [*args, "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    # kill a's worker once its frontend is checkpointed (the job is then in its registration)
    deadline = time.monotonic() + WAIT_S
    while not list((out / "a" / ".checkpoint").glob("frontend-*")):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "a did not reach its frontend checkpoint"
        time.sleep(0.02)
    pid = int((out / ".batch" / "a" / "attempts").read_text().split()[-1])
    assert pid in head.task_pids(), "a's job is not a task of this cluster"
    os.kill(pid, signal.SIGKILL)
    stdout, stderr = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 1, stderr  # bad failed, the others mapped
    rows = _rows(out)
    assert rows["a"]["status"] == "ok" and rows["a"]["attempts"] == 2, rows["a"]
    assert rows["a"]["resumed_from"] is not None  # the retry continued from the checkpoint
    assert rows["b"]["status"] == "ok" and rows["b"]["attempts"] == 1
    assert rows["bad"]["status"] == "failed" and "bad.mp4" in rows["bad"]["error"]
    assert rows["bad"]["attempts"] == 1  # a failing recording is not retried
    for name in ("a", "b"):
        assert_same_as_run(out / name, reference)
    doc = json.loads((out / "batch.json").read_text())
    assert doc["engine"]["engine"] == "ray" and doc["engine"]["address"] == head.address
    page = (out / "index.html").read_text()
    # without --report (test_batch.py asks for it) the index links each recording's summary
    assert 'href="a/summary.json"' in page and 'href="b/summary.json"' in page and "not a video" in page
    assert "bad: failed:" in stdout and stderr == ""


def test_unreachable_ray_address_is_one_line(tmp_path, capsys):
    _needs_tiny()
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = main(["batch", f"--ray=127.0.0.1:{port}", str(TINY / "video.mp4"), "--out", str(tmp_path / "o")])
    assert code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"127.0.0.1:{port}: no Ray cluster answers there" in err, err
    assert not (tmp_path / "o").exists()
