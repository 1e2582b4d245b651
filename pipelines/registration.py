"""Keyframe registration with the run's settings: forward in the run's process, and backward (the
second start of `mapping/reverse_start.py`) in a worker process beside it.

gtsam's optimisers hold Python's GIL, so a thread would not run the backward registration beside the
forward one; a process does, on a second core. The worker is started when the run starts (its
imports overlap the frontend), gets the tracks when the frontend has them, and is stopped when the
run ends, whether or not its poses were used. Where no worker can run (one core, a worker that
died), the backward registration runs in the run's process when its poses are needed, with the
same answer.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import pickle
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from types import TracebackType

import numpy as np

from papl_mapper.mapping.incremental import Registration, register_keyframes
from papl_mapper.mapping.reverse_start import backward_poses
from papl_mapper.mapping.windowed import WindowedRefiner
from papl_mapper.pipelines.config import RunConfig
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)

ProgressCallback = Callable[[int, int, str], None]


def register_tracks(tracks: Tracks, cfg: RunConfig, progress: ProgressCallback | None) -> Registration:
    """`register_keyframes` with the windowed BA as its refinement."""
    local = dataclasses.replace(cfg.ba, relative_error_tol=cfg.local_ba_relative_error_tol)
    refine = WindowedRefiner(tracks, local, cfg.local_ba_window, cfg.max_point_error_px)
    return register_keyframes(
        tracks, cfg.mapping, progress, refine if cfg.mapping.refine_every > 0 else None, cfg.seed
    )


@dataclasses.dataclass
class BackwardResult:
    """The backward registration's keyframe poses (T_wc by frame row of the forward tracks; empty
    where it registered none), its wall time, and whether it ran in the worker process."""

    poses: dict[int, np.ndarray]
    seconds: float
    in_worker: bool

    def summary(self) -> dict:
        """For summary.json's reverse_check."""
        return {"registration_s": round(self.seconds, 4), "in_worker": self.in_worker}


