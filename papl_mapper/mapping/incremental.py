"""Incremental keyframe registration from point tracks: initialise, PnP, triangulate, repeat; a frame
with too few points is registered by its relative pose to the last keyframe, or else from its lines.

This gives the first estimate of keyframe poses and points; line triangulation, axis
management and bundle adjustment refine it. Poses are `T_cw` (world to camera) here because
PnP and projection want them; the Map stores `T_wc`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from papl_mapper.errors import PaplError, UnmappableError
from papl_mapper.frontend.descriptors import match_descriptors
from papl_mapper.geometry.se3 import invert, rotation_angle_deg, similarity_T_cw
from papl_mapper.geometry.similarity import Sim3, umeyama
from papl_mapper.geometry.triangulation import max_reprojection_px, triangulate_points
from papl_mapper.geometry.two_view import normalised
from papl_mapper.mapping.initialise import InitConfig, initialise_two_view
from papl_mapper.mapping.point_store import PointStore
from papl_mapper.mapping.pose_refine import RegistrationDirections, frame_directions
from papl_mapper.mapping.registration_lines import RegistrationLines, RegistrationLinesConfig
from papl_mapper.mapping.relative_pose import RelativePoseConfig, register_relative
from papl_mapper.mapping.revisit import (
    Revisit,
    RevisitConfig,
    RevisitGate,
    TrackIndex,
    close_loop,
    find_revisit,
)
from papl_mapper.mapping.rotation_only import RotationOnlyConfig, rotation_only_recording
from papl_mapper.mapping.tracking import PnPConfig, PnPResult, pose_from_lines, track_pnp
from papl_mapper.tracks import PointRows, Tracks

log = logging.getLogger(__name__)


@dataclass
class IncrementalConfig:
    """Settings of incremental keyframe registration."""

    init: InitConfig = field(default_factory=InitConfig)
    """Two-view initialisation thresholds."""
    pnp: PnPConfig = field(default_factory=PnPConfig)
    """PnP tracking thresholds."""
    revisit: RevisitConfig = field(default_factory=RevisitConfig)
    """Revisit detection and loop closure."""
    relative_pose: RelativePoseConfig = field(default_factory=RelativePoseConfig)
    """A frame that PnP cannot pose is registered by its essential matrix to the last keyframe."""
    rotation_only: RotationOnlyConfig = field(default_factory=RotationOnlyConfig)
    """Orientations of frames that turn in place where PnP cannot pose them (no parallax)."""
    init_search_keyframes: int = 25
    """How many keyframes after the first one to try as the initialisation partner."""
    min_parallax_deg: float = 2.0
    """Smallest ray angle for triangulating a new point."""
    starved_parallax_deg: float = 0.5
    """Smallest ray angle when the frame sees fewer than `starved_below` mapped points: in a fast
    turn new points leave the view before they gain 2 degrees, and far ones still fix rotation."""
    starved_below: int = 120
    """Mapped points seen by a keyframe under which the map counts as starved."""
    max_reprojection_px: float = 3.0
    """Largest reprojection error of a newly triangulated point in the views that made it."""
    mature_parallax_deg: float = 8.0
    """Points triangulated with at least this ray angle are not re-triangulated from new views."""
    keyframe_min_inliers: int = 60
    """A frame with fewer PnP inliers becomes a keyframe (the map needs new points)."""
    keyframe_min_known: float = 0.5
    """A frame whose mapped points are fewer than this fraction of its point tracks becomes a keyframe."""
    keyframe_min_gap: int = 1
    """...if at least this many frames have passed since the last keyframe."""
    refine_every: int = 10
    """New keyframes between two calls of the refinement callback (the windowed BA; 0: never)."""
    starved_refine_every: int = 1
    """...while the keyframes see fewer than `starved_below` mapped points (a turn): the points they
    add have little parallax, and their depths, biased low, scale the next frames' poses; refined
    only every `refine_every` keyframes, that bias compounds into a scale drift through the turn."""
    max_lost_frames: int = 5
    """Frames in a row that fail to register before tracking counts as lost and a new segment starts."""
    segment_overlap_frames: int = 30
    """A new segment tracks backwards this far into the frames the previous one posed, triangulating
    as it goes, so that the two share frames and points to be joined on (0: not past its start)."""
    merge_min_points: int = 12
    """Fewest shared points (agreeing under the Sim(3)) to merge a segment into the map."""
    merge_ransac_iterations: int = 2000
    """3-point samples tried when estimating a segment's Sim(3) to the map."""
    merge_match_ratio: float = 0.8
    """Lowe ratio for matching keyframe ORB descriptors between tracking segments."""
    merge_min_frames: int = 3
    """Fewest frames posed by both segments to join them on those frames where too few shared points
    agree under one Sim(3) (points triangulated in a turn carry poor depths; the poses are good)."""
    merge_min_frame_points: int = 5
    """...and fewest points both triangulated, whose depths give the scale."""
    merge_max_rotation_deg: float = 2.0
    """...and most any shared frame's rotation between the segments may differ from their mean."""
    merge_tolerance: float = 0.05
    """Largest point disagreement after the Sim(3), as a fraction of the map's median point spread."""
    retry_lost: bool = True
    """After the pass in frame order, try the frames it could not pose again against the whole map,
    those seeing the most mapped points first, until none more registers: a photo of a place the pass
    reached only later (photos out of order, a frame before a cut) is posed from the points mapped
    there, instead of being left to the final map with few of its points triangulated."""
    track_lines: RegistrationLinesConfig = field(default_factory=RegistrationLinesConfig)
    """Line tracks triangulated from the keyframes so far: they refine each frame's pose with the points
    (when enabled) and pose the frames points cannot (`pnp.from_lines`)."""


