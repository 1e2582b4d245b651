"""The backward registration in a worker process (pipelines/registration.py): the same poses as in the
run's process, and a worker that dies or cannot run costs nothing but time."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from papl_mapper.geometry.se3 import invert
from papl_mapper.geometry.similarity import umeyama
from papl_mapper.pipelines import registration
from papl_mapper.pipelines.batch import thread_limits
from papl_mapper.pipelines.config import RunConfig
from papl_mapper.pipelines.registration import BackwardRegistration
from tests.test_mapping_incremental import make_tracks


@pytest.fixture(scope="module")
def recording():
    tracks, T_cw, _ = make_tracks(n_frames=30, noise_px=0.3)
    return tracks, invert(T_cw)


@pytest.fixture
def two_cores(monkeypatch):
    """The worker runs even on a one-core machine (where the run would not start it)."""
    monkeypatch.setattr(registration, "_cores", lambda: 2)


def _poses(result) -> tuple[list[int], np.ndarray]:
    frames = sorted(result.poses)
    return frames, np.stack([result.poses[f] for f in frames])


def test_the_worker_registers_the_tracks_as_this_process_does(two_cores, recording) -> None:
    tracks, truth = recording
    cfg = RunConfig()
    with BackwardRegistration(cfg) as worker:
        worker.submit(tracks)
        tracks.point_track[:] = tracks.point_track[::-1].copy()  # renamed after submit: not seen
        in_worker = worker.result()
        tracks.point_track[:] = tracks.point_track[::-1].copy()
    here = BackwardRegistration(cfg, worker=False)
    here.submit(tracks)
    in_process = here.result()
    assert in_worker.in_worker and not in_process.in_worker
    frames, T = _poses(in_worker)
    assert frames == sorted(in_process.poses) and len(frames) >= 10
    assert np.array_equal(T, _poses(in_process)[1])  # the same computation, bit for bit
    s = umeyama(T[:, :3, 3], truth[frames, :3, 3])  # and the right one
    assert np.abs(s.apply(T[:, :3, 3]) - truth[frames, :3, 3]).max() < 0.02
    assert in_worker.summary()["in_worker"] is True and in_worker.summary()["registration_s"] > 0


def test_the_workers_log_reaches_this_process(two_cores, recording, caplog) -> None:
    tracks, _ = recording
    with BackwardRegistration(RunConfig()) as worker, caplog.at_level(logging.INFO, logger="papl_mapper"):
        worker.submit(tracks)
        worker.result()
    assert any(r.getMessage().startswith("backward registration: initialised") for r in caplog.records)


def test_a_worker_that_dies_leaves_the_registration_to_this_process(two_cores, recording) -> None:
    tracks, _ = recording
    with BackwardRegistration(RunConfig()) as worker:
        assert worker._proc is not None
        worker._proc.kill()
        worker._proc.wait()
        worker.submit(tracks)
        result = worker.result()
    assert not result.in_worker and len(result.poses) >= 10


def test_no_worker_without_a_second_core_or_the_check_or_when_told(monkeypatch, recording) -> None:
    tracks, _ = recording
    off = RunConfig()
    off.reverse.enabled = False
    with BackwardRegistration(off) as worker:
        assert worker._proc is None
        worker.submit(tracks)  # nothing to do
    alone = RunConfig()
    alone.reverse.worker = False
    with BackwardRegistration(alone) as worker:
        assert worker._proc is None
    with thread_limits(1), BackwardRegistration(RunConfig()) as worker:  # papl-map batch --threads 1
        assert worker._proc is None
    monkeypatch.setattr(registration, "_cores", lambda: 1)
    with BackwardRegistration(RunConfig()) as worker:
        assert worker._proc is None
        worker.submit(tracks)
        assert len(worker.result().poses) >= 10


def test_result_before_submit_is_a_programming_error() -> None:
    with BackwardRegistration(RunConfig(), worker=False) as worker, pytest.raises(RuntimeError):
        worker.result()


def test_the_worker_runs_under_a_script_without_a_main_guard(tmp_path) -> None:
    """The worker does not import the caller's main script again (as multiprocessing's children do)."""
    out = _run_script(
        tmp_path,
        "tracks, _, _ = make_tracks(n_frames=30, noise_px=0.3)\n"
        "with BackwardRegistration(RunConfig()) as worker:\n"
        "    worker.submit(tracks)\n"
        "    result = worker.result()\n"
        "print(result.in_worker, len(result.poses))\n",
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    in_worker, n = out.stdout.split()
    assert in_worker == "True" and int(n) >= 10
    assert "Error" not in out.stderr


def test_the_backward_start_is_adjusted_in_the_worker_as_here(two_cores, recording) -> None:
    tracks, truth = recording
    from papl_mapper.backend import BAConfig, global_ba
    from tests.test_reverse_start import FRAMES, _adjusted_map

    m = _adjusted_map(tracks, truth[FRAMES])
    ba = BAConfig(max_iterations=5)
    with BackwardRegistration(RunConfig()) as worker:
        worker.submit(tracks)
        assert worker.result().in_worker
        wait = worker.ba_aside(m, ba)
        assert worker._proc is not None and worker._proc.poll() is None
        # nicer than the run: the run's own stages go first where both want a core
        assert os.getpriority(os.PRIO_PROCESS, worker._proc.pid) > os.getpriority(os.PRIO_PROCESS, 0)
        there = wait()
    here = global_ba(m, ba).map
    assert np.array_equal(there.keyframes.T_wc, here.keyframes.T_wc)
    assert np.array_equal(there.points.xyz, here.points.xyz)


def test_a_ba_that_fails_in_the_worker_fails_here_too(two_cores, recording) -> None:
    """An error other than the BA's own (here the map check's) makes the run's process run it again,
    which raises it where the caller sees it."""
    from papl_mapper.backend import BAConfig
    from papl_mapper.errors import MapFormatError
    from tests.test_reverse_start import FRAMES, _adjusted_map

    tracks, truth = recording
    m = _adjusted_map(tracks, truth[FRAMES])
    m.points.xyz[:] = np.nan
    with BackwardRegistration(RunConfig()) as worker:
        worker.submit(tracks)
        worker.result()
        wait = worker.ba_aside(m, BAConfig(max_iterations=5))
        with pytest.raises(MapFormatError):
            wait()
        assert worker._proc is None  # stopped: what follows runs here


def test_the_workers_warnings_are_logged_as_information(caplog) -> None:
    with caplog.at_level(logging.DEBUG, logger="papl_mapper"):
        registration._relog(
            [
                (
                    "papl_mapper.mapping.incremental",
                    logging.WARNING,
                    "tracking segment of frames 7-9 left out",
                ),
                ("papl_mapper.mapping.incremental", logging.DEBUG, "detail"),
            ]
        )
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (logging.INFO, "backward registration: tracking segment of frames 7-9 left out"),
        (logging.DEBUG, "backward registration: detail"),
    ]


def test_the_worker_ends_with_the_run_that_started_it(tmp_path) -> None:
    """A run's process that dies (killed, out of memory) takes its worker with it."""
    out = _run_script(
        tmp_path,
        "import os, time\n"
        "tracks, _, _ = make_tracks(n_frames=150, noise_px=0.3)\n"
        "worker = BackwardRegistration(RunConfig())\n"
        "worker.submit(tracks)\n"
        "time.sleep(1.5)  # the worker is registering (about 4 s): it does not wait for a read or write\n"
        "print(worker._proc.pid, flush=True)\n"
        "os._exit(0)\n",
        timeout=120,
    )
    pid = int(out.stdout.split()[0])
    for _ in range(20):  # within a second, not when its registration is done
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        with open(f"/proc/{pid}/stat") as fh:  # a zombie until reaped by init: it has ended
            if fh.read().split()[2] == "Z":
                return
        time.sleep(0.05)
    os.kill(pid, 9)
    raise AssertionError("the worker outlived the run's process")


