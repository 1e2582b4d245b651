"""`papl-map batch`: many recordings, one `run` each, on a local process pool or as Ray tasks.

The job of one recording is `run_job(spec)`: it limits the thread pools (OpenCV, BLAS/OpenMP through
threadpoolctl) to its share of the cores, calls `pipelines.run.run` into OUT/<name> with
`resume=True` (so a half-finished recording continues from its stage checkpoints), writes the
exports, evaluation, previews and report the batch asks for, exactly as `papl-map run` does, and
returns one row for batch.json. Both engines run that same function:

- local (`LocalPool`): a concurrent.futures pool of N slots; each recording runs in a fresh worker
  process (`python -m papl_mapper.pipelines.batch_worker`), so a crash, a kill or a memory blow-up
  (a worker above --memory-limit is stopped) ends that recording only, with its one-line error;
- Ray (`pipelines.batch_ray`): the same function as a Ray task with CPU and memory requests, retried
  by Ray when its worker dies.

A recording is finished when OUT/.batch/<name>/result.json says "ok" under the key of its current
inputs and settings (`job_key`: the stage checkpoint keys of `pipelines/checkpoint.py` chained from
the frontend key, plus the whole config and the extras) and its files are there; a rerun of the
batch skips it. The job computes its key where it runs; the driver recomputes it only for recordings
that finished before, from the input's size and mtime when they are unchanged (no hashing of
unchanged videos on the driver). batch.json and index.html are rewritten as recordings finish.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import fcntl
import hashlib
import json
import logging
import os
import resource
import signal
import socket
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from papl_mapper import __version__
from papl_mapper.atomic import atomic_path
from papl_mapper.errors import InputError, PaplError
from papl_mapper.pipelines.batch_index import write_index
from papl_mapper.pipelines.batch_inputs import Recording, assign_names, collect
from papl_mapper.pipelines.logfile import close_log, file_log

log = logging.getLogger(__name__)

FORMAT = "papl-batch"
VERSION = 1
STATE = ".batch"
"""OUT/.batch/<name>/ holds one recording's job.json, result.json, attempts and worker.log."""

DEFAULT_MEMORY_GIB = 2.0
"""Memory one recording is expected to need: sizes the default --workers and Ray's memory request.
Above the peak of the 5-minute 720p walk in benchmarks/results/memory_long.json (benchmarks/RESULTS.md)."""

Row = dict[str, Any]

WRITE_EVERY_S = 2.0
"""batch.json and index.html are rewritten at most this often while a batch runs (and at its end)."""


# ---- options and jobs ---------------------------------------------------------------------------------


@dataclass
class BatchOptions:
    """Settings for every recording of a batch (a manifest entry's own settings come after them)."""

    camera: Path | None = None
    preset: str = "full"
    config: Path | None = None
    set: list[str] = field(default_factory=list)
    seed: int | None = None
    start: float | None = None
    end: float | None = None
    step: int = 1
    max_size: int | None = None
    export: str | None = None
    render: bool = False
    report: bool = False
    force: bool = False
    """Recompute every recording from scratch (no skipping, no checkpoints)."""


