"""Stage checkpoints of `papl-map run`: Ctrl-C in any stage, `--resume`, stale and corrupt checkpoints.

Every run maps the first 1.2 s of samples/tiny with 3 BA iterations and no focal check (a few seconds
each). An interrupted run starts from the checkpoint just before the interrupted stage, so each case
pays only for the stages it tests; the resumed map is compared with one uninterrupted run.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import papl_mapper.mapping.adjust as adjust
import papl_mapper.mapping.structure as structure
import papl_mapper.pipelines.registration as registration
import papl_mapper.pipelines.run_outputs as run_outputs
from papl_mapper.cli import main
from papl_mapper.map import Map
from papl_mapper.mapping.incremental import Registration
from papl_mapper.mapping.revisit import Revisit
from papl_mapper.pipelines import checkpoint as ckpt
from papl_mapper.pipelines.config import RunConfig
from papl_mapper.tracks import Tracks

from .conftest import default_sigint

TINY = Path(__file__).resolve().parents[1] / "samples" / "tiny"
FAST = ["--end", "1.2", "--set", "ba.max_iterations=3", "--set", "focal.enabled=false"]
OUTPUTS = ("map.papl", "trajectory.tum", "keyframes.tum", "config.toml", "summary.json", "log.txt")
SIGINT_WAIT_S = 60.0  # generous: the machine is shared; a run to the registration takes ~2 s
POSE_TOL = 1e-9  # resumed vs uninterrupted: the same computation on the same numbers (seen: 0.0)


def _run(out: Path, *extra: str, resume: bool = True) -> int:
    args = ["-q", "run", str(TINY / "video.mp4"), "--camera", str(TINY / "camera.json"), "--out", str(out)]
    return main(args + FAST + list(extra) + (["--resume"] if resume else []))


def _stage_dir(out: Path, stage: str) -> Path:
    found = sorted((out / ".checkpoint").glob(f"{stage}-*"))
    assert len(found) == 1, found
    return found[0]


def _copy(reference: Path, out: Path, stages: tuple[str, ...], outputs: bool = True) -> None:
    """A fresh output folder holding the reference's outputs and the checkpoints of `stages`."""
    (out / ".checkpoint").mkdir(parents=True)
    for stage in stages:
        src = _stage_dir(reference, stage)
        shutil.copytree(src, out / ".checkpoint" / src.name)
    if outputs:
        for name in OUTPUTS:
            shutil.copy2(reference / name, out / name)


def _assert_same_map(a: Path, b: Path) -> None:
    ma, mb = Map.load(a / "map.papl"), Map.load(b / "map.papl")
    assert np.array_equal(ma.keyframes.ids, mb.keyframes.ids)
    assert np.abs(ma.keyframes.T_wc - mb.keyframes.T_wc).max() <= POSE_TOL
    assert np.array_equal(ma.points.ids, mb.points.ids)
    assert np.abs(ma.points.xyz - mb.points.xyz).max() <= POSE_TOL
    assert np.array_equal(ma.lines.ids, mb.lines.ids)
    assert np.abs(ma.lines.endpoints_w - mb.lines.endpoints_w).max() <= POSE_TOL
    assert np.array_equal(ma.axes.directions, mb.axes.directions) or (
        np.abs(ma.axes.directions - mb.axes.directions).max() <= POSE_TOL
    )
    ta = np.loadtxt(a / "trajectory.tum")
    tb = np.loadtxt(b / "trajectory.tum")
    assert ta.shape == tb.shape and np.abs(ta - tb).max() <= POSE_TOL


def _summary(out: Path) -> dict:
    import json

    return json.loads((out / "summary.json").read_text())


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """One uninterrupted run with every checkpoint."""
    if not (TINY / "video.mp4").exists():
        pytest.skip("samples/tiny is not there")
    out = tmp_path_factory.mktemp("reference")
    assert _run(out, resume=False) == 0
    return out


def test_uninterrupted_run_writes_every_checkpoint(reference):
    for stage in ckpt.STAGES:
        folder = _stage_dir(reference, stage)
        assert (folder / "stage.json").exists()
    assert not list((reference / ".checkpoint").glob(".*"))  # no temporary folders left
    assert not (reference / ".checkpoint" / "log.txt").exists()  # moved to log.txt at the end
    assert _summary(reference)["resumed"] is None
    assert "checkpoints" in _summary(reference)["timings_s"]