@dataclass
class Registration:
    """Registered keyframes (rows into the Tracks frames) with poses `T_cw`, and points by track id."""

    frames: list[int] = field(default_factory=list)
    T_cw: dict[int, np.ndarray] = field(default_factory=dict)
    points_w: PointStore = field(default_factory=PointStore)
    point_angle: dict[int, float] = field(default_factory=dict)
    """Largest ray angle (deg) each point was triangulated with."""
    T_cw_frames: dict[int, np.ndarray] = field(default_factory=dict)
    """PnP poses of the registered frames that are not keyframes."""
    lost: list[int] = field(default_factory=list)
    """Frames that could not be registered (tracking loss)."""
    revisits: list[Revisit] = field(default_factory=list)
    """Loops closed during registration."""
    left_out: list[Registration] = field(default_factory=list)
    """The tracking segments that could not be joined to the map (their frames are among `lost`), each
    with its own registration (its own frame and scale), in frame order, for maps of their own."""
    init_frames: tuple[int, int] = (-1, -1)

    def __post_init__(self) -> None:
        if not isinstance(self.points_w, PointStore):
            self.points_w = PointStore(self.points_w)

    def poses(self) -> dict[int, np.ndarray]:
        """T_cw of every frame with a pose: the keyframes' and those of the frames between them."""
        return {**self.T_cw_frames, **self.T_cw}

    @property
    def segments_left_out(self) -> list[tuple[int, int]]:
        """First and last frame (rows) posed by each segment in `left_out`."""
        return [(min(seg.poses()), max(seg.poses())) for seg in self.left_out]


ProgressCallback = Callable[[int, int, str], None]


