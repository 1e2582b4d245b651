"""Hand-held walkthrough camera paths along a scene's route: forward motion, turns, jitter, return.

The route (a closed loop of waypoints in free space) is smoothed locally at its corners. A run
long enough for most of a loop walks whole loops and ends at the start; a shorter one walks out
along the route keeping to the right, turns round in a U (moving, so the turn has parallax) and
walks back. Heading follows the path, with slow look-around,
small pitch/roll jitter and a walking bob. Poses are T_wc (camera -> world), OpenCV camera frame.

Two rotation-only motions start from the same walk: `pan_then_walk` stands at its start and pans in
place before walking it; `look_around` stands there and pans back and forth, never moving.
"""

from __future__ import annotations

import math

import numpy as np

from papl_mapper.synth.scenes import Scene

CORNER_CUT_M = 0.8  # corners are rounded within this distance of a waypoint
HEADING_SMOOTH_M = 0.3  # heading looks from this far behind on the path...
LOOK_AHEAD_M = 1.5  # ...to this far ahead, so the walker looks into a corner before reaching it
U_TURN_OFFSET_M = 0.35  # out and back: walk this far right of the route, turning round in a U
TURN_HALF_S = 1.0  # out and back: the U-turn takes twice this long (90 deg/s)
LOOP_FRACTION = 0.75  # walk whole loops when the distance is at least this part of one


def _smooth_loop(waypoints: np.ndarray, cut: float = CORNER_CUT_M, iterations: int = 5) -> np.ndarray:
    """Closed polyline with each corner rounded within `cut` of it (Chaikin on densified corners)."""
    pts = []
    n = len(waypoints)
    for i in range(n):
        p, prev, nxt = waypoints[i], waypoints[i - 1], waypoints[(i + 1) % n]
        d_in, d_out = p - prev, nxt - p
        c_in = min(cut, 0.45 * np.linalg.norm(d_in))
        c_out = min(cut, 0.45 * np.linalg.norm(d_out))
        pts += [p - d_in / np.linalg.norm(d_in) * c_in, p, p + d_out / np.linalg.norm(d_out) * c_out]
    poly = np.array(pts)
    for _ in range(iterations):
        nxt = np.roll(poly, -1, axis=0)
        poly = np.stack([0.75 * poly + 0.25 * nxt, 0.25 * poly + 0.75 * nxt], axis=1).reshape(-1, 2)
    # start the loop where the route starts (its first waypoint is mid-edge on a straight)
    start = int(np.argmin(np.linalg.norm(poly - waypoints[0], axis=1)))
    return np.roll(poly, -start, axis=0)


class _Loop:
    """Arc-length parametrised closed polyline."""

    def __init__(self, poly: np.ndarray):
        closed = np.vstack([poly, poly[:1]])
        seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
        self.s = np.concatenate([[0.0], np.cumsum(seg)])
        self.pts = closed
        self.length = float(self.s[-1])

    def at(self, s: np.ndarray) -> np.ndarray:
        s = np.mod(s, self.length)
        return np.stack([np.interp(s, self.s, self.pts[:, k]) for k in (0, 1)], axis=-1)

    def heading(self, s: np.ndarray, direction: float = 1.0) -> np.ndarray:
        """Yaw looking from a little behind `s` to LOOK_AHEAD_M ahead (walking towards +s or -s)."""
        d = self.at(s + direction * LOOK_AHEAD_M) - self.at(s - direction * HEADING_SMOOTH_M)
        return np.arctan2(d[:, 1], d[:, 0])


def _smooth_noise(
    rng: np.random.Generator, t: np.ndarray, f_lo: float, f_hi: float, k: int = 4
) -> np.ndarray:
    """Sum of k seeded sinusoids with frequencies in [f_lo, f_hi] Hz, unit RMS."""
    f = rng.uniform(f_lo, f_hi, k)
    ph = rng.uniform(0, 2 * math.pi, k)
    return np.sin(2 * math.pi * f[None] * t[:, None] + ph[None]).sum(1) * math.sqrt(2.0 / k)