class _Boom:
    """Raise KeyboardInterrupt on the n-th call, else call through."""

    def __init__(self, fn, n: int = 1) -> None:
        self.fn, self.n, self.calls = fn, n, 0

    def __call__(self, *args, **kwargs):
        self.calls += 1
        if self.calls == self.n:
            raise KeyboardInterrupt
        return self.fn(*args, **kwargs)


def _break_ba(mp: pytest.MonkeyPatch) -> None:
    mp.setattr(adjust, "global_ba", _Boom(adjust.global_ba))  # the first BA after the checkpoint


# interrupted stage: (what to break, checkpoints there before, the checkpoint a resume continues from);
# each run starts from the checkpoint just before the stage it interrupts
CASES = {
    "registration": (lambda mp: mp.setattr(registration, "register_keyframes", _Boom(None)), 1, "frontend"),
    "ba_points": (_break_ba, 2, "registration"),
    "ba_full": (_break_ba, 3, "ba_points"),
    "axis_update": (
        lambda mp: mp.setattr(structure, "update_axes", _Boom(structure.update_axes)),
        4,
        "ba_full",
    ),
    "writing outputs": (
        lambda mp: mp.setattr(run_outputs, "write_tum", _Boom(run_outputs.write_tum)),
        4,
        "ba_full",
    ),
}


@pytest.mark.parametrize("stage", list(CASES))
def test_interrupt_then_resume_matches_an_uninterrupted_run(stage, reference, tmp_path, monkeypatch, capsys):
    breaker, n_before, resume_from = CASES[stage]
    out = tmp_path / "out"
    _copy(reference, out, ckpt.STAGES[:n_before])
    before = {name: (out / name).read_bytes() for name in OUTPUTS}
    capsys.readouterr()
    with monkeypatch.context() as mp:
        breaker(mp)
        assert _run(out) == 130
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert f"interrupted in {stage}:" in err
    assert f"continue from the {ckpt.TITLES[resume_from]} checkpoint" in err
    # the previous complete run's outputs are untouched and no temporary file is left beside them
    assert {name: (out / name).read_bytes() for name in OUTPUTS} == before
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == [".checkpoint"]
    assert not list((out / ".checkpoint").glob(".*"))
    assert f"interrupted in {stage}" in (out / ".checkpoint" / "log.txt").read_text()

    assert _run(out) == 0
    assert _summary(out)["resumed"]["stage"] == resume_from
    log = (out / "log.txt").read_text()
    assert f"resumed: {ckpt.TITLES[resume_from]} from" in log
    assert f"interrupted in {stage}" in log  # the resumed run's log continues the interrupted one's
    _assert_same_map(reference, out)


def _frontend_started(out: Path) -> bool:
    log = out / ".checkpoint" / "log.txt"
    return log.exists() and "frames announced" in log.read_text()


def _registered(out: Path) -> bool:
    return bool(list((out / ".checkpoint").glob("registration-*")))


@pytest.mark.parametrize(
    ("ready", "copied"), [(_frontend_started, 0), (_registered, 1)], ids=["in-frontend", "after-registration"]
)
def test_a_real_ctrl_c_leaves_the_outputs_and_a_checkpoint_to_resume(ready, copied, reference, tmp_path):
    """SIGINT to a `papl-map run` process once it decodes, or once its registration checkpoint appears."""
    out = tmp_path / "out"
    _copy(reference, out, ckpt.STAGES[:copied])
    before = {name: (out / name).read_bytes() for name in OUTPUTS}
    args = [sys.executable, "-m", "papl_mapper.cli", "-q", "run", str(TINY / "video.mp4")]
    args += ["--camera", str(TINY / "camera.json"), "--out", str(out), "--resume", *FAST]
    proc = subprocess.Popen(
        args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=default_sigint
    )
    deadline = time.monotonic() + SIGINT_WAIT_S
    while not ready(out) and proc.poll() is None:
        assert time.monotonic() < deadline, f"{ready.__name__} did not happen"
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=SIGINT_WAIT_S)
    assert proc.returncode == 130, err
    assert err.count("\n") == 1 and "interrupted in " in err and "--resume" in err, err
    assert {name: (out / name).read_bytes() for name in OUTPUTS} == before
    assert not list((out / ".checkpoint").glob(".*"))
    assert _run(out) == 0
    _assert_same_map(reference, out)


