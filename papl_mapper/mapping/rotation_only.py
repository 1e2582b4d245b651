"""Orientations of frames that turn in place: the rotation of the rays they share with a posed frame.

A hand-held recording often starts by standing and panning, or turns in place where nothing is
mapped yet. Such frames have no baseline, so no structure may come from them, but their orientation
is well defined: the rotation that maps the rays of the point tracks they share with a posed frame
(`rotation_between_rays`), accepted only where it explains those rays to `max_residual_deg`, that
is where no parallax is left. The camera centre stays at the posed frame's. The anchor moves on to
the newest frame so posed while the rotation phase lasts; a frame that translated shows parallax
against its anchor and ends the chain, so positions are never frozen over a walk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from papl_mapper.geometry.se3 import bearings, rotation_between_rays
from papl_mapper.tracks import Tracks


@dataclass
class RotationOnlyConfig:
    """When a frame counts as turning in place relative to a posed frame."""

    enabled: bool = True
    """Give frames that PnP cannot pose an orientation where a pure rotation explains them."""
    min_tracks: int = 20
    """Fewest point tracks shared with the anchor frame."""
    max_residual_deg: float = 0.3
    """Largest median angle between the shared rays after the rotation (the parallax left)."""
    reanchor_below: int = 60
    """Move the anchor to the newest rotation-posed frame once fewer tracks than this are shared."""


def rotation_pose(
    tracks: Tracks, f: int, g: int, T_cw_g: np.ndarray, cfg: RotationOnlyConfig
) -> tuple[np.ndarray | None, int]:
    """T_cw of frame f turned in place from frame g (pose T_cw_g), or None; and the tracks they share."""
    id_f, uv_f = tracks.points_in(f)
    id_g, uv_g = tracks.points_in(g)
    _, i_f, i_g = np.intersect1d(id_f, id_g, assume_unique=True, return_indices=True)
    if len(i_f) < cfg.min_tracks:
        return None, len(i_f)
    K = tracks.camera.K
    focal = np.array([K[0, 0], K[1, 1]])
    b_f = bearings((uv_f[i_f] - K[:2, 2]) / focal)
    b_g = bearings((uv_g[i_g] - K[:2, 2]) / focal)
    R_fg, err = rotation_between_rays(b_g, b_f)
    if float(np.median(err)) > cfg.max_residual_deg:
        return None, len(i_f)
    T = np.eye(4)
    T[:3, :3] = R_fg @ T_cw_g[:3, :3]
    centre = -T_cw_g[:3, :3].T @ T_cw_g[:3, 3]
    T[:3, 3] = -T[:3, :3] @ centre + 0.0  # + 0.0: no negative zeros in the written trajectory
    return T, len(i_f)


def _chain(
    tracks: Tracks, frames: range, anchor: int, T_cw: dict[int, np.ndarray], cfg: RotationOnlyConfig
) -> dict[int, np.ndarray]:
    """Pose `frames` in order from `anchor` while each turns in place; stops at the first that does not."""
    out: dict[int, np.ndarray] = {}
    last = anchor
    for f in frames:
        T, shared = rotation_pose(tracks, f, anchor, T_cw[anchor] if anchor in T_cw else out[anchor], cfg)
        if T is None and last != anchor:  # too little overlap left with the anchor: move it on
            anchor = last
            T, shared = rotation_pose(tracks, f, anchor, out[anchor], cfg)
        if T is None:
            break
        out[f] = T
        last = f
        if shared < cfg.reanchor_below:
            anchor = f
    return out


def fill_rotation_only(
    tracks: Tracks, T_cw: dict[int, np.ndarray], cfg: RotationOnlyConfig
) -> dict[int, np.ndarray]:
    """Poses (T_cw) for the frames without one that turn in place next to posed frames."""
    if not cfg.enabled or not T_cw:
        return {}
    out: dict[int, np.ndarray] = {}
    n = len(tracks)
    posed = np.zeros(n, bool)
    posed[list(T_cw)] = True
    f = 0
    while f < n:
        if posed[f]:
            f += 1
            continue
        end = f
        while end < n and not posed[end]:
            end += 1
        if f > 0:  # forward from the posed frame before the gap
            out.update(_chain(tracks, range(f, end), f - 1, T_cw, cfg))
        if end < n:  # backward from the posed frame after it, for what is left
            rest = [g for g in range(end - 1, f - 1, -1) if g not in out]
            if rest:
                back = _chain(tracks, range(end - 1, f - 1, -1), end, T_cw, cfg)
                out.update({g: T for g, T in back.items() if g not in out})
        f = end
    return out


def rotation_only_recording(tracks: Tracks, cfg: RotationOnlyConfig) -> dict[int, np.ndarray] | None:
    """Orientations (T_cw, centre at the origin) of every frame if the whole recording turns in place."""
    if len(tracks) < 2:
        return None
    start = {0: np.eye(4)}
    rest = _chain(tracks, range(1, len(tracks)), 0, start, cfg)
    if len(rest) < len(tracks) - 1:
        return None
    return {**start, **rest}