def walkthrough(
    scene: Scene, n_frames: int, fps: float, seed: int = 0, speed: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (N,) in seconds and poses T_wc (N, 4, 4) of a hand-held walk through `scene`."""
    rng = np.random.default_rng([seed, 7])
    t = np.arange(n_frames) / fps
    T = n_frames / fps
    loop = _Loop(_smooth_loop(scene.route))
    dist = speed * T
    if dist >= LOOP_FRACTION * loop.length:
        laps = max(1, round(dist / loop.length))
        s = t / T * laps * loop.length
        yaw = loop.heading(s)
        side = np.zeros_like(t)
    else:
        # out and back: constant speed, reversing smoothly over 2 tau around the middle
        tau = min(TURN_HALF_S, T / 6)
        v = speed * np.clip((T / 2 - t) / tau, -1.0, 1.0)
        s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) / fps)])
        turn = np.clip((t - (T / 2 - tau)) / (2 * tau), 0.0, 1.0)
        turn = turn * turn * (3 - 2 * turn)  # smoothstep
        yaw_out = loop.heading(s, 1.0)
        yaw_back = yaw_out + np.mod(loop.heading(s, -1.0) - yaw_out, 2 * math.pi)  # turning left
        yaw = yaw_out + turn * (yaw_back - yaw_out)
        # keep to the right both ways: the turn is a U-turn with translation (parallax), not a spin
        side = U_TURN_OFFSET_M * (2 * turn - 1)
    route_left = loop.heading(s, 1.0) + math.pi / 2
    xy = loop.at(s) + side[:, None] * np.stack([np.cos(route_left), np.sin(route_left)], axis=1)
    lateral = np.stack([-np.sin(yaw), np.cos(yaw)], axis=1)
    xy = xy + lateral * (0.05 * _smooth_noise(rng, t, 0.1, 0.4))[:, None]
    z = (
        scene.eye_height
        + 0.015 * np.sin(2 * math.pi * 1.8 * t + rng.uniform(0, 6.3))
        + 0.02 * _smooth_noise(rng, t, 0.05, 0.2)
    )
    yaw = yaw + math.radians(6.0) * _smooth_noise(rng, t, 0.05, 0.25)
    pitch = math.radians(scene.pitch_deg) + math.radians(1.5) * _smooth_noise(rng, t, 0.2, 1.2)
    roll = math.radians(1.5) * _smooth_noise(rng, t, 0.2, 1.2)
    T_wc = np.repeat(np.eye(4)[None], n_frames, axis=0)
    T_wc[:, :3, :3] = rotation_wc(yaw, pitch, roll)
    T_wc[:, :3, 3] = np.column_stack([xy, z])
    return t, T_wc


def rotation_wc(yaw: np.ndarray, pitch: np.ndarray | float, roll: np.ndarray | float) -> np.ndarray:
    """(N, 3, 3) camera -> world rotations: looking along `yaw` in the XY plane, pitched up, rolled."""
    yaw = np.atleast_1d(np.asarray(yaw, float))
    pitch = np.broadcast_to(pitch, yaw.shape)
    roll = np.broadcast_to(roll, yaw.shape)
    cy, sy = np.cos(yaw), np.sin(yaw)
    zero = np.zeros_like(yaw)
    right = np.stack([sy, -cy, zero], -1)
    down = np.stack([zero, zero, zero - 1], -1)
    fwd = np.stack([cy, sy, zero], -1)
    R0 = np.stack([right, down, fwd], axis=-1)  # columns: camera x, y, z in the world
    cp, sp = np.cos(pitch), np.sin(pitch)
    Rx = np.zeros(yaw.shape + (3, 3))
    Rx[:, 0, 0] = 1
    Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = cp, -sp, sp, cp  # positive pitch looks up
    cr, sr = np.cos(roll), np.sin(roll)
    Rz = np.zeros(yaw.shape + (3, 3))
    Rz[:, 2, 2] = 1
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1] = cr, -sr, sr, cr
    return R0 @ Rx @ Rz


def _yaw_about_centre(T_wc: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Copies of the pose T_wc (4, 4) turned by `yaw` (N,) about the world vertical through its centre."""
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.zeros((len(yaw), 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -s, s, c, 1.0
    out = np.repeat(T_wc[None], len(yaw), axis=0)
    out[:, :3, :3] = Rz @ T_wc[:3, :3]
    return out


def _pan_sign(seed: int) -> float:
    """Which way a pan turns (+1 left, -1 right): seeded."""
    return 1.0 if np.random.default_rng([seed, 41]).random() < 0.5 else -1.0


def pan_then_walk(
    scene: Scene,
    n_frames: int,
    fps: float,
    seed: int = 0,
    speed: float = 1.0,
    pan_seconds: float = 2.5,
    pan_deg: float = 45.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A rotation-only start: stand at the start of the walk and pan in place, then walk.

    The first round(pan_seconds * fps) frames turn by `pan_deg` (seeded direction, smoothstep
    profile) about the camera centre into the walk's first view; the camera centre stays exactly at
    the walk's start until the walk begins. The walk is `walkthrough` for the remaining frames.
    """
    n_pan = min(int(round(pan_seconds * fps)), n_frames - 1)
    t = np.arange(n_frames) / fps
    _, walk = walkthrough(scene, n_frames - n_pan, fps, seed, speed)
    u = t[:n_pan] * fps / max(n_pan, 1)  # 0 .. (n_pan - 1) / n_pan: the turn ends on the first walk frame
    offset = _pan_sign(seed) * math.radians(pan_deg) * (1.0 - u * u * (3 - 2 * u))
    return t, np.concatenate([_yaw_about_centre(walk[0], offset), walk])


def look_around(
    scene: Scene,
    n_frames: int,
    fps: float,
    seed: int = 0,
    speed: float = 1.0,
    pan_seconds: float = 2.5,
    pan_deg: float = 45.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A rotation-only recording: stand at the start of the walk and pan back and forth, never moving.

    Yaw sweeps `pan_deg` away from the walk's first view and back (one sweep every `pan_seconds`,
    sinusoidal speed, seeded direction), with hand-held pitch/roll wobble; the camera centre is the
    walk's first position in every frame.
    """
    rng = np.random.default_rng([seed, 47])
    t = np.arange(n_frames) / fps
    _, walk = walkthrough(scene, n_frames, fps, seed, speed)
    offset = _pan_sign(seed) * math.radians(pan_deg) * 0.5 * (1.0 - np.cos(math.pi * t / pan_seconds))
    pitch = math.radians(1.0) * _smooth_noise(rng, t, 0.2, 1.2)
    roll = math.radians(1.0) * _smooth_noise(rng, t, 0.2, 1.2)
    T_wc = _yaw_about_centre(walk[0], offset)
    # wobble about the camera's own axes (still a pure rotation about its centre)
    cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    Rx = np.zeros((n_frames, 3, 3))
    Rx[:, 0, 0], Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = 1, cp, -sp, sp, cp
    Rz = np.zeros((n_frames, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = cr, -sr, sr, cr, 1
    T_wc[:, :3, :3] = T_wc[:, :3, :3] @ Rx @ Rz
    return t, T_wc
