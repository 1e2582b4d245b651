"""Keyframe registration with the run's settings: forward in the run's process, and backward (the
second start of `mapping/reverse_start.py`) in a worker process beside it, which then runs other jobs
of the run beside its own stages (the backward start's BA, the focal check).

gtsam's optimisers hold Python's GIL, so a thread would not run the backward registration beside the
forward one; a process does, on a second core. The worker is forked when the run starts (so it
imports nothing), gets the tracks when the frontend has them, and is stopped when the run ends,
whether or not its poses were used. Where no worker can run (one core, a worker that
died), the backward registration runs in the run's process when its poses are needed, with the
same answer.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import functools
import logging
import os
import pickle
import signal
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable
from types import TracebackType
from typing import Any, BinaryIO, TypeVar

import cv2
import numpy as np

from papl_mapper.backend import BAConfig, global_ba
from papl_mapper.errors import GeometryError, OptimizationError
from papl_mapper.map import Map
from papl_mapper.mapping.incremental import Registration, register_keyframes
from papl_mapper.mapping.reverse_start import backward_poses
from papl_mapper.mapping.windowed import WindowedRefiner
from papl_mapper.pipelines.config import RunConfig
from papl_mapper.tracks import Tracks

log = logging.getLogger(__name__)

ProgressCallback = Callable[[int, int, str], None]
T = TypeVar("T")
_PR_SET_PDEATHSIG = 1  # prctl(2)
_WORKER_NICENESS = 10
"""The worker runs this much nicer than the run: where both want the cores (its imports during the
frontend), the run's stages go first (benchmarks/results/notes.md)."""


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
    frontend made them, before the forward registration renames any) to `result`; then, on request
    (`aside`), jobs beside the run's own stages: the global BA of the backward start beside the
    forward start's, the focal check beside the frames' poses. A context manager: leaving it stops
    the worker.

    The worker is this process forked, with two pipes (pickles each way): it has every module the run
    has (a new interpreter would spend a core's half second importing them while the frontend wants
    both cores), and it is not a multiprocessing child, which would import the caller's main script
    again (a spawn child) or run its exit handlers (a fork child's finalisers)."""

    def __init__(self, cfg: RunConfig, worker: bool = True) -> None:
        self._cfg = cfg
        self._tracks: Tracks | None = None
        self._proc: _Forked | None = None
        self._send: BinaryIO | None = None
        self._recv: BinaryIO | None = None
        self._sender: threading.Thread | None = None
        self._stderr: BinaryIO | None = None
        self._taking_jobs = False  # the worker answered the registration and waits for jobs
        if worker and cfg.reverse.enabled and cfg.reverse.worker and _cores() > 1 and hasattr(os, "fork"):
            r_in, w_in = os.pipe()
            r_out, w_out = os.pipe()
            try:
                self._stderr = tempfile.TemporaryFile()
                self._proc = _fork_worker(r_in, w_out, (w_in, r_out), self._stderr.fileno())
            except OSError as exc:
                log.info("no worker process for the backward registration (%s): it runs in this one", exc)
                os.close(w_in)
                os.close(r_out)
            else:
                self._send, self._recv = os.fdopen(w_in, "wb"), os.fdopen(r_out, "rb")
            finally:
                os.close(r_in)
                os.close(w_out)

    @property
    def submitted(self) -> bool:
        """Whether `submit` gave it tracks."""
        return self._tracks is not None

    def submit(self, tracks: Tracks) -> None:
        """Start registering `tracks` backwards (in the worker, where there is one)."""
        if not self._cfg.reverse.enabled:
            return
        self._tracks = tracks.reversed()  # a copy: what the forward registration renames stays out
        if self._send is not None:
            data = pickle.dumps((self._cfg, self._tracks), pickle.HIGHEST_PROTOCOL)
            self._sender = threading.Thread(target=_write, args=(self._send, data), daemon=True)
            self._sender.start()  # the worker may still be importing: do not wait for it here

    def result(self, progress: ProgressCallback | None = None) -> BackwardResult:
        """The backward keyframe poses; waits for the worker, or registers in this process (with
        `progress`) where it has none or it failed. `submit` first."""
        if self._tracks is None:
            raise RuntimeError("BackwardRegistration.result before submit")
        if self._recv is not None:
            reply = self._reply(second_start=True)
            if reply is not None and reply[0] is not None:
                poses, seconds = reply
                self._taking_jobs = True
                return BackwardResult(poses, seconds, True)
            self.close()
        t0 = time.perf_counter()
        poses = _backward(self._tracks, self._cfg, progress)
        return BackwardResult(poses, time.perf_counter() - t0, False)

    def ba_aside(self, m: Map, ba: BAConfig) -> Callable[[], Map]:
        """`aside` of the global BA of `m`: what it returns waits for the adjusted map."""
        wait = self.aside(global_ba, m, ba, second_start=True)
        return lambda: wait().map

    def aside(self, fn: Callable[..., T], *args: Any, second_start: bool = False) -> Callable[[], T]:
        """Start fn(*args) in the worker (one job at a time, after `result`); what it returns waits for
        fn's answer. Without a worker taking jobs, fn runs in this process when waited for. A
        GeometryError or OptimizationError of fn is raised by the wait, as fn would; after another
        error in the worker, fn runs again here. `fn` must be importable by name (pickled).
        `second_start`: a job of the backward start, whose log is relogged as such (`_relog`)."""
        if self._sender is not None:
            self._sender.join()  # the tracks are through: the pipe is free
            self._sender = None
        if self._taking_jobs and self._send is not None and self._recv is not None:
            try:
                self._send.write(pickle.dumps((fn, args), pickle.HIGHEST_PROTOCOL))
                self._send.flush()
            except OSError:
                self.close()
            else:
                return functools.partial(self._answer, fn, args, second_start)
        return lambda: fn(*args)

    def _answer(self, fn: Callable[..., T], args: tuple, second_start: bool) -> T:
        reply = self._reply(second_start)
        if reply is not None and isinstance(reply[0], (GeometryError, OptimizationError)):
            raise reply[0]
        if reply is not None and reply[0] is not None:
            return reply[0]
        self.close()
        return fn(*args)

    def _reply(self, second_start: bool) -> tuple[Any, float] | None:
        """The worker's next (answer, seconds), its log records logged here (as `_relog`); None when it
        ended."""
        assert self._recv is not None
        try:
            answer, seconds, records = pickle.load(self._recv)
        except (EOFError, OSError, pickle.UnpicklingError, ValueError, TypeError, AttributeError):
            log.info(
                "the backward registration's worker process ended early (%s): this process goes on alone",
                self._worker_error(),
            )
            self.close()
            return None
        _relog(records, second_start)
        return answer, seconds

    def close(self) -> None:
        """Stop the worker (idempotent); the registration and the BA then run in this process."""
        if self._proc is not None:
            if self._proc.poll() is None:
                self._proc.kill()
            self._proc.wait()
            self._proc = None
        if self._sender is not None:
            self._sender.join()  # the worker's end is closed: the write has returned
            self._sender = None
        for fh in (self._send, self._recv):
            if fh is not None:
                with contextlib.suppress(OSError):
                    fh.close()
        self._send = self._recv = None
        self._taking_jobs = False
        if self._stderr is not None:
            self._stderr.close()
            self._stderr = None

    def _worker_error(self) -> str:
        """The last line the worker wrote to stderr, or its exit status."""
        if self._proc is None or self._stderr is None:
            return "no worker"
        if self._proc.poll() is None:
            self._proc.kill()
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


class _Forked:
    """A forked child: the part of subprocess.Popen's interface the worker's owner uses."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        """Its exit code once it has ended (reaped), else None."""
        if self.returncode is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self) -> int:
        """Wait for it to end; its exit code (negative: the signal that ended it)."""
        if self.returncode is None:
            _, status = os.waitpid(self.pid, 0)
            self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def kill(self) -> None:
        if self.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGKILL)


def _fork_worker(fd_in: int, fd_out: int, parents_ends: tuple[int, ...], stderr_fd: int) -> _Forked:
    """Fork the worker (`_work` on the pipes fd_in, fd_out); its standard error goes to stderr_fd."""
    parent = os.getpid()
    for stream in (sys.stdout, sys.stderr):  # else the child would write what is buffered a second time
        with contextlib.suppress(OSError, ValueError, AttributeError):
            stream.flush()
    pid = os.fork()
    if pid:
        return _Forked(pid)
    code = 0
    try:
        os.setsid()  # Ctrl-C is the run's to handle; leaving the run stops the worker
        for fd in parents_ends:
            os.close(fd)
        devnull = os.open(os.devnull, os.O_RDWR)
        os.dup2(devnull, 0)
        os.dup2(devnull, 1)
        os.dup2(stderr_fd, 2)
        with contextlib.suppress(OSError):  # the run's own stages go first where both want a core
            os.nice(_WORKER_NICENESS)
        for logger in [logging.getLogger(), *logging.Logger.manager.loggerDict.values()]:
            if isinstance(logger, logging.Logger):  # the run's terminal and log file are not the worker's
                logger.handlers.clear()
        _work(fd_in, fd_out, parent)
    except BaseException:  # noqa: BLE001 - the owner reads the last line of standard error
        code = 1
        with contextlib.suppress(Exception):
            traceback.print_exc()
            sys.stderr.flush()
    finally:
        os._exit(code)  # not the run's exit handlers, buffers or finalisers


def _write(fh: BinaryIO, data: bytes) -> None:
    """Send `data` to the worker (the sender thread; a worker that died has closed its end, and `close`
    may close `fh` under it)."""
    with contextlib.suppress(OSError, ValueError):
        fh.write(data)
        fh.flush()


def _cores() -> int:
    """The cores this process may use: its CPU affinity, and OpenCV's thread count, which a caller that
    gives the job fewer threads limits (`papl-map batch --threads`, `pipelines.batch.thread_limits`)."""
    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return min(affinity, max(1, cv2.getNumThreads()))


def _backward(
    reversed_tracks: Tracks, cfg: RunConfig, progress: ProgressCallback | None
) -> dict[int, np.ndarray]:
    return backward_poses(reversed_tracks, lambda t: register_tracks(t, cfg, progress))


def _die_with_parent(parent: int) -> None:
    """Have Linux kill this worker when the run's process ends (killed, out of memory), instead of it
    finishing a registration nobody waits for; elsewhere it ends at its next write or read."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # the run ended before that took effect (adopted by init or a subreaper)
        os._exit(0)


def _relog(records: list[tuple[str, int, str]], second_start: bool = True) -> None:
    """Log the worker's records here. Those of the second start prefixed, its warnings as INFO: they
    are about the backward start (a segment its registration left out), not about the map the run
    writes; other jobs' records as they are."""
    for name, level, message in records:
        if second_start:
            logging.getLogger(name).log(min(level, logging.INFO), "backward registration: %s", message)
        else:
            logging.getLogger(name).log(level, "%s", message)


class _Records(logging.Handler):
    """The worker's log records as (logger, level, message), for the run's process to log."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[tuple[str, int, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append((record.name, record.levelno, record.getMessage()))


def _work(fd_in: int, fd_out: int, parent: int) -> None:
    """The worker process. First (config, reversed tracks) in, (poses, seconds, log records) out, the
    poses None where the registration raised (the run's process then raises it again itself); then,
    until the run closes the pipe, jobs: (function, arguments) in, (its answer, seconds, log records)
    out, the answer a GeometryError or OptimizationError where the function raised one, None where
    it raised another."""
    _die_with_parent(parent)
    handler = _Records()
    root = logging.getLogger("papl_mapper")
    root.addHandler(handler)
    root.setLevel(logging.DEBUG)
    with os.fdopen(fd_in, "rb") as fin, os.fdopen(fd_out, "wb") as fout:

        def reply(answer: Any, t0: float) -> None:
            pickle.dump((answer, time.perf_counter() - t0, handler.records), fout, pickle.HIGHEST_PROTOCOL)
            fout.flush()
            handler.records = []

        cfg, tracks = pickle.load(fin)
        t0 = time.perf_counter()
        try:
            poses = _backward(tracks, cfg, None)
        except Exception:  # noqa: BLE001 - reported through the pipe, raised again in the run's process
            log.debug("the backward registration failed in the worker", exc_info=True)
            poses = None
        reply(poses, t0)
        while True:
            try:
                fn, args = pickle.load(fin)
            except EOFError:
                return
            t0 = time.perf_counter()
            try:
                answer: Any = fn(*args)
            except (GeometryError, OptimizationError) as exc:
                answer = exc
            except Exception:  # noqa: BLE001 - the run's process runs the job again itself
                log.debug("a job failed in the worker", exc_info=True)
                answer = None
            reply(answer, t0)
