"""Keyframe registration with the run's settings: forward in the run's process, and backward (the
second start of `mapping/reverse_start.py`) in a worker process beside it.

gtsam's optimisers hold Python's GIL, so a thread would not run the backward registration beside the
forward one; a process does, on a second core. The worker is spawned when the run starts (its
imports overlap the frontend), gets the tracks when the frontend has them, and is stopped when the
run ends, whether or not its poses were used. Where no worker can run (one core, a daemonic process,
a worker that died), the backward registration runs in the run's process when its poses are needed,
with the same answer.
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import os
import signal
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
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
    manager: leaving it stops the worker."""

    def __init__(self, cfg: RunConfig, worker: bool = True) -> None:
        self._cfg = cfg
        self._tracks: Tracks | None = None
        self._conn: Connection | None = None
        self._proc: multiprocessing.process.BaseProcess | None = None
        if worker and cfg.reverse.enabled and _cores() > 1 and not multiprocessing.current_process().daemon:
            try:
                ctx = multiprocessing.get_context("spawn")
                self._conn, child = ctx.Pipe()
                self._proc = ctx.Process(
                    target=_work, args=(child, cfg), name="papl-map backward", daemon=True
                )
                self._proc.start()
                child.close()
            except OSError as exc:
                log.info("no worker process for the backward registration (%s): it runs in this one", exc)
                self.close()

    def submit(self, tracks: Tracks) -> None:
        """Start registering `tracks` backwards (in the worker, where there is one)."""
        if not self._cfg.reverse.enabled:
            return
        self._tracks = tracks.reversed()  # a copy: what the forward registration renames stays out
        if self._conn is not None:
            try:
                self._conn.send(self._tracks)
            except OSError:
                self.close()

    def result(self, progress: ProgressCallback | None = None) -> BackwardResult:
        """The backward keyframe poses; waits for the worker, or registers in this process (with
        `progress`) where it has none or it failed. `submit` first."""
        if self._tracks is None:
            raise RuntimeError("BackwardRegistration.result before submit")
        if self._conn is not None:
            try:
                poses, seconds, records = self._conn.recv()
            except (EOFError, OSError):
                log.info("the backward registration's worker process ended early: it runs in this one")
            else:
                for name, level, message in records:
                    logging.getLogger(name).log(level, "backward registration: %s", message)
                return BackwardResult(poses, seconds, True)
            finally:
                self.close()
        t0 = time.perf_counter()
        poses = _backward(self._tracks, self._cfg, progress)
        return BackwardResult(poses, time.perf_counter() - t0, False)

    def close(self) -> None:
        """Stop the worker (idempotent); `result` then registers in this process."""
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._proc is not None:
            if self._proc.is_alive():
                self._proc.terminate()
            self._proc.join()
            self._proc = None

    def __enter__(self) -> BackwardRegistration:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


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


def _work(conn: Connection, cfg: RunConfig) -> None:
    """The worker process: one set of reversed tracks in, (poses, seconds, log records) out."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the run's to handle; it stops the worker
    handler = _Records()
    root = logging.getLogger("papl_mapper")
    root.addHandler(handler)
    root.setLevel(logging.DEBUG)
    try:
        tracks = conn.recv()
    except EOFError:
        return
    t0 = time.perf_counter()
    poses = _backward(tracks, cfg, None)
    conn.send((poses, time.perf_counter() - t0, handler.records))
    conn.close()