@pytest.mark.parametrize(
    ("override", "resumed"),
    [
        ("lines.min_views=4", "ba_points"),  # a line setting keeps registration and points BA
        ("cull.enabled=true", "registration"),  # culling runs after registration
        ("rotations.check_deg=0.4", "registration"),  # the rotation check follows the points BA
        ("mapping.min_parallax_deg=2.5", "frontend"),  # a mapping setting recomputes registration
    ],
)
def test_a_config_change_reuses_only_the_stages_before_it(override, resumed, reference, tmp_path):
    out = tmp_path / "out"
    _copy(reference, out, ckpt.STAGES, outputs=False)
    old = {s: _stage_dir(out, s).name for s in ckpt.STAGES}
    assert _run(out, "--set", override) == 0
    assert _summary(out)["resumed"]["stage"] == resumed
    log = (out / "log.txt").read_text()
    later = ckpt.STAGES[ckpt.STAGES.index(resumed) + 1 :]
    for stage in ckpt.STAGES:
        now = _stage_dir(out, stage).name
        assert (now == old[stage]) == (stage not in later), stage
    stale = later[0]
    assert f"ignored: {ckpt.TITLES[stale]} checkpoint {old[stale]} was made from other" in log


@pytest.mark.parametrize(
    ("stage", "name", "data", "resumed"),
    [
        ("ba_full", "map.papl", b"PK\x03\x04 truncated", "ba_points"),
        ("registration", "registration.npz", b"\x00" * 64, "frontend"),
        ("ba_points", "stage.json", b"{not json", "registration"),
    ],
    ids=["truncated-map", "zeroed-registration", "bad-stage-json"],
)
def test_a_corrupt_checkpoint_is_ignored_with_a_log_line(stage, name, data, resumed, reference, tmp_path):
    out = tmp_path / "out"
    _copy(reference, out, ckpt.STAGES[: ckpt.STAGES.index(stage) + 1], outputs=False)
    (_stage_dir(out, stage) / name).write_bytes(data)
    assert _run(out) == 0
    assert _summary(out)["resumed"]["stage"] == resumed
    assert f"ignored: unreadable {ckpt.TITLES[stage]} checkpoint" in (out / "log.txt").read_text()
    _assert_same_map(reference, out)
    assert (_stage_dir(out, stage) / name).read_bytes() != data  # written again, whole


def test_a_checkpoint_whose_key_differs_from_its_name_is_ignored(reference, tmp_path):
    out = tmp_path / "out"
    _copy(reference, out, ckpt.STAGES[:3], outputs=False)
    meta = _stage_dir(out, "ba_points") / "stage.json"
    text = meta.read_text()
    assert '\\"seed\\": 0' in text
    meta.write_text(text.replace('\\"seed\\": 0', '\\"seed\\": 1'))
    assert _run(out) == 0
    assert _summary(out)["resumed"]["stage"] == "registration"
    assert "its key does not match" in (out / "log.txt").read_text()


# ---- the store and the registration round trip, without a run ----------------------------------


@contextlib.contextmanager
def _records(name: str) -> Iterator[list[logging.LogRecord]]:
    """Records of one logger, whatever handlers and propagation the CLI left configured."""
    got: list[logging.LogRecord] = []
    handler = logging.Handler(logging.DEBUG)
    handler.emit = got.append
    logger = logging.getLogger(name)
    old = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        yield got
    finally:
        logger.removeHandler(handler)
        logger.setLevel(old)