def _common(tracks: Tracks, f1: int, f2: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    id1, uv1 = tracks.points_in(f1)
    id2, uv2 = tracks.points_in(f2)
    common, i1, i2 = np.intersect1d(id1, id2, assume_unique=True, return_indices=True)
    return common, uv1[i1], uv2[i2]


def _starved(res: PnPResult, cfg: IncrementalConfig) -> bool:
    """Whether the frame `res` posed sees fewer than `starved_below` mapped points (its inlier mask has
    one entry per mapped point it sees): a turn, where new points come at little parallax."""
    return len(res.inliers) < cfg.starved_below


def _triangulate_new(
    tracks: Tracks, rows: PointRows, reg: Registration, frame: int, cfg: IncrementalConfig, starved: bool
) -> int:
    """Triangulate the point tracks seen in `frame` from all their registered keyframes (vectorised).

    New tracks enter the map once their rays span `min_parallax_deg` (`starved_parallax_deg` where the
    frame is `starved`); mapped ones are re-triangulated when the new view widens their ray angle by
    a fifth, so early low-parallax depths mature instead of dragging the scale. Returns the number of
    new points.
    """
    K = tracks.camera.K
    ids, _ = tracks.points_in(frame)
    min_parallax = cfg.starved_parallax_deg if starved else cfg.min_parallax_deg
    ids = np.array(
        [t for t in ids.tolist() if reg.point_angle.get(t, 0.0) < cfg.mature_parallax_deg], np.int64
    )
    if len(ids) == 0:
        return 0
    sel = rows.rows(ids)
    sel = sel[np.isin(tracks.point_frame[sel], reg.frames)]
    obs_track, obs_frame, uv = tracks.point_track[sel], tracks.point_frame[sel], tracks.point_uv[sel]
    uniq, point_index = np.unique(obs_track, return_inverse=True)
    T_cw = np.stack([reg.T_cw[int(f)] for f in obs_frame])
    T_wc = invert(T_cw)
    X, ok = triangulate_points(point_index, T_wc, K, uv, len(uniq), min_parallax)
    max_err = max_reprojection_px(point_index, T_cw, K, uv, X)
    angle = _ray_angle_deg(point_index, T_wc[:, :3, 3], X, len(uniq))
    ok &= (max_err < cfg.max_reprojection_px) & (angle >= min_parallax)
    added = 0
    for i in np.flatnonzero(ok):
        tid = int(uniq[i])
        old = reg.point_angle.get(tid)
        if old is not None and angle[i] < 1.2 * old:
            continue
        added += old is None
        reg.points_w[tid] = X[i]
        reg.point_angle[tid] = float(angle[i])
    return added


def _ray_angle_deg(point_index: np.ndarray, centres: np.ndarray, X: np.ndarray, n: int) -> np.ndarray:
    """Largest angle (deg) between the rays from a point to the cameras that saw it."""
    rays = X[point_index] - centres
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-300)
    mean = np.zeros((n, 3))
    np.add.at(mean, point_index, rays)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-300)
    # the two rays farthest from the mean, on opposite sides, span about twice the largest offset
    cos = np.full(n, 1.0)
    np.minimum.at(cos, point_index, np.sum(rays * mean[point_index], axis=1))
    return 2.0 * np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _initialise(
    tracks: Tracks, keyframes: np.ndarray, cfg: IncrementalConfig, seed: int = 0
) -> Registration | None:
    """Two-view start from the first keyframe that has a usable partner, with its best partner.

    An offline mapper can afford to compare partners: among those within `init_search_keyframes`,
    the one with the most well-triangulated points (parallax of `init.strong_parallax_deg`, then the
    most points) wins, not the first one over the thresholds, which is the shortest usable baseline.
    """
    K = tracks.camera.K
    for a in range(len(keyframes)):
        best: tuple[tuple[int, int], int, np.ndarray, object] | None = None
        for b in range(a + 1, min(len(keyframes), a + 1 + cfg.init_search_keyframes)):
            f1, f2 = int(keyframes[a]), int(keyframes[b])
            common, uv1, uv2 = _common(tracks, f1, f2)
            res = initialise_two_view(normalised(uv1, K), normalised(uv2, K), K[0, 0], cfg.init, seed)
            if not res.ok:
                log.debug("init %d-%d: %s", f1, f2, res.reason)
                continue
            score = (res.strong_points, len(res.point_index))
            if best is None or score > best[0]:
                best = (score, f2, common, res)
        if best is None:
            continue
        _, f2, common, res = best
        f1 = int(keyframes[a])
        reg = Registration(frames=[f1, f2], init_frames=(f1, f2))
        reg.T_cw[f1] = np.eye(4)
        T2 = np.eye(4)
        T2[:3, :3], T2[:3, 3] = res.R_21, res.t_21
        reg.T_cw[f2] = T2
        for tid, X in zip(common[res.point_index], res.points_1, strict=True):
            reg.points_w[int(tid)] = X
        log.info("initialised on keyframes %d and %d: %s", f1, f2, res.reason)
        return reg
    return None


