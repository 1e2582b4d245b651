"""Shared fixtures: small maps with known content, the shared data folder."""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
import pytest

from papl_mapper.map import Axes, Camera, Keyframes, Lines, LineState, Map, Points

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """../shared/data, or skip with a reason where it is absent (a user's fresh clone)."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


def make_map(n_kf: int = 5, n_pts: int = 50, n_lines: int = 30, seed: int = 0) -> Map:
    """A small consistent map: three orthogonal axes, anchored and unanchored lines."""
    rng = np.random.default_rng(seed)
    cam = Camera(640, 480, 500.0, 500.0, 319.5, 239.5)
    T = np.repeat(np.eye(4)[None], n_kf, axis=0)
    T[:, 0, 3] = np.arange(n_kf) * 0.5
    kf = Keyframes(np.arange(n_kf) * 10, np.arange(n_kf) * 3, np.arange(n_kf) / 10.0, T)
    pids = np.arange(n_pts) + 1000
    obs_p = np.stack([np.repeat(pids, 2), np.tile(kf.ids[:2], n_pts)], axis=1)
    pts = Points(
        pids,
        rng.normal(size=(n_pts, 3)),
        rng.integers(0, 255, (n_pts, 3), dtype=np.uint8),
        obs_p,
        rng.uniform(0, 480, (len(obs_p), 2)),
    )
    axes = Axes(np.eye(3)[[2, 0, 1]], vertical_index=0)
    lab = rng.integers(-1, 3, n_lines)
    mid = rng.normal(size=(n_lines, 3)) * 3
    d = np.where(lab[:, None] >= 0, axes.directions[np.maximum(lab, 0)], rng.normal(size=(n_lines, 3)))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ends = np.stack([mid - d, mid + d], axis=1)
    w = np.zeros((n_lines, 3))
    w[lab >= 0, lab[lab >= 0]] = 1.0
    state = np.where(lab >= 0, LineState.ANCHORED, LineState.ORTHONORMAL).astype(np.int8)
    lids = np.arange(n_lines) + 5000
    obs_l = np.stack([lids, np.full(n_lines, kf.ids[0])], axis=1)
    lines = Lines(
        lids,
        ends,
        w,
        state,
        np.where(lab >= 0, kf.ids[0], -1),
        np.where(lab >= 0, 0.3, np.nan),
        obs_l,
        rng.uniform(0, 480, (n_lines, 4)),
    )
    return Map(cam, kf, pts, lines, axes, {"units": "arbitrary"})


@pytest.fixture
def small_map() -> Map:
    return make_map()


def default_sigint() -> None:
    """`preexec_fn` for a child the test interrupts: SIGINT as a terminal's Ctrl-C reaches it, even when
    the test runner inherited SIGINT ignored (a shell starts background jobs so) and would pass that on."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
