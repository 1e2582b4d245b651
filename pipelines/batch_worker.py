"""One recording of a local `papl-map batch` in its own process.

The pool forks each worker from a multiprocessing forkserver that has imported the pipeline once
(`child`), so a worker starts in milliseconds instead of re-importing OpenCV, gtsam and scipy; it is
still a process of its own, so its crash or kill ends only its recording. By hand, the same job:

    python -m papl_mapper.pipelines.batch_worker OUT/.batch/<name>/job.json

Either runs `pipelines.batch.run_job` (which writes result.json beside job.json) and exits 0 when the
recording mapped, 1 when it failed, 130 when interrupted. The first SIGINT interrupts the run at its
next stage boundary (run() keeps the checkpoints); later ones are ignored, so Ctrl-C on the terminal
and the batch forwarding it do not interrupt twice.
"""

from __future__ import annotations

import faulthandler
import json
import os
import signal
import sys
from pathlib import Path

import papl_mapper.pipelines.run  # noqa: F401 - preloaded by the forkserver: what every job imports


def _interrupt_once(signum: int, frame: object) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    raise KeyboardInterrupt


def _job(spec: Path) -> int:
    signal.signal(signal.SIGINT, _interrupt_once)
    try:
        from papl_mapper.pipelines.batch import run_job

        row = run_job(json.loads(spec.read_text()))
    except KeyboardInterrupt:
        return 130
    return {"ok": 0, "interrupted": 130}.get(row["status"], 1)


def child(spec: str, log_path: str) -> None:
    """The target of a forked worker: stdout and stderr (and a crash's traceback) into `log_path`."""
    fd = os.open(log_path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    sys.stdout.flush()
    sys.stderr.flush()
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    faulthandler.enable()
    code = _job(Path(spec))
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)  # no atexit handlers inherited from the forkserver


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    return _job(Path(args[0]))


if __name__ == "__main__":
    sys.exit(main())