def register_keyframes(
    tracks: Tracks,
    config: IncrementalConfig | None = None,
    progress: ProgressCallback | None = None,
    refine: Callable[[Registration], None] | None = None,
    seed: int = 0,
) -> Registration:
    """Register the frames of `tracks`; where tracking is lost, map on in a new segment and merge it.

    A frame becomes a keyframe when the frontend chose it, or when the map no longer explains it
    well (few PnP inliers, or most of its tracks not yet in the map): an offline mapper can
    afford the extra keyframes that keep it from losing track in turns. After `max_lost_frames`
    frames in a row fail, a new segment is initialised further on; segments that share enough
    triangulated points with the map are merged into it by a Sim(3), the others are reported and
    left out (their frames are `lost`). `refine(reg)` runs after every `refine_every` keyframes.
    Revisits of places mapped long before close loops and rename the later point tracks to the
    earlier ones in `tracks.point_track` (in place), so later stages see one track per 3D point.
    `seed` seeds every random choice (the RANSACs of initialisation, PnP and segment merging).
    """
    cfg = config or IncrementalConfig()
    tracks.validate()
    index = TrackIndex.build(tracks)
    keyframes = np.flatnonzero(tracks.is_keyframe)
    segments: list[Registration] = []
    start = 0
    while start < len(tracks):
        reg = _initialise(tracks, keyframes[keyframes >= start], cfg, seed)
        if reg is None:
            break
        end = _extend(tracks, reg, start, cfg, progress, refine, index if cfg.revisit.enabled else None, seed)
        segments.append(reg)
        start = end + 1
    if not segments:
        if len(tracks) < 2:
            raise UnmappableError(
                f"too few frames: {len(tracks)} decoded frame, a map needs at least two views of the place "
                "from different positions; give a longer recording (or check --start/--end/--step)"
            )
        turned = rotation_only_recording(tracks, cfg.rotation_only) if cfg.rotation_only.enabled else None
        if (
            turned is not None
            and max(rotation_angle_deg(T[:3, :3], np.eye(3)) for T in turned.values()) < 1.0
        ):
            raise UnmappableError(
                f"no motion: the camera stands still in all {len(tracks)} frames, nothing to map; "
                "record while walking through the place",
                T_cw_frames=turned,
            )
        if turned is not None:
            raise UnmappableError(
                f"rotation only: the camera turns in place in all {len(tracks)} frames, so there is no "
                "parallax to map from; orientations are written to trajectory.tum, no structure; "
                "record while walking, not only panning",
                T_cw_frames=turned,
            )
        raise UnmappableError(
            f"could not initialise from {len(keyframes)} keyframes: too little parallax or too few "
            "tracked points; try a recording with sideways or forward motion, or a lower --step"
        )
    reg = _merge_segments(segments, cfg, index, seed)
    if cfg.retry_lost:
        _register_lost(tracks, reg, cfg, seed)
    registered = reg.poses()
    reg.lost = [f for f in range(len(tracks)) if f not in registered]
    reg.frames.sort()
    return reg