def _run_script(tmp_path: Path, body: str, timeout: float) -> subprocess.CompletedProcess:
    """`body` run as a user's script (its own main module, no main guard) with the worker forced on
    (as `two_cores`) and `make_tracks`, `RunConfig` and `BackwardRegistration` imported."""
    script = tmp_path / "script.py"
    script.write_text(
        "from papl_mapper.pipelines.config import RunConfig\n"
        "from papl_mapper.pipelines import registration\n"
        "from papl_mapper.pipelines.registration import BackwardRegistration\n"
        "registration._cores = lambda: 2  # as the two_cores fixture\n"
        "from tests.test_mapping_incremental import make_tracks\n" + body
    )
    root = Path(__file__).resolve().parents[1]
    return subprocess.run(
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        cwd=root,
        timeout=timeout,
        env={**os.environ, "PYTHONPATH": str(root)},
    )


def test_a_job_runs_in_the_worker_as_here_and_here_before_the_worker_takes_jobs(two_cores, recording) -> None:
    """`aside` (the run's focal check): the worker's answer is this process's; before the worker has
    answered the registration (a run resumed after it) the job runs in this process."""
    from papl_mapper.backend.calibration import FocalCheckConfig, check_focal
    from tests.test_reverse_start import FRAMES, _adjusted_map

    tracks, truth = recording
    m = _adjusted_map(tracks, truth[FRAMES])
    cfg = FocalCheckConfig()
    here = check_focal(m, cfg, 0)
    with BackwardRegistration(RunConfig()) as worker:
        early = worker.aside(check_focal, m, cfg, 0)
        assert worker._proc is not None and not worker._taking_jobs
        assert early().f_estimated == here.f_estimated
        worker.submit(tracks)
        assert worker.result().in_worker
        pid = worker._proc.pid
        wait = worker.aside(check_focal, m, cfg, 0)
        there = wait()
        assert worker._proc is not None and worker._proc.pid == pid  # answered by the worker
    assert there.f_estimated == here.f_estimated and there.rel_sigma == here.rel_sigma
    assert there.n_windows == here.n_windows
