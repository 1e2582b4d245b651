"""The Ray engine of `papl-map batch`: each recording's `run_job` as one Ray task.

Optional: `pip install 'papl-mapper[ray]'`. `--ray` starts a local Ray for the batch and stops it;
`--ray HOST:PORT` connects to a running cluster (`ray start --head --port PORT` on one node,
`ray start --address HOST:PORT` on the others). Every node must have papl-mapper installed and see
the recordings and the output folder at the same paths (a shared file system): the tasks read and
write there, and only the small batch.json rows travel through Ray.

Each task asks for `--threads` CPUs (its OpenCV and BLAS pools are that size) and `--memory` GiB, runs
in a fresh worker process (max_calls=1: no state or memory carries over to the next recording), and
is retried `--retries` times when its worker or node dies (a retry resumes from the recording's
checkpoints). A recording that fails on its own (bad file, cannot initialise) is not retried: its
row says why.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from papl_mapper.errors import InputError
from papl_mapper.extras import require
from papl_mapper.pipelines.batch import EngineOptions, Job, Row, attempts, cpu_count, read_result, run_job

log = logging.getLogger(__name__)

CANCEL_GRACE_S = 120.0
"""After Ctrl-C, how long the driver waits for cancelled tasks to checkpoint and return."""


def import_ray():
    return require("ray", "papl-map batch --ray (leave out --ray for the local pool)")


def check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """InputError (one line) unless HOST:PORT accepts a connection ('local', 'auto', ray:// pass)."""
    if address in ("local", "auto") or address.startswith("ray://"):
        return
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise InputError(
            f"--ray {address}: expected HOST:PORT of a Ray cluster's head (its GCS port, 6379 unless "
            "started with --port), 'auto', or no address for a local Ray"
        )
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise InputError(
            f"--ray {address}: no Ray cluster answers there ({exc.strerror or exc}); start one with "
            f"`ray start --head --port {port}` or check the address"
        ) from exc


def _first_line(exc: BaseException) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return lines[0] if lines else type(exc).__name__


class RayEngine:
    """Connects on creation (InputError for an unreachable address or a cluster too small for one task)."""

    def __init__(self, eng: EngineOptions) -> None:
        self.ray = ray = import_ray()
        self.eng = eng
        check_reachable(eng.ray)
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        kwargs: dict[str, Any] = {"log_to_driver": False, "logging_level": logging.WARNING}
        if eng.ray == "local":
            kwargs.update(num_cpus=cpu_count(), include_dashboard=False, object_store_memory=256 << 20)
        try:
            ray.init(address=eng.ray, **kwargs)
        except Exception as exc:  # noqa: BLE001 - Ray raises many kinds; each means: cannot use that cluster
            raise InputError(
                f"--ray {eng.ray}: cannot connect ({type(exc).__name__}: {_first_line(exc)})"
            ) from exc
        self.memory = int(eng.memory_gib * 2**30)
        res = self._resources()
        if res.get("CPU", 0) < eng.threads or res.get("memory", 0) < self.memory:
            self.close()
            raise InputError(
                f"--ray {eng.ray}: the cluster has {res.get('CPU', 0):g} CPUs and "
                f"{res.get('memory', 0) / 2**30:.1f} GiB for tasks; one recording asks for "
                f"{eng.threads} CPUs and {eng.memory_gib:g} GiB (--threads, --memory)"
            )
        self.task = ray.remote(max_calls=1)(run_job).options(
            num_cpus=eng.threads, memory=self.memory, max_retries=eng.retries, retry_exceptions=False
        )

    def _resources(self, wait_s: float = 30.0) -> dict[str, float]:
        """The cluster's resources, waiting a little for a head that has just started to list its node."""
        t0 = time.perf_counter()
        while True:
            res = self.ray.cluster_resources()
            if res.get("CPU", 0) > 0 or time.perf_counter() - t0 > wait_s:
                return res
            time.sleep(0.5)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            if self.ray.is_initialized():
                self.ray.shutdown()

    def run(self, jobs: list[Job], on_done: Callable[[Row], None], on_start: Callable[..., None]) -> None:
        ray = self.ray
        pending: dict[Any, Job] = {}
        for job in jobs:
            state = Path(job.state)
            state.mkdir(parents=True, exist_ok=True)
            for name in ("result.json", "attempts"):
                (state / name).unlink(missing_ok=True)
            on_start(job, "submitted")  # Ray starts it when a node has the CPUs and memory
            pending[self.task.remote(job.to_dict())] = job
        try:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
                for ref in ready:
                    job = pending.pop(ref)
                    on_done(self._row(ref, job))
        except KeyboardInterrupt:
            for ref in pending:
                with contextlib.suppress(Exception):
                    ray.cancel(ref)  # KeyboardInterrupt in the task: run() stops at a checkpoint
            deadline = time.perf_counter() + CANCEL_GRACE_S
            try:
                for ref, job in pending.items():
                    ray.wait([ref], timeout=max(0.0, deadline - time.perf_counter()))
                    on_done(self._row(ref, job, cancelled=True))
            except KeyboardInterrupt:
                pass
            raise

    def _row(self, ref: Any, job: Job, cancelled: bool = False) -> Row:
        ray = self.ray
        state = Path(job.state)
        try:
            row = ray.get(ref, timeout=0 if cancelled else None)
        except (ray.exceptions.TaskCancelledError, ray.exceptions.GetTimeoutError):
            got = read_result(state)  # removed before the submission: any result is this run's
            if got is not None:
                row = got[1]
            else:
                row = job.row("interrupted" if attempts(state) else "pending", "interrupted")
        except ray.exceptions.RayError as exc:
            n = attempts(state)
            row = job.row(
                "failed", f"Ray gave up after {n} attempts: {type(exc).__name__}: {_first_line(exc)}"
            )
        row["attempts"] = max(int(row.get("attempts") or 0), attempts(state))
        return row


class LocalRayHead:
    """A one-machine Ray cluster on 127.0.0.1 (for tests and benchmarks): `ray start --head --block`
    on free ports in its own session, stopped by signalling the processes of that session only."""

    def __init__(self, num_cpus: int = 2) -> None:
        self.num_cpus = num_cpus
        self.proc: subprocess.Popen | None = None
        self.address = ""
        self.temp_dir = ""

    @staticmethod
    def _free_port() -> int:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            return s.getsockname()[1]

    def start(self, timeout_s: float = 180.0) -> str:
        ray_cli = Path(sys.executable).parent / "ray"
        port = self._free_port()
        self.temp_dir = tempfile.mkdtemp(prefix="papl-ray-", dir="/tmp")
        ports = {
            "dashboard-port": self._free_port(),
            "dashboard-agent-listen-port": self._free_port(),
            "dashboard-agent-grpc-port": self._free_port(),
            "metrics-export-port": self._free_port(),
            "runtime-env-agent-port": self._free_port(),
            "node-manager-port": self._free_port(),
            "object-manager-port": self._free_port(),
        }
        cmd = [
            str(ray_cli) if ray_cli.exists() else "ray",
            "start",
            "--head",
            "--block",
            f"--port={port}",
            "--node-ip-address=127.0.0.1",
            f"--num-cpus={self.num_cpus}",
            "--include-dashboard=false",
            "--disable-usage-stats",
            f"--object-store-memory={256 << 20}",
            f"--temp-dir={self.temp_dir}",
            *(f"--{k}={v}" for k, v in ports.items()),
        ]
        self._log = Path(self.temp_dir) / "ray_start.log"
        with open(self._log, "wb") as fh:
            self.proc = subprocess.Popen(
                cmd, stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True
            )
        self.address = f"127.0.0.1:{port}"
        t0 = time.perf_counter()
        while "block forever" not in self._log.read_text(errors="replace"):
            if self.proc.poll() is not None or time.perf_counter() - t0 > timeout_s:
                text = self._log.read_text(errors="replace")
                self.stop()
                raise RuntimeError(f"ray start did not come up: {text[-2000:]}")
            time.sleep(0.2)
        return self.address

    def session_pids(self) -> list[int]:
        """The processes of the head's session (the head, its raylet, GCS and workers), by /proc."""
        if self.proc is None:
            return []
        sid = self.proc.pid  # start_new_session: the session id is the ray start process's pid
        pids = []
        for p in Path("/proc").iterdir():
            if not p.name.isdigit():
                continue
            try:
                fields = (p / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[3]) == sid:  # after ") ": state ppid pgrp session
                pids.append(int(p.name))
        return pids

    def task_pids(self, function: str = "run_job") -> list[int]:
        """Workers of this cluster now executing `function` (Ray titles them "ray::<function>")."""
        out = []
        for pid in self.session_pids():
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[0].decode(errors="replace")
            except OSError:
                continue
            if cmd.startswith(f"ray::{function}"):
                out.append(pid)
        return out

    def stop(self, timeout_s: float = 60.0) -> None:
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)  # ray start --block drains and stops its processes
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                pass
        for pid in self.session_pids():  # anything left of this session only
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        if self.proc.poll() is None:
            self.proc.wait(10)
        self.proc = None
        shutil.rmtree(self.temp_dir, ignore_errors=True)

    def __enter__(self) -> LocalRayHead:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