def _extend(
    tracks: Tracks,
    reg: Registration,
    start: int,
    cfg: IncrementalConfig,
    progress: ProgressCallback | None,
    refine: Callable[[Registration], None] | None,
    index: TrackIndex | None = None,
    seed: int = 0,
) -> int:
    """Register frames after the initial pair until tracking is lost; returns the last frame tried."""
    f1, f2 = reg.init_frames
    last_T = reg.T_cw[f1]
    since_refine = 0
    misses = 0
    last_keyframe = f1
    rc = cfg.pnp.refine
    use_dirs = rc.enabled and rc.directions and rc.in_registration
    dirs = RegistrationDirections(tracks, vertical_only=rc.vertical_only) if use_dirs else None
    use_lines = cfg.track_lines.enabled or cfg.pnp.from_lines.enabled
    lines = RegistrationLines(tracks, cfg.track_lines) if use_lines else None
    rows = PointRows(tracks)
    gate = RevisitGate(cfg.revisit)
    f = f1
    for f in range(f1 + 1, len(tracks)):
        if f == f2:
            last_T = reg.T_cw[f2]
            last_keyframe = f2
            continue
        res, n_tracks = _pnp(tracks, reg, f, last_T, cfg, dirs, lines, seed)
        if (res is None or not res.ok) and cfg.relative_pose.enabled:
            # too few mapped points (a wide baseline): the step from the last keyframe, scaled by them
            rel = register_relative(
                tracks, f, last_keyframe, reg.T_cw[last_keyframe], reg.points_w, cfg.relative_pose, seed
            )
            res = rel if rel.ok else res
        if res is None or not res.ok:
            # too few points at all (blank walls): the lines and directions the frame sees hold the pose
            res = _pose_from_lines(tracks, reg, f, last_T, cfg, dirs, lines, seed) or res
        if res is None or not res.ok:
            log.debug("frame %d not registered: %s", f, "no map points" if res is None else res.reason)
            misses += 1
            if misses >= cfg.max_lost_frames and f > f2:
                log.info("tracking lost at frame %d: %s", f - misses + 1, "segment ends")
                break
            continue
        misses = 0
        last_T = res.T_cw
        weak = int(res.inliers.sum()) < cfg.keyframe_min_inliers
        # mapped points, not inliers: a frame whose points are mapped but loosely (early, low-parallax
        # depths) is refined by BA; a keyframe is for tracks the map does not hold yet
        unmapped = (
            len(res.inliers) < cfg.keyframe_min_known * n_tracks and f - last_keyframe >= cfg.keyframe_min_gap
        )
        if tracks.is_keyframe[f] or weak or unmapped:
            reg.T_cw[f] = res.T_cw
            reg.frames.append(f)
            last_keyframe = f
            starved = _starved(res, cfg)
            added = _triangulate_new(tracks, rows, reg, f, cfg, starved)
            log.debug("keyframe %d: %s, %d new points", f, res.reason, added)
            if index is not None and tracks.is_keyframe[f]:
                rv = find_revisit(
                    tracks, reg.points_w, reg.T_cw, f, index, cfg.revisit, seed, reg.point_angle
                )
                if gate.admit(rv) and close_loop(tracks, reg.points_w, reg.T_cw, reg.T_cw_frames, rv, index):
                    reg.revisits.append(rv)
                    rows.rename(rv.fused)  # the loop renamed tracks
                    last_T = reg.T_cw[f]
            since_refine += 1
            every = cfg.starved_refine_every if starved else cfg.refine_every
            if refine is not None and cfg.refine_every > 0 and since_refine >= every:
                refine(reg)
                last_T = reg.T_cw[f]
                since_refine = 0
        else:
            reg.T_cw_frames[f] = res.T_cw
        if progress:
            progress(f + 1, len(tracks), f"{len(reg.frames)} keyframes, {len(reg.points_w)} points")
    # the next segment may start right after the last registered frame: where tracking was lost, and
    # where the recording ended on fewer than max_lost_frames frames this one could not register (a
    # sparse photo set, a cut near the end)
    f -= misses
    # frames between the segment's start and its initialisation pair are tracked backwards, and on
    # into the previous segment's last frames, where new points give the two something to share
    for g in range(f1 - 1, max(0, start - cfg.segment_overlap_frames) - 1, -1):
        guess = reg.T_cw[min(reg.T_cw)]
        res, _ = _pnp(tracks, reg, g, guess, cfg, dirs, lines, seed)
        if res is None or not res.ok:
            res = _pose_from_lines(tracks, reg, g, guess, cfg, dirs, lines, seed) or res
        if res is None or not res.ok:
            break
        reg.T_cw[g] = res.T_cw
        reg.frames.append(g)
        if g < start:
            _triangulate_new(tracks, rows, reg, g, cfg, _starved(res, cfg))
    return max(f, f2)