class BackwardRegistration:
    """The recording registered backwards, in a worker process from `submit` (the tracks as the
    frontend made them, before the forward registration renames any) to `result`. A context
    manager: leaving it stops the worker.

    The worker is `python -m papl_mapper.pipelines.registration` with two pipes (pickles in, one
    pickle out), not a multiprocessing child: those import the caller's main script again, which a
    script without a main guard cannot survive."""

    def __init__(self, cfg: RunConfig, worker: bool = True) -> None:
        self._cfg = cfg
        self._tracks: Tracks | None = None
        self._proc: subprocess.Popen | None = None
        self._to_worker: int | None = None
        self._from_worker: int | None = None
        self._sender: threading.Thread | None = None
        self._stderr = None
        if worker and cfg.reverse.enabled and _cores() > 1:
            r_in, w_in = os.pipe()
            r_out, w_out = os.pipe()
            try:
                self._stderr = tempfile.TemporaryFile()
                self._proc = subprocess.Popen(
                    [sys.executable, "-m", __name__, str(r_in), str(w_out)],
                    pass_fds=(r_in, w_out),
                    stdin=subprocess.DEVNULL,
                    stdout=subprocess.DEVNULL,
                    stderr=self._stderr,
                    start_new_session=True,  # Ctrl-C is the run's to handle; leaving it stops the worker
                )
            except OSError as exc:
                log.info("no worker process for the backward registration (%s): it runs in this one", exc)
                os.close(w_in)
                os.close(r_out)
            else:
                self._to_worker, self._from_worker = w_in, r_out
            finally:
                os.close(r_in)
                os.close(w_out)

    def submit(self, tracks: Tracks) -> None:
        """Start registering `tracks` backwards (in the worker, where there is one)."""
        if not self._cfg.reverse.enabled:
            return
        self._tracks = tracks.reversed()  # a copy: what the forward registration renames stays out
        if self._to_worker is not None:
            data = pickle.dumps((self._cfg, self._tracks), pickle.HIGHEST_PROTOCOL)
            fd, self._to_worker = self._to_worker, None
            self._sender = threading.Thread(target=_send, args=(fd, data), daemon=True)
            self._sender.start()  # the worker may still be importing: do not wait for it here

    def result(self, progress: ProgressCallback | None = None) -> BackwardResult:
        """The backward keyframe poses; waits for the worker, or registers in this process (with
        `progress`) where it has none or it failed. `submit` first."""
        if self._tracks is None:
            raise RuntimeError("BackwardRegistration.result before submit")
        if self._from_worker is not None:
            fd, self._from_worker = self._from_worker, None
            try:
                with os.fdopen(fd, "rb") as fh:
                    poses, seconds, records = pickle.load(fh)
            except (EOFError, OSError, pickle.UnpicklingError, ValueError, TypeError):
                log.info(
                    "the backward registration's worker process ended early (%s): it runs in this one",
                    self._worker_error(),
                )
            else:
                for name, level, message in records:
                    logging.getLogger(name).log(level, "backward registration: %s", message)
                if poses is not None:
                    return BackwardResult(poses, seconds, True)
            finally:
                self.close()
        t0 = time.perf_counter()
        poses = _backward(self._tracks, self._cfg, progress)
        return BackwardResult(poses, time.perf_counter() - t0, False)

    def close(self) -> None:
        """Stop the worker (idempotent); `result` then registers in this process."""
        if self._proc is not None:
            if self._proc.poll() is None:
                self._proc.kill()
            self._proc.wait()
            self._proc = None
        for fd in (self._to_worker, self._from_worker):
            if fd is not None:
                os.close(fd)
        self._to_worker = self._from_worker = None
        if self._sender is not None:
            self._sender.join()
            self._sender = None
        if self._stderr is not None:
            self._stderr.close()
            self._stderr = None

    def _worker_error(self) -> str:
        """The last line the worker wrote to stderr, or its exit status."""
        if self._proc is None or self._stderr is None:
            return "no worker"
        code = self._proc.wait()
        self._stderr.seek(0)
        lines = [ln.strip() for ln in self._stderr.read().decode(errors="replace").splitlines() if ln.strip()]
        return lines[-1] if lines else f"exit status {code}"

    def __enter__(self) -> BackwardRegistration:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def _send(fd: int, data: bytes) -> None:
    """Write `data` into the pipe `fd` and close it (a worker that died has closed its end)."""
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
    except OSError:
        pass


def _cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _backward(
    reversed_tracks: Tracks, cfg: RunConfig, progress: ProgressCallback | None
) -> dict[int, np.ndarray]:
    return backward_poses(reversed_tracks, lambda t: register_tracks(t, cfg, progress))


class _Records(logging.Handler):
    """The worker's log records as (logger, level, message), for the run's process to log."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[tuple[str, int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append((record.name, record.levelno, record.getMessage()))


def _work(fd_in: int, fd_out: int) -> None:
    """The worker process: (config, reversed tracks) in, (poses, seconds, log records) out; poses
    None where the registration raised (the run's process then raises it again itself)."""
    handler = _Records()
    root = logging.getLogger("papl_mapper")
    root.addHandler(handler)
    root.setLevel(logging.DEBUG)
    with os.fdopen(fd_in, "rb") as fh:
        cfg, tracks = pickle.load(fh)
    t0 = time.perf_counter()
    try:
        poses = _backward(tracks, cfg, None)
    except Exception:  # noqa: BLE001 - reported through the pipe, raised again in the run's process
        log.debug("the backward registration failed in the worker", exc_info=True)
        poses = None
    with os.fdopen(fd_out, "wb") as fh:
        pickle.dump((poses, time.perf_counter() - t0, handler.records), fh, pickle.HIGHEST_PROTOCOL)


if __name__ == "__main__":
    _work(int(sys.argv[1]), int(sys.argv[2]))