@dataclass
class EngineOptions:
    """Where the jobs run: a local pool (`ray` None) or Ray (`ray` "local" or a cluster address)."""

    workers: int | None = None
    """Local worker processes at once (default: from the core count and the available memory)."""
    threads: int | None = None
    """CPU threads of one recording (default: cores // workers locally, 1 on Ray): the size of its
    OpenCV and BLAS pools and Ray's num_cpus request."""
    memory_gib: float = DEFAULT_MEMORY_GIB
    memory_limit_gib: float | None = None
    """Local: a worker whose resident memory passes this is stopped and its recording marked failed
    (default: the available memory at the start divided by the workers)."""
    ray: str | None = None
    retries: int = 2
    """Ray: how often a recording whose worker died is retried."""

    def resolved(self) -> EngineOptions:
        """A copy with every default filled in for this machine."""
        out = dataclasses.replace(self)
        if out.memory_gib <= 0:
            raise InputError(f"--memory {out.memory_gib:g}: must be positive (GiB per recording)")
        cores = cpu_count()
        if out.ray is None:
            if out.workers is None:
                out.workers = default_workers(out.memory_gib)
            if out.workers < 1:
                raise InputError(f"--workers {out.workers}: must be at least 1")
            if out.threads is None:
                out.threads = max(1, cores // out.workers)
            if out.memory_limit_gib is None:
                out.memory_limit_gib = round(memory_available() / out.workers / 2**30, 2)
        else:
            if out.workers is not None:
                raise InputError(
                    "--workers is for the local pool; on Ray as many recordings run at once as the "
                    "cluster's CPUs and memory hold (--threads and --memory per recording)"
                )
            out.threads = out.threads or 1
            if out.retries < 0:
                raise InputError(f"--retries {out.retries}: must be 0 or more")
        if out.threads < 1:
            raise InputError(f"--threads {out.threads}: must be at least 1")
        return out

    def describe(self) -> dict[str, Any]:
        if self.ray is None:
            return {
                "engine": "local",
                "workers": self.workers,
                "threads_per_worker": self.threads,
                "memory_limit_gib": self.memory_limit_gib,
            }
        return {
            "engine": "ray",
            "address": self.ray,
            "num_cpus_per_task": self.threads,
            "memory_gib_per_task": self.memory_gib,
            "max_retries": self.retries,
        }


@dataclass
class Job:
    """One recording's job, as plain JSON (the spec a worker process or a Ray task receives)."""

    name: str
    recording: str
    origin: str
    out: str
    state: str
    camera: str | None
    gt: str | None
    start: float | None
    end: float | None
    step: int
    max_size: int | None
    config_file: str | None
    overrides: list[str]
    render: bool
    report: bool
    resume: bool
    threads: int

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Job:
        return cls(**d)

    def config(self):
        """The RunConfig, built as `papl-map run` builds it: config file, then the overrides, then the
        recording's camera, frame range, ground truth and extras."""
        from papl_mapper.config import load_config
        from papl_mapper.pipelines.config import RunConfig, with_extras, with_input

        cfg = load_config(RunConfig, Path(self.config_file) if self.config_file else None, self.overrides)
        cfg = with_input(
            cfg,
            camera=Path(self.camera) if self.camera else None,
            start_s=self.start,
            end_s=self.end,
            step=self.step,
            max_size=self.max_size,
        )
        return with_extras(cfg, self.render, self.report, Path(self.gt) if self.gt else None)

    def row(self, status: str = "pending", error: str | None = None) -> Row:
        """The batch.json row of this recording before any result."""
        return {
            "name": self.name,
            "status": status,
            "error": error,
            "source": self.recording,
            "origin": self.origin,
            "out": self.name,
            "camera": self.camera,
            "gt": self.gt,
            "range": {"start_s": self.start, "end_s": self.end, "step": self.step, "max_size": self.max_size},
        }


def cpu_count() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def memory_available() -> int:
    """Bytes of memory available for new work (MemAvailable; 4 GiB when it cannot be read)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 4 << 30


def default_workers(memory_gib: float = DEFAULT_MEMORY_GIB) -> int:
    """One worker per core, fewer when the available memory does not hold `memory_gib` for each."""
    by_memory = int(memory_available() // (memory_gib * 2**30))
    return max(1, min(cpu_count(), by_memory))


def make_jobs(
    recordings: list[Recording], names: list[str], out: Path, options: BatchOptions, threads: int
) -> list[Job]:
    """The job of each recording, with its config checked (InputError naming the recording's origin)."""
    from papl_mapper.pipelines.config import PRESETS

    jobs = []
    for rec, name in zip(recordings, names, strict=True):
        preset = rec.preset or options.preset
        if preset not in PRESETS:
            raise InputError(f"{rec.origin}: unknown preset {preset!r}; known: {', '.join(PRESETS)}")
        overrides = list(PRESETS[preset]) + list(options.set) + list(rec.set)
        if options.seed is not None:
            overrides.append(f"seed={options.seed}")
        if options.export:
            overrides.append(f"output.export={options.export}")
        config = rec.config or options.config
        job = Job(
            name=name,
            recording=str(rec.path),
            origin=rec.origin,
            out=str(out / name),
            state=str(out / STATE / name),
            camera=str(rec.camera) if rec.camera else None,
            gt=str(rec.gt) if rec.gt else None,
            start=rec.start if rec.start is not None else options.start,
            end=rec.end if rec.end is not None else options.end,
            step=rec.step or options.step,
            max_size=rec.max_size or options.max_size,
            config_file=str(Path(config).resolve()) if config else None,
            overrides=overrides,
            render=options.render,
            report=options.report,
            resume=not options.force,
            threads=threads,
        )
        try:
            job.config()
        except PaplError as exc:
            raise InputError(f"{rec.origin}: {exc}") from exc
        jobs.append(job)
    return jobs


# ---- keys ---------------------------------------------------------------------------------------------


@contextlib.contextmanager
def _quiet_logs() -> Iterator[None]:
    """Silence papl_mapper's INFO and warnings, and FFmpeg's and OpenCV's own messages on stderr, while
    the driver opens a recording for its key (the job opens it again and logs what it finds)."""
    root = logging.getLogger("papl_mapper")
    level = root.level
    root.setLevel(logging.ERROR)
    saved = None
    with contextlib.suppress(OSError, ValueError):
        sys.stderr.flush()
        saved = os.dup(2)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)
        os.close(devnull)
    try:
        yield
    finally:
        if saved is not None:
            os.dup2(saved, 2)
            os.close(saved)
        root.setLevel(level)


def probe(job: Job, cached: dict[str, Any] | None = None) -> dict[str, Any]:
    """What the keys need from the recording: its SHA-256 and its frame size after `max_size`.

    Reused from `cached` (a finished job's probe) when the file's size, mtime and the frame range
    are unchanged; else the recording is opened and hashed (InputError when it cannot be opened).
    """
    from papl_mapper.frontend.video import open_recording
    from papl_mapper.pipelines.run import _sha256

    path = Path(job.recording)
    try:
        st = path.stat()
    except OSError as exc:
        raise InputError(f"{path}: {exc.strerror or exc}") from exc
    sig = [st.st_size, st.st_mtime_ns, job.start, job.end, job.step, job.max_size]
    if cached and cached.get("sig") == sig:
        return cached
    with _quiet_logs():
        rec = open_recording(path, job.step, job.start, job.end, job.max_size)
    return {"sig": sig, "sha256": _sha256(path), "width": rec.width, "height": rec.height}


def frontend_key(job: Job, cfg, probed: dict[str, Any]) -> str:
    """The key `pipelines.run.run` gives the frontend checkpoint of this job (JSON text), from the
    same function. tests/test_batch.py checks it names the frontend checkpoint the run wrote."""
    from papl_mapper.frontend.camera import camera_for_recording
    from papl_mapper.pipelines import checkpoint as ckpt

    with _quiet_logs():
        cam = camera_for_recording(cfg.input.camera, probed["width"], probed["height"], cfg.hfov_deg)
    return ckpt.frontend_key(probed["sha256"], cfg, cam.camera.to_dict())


def job_key(job: Job, cfg, probed: dict[str, Any]) -> str:
    """A digest of everything a finished recording's outputs depend on.

    The stage checkpoint keys chained from the frontend key (input, camera, range, each stage's
    settings), the whole config (the stages' keys leave out what only the final outputs read) and
    the extras asked for. PaplError when the camera file cannot be read.
    """
    from papl_mapper.config import config_to_dict
    from papl_mapper.pipelines.checkpoint import StageStore

    stages = StageStore(None, frontend_key(job, cfg, probed)).chain(copy.deepcopy(cfg))
    text = json.dumps(
        {
            "stages": stages,
            "config": config_to_dict(cfg),
            "extras": {"gt": job.gt, "render": job.render, "report": job.report},
            "software": __version__,
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(text.encode()).hexdigest()


def _key_of(job: Job, cfg, cached: dict[str, Any] | None = None) -> tuple[str | None, dict | None]:
    """(key, probe), or (None, None) when the recording or its camera cannot be read (the run says why)."""
    try:
        probed = probe(job, cached)
        return job_key(job, cfg, probed), probed
    except PaplError:
        return None, None


# ---- the job (both engines) ---------------------------------------------------------------------------


@contextlib.contextmanager
def thread_limits(threads: int) -> Iterator[None]:
    """OpenCV's pool (cv2.setNumThreads) and the BLAS/OpenMP pools (threadpoolctl) at `threads`."""
    import cv2
    from threadpoolctl import threadpool_limits

    before = cv2.getNumThreads()
    cv2.setNumThreads(threads)
    try:
        with threadpool_limits(limits=threads):
            yield
    finally:
        cv2.setNumThreads(before)


def _attempt(state: Path) -> int:
    """Count this start of the job (the attempts file is cleared when the batch submits it)."""
    state.mkdir(parents=True, exist_ok=True)
    with open(state / "attempts", "a") as fh:
        fh.write(f"{time.time():.3f} {socket.gethostname()} {os.getpid()}\n")
    return attempts(state)


def attempts(state: Path) -> int:
    try:
        return len((state / "attempts").read_text().splitlines())
    except OSError:
        return 0


def _one_line(text: str) -> str:
    lines = [ln.strip() for ln in str(text).strip().splitlines() if ln.strip()]
    return lines[0] if lines else ""


def run_job(spec: dict[str, Any]) -> Row:
    """Map one recording into its output folder and return its batch.json row (never raises for a
    failure of the recording: the row says "failed" with the one-line error). The row is also written
    to OUT/.batch/<name>/result.json, so the batch can be resumed from disk."""
    from papl_mapper.pipelines.run import ExtrasInterrupted, RunInterrupted, run
    from papl_mapper.pipelines.run_outputs import OUTPUT_FILES

    job = Job.from_dict(spec)
    t0 = time.perf_counter()
    out, state = Path(job.out), Path(job.state)
    row = job.row("running")
    row.update(attempts=_attempt(state), host=socket.gethostname(), pid=os.getpid(), threads=job.threads)
    running_log = out / ".checkpoint" / "log.txt"
    stage = "setting up"
    key = None
    try:
        with thread_limits(job.threads):
            cfg = job.config()
            key, row["probe"] = _key_of(job, cfg)
            stage = "mapping"
            result = run(job.recording, out, cfg, resume=job.resume)  # writes the extras and log.txt too
        row.update(_result_fields(result.summary.to_dict(), out))
        row["files"] = [
            *OUTPUT_FILES,
            "log.txt",
            *(os.path.relpath(p, out) for p in result.extras.paths(out)),
        ]
        row["status"] = "ok"
    except RunInterrupted as exc:
        then = (
            "its checkpoints keep nothing yet"
            if exc.resume_from is None
            else f"rerunning the batch continues after its {exc.resume_from} checkpoint"
        )
        row.update(status="interrupted", error=f"interrupted in {exc.stage}; {then}")
    except ExtrasInterrupted:
        row.update(
            status="interrupted",
            error="interrupted while writing the exports, evaluation, previews or report",
        )
    except KeyboardInterrupt:
        row.update(status="interrupted", error=f"interrupted while {stage}")
    except PaplError as exc:
        row.update(status="failed", error=_one_line(str(exc)))
    except MemoryError:
        row.update(status="failed", error=f"out of memory (MemoryError) while {stage}")
    except Exception as exc:  # noqa: BLE001 - any fault of one recording is that recording's, not the batch's
        log.error("internal error while %s:\n%s", stage, traceback.format_exc())
        row.update(
            status="failed", error=f"internal error while {stage}: {type(exc).__name__}: {_one_line(exc)}"
        )
        row["log"] = str(running_log if running_log.exists() else out / "log.txt")
    if row["status"] != "ok" and row.get("error"):
        _append_log(
            running_log if running_log.exists() else out / "log.txt",
            f"batch: {row['status']}: {row['error']}",
        )
    row["wall_s"] = round(time.perf_counter() - t0, 3)
    row["peak_rss_mib"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    row["key"] = key
    write_result(state, key, row)
    return row


def _append_log(path: Path, message: str) -> None:
    """An ERROR line at the end of a run's log (when the folder still holds one)."""
    if not path.parent.is_dir():
        return
    handler = file_log(path, "a")
    try:
        logging.getLogger("papl_mapper").error("%s", message)
    finally:
        close_log(handler)


def _result_fields(summary: dict[str, Any], out: Path) -> dict[str, Any]:
    c = summary.get("counts", {})
    frames = int(summary.get("recording", {}).get("frames", 0))
    fields: dict[str, Any] = {
        "frames": frames,
        "frames_posed": frames - int(summary.get("frames_lost", 0)),
        "keyframes": c.get("keyframes", 0),
        "points": c.get("points", 0),
        "lines": c.get("lines", 0),
        "lines_per_axis": c.get("lines_per_axis", []),
        "unanchored_lines": c.get("unanchored_lines", 0),
        "anchored_fraction": c.get("anchored_fraction", 0.0),
        "axes": len(c.get("axes", [])),
        "vertical_index": c.get("vertical_index"),
        "camera_guessed": bool(summary.get("camera", {}).get("guessed", False)),
        "timings_s": summary.get("timings_s", {}),
        "resumed_from": (summary.get("resumed") or {}).get("stage"),
    }
    ev = out / "eval.json"
    if ev.exists():
        e = json.loads(ev.read_text())
        fields["ate_rmse"] = e.get("ate_rmse")
        fields["ate_rmse_rel_path"] = e.get("ate_rmse_rel_path")
    fields["report"] = "report.html" if (out / "report.html").exists() else None
    return fields


def write_result(state: Path, key: str | None, row: Row) -> None:
    state.mkdir(parents=True, exist_ok=True)
    with atomic_path(state / "result.json") as tmp:
        tmp.write_text(json.dumps({"key": key, "row": row}, indent=1, default=str))


def read_result(state: Path) -> tuple[str | None, Row] | None:
    try:
        d = json.loads((state / "result.json").read_text())
        return d.get("key"), dict(d["row"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def finished(job: Job) -> Row | None:
    """The row of a finished recording whose key and files are unchanged, else None."""
    if not job.resume:
        return None
    got = read_result(Path(job.state))
    if got is None or got[0] is None or got[1].get("status") != "ok":
        return None
    row = got[1]
    if not all((Path(job.out) / f).exists() for f in row.get("files", ["map.papl"])):
        return None
    key, probed = _key_of(job, job.config(), row.get("probe"))
    if key != got[0]:
        return None
    if probed != row.get("probe"):  # touched but the same: remember the new size and mtime
        row = {**row, "probe": probed}
        write_result(Path(job.state), key, row)
    return row


# ---- local engine -------------------------------------------------------------------------------------


def _rss(pid: int) -> int:
    """Resident memory of a process and its child processes (a run's backward-registration worker) in
    bytes; 0 for what cannot be read."""
    total = 0
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    total = int(line.split()[1]) * 1024
                    break
    except (OSError, ValueError):
        return 0
    for children in Path(f"/proc/{pid}/task").glob("*/children"):
        with contextlib.suppress(OSError, ValueError):
            total += sum(_rss(int(child)) for child in children.read_text().split())
    return total


def _last_line(path: Path) -> str:
    try:
        lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return lines[-1] if lines else ""


class LocalPool:
    """At most `workers` recordings at once, each in a worker process of its own, from a
    concurrent.futures pool. Not a ProcessPoolExecutor: when one of its processes dies the whole pool
    is broken and it cannot say whose job killed it; here a dead worker is one failed recording.
    Workers fork from a forkserver that has imported the pipeline (`batch_worker.child`)."""

    POLL_S = 0.2
    SIGINT_GRACE_S = 120.0
    """After Ctrl-C a worker has this long to checkpoint and exit before it is killed."""

    def __init__(self, workers: int, memory_limit_gib: float | None = None) -> None:
        self.workers = workers
        self.memory_limit = int(memory_limit_gib * 2**30) if memory_limit_gib else None
        self._stop = threading.Event()
        self._kill = threading.Event()
        import multiprocessing

        self._ctx = multiprocessing.get_context("forkserver")
        self._ctx.set_forkserver_preload(["papl_mapper.pipelines.batch_worker"])

    def run(self, jobs: list[Job], on_done: Callable[[Row], None], on_start: Callable[[Job], None]) -> None:
        """Run `jobs`; `on_done(row)` for each as it ends. Ctrl-C: the running workers are interrupted
        (they keep their checkpoints), their rows and "pending" rows of the others are reported, then
        KeyboardInterrupt is raised again."""
        pool = ThreadPoolExecutor(max_workers=self.workers, thread_name_prefix="papl-batch")
        futures: dict[Future, Job] = {pool.submit(self._one, job, on_start): job for job in jobs}
        left = set(futures)
        try:
            while left:
                done, left = wait(left, timeout=0.5, return_when="FIRST_COMPLETED")
                for fut in done:
                    on_done(fut.result())
        except KeyboardInterrupt:
            self._stop.set()
            for fut in left:
                fut.cancel()
            try:
                for fut in list(left):
                    on_done(
                        futures[fut].row("pending", "not started: the batch was interrupted")
                        if fut.cancelled()
                        else fut.result()
                    )
            except KeyboardInterrupt:  # a second Ctrl-C: stop waiting for checkpoints
                self._kill.set()
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)

    def _one(self, job: Job, on_start: Callable[[Job], None]) -> Row:
        if self._stop.is_set():
            return job.row("pending", "not started: the batch was interrupted")
        on_start(job)
        state = Path(job.state)
        state.mkdir(parents=True, exist_ok=True)
        (state / "result.json").unlink(missing_ok=True)
        (state / "attempts").unlink(missing_ok=True)
        spec = state / "job.json"
        spec.write_text(json.dumps(job.to_dict(), indent=1))
        from papl_mapper.pipelines import batch_worker

        t0 = time.perf_counter()
        peak = over = 0
        interrupted_at = None
        proc = self._ctx.Process(
            target=batch_worker.child,
            args=(str(spec), str(state / "worker.log")),
            name=f"papl-batch {job.name}",
        )
        proc.start()
        while True:
            proc.join(self.POLL_S)
            if proc.exitcode is not None:
                code = proc.exitcode
                break
            rss = _rss(proc.pid)
            peak = max(peak, rss)
            if self.memory_limit and rss > self.memory_limit and not over:
                over = rss
                proc.kill()
            if self._stop.is_set() and interrupted_at is None:
                interrupted_at = time.perf_counter()
                with contextlib.suppress(OSError):
                    os.kill(proc.pid, signal.SIGINT)
            if self._kill.is_set() or (
                interrupted_at is not None and time.perf_counter() - interrupted_at > self.SIGINT_GRACE_S
            ):
                proc.kill()
        proc.close()
        got = read_result(state)  # removed before the start: any result is this run's
        row = got[1] if got is not None else None
        if over:
            row = job.row(
                "failed",
                f"its worker was stopped at {over / 2**30:.2f} GiB of resident memory, over the limit "
                f"of {self.memory_limit / 2**30:.2f} GiB (--memory-limit)",
            )
        elif row is None and (interrupted_at is not None or code in (130, -signal.SIGINT)):
            row = job.row("interrupted", "interrupted before its first checkpoint")
        elif row is None:
            detail = _last_line(state / "worker.log")
            if code < 0:
                name = signal.Signals(-code).name
                why = " (out of memory? the kernel kills with SIGKILL)" if code == -signal.SIGKILL else ""
                error = f"its worker died of {name}{why}"
            else:
                error = f"its worker exited with code {code}"
            row = job.row("failed", f"{error}: {detail}" if detail else error)
            row["log"] = str(state / "worker.log")
        row["worker_s"] = round(time.perf_counter() - t0, 3)
        row["peak_rss_mib"] = max(float(row.get("peak_rss_mib") or 0.0), round(peak / 2**20, 1))
        row["attempts"] = max(int(row.get("attempts") or 0), attempts(state), 1)
        if row["status"] != "ok":
            write_result(state, row.get("key"), row)
        return row


# ---- the batch ----------------------------------------------------------------------------------------


class BatchInterrupted(KeyboardInterrupt):
    """Ctrl-C during a batch: batch.json says which recordings finished; a rerun continues."""

    def __init__(self, result: BatchResult) -> None:
        super().__init__("batch interrupted")
        self.result = result


@dataclass
class BatchResult:
    out: Path
    rows: list[Row]
    engine: dict[str, Any]

    def count(self, status: str) -> int:
        return sum(r["status"] == status for r in self.rows)

    @property
    def failed(self) -> list[Row]:
        return [r for r in self.rows if r["status"] == "failed"]


def totals(rows: list[Row], wall_s: float | None = None) -> dict[str, Any]:
    ok = [r for r in rows if r["status"] == "ok"]
    out: dict[str, Any] = {
        "recordings": len(rows),
        **{s: sum(r["status"] == s for r in rows) for s in ("ok", "failed", "interrupted", "pending")},
        "reused": sum(bool(r.get("reused")) for r in rows),
        "frames": sum(int(r.get("frames") or 0) for r in ok),
        "frames_posed": sum(int(r.get("frames_posed") or 0) for r in ok),
        "keyframes": sum(int(r.get("keyframes") or 0) for r in ok),
        "lines": sum(int(r.get("lines") or 0) for r in ok),
        "peak_rss_mib_max": max((float(r.get("peak_rss_mib") or 0) for r in rows), default=0.0),
    }
    if wall_s is not None:
        computed = [r for r in ok if not r.get("reused")]
        out["wall_s"] = round(wall_s, 3)
        out["recordings_per_minute"] = (
            round(60 * len(computed) / wall_s, 3) if wall_s > 0 and computed else None
        )
    return out


class _Folder:
    """The batch's output folder: its lock, the previous batch.json, and writing batch.json + index.html."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self._lock_fh = None

    def check(self) -> dict[str, Any] | None:
        out = self.out
        if out.exists() and not out.is_dir():
            raise InputError(f"{out}: exists and is not a folder; give a folder for --out")
        for name in ("map.papl", "summary.json"):
            if (out / name).exists():
                raise InputError(f"{out}: holds the outputs of a `papl-map run` ({name}); give another --out")
        path = out / "batch.json"
        if not path.exists():
            return None
        try:
            prev = json.loads(path.read_text())
            if prev.get("format") != FORMAT:
                raise ValueError("not a papl-map batch file")
            return prev
        except (OSError, ValueError, AttributeError) as exc:
            raise InputError(f"{path}: cannot read the batch file ({exc}); give another --out") from exc

    def lock(self) -> None:
        (self.out / STATE).mkdir(parents=True, exist_ok=True)
        fh = open(self.out / STATE / "lock", "a+")  # noqa: SIM115 - held for the batch's lifetime
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            fh.seek(0)
            owner = fh.read().strip() or "another process"
            fh.close()
            raise InputError(f"{self.out}: another papl-map batch is writing there ({owner})") from exc
        fh.truncate(0)
        fh.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        fh.flush()
        self._lock_fh = fh

    def unlock(self) -> None:
        if self._lock_fh is not None:
            self._lock_fh.close()
            self._lock_fh = None

    def write(self, doc: dict[str, Any]) -> None:
        with atomic_path(self.out / "batch.json") as tmp:
            tmp.write_text(json.dumps(doc, indent=1, default=str))
        write_index(doc, self.out / "index.html")


def _check_same_batch(prev: dict[str, Any], jobs: list[Job], out: Path) -> None:
    """An output folder may hold this batch (or a smaller one it extends), never another one."""
    now = {j.name: j.recording for j in jobs}
    for r in prev.get("recordings", []):
        name, source = r.get("name"), r.get("source")
        if now.get(name) != source:
            other = f"from {now[name]}" if name in now else "not in this batch"
            raise InputError(
                f"{out}: holds another batch ({name} there is {source}, here {other}); "
                "give another --out, or remove that folder"
            )


def run_batch(
    inputs: list[str | Path],
    out_dir: str | Path,
    options: BatchOptions | None = None,
    engine: EngineOptions | None = None,
    *,
    on_row: Callable[[Row], None] | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> BatchResult:
    """Map every recording of `inputs` into OUT/<name>, skipping finished ones; batch.json and index.html.

    InputError (one line, nothing started) for bad inputs, an unusable output folder or Ray address.
    BatchInterrupted after Ctrl-C, with batch.json written.
    """
    options = options or BatchOptions()
    eng = (engine or EngineOptions()).resolved()
    out = Path(out_dir).expanduser().resolve()
    folder = _Folder(out)
    prev = folder.check()
    recordings = collect(inputs, options.camera, exclude=out)
    previous_names = {
        r["identity"]: r["name"] for r in (prev or {}).get("recordings", []) if r.get("identity")
    }
    names = assign_names(recordings, previous_names)
    jobs = make_jobs(recordings, names, out, options, eng.threads)
    if prev is not None:
        _check_same_batch(prev, jobs, out)
    ray_engine = None
    if eng.ray is not None:
        from papl_mapper.pipelines.batch_ray import RayEngine

        ray_engine = RayEngine(eng)  # connects now: an unreachable address fails before anything is written
    try:
        out.mkdir(parents=True, exist_ok=True)
        folder.lock()
    except BaseException:
        if ray_engine is not None:
            ray_engine.close()
        raise
    t0 = time.perf_counter()
    identities = {j.name: r.identity() for j, r in zip(jobs, recordings, strict=True)}
    rows: dict[str, Row] = {}
    todo: list[Job] = []
    for job in jobs:
        done = finished(job)
        if done is not None:
            rows[job.name] = {**done, "reused": True}
        else:
            rows[job.name] = job.row()
            todo.append(job)
    running: set[str] = set()
    lock = threading.Lock()
    last_write = [0.0, 0.0]  # when, and how long it took
    n_done = [len(jobs) - len(todo)]

    def doc(final: bool = False) -> dict[str, Any]:
        ordered = [{**rows[j.name], "identity": identities[j.name]} for j in jobs]
        return {
            "format": FORMAT,
            "version": VERSION,
            "software": f"papl-mapper {__version__}",
            "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "finished": final,
            "out": str(out),
            "inputs": [str(i) for i in inputs],
            "options": {
                k: (str(v) if isinstance(v, Path) else v) for k, v in dataclasses.asdict(options).items()
            },
            "engine": eng.describe(),
            "totals": totals(ordered, time.perf_counter() - t0),
            "recordings": ordered,
        }

    def write(final: bool = False) -> None:
        # at most every WRITE_EVERY_S, and never more than 5% of the driver's time (large batches)
        now = time.perf_counter()
        if final or now - last_write[0] >= max(WRITE_EVERY_S, 20 * last_write[1]):
            folder.write(doc(final))
            last_write[:] = [time.perf_counter(), time.perf_counter() - now]

    def tick() -> None:
        if progress is not None:
            names = sorted(running)
            more = f" +{len(names) - 3}" if len(names) > 3 else ""
            progress(n_done[0], len(jobs), ", ".join(names[:3]) + more)

    def on_start(job: Job, status: str = "running") -> None:
        with lock:
            running.add(job.name)
            rows[job.name] = {**rows[job.name], "status": status}
            tick()

    def on_done(row: Row) -> None:
        with lock:
            running.discard(row["name"])
            rows[row["name"]] = row
            if row["status"] in ("ok", "failed"):
                n_done[0] += 1
            write()
            tick()
        if on_row is not None:
            on_row(row)

    try:
        waiting = {t.name for t in todo}
        for job in jobs:
            if job.name not in waiting and on_row is not None:
                on_row(rows[job.name])
        write(final=not todo)
        tick()
        if todo:
            if ray_engine is None:
                LocalPool(eng.workers, eng.memory_limit_gib).run(todo, on_done, on_start)
            else:
                ray_engine.run(todo, on_done, on_start)
    except KeyboardInterrupt as exc:
        for name, r in rows.items():
            if r["status"] in ("running", "submitted"):
                rows[name] = {**r, "status": "interrupted", "error": "interrupted"}
        folder.write(doc(final=False))
        raise BatchInterrupted(BatchResult(out, [rows[j.name] for j in jobs], eng.describe())) from exc
    finally:
        if ray_engine is not None:
            ray_engine.close()
        folder.unlock()
    folder.write(doc(final=True))
    return BatchResult(out, [rows[j.name] for j in jobs], eng.describe())