def _register_lost(tracks: Tracks, reg: Registration, cfg: IncrementalConfig, seed: int = 0) -> int:
    """Pose the frames without one by PnP against the whole map, as keyframes that triangulate their
    tracks: in sweeps over those frames, the ones seeing the most mapped points first, until a sweep
    registers none (a frame that failed is tried again only once it sees more mapped points). No
    pose guess: the frame may lie anywhere along the recording. Returns the frames registered."""
    rows = PointRows(tracks)
    posed = reg.poses()
    waiting = [f for f in range(len(tracks)) if f not in posed]
    tried: dict[int, int] = {}  # frame -> mapped points it saw when PnP last failed
    added = 0
    while waiting:
        seen = {f: int(reg.points_w.has(tracks.points_in(f)[0]).sum()) for f in waiting}
        due = [f for f in waiting if seen[f] >= cfg.pnp.min_inliers and seen[f] > tried.get(f, 0)]
        registered = set()
        for f in sorted(due, key=lambda g: -seen[g]):
            res, _ = _pnp(tracks, reg, f, None, cfg, seed=seed)
            if res is None or not res.ok:
                tried[f] = seen[f]
                continue
            reg.T_cw[f] = res.T_cw
            reg.frames.append(f)
            _triangulate_new(tracks, rows, reg, f, cfg, _starved(res, cfg))
            log.debug("frame %d registered against the whole map: %s", f, res.reason)
            registered.add(f)
        if not registered:
            break
        added += len(registered)
        waiting = [f for f in waiting if f not in registered]
    if added:
        log.info("%d frames the pass in frame order could not pose registered against the whole map", added)
    return added


def _matched_tracks(index: TrackIndex, a: set[int], b: set[int], ratio: float) -> list[tuple[int, int]]:
    """Pairs (track in b, track in a) whose keyframe ORB descriptors match (ratio test, mutual best)."""
    ta = index.desc_ids[np.isin(index.desc_ids, np.fromiter(a, np.int64, len(a)))]
    tb = index.desc_ids[np.isin(index.desc_ids, np.fromiter(b, np.int64, len(b)))]
    if len(ta) < 2 or len(tb) < 2:
        return []
    da = index.desc[np.searchsorted(index.desc_ids, ta)]
    db = index.desc[np.searchsorted(index.desc_ids, tb)]
    pairs = match_descriptors(db, da, 256, ratio)
    return [(int(tb[i]), int(ta[j])) for i, j in pairs.tolist()]


def _posed(reg: Registration) -> int:
    """Frames a segment gives a pose (keyframes and the frames registered between them)."""
    return len(reg.poses())


def _merge_segments(
    segments: list[Registration], cfg: IncrementalConfig, index: TrackIndex, seed: int = 0
) -> Registration:
    """Join the segments pairwise until no two can be: a Sim(3) on the points they share, by track id
    or by matching keyframe ORB descriptors (a revisit of a mapped place), or else on the frames both
    posed (`_sim3_from_shared_frames`). Any two may join, not only a segment and the largest: two
    segments after a blind stretch often share tracks with each other but not with the map before it.
    The group posing the most frames is the map; the others are reported and left out."""
    groups = sorted(segments, key=_posed, reverse=True)
    failed: set[tuple[int, int]] = set()  # (id of the larger group, id of the smaller) that did not join
    while len(groups) > 1 and _join_first(groups, failed, cfg, index, seed):
        groups.sort(key=_posed, reverse=True)
    for seg in groups[1:]:
        log.warning(
            "tracking segment of frames %d-%d (%d keyframes) could not be joined to the map: left out",
            min(seg.frames),
            max(seg.frames),
            len(seg.frames),
        )
    groups[0].left_out = sorted(groups[1:], key=lambda seg: min(seg.poses()))
    return groups[0]