def test_stage_keys_chain_and_ignore_what_a_stage_does_not_read():
    base = ckpt.StageStore(None, "frontend key").chain(RunConfig())
    changed = {
        "lines.min_views": ("ba_full",),
        "axes.tau_n": ("ba_full",),
        "cull.enabled": ("ba_points", "ba_full"),
        "mapping.min_parallax_deg": ("registration", "ba_points", "ba_full"),
        "ba.max_iterations": ("registration", "ba_points", "ba_full"),
        "output.render": (),
        "focal.enabled": (),
    }
    for what, stages in changed.items():
        cfg = RunConfig()
        if what == "lines.min_views":
            cfg.lines.min_views = 4
        elif what == "axes.tau_n":
            cfg.axes.tau_n += 1
        elif what == "cull.enabled":
            cfg.cull.enabled = True
        elif what == "mapping.min_parallax_deg":
            cfg.mapping.min_parallax_deg = 2.5
        elif what == "ba.max_iterations":
            cfg.ba.max_iterations = 3
        elif what == "output.render":
            cfg.output.render = True
        else:
            cfg.focal.enabled = False
        keys = ckpt.StageStore(None, "frontend key").chain(cfg)
        assert {s for s in ckpt.STAGES if keys[s] != base[s]} == set(stages), what
    other = ckpt.StageStore(None, "another recording").chain(RunConfig())
    assert all(other[s] != base[s] for s in ckpt.STAGES)


def test_the_not_read_lists_name_real_fields():
    """A new RunConfig field lands in every key (safe); a misspelt name here would be a stale risk."""
    fields = set(RunConfig.__dataclass_fields__)
    assert ckpt.NOT_READ["ba_full"] < fields  # no typo in the lists
    assert ckpt.NOT_READ["registration"] <= fields