def _join_first(
    groups: list[Registration],
    failed: set[tuple[int, int]],
    cfg: IncrementalConfig,
    index: TrackIndex,
    seed: int,
) -> bool:
    """Join the first pair of `groups` (larger first) not in `failed` that can be joined; the smaller
    leaves `groups` and the grown one may be tried again with the others. False when none joins."""
    for i, big in enumerate(groups):
        for j in range(i + 1, len(groups)):
            key = (id(big), id(groups[j]))
            if key in failed:
                continue
            if _merge_into(big, groups[j], cfg, index, seed):
                del groups[j]
                failed -= {k for k in failed if id(big) in k}
                return True
            failed.add(key)
    return False


def _merge_into(
    base: Registration, seg: Registration, cfg: IncrementalConfig, index: TrackIndex, seed: int
) -> bool:
    """Map `seg` into `base`'s frame by a robust Sim(3) on the points they share, or else on the frames
    both posed, and add its poses and points (base's own are kept where both have one); False when
    neither gives one."""
    pairs = [(t, t) for t in sorted(set(seg.points_w) & set(base.points_w))]
    pairs += [
        p
        for p in _matched_tracks(index, set(base.points_w), set(seg.points_w), cfg.merge_match_ratio)
        if p[0] != p[1]
    ]
    sim = None
    if len(pairs) >= cfg.merge_min_points:
        x = np.array([seg.points_w[tb] for tb, _ in pairs])
        y = np.array([base.points_w[ta] for _, ta in pairs])
        try:
            sim = _robust_sim3(x, y, cfg, seed)
        except PaplError as exc:
            log.debug("segment merge: %s", exc)
    if sim is None:
        sim = _sim3_from_shared_frames(base, seg, cfg)
    if sim is None:
        return False
    R, t, c = sim.R, sim.t, sim.scale
    log.info(
        "merged the segment of frames %d-%d into that of frames %d-%d on %s",
        min(seg.frames),
        max(seg.frames),
        min(base.frames),
        max(base.frames),
        "the frames both posed" if sim.method == "shared frames" else f"{len(pairs)} shared points",
    )
    posed = base.poses()
    for src, dst in ((seg.T_cw, base.T_cw), (seg.T_cw_frames, base.T_cw_frames)):
        for f, T in src.items():
            if f not in posed:
                dst[f] = similarity_T_cw(T, R, t, c)
    base.frames = sorted(set(base.frames) | {f for f in seg.frames if f in base.T_cw})
    for tid, X in seg.points_w.items():
        base.points_w.setdefault(tid, c * R @ X + t)
    return True


def _sim3_from_shared_frames(base: Registration, seg: Registration, cfg: IncrementalConfig) -> Sim3 | None:
    """Sim(3) from `seg`'s world to `base`'s from frames both posed (a segment tracked back into the
    previous one): rotation and translation from the poses, scale from the depths of the points both
    triangulated, as seen from those frames; None with too few frames or points, or poses that disagree."""
    posed_base, posed_seg = base.poses(), seg.poses()
    frames = sorted(set(posed_base) & set(posed_seg))
    shared = sorted(set(base.points_w) & set(seg.points_w))
    if len(frames) < cfg.merge_min_frames or len(shared) < cfg.merge_min_frame_points:
        return None
    Rs = np.stack([posed_base[g][:3, :3].T @ posed_seg[g][:3, :3] for g in frames])
    u, _, vt = np.linalg.svd(Rs.sum(axis=0))  # chordal mean of the per-frame rotations
    R = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    if max(rotation_angle_deg(R, Rg) for Rg in Rs) > cfg.merge_max_rotation_deg:
        return None
    Xb = np.stack([base.points_w[t] for t in shared])
    Xs = np.stack([seg.points_w[t] for t in shared])
    ratios = []
    for g in frames:
        zb = Xb @ posed_base[g][2, :3] + posed_base[g][2, 3]
        zs = Xs @ posed_seg[g][2, :3] + posed_seg[g][2, 3]
        ok = (zb > 0) & (zs > 0)
        ratios.append(zb[ok] / zs[ok])
    ratios = np.concatenate(ratios)
    if len(ratios) < cfg.merge_min_frame_points:
        return None
    scale = float(np.median(ratios))
    centres_b = invert(np.stack([posed_base[g] for g in frames]))[:, :3, 3]
    centres_s = invert(np.stack([posed_seg[g] for g in frames]))[:, :3, 3]
    t = np.mean(centres_b - scale * centres_s @ R.T, axis=0)
    return Sim3(R, t, scale, "shared frames")


def _robust_sim3(x: np.ndarray, y: np.ndarray, cfg: IncrementalConfig, seed: int = 0) -> Sim3 | None:
    """Sim(3) y ~ s R x + t by RANSAC over 3-point samples, refit on the inliers; None if too few agree."""
    rng = np.random.default_rng(seed)
    scale = np.median(np.linalg.norm(y - np.median(y, axis=0), axis=1))
    tol = cfg.merge_tolerance * scale
    best = np.zeros(len(x), bool)
    for _ in range(cfg.merge_ransac_iterations):
        idx = rng.choice(len(x), 3, replace=False)
        try:
            sim = umeyama(x[idx], y[idx])
        except PaplError:  # degenerate samples (collinear, coincident points) are skipped
            continue
        inl = np.linalg.norm(sim.scale * x @ sim.R.T + sim.t - y, axis=1) < tol
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < cfg.merge_min_points:
        return None
    return umeyama(x[best], y[best])


def _pnp(
    tracks: Tracks,
    reg: Registration,
    f: int,
    guess: np.ndarray | None,
    cfg: IncrementalConfig,
    dirs: RegistrationDirections | None = None,
    lines: RegistrationLines | None = None,
    seed: int = 0,
) -> tuple[PnPResult | None, int]:
    """PnP of frame f against the points mapped so far; None when too few of them are seen."""
    ids, uv = tracks.points_in(f)
    known = reg.points_w.has(ids)
    if known.sum() < cfg.pnp.min_inliers:
        return None, len(ids)
    X = reg.points_w.xyz(ids[known])
    # the line tracks the keyframes so far triangulate hold the pose where points are few
    refine_lines = lines is not None and cfg.track_lines.enabled
    lines_w, line_xy, _ = lines.frame_lines(f, reg.T_cw) if refine_lines else (None, None, None)
    pnp = lines.pnp_config(cfg.pnp) if refine_lines else cfg.pnp
    if dirs is None:
        res = track_pnp(
            X, uv[known], tracks.camera.K, guess, pnp, lines_w=lines_w, line_xy=line_xy, seed=seed
        )
        return res, len(ids)
    # the vanishing directions of the keyframes so far hold the rotation where points are weak
    dirs_w, sigma = dirs(reg.T_cw)
    res = track_pnp(
        X,
        uv[known],
        tracks.camera.K,
        guess,
        pnp,
        lines_w=lines_w,
        line_xy=line_xy,
        dirs_w=dirs_w,
        dirs_c=frame_directions(tracks, f),
        dirs_sigma_deg=sigma,
        seed=seed,
    )
    return res, len(ids)


def _pose_from_lines(
    tracks: Tracks,
    reg: Registration,
    f: int,
    guess: np.ndarray,
    cfg: IncrementalConfig,
    dirs: RegistrationDirections | None,
    lines: RegistrationLines | None,
    seed: int = 0,
) -> PnPResult | None:
    """Frame f posed from the line tracks the keyframes so far triangulate, its vanishing directions and
    its few mapped points (`tracking.pose_from_lines`); None when that is off or the frame sees fewer
    lines than it needs."""
    if lines is None or not cfg.pnp.from_lines.enabled:
        return None
    lines_w, line_xy, _ = lines.frame_lines(f, reg.T_cw)
    if len(lines_w) < cfg.pnp.from_lines.min_lines:
        return None
    ids, uv = tracks.points_in(f)
    known = reg.points_w.has(ids)
    X = reg.points_w.xyz(ids[known])
    dirs_w = dirs(reg.T_cw)[0] if dirs is not None else None
    res = pose_from_lines(
        X,
        uv[known],
        tracks.camera.K,
        guess,
        lines_w,
        line_xy,
        cfg.pnp,
        dirs_w=dirs_w,
        dirs_c=frame_directions(tracks, f),
        seed=seed,
    )
    log.debug("frame %d from lines: %s", f, res.reason)
    return res