def _small_tracks(n_obs: int = 40) -> Tracks:
    from papl_mapper.map import Camera

    rng = np.random.default_rng(0)
    return Tracks(
        camera=Camera(640, 480, 500.0, 500.0, 320.0, 240.0),
        frame_index=np.arange(5),
        timestamp=np.arange(5) / 30.0,
        is_keyframe=np.ones(5, bool),
        point_frame=np.repeat(np.arange(5), n_obs // 5),
        point_track=rng.integers(0, 20, n_obs),
        point_uv=rng.uniform(0, 400, (n_obs, 2)),
        line_frame=np.zeros(0, np.int64),
        line_track=np.zeros(0, np.int64),
        line_xy=np.zeros((0, 4)),
        line_vp=np.zeros(0, np.int64),
        vp_dirs_c=np.full((5, 3, 3), np.nan),
    )


def _registration(rng: np.random.Generator) -> Registration:
    def pose() -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        T[:3, 3] = rng.normal(size=3)
        return T

    reg = Registration(
        frames=[0, 3, 1],
        T_cw={0: pose(), 3: pose(), 1: pose()},
        points_w={7: rng.normal(size=3), 2: rng.normal(size=3)},
        point_angle={2: 3.5, 7: 0.25},
        T_cw_frames={2: pose()},
        lost=[4],
        revisits=[
            Revisit(3, pose(), np.array([[9, 2], [11, 7]]), 0, drift=0.125, scale=1.5),
            Revisit(1, pose(), np.zeros((0, 2), np.int64), 0),
        ],
        init_frames=(0, 3),
        left_out=[
            Registration(
                frames=[5, 9],
                T_cw={5: pose(), 9: pose()},
                points_w={3: rng.normal(size=3)},
                point_angle={3: 2.5},
                T_cw_frames={6: pose()},
                init_frames=(5, 9),
            )
        ],
    )
    return reg


def test_registration_round_trip_keeps_order_revisits_and_renamed_tracks(tmp_path):
    assert ckpt.registration_storable()
    rng = np.random.default_rng(1)
    reg, tracks = _registration(rng), _small_tracks()
    tracks.point_track[:5] = 99  # as a loop closure renames tracks in place
    ckpt.write_registration(tmp_path, reg, tracks)
    back, point_track = ckpt.read_registration(tmp_path, {}, _small_tracks())
    assert np.array_equal(point_track, tracks.point_track)
    assert back.frames == reg.frames and back.lost == reg.lost and back.init_frames == reg.init_frames
    assert back.segments_left_out == reg.segments_left_out == [(5, 9)]
    for name in ("T_cw", "points_w", "T_cw_frames", "point_angle"):
        a, b = getattr(reg, name), getattr(back, name)
        assert list(a) == list(b), name  # insertion order too
        assert all(np.array_equal(a[k], b[k]) for k in a), name
    # every field of Registration is compared here: a new one must be added to this test
    compared = {"frames", "lost", "init_frames", "T_cw", "points_w", "T_cw_frames", "point_angle", "revisits"}
    compared.add("left_out")
    assert {f.name for f in dataclasses.fields(Registration)} == compared
    # the segments left out of the map, each with its own registration
    assert len(back.left_out) == 1
    seg, seg_back = reg.left_out[0], back.left_out[0]
    assert seg_back.frames == seg.frames and seg_back.init_frames == seg.init_frames
    for name in ("T_cw", "points_w", "T_cw_frames", "point_angle"):
        a, b = getattr(seg, name), getattr(seg_back, name)
        assert list(a) == list(b) and all(np.array_equal(a[k], b[k]) for k in a), name
    for a, b in zip(reg.revisits, back.revisits, strict=True):
        assert (a.frame, a.old_frame, a.scale) == (b.frame, b.old_frame, b.scale)
        assert np.array_equal(a.T_cw, b.T_cw) and np.array_equal(a.pairs.reshape(-1, 2), b.pairs)
        assert a.drift == b.drift or (np.isnan(a.drift) and np.isnan(b.drift))
    with pytest.raises(ValueError, match="point_track"):
        ckpt.read_registration(tmp_path, {}, _small_tracks(30))


def test_store_writes_atomically_and_an_interrupted_write_leaves_nothing(tmp_path):
    store = ckpt.StageStore(tmp_path, "k", resume=True)
    store.chain(RunConfig())

    def half_written(folder: Path) -> None:
        (folder / "tracks.npz").write_bytes(b"half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        store.save("frontend", half_written)
    assert list(tmp_path.iterdir()) == []
    again = ckpt.StageStore(tmp_path, "k", resume=True)
    with _records("papl_mapper.pipelines.checkpoint") as got:
        assert again.load("frontend", ckpt.read_tracks) is None
    assert got == [] and again.latest is None

    tracks = _small_tracks()
    assert store.save("frontend", lambda f: ckpt.write_tracks(f, tracks), {"frames": 5}) is not None
    assert store.latest == "frontend"
    other = ckpt.StageStore(tmp_path, "other key", resume=True)
    with _records("papl_mapper.pipelines.checkpoint") as got:
        assert other.load("frontend", ckpt.read_tracks) is None
    assert any("other input or settings" in r.getMessage() for r in got)
    again = ckpt.StageStore(tmp_path, "k", resume=True)
    back, stats = again.load("frontend", ckpt.read_tracks)
    assert stats == {"frames": 5} and np.array_equal(back.point_uv, tracks.point_uv)
    assert again.resumed.stage == "frontend"
    # without --resume nothing is read, and a stage recomputed in this run stops later loads
    assert ckpt.StageStore(tmp_path, "k", resume=False).load("frontend", ckpt.read_tracks) is None
    again.skip("registration")
    assert again.load("frontend", ckpt.read_tracks) is None


@pytest.mark.parametrize("latest", ["ba_points", "ba_full"])
def test_a_run_resumed_after_the_points_ba_starts_no_backward_registration(
    latest, reference, tmp_path, monkeypatch
):
    """The backward registration only serves the points BA: a run resumed after it does not start one
    (nor a worker's work beside the resumed stages), and the map is the uninterrupted run's."""
    out = tmp_path / "out"
    _copy(reference, out, ckpt.STAGES[: ckpt.STAGES.index(latest) + 1])
    submitted = []
    real_submit = registration.BackwardRegistration.submit
    monkeypatch.setattr(
        registration.BackwardRegistration,
        "submit",
        lambda self, t: submitted.append(1) or real_submit(self, t),
    )
    assert _run(out) == 0
    assert _summary(out)["resumed"]["stage"] == latest
    assert submitted == []
    _assert_same_map(reference, out)


def test_a_checkpoint_that_does_not_load_gets_its_backward_registration_late(reference, tmp_path):
    """A points-BA checkpoint that was to be resumed from but is unreadable: the stage is recomputed,
    with the backward registration submitted then, and the map is the uninterrupted run's."""
    out = tmp_path / "out"
    _copy(reference, out, ckpt.STAGES[: ckpt.STAGES.index("ba_points") + 1])
    (_stage_dir(out, "ba_points") / "stage.json").write_text("not json")
    assert _run(out) == 0
    assert _summary(out)["resumed"]["stage"] == "registration"
    assert _summary(out)["reverse_check"]["posed_backward"] > 0
    _assert_same_map(reference, out)
