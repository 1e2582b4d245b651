"""Global and local bundle adjustment of a Map in gtsam: poses, points, anchored / temporary-VP /
orthonormal lines and principal axes in one factor graph, solved by Levenberg-Marquardt.

Both functions return a BAResult whose `map` is an optimised deep copy: the input Map is never changed.
Written back: keyframe poses, point positions, line endpoints (the optimised infinite line clipped to
its observed extent), `ref_keyframe_id` and `inverse_depth` (1/z of the point of the observed segment
midpoint's ray in the reference keyframe closest to the optimised line) of anchored and temporary-VP
lines, and axis directions. With BAConfig.anchor_offset anchored lines are optimised as the shared axis
plus (inverse depth, sideways offset) per line (the offset starts at 0 on that ray and is not stored).
"""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import gtsam
import numpy as np

from papl_mapper import geometry as geo
from papl_mapper.backend.config import BAConfig, min_parallax_deg
from papl_mapper.backend.factors import (
    AX,
    RS,
    D,
    F,
    P,
    R,
    U,
    W,
    X,
    axis_prior_factor,
    scale_prior_factor,
    symbols,
)
from papl_mapper.backend.linebatch import KIND_FIXDIR, LineBatch
from papl_mapper.backend.lm import LevenbergMarquardt
from papl_mapper.backend.problem import (
    KIND_ANCHORED,
    KIND_ORTHO,
    KIND_TVP,
    LineGroup,
    Problem,
    build_problem,
    uses_offset,
)
from papl_mapper.errors import GeometryError, OptimizationError
from papl_mapper.geometry.lines import line_parallax_deg
from papl_mapper.map import Map

log = logging.getLogger(__name__)

FIXED_POSE_NOISE = gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
"""Poses held at their value: radians and map units, far below anything observable."""
HELD_ROTATION_NOISE = gtsam.noiseModel.Isotropic.Sigma(3, 1e-4)
"""Rotations held by `hold_rotations` (radians, 0.006 degrees): they stay, positions move freely."""

ProgressFn = Callable[[int, int, float], None]
"""progress(iteration, max_iterations, cost) after every Levenberg-Marquardt iteration."""


@dataclass
class BAResult:
    """Outcome of one bundle adjustment. Costs are gtsam's (0.5 sum of robust whitened squares)."""

    map: Map
    initial_cost: float
    final_cost: float
    iterations: int
    converged: bool
    time_s: float
    setup_s: float
    linearize_s: float
    """Mean seconds of one linearisation of the whole graph during the optimisation (once per iteration)."""
    solve_s: float
    """Mean seconds of one damped sparse solve during the optimisation (once per damping trial)."""
    initial_rms_px: dict[str, float]
    final_rms_px: dict[str, float]
    n_variables: dict[str, int]
    n_observations: dict[str, int]
    line_params: dict[str, int]
    """Optimised line parameters: anchored n, the paper's count (2n with BAConfig.anchor_offset) + 2 per
    optimised axis, temporary-VP 3n (4n with BAConfig.tvp_offset), orthonormal 4n."""
    dropped: dict[str, int] = field(default_factory=dict)
    lm_linearize_s: float = 0.0
    """Total seconds in linearisation during the optimisation."""
    lm_solve_s: float = 0.0
    """Total seconds in damped solves during the optimisation."""
    lm_error_s: float = 0.0
    """Total seconds in retract + cost evaluation of trial steps."""
    n_solves: int = 0
    cost_history: list[float] = field(default_factory=list)
    iteration_s: list[float] = field(default_factory=list)
    iteration_cpu_s: list[float] = field(default_factory=list)
    """CPU seconds of this process per iteration (robust to other jobs sharing the machine)."""

    def summary(self) -> dict[str, Any]:
        """Plain-JSON statistics (everything except the map)."""
        return {k: v for k, v in self.__dict__.items() if k != "map"}


def global_ba(
    m: Map, config: BAConfig | None = None, progress: ProgressFn | None = None, hold_rotations: bool = False
) -> BAResult:
    """Adjust every keyframe, point, line and axis of `m`; the monocular gauge is fixed by holding the first
    keyframe and the distance from it to the next keyframe that moved. `hold_rotations`: the keyframe
    rotations stay as they are (tight priors); positions, points and lines move (global positioning
    from known rotations)."""
    config = config or BAConfig()
    if config.huber_k_start is not None:
        return _graduated(m, config, progress, lambda mm, cfg, pr: global_ba(mm, cfg, pr, hold_rotations))
    t0 = time.perf_counter()
    problem = build_problem(m, config)
    return _run(m, problem, config, progress, t0, hold_rotations)


def local_ba(
    m: Map, keyframe_ids: np.ndarray, config: BAConfig | None = None, progress: ProgressFn | None = None
) -> BAResult:
    """Adjust the keyframes `keyframe_ids` and every point and line they see; other keyframes seeing
    those landmarks enter as fixed poses (they also fix the gauge)."""
    config = config or BAConfig()
    if config.huber_k_start is not None:
        return _graduated(m, config, progress, lambda mm, cfg, pr: local_ba(mm, keyframe_ids, cfg, pr))
    t0 = time.perf_counter()
    ids = np.asarray(keyframe_ids, dtype=np.int64)
    known = np.isin(ids, m.keyframes.ids)
    if not known.all():
        raise GeometryError(f"local BA: unknown keyframe ids {ids[~known][:5].tolist()}")
    rows = np.flatnonzero(np.isin(m.keyframes.ids, ids))
    problem = build_problem(m, config, window=rows)
    return _run(m, problem, config, progress, t0)


def _graduated(
    m: Map, config: BAConfig, progress: ProgressFn | None, adjust: Callable[[Map, BAConfig, Any], BAResult]
) -> BAResult:
    """BAConfig.huber_k_start: adjust with the wide Huber threshold, then again from that map with huber_k.
    The second stage is a fresh problem (observations re-checked against the new geometry, anchors and the
    axis prior taken from the first stage's result); keeping one problem and only tightening the loss was
    worse (benchmarks/RESULTS.md)."""
    wide = adjust(
        m,
        replace(config, huber_k=config.huber_k_start, huber_k_start=None),
        progress,
    )
    tight_cfg = replace(config, huber_k_start=None)
    res = adjust(wide.map, tight_cfg, progress)
    pb = build_problem(m, tight_cfg)  # the tight loss's cost at the true start, for comparable statistics
    g0 = _build_graph(m, pb, tight_cfg)
    start_cost = g0.error(g0.values)
    res.initial_cost = start_cost
    res.initial_rms_px = wide.initial_rms_px
    res.cost_history = [start_cost, *res.cost_history]
    res.iterations += wide.iterations
    res.time_s += wide.time_s
    res.setup_s += wide.setup_s
    res.iteration_s = wide.iteration_s + res.iteration_s
    res.iteration_cpu_s = wide.iteration_cpu_s + res.iteration_cpu_s
    res.lm_linearize_s += wide.lm_linearize_s
    res.lm_solve_s += wide.lm_solve_s
    res.lm_error_s += wide.lm_error_s
    res.n_solves += wide.n_solves
    res.dropped = {**{f"wide_stage_{k}": v for k, v in wide.dropped.items()}, **res.dropped}
    return res


# ---- graph -------------------------------------------------------------------------------------


@dataclass
class _Graph:
    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    pose_var: np.ndarray
    batches: dict[str, LineBatch]
    base: gtsam.NonlinearFactorGraph
    """The graph without the line factors (gtsam evaluates these; the batches evaluate the lines)."""

    def error(self, values: gtsam.Values) -> float:
        """gtsam's cost of the whole graph, the line factors summed in one vectorised pass per batch
        instead of one Python callback per factor."""
        return float(self.base.error(values)) + sum(b.cost(values) for b in self.batches.values())


def _build_graph(m: Map, pb: Problem, config: BAConfig, hold_rotations: bool = False) -> _Graph:
    T = m.keyframes.T_wc
    K = m.camera.K
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    pose_var = pb.kf_in & ~pb.kf_fixed
    if pb.gauge is not None:
        pose_var[pb.gauge[0]] = False
    for i in np.flatnonzero(pb.kf_in):
        values.insert(X(i), gtsam.Pose3(T[i]))
    for i in np.flatnonzero(pb.kf_in & ~pose_var):
        # a tight prior, not NonlinearEqualityPose3: gtsam eliminates hard constraints by QR, many times
        # slower for the same solution (benchmarks/RESULTS.md)
        graph.add(gtsam.PriorFactorPose3(X(i), gtsam.Pose3(T[i]), FIXED_POSE_NOISE))
    if hold_rotations:
        for i in np.flatnonzero(pose_var):
            graph.add(gtsam.PoseRotationPrior3D(X(i), gtsam.Pose3(T[i]), HELD_ROTATION_NOISE))
    if pb.gauge is not None and config.optimize_poses:
        a, b = pb.gauge
        dist = float(np.linalg.norm(T[b, :3, 3] - T[a, :3, 3]))
        graph.add(scale_prior_factor(a, T[a], b, dist, config.scale_prior_sigma * dist))

    # points: gtsam's own projection factors with a Huber loss
    cal = gtsam.Cal3_S2(m.camera.fx, m.camera.fy, 0.0, m.camera.cx, m.camera.cy)
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(config.huber_k),
        gtsam.noiseModel.Isotropic.Sigma(2, config.point_sigma_px),
    )
    xyz = m.points.xyz
    for key, x in zip(symbols("p", np.arange(len(pb.pt_rows))), xyz[pb.pt_rows], strict=True):
        values.insert(key, x)
    factor, add = gtsam.GenericProjectionFactorCal3_S2, graph.add
    x_keys, p_keys = symbols("x", pb.pt_obs_kf), symbols("p", pb.pt_obs_pt)
    for uv, x_key, p_key in zip(pb.pt_obs_uv, x_keys, p_keys, strict=True):
        add(factor(uv, noise, x_key, p_key, cal))

    # axes
    A = len(m.axes)
    for a in range(A):
        if pb.axis_var[a]:
            values.insert(AX(a), gtsam.Unit3(m.axes.directions[a]))
            graph.add(axis_prior_factor(a, m.axes.directions[a], np.radians(config.axis_prior_sigma_deg)))

    base = gtsam.NonlinearFactorGraph()
    base.push_back(graph)
    batches = {}
    for kind, grp in pb.lines.items():
        if kind == KIND_ANCHORED and config.structural_lines == KIND_FIXDIR:
            kind = KIND_FIXDIR
        for i in range(len(grp)):
            if kind == KIND_FIXDIR:
                values.insert(F(i), np.zeros(2))
            elif kind == KIND_ORTHO:
                Urot, phi = geo.ortho_from_plucker(
                    geo.plucker_to_local(grp.L0[i], grp.frame_origin[i], grp.frame_scale[i])
                )
                values.insert(U(i), gtsam.Rot3(Urot))
                values.insert(W(i), np.array([phi]))
            else:
                if uses_offset(config, kind):
                    values.insert(RS(kind, i), np.array([grp.inv_depth[i], 0.0]))
                else:
                    values.insert(R(kind, i), np.array([grp.inv_depth[i]]))
                if kind == KIND_TVP:
                    values.insert(D(i), gtsam.Unit3(grp.L0[i, 3:]))
        if len(grp):
            batch = LineBatch(
                kind,
                grp,
                K,
                T,
                pose_var,
                m.axes.directions,
                pb.axis_var,
                config.line_sigma_px,
                config.huber_k,
                uses_offset(config, kind),
            )
            for f in batch.make_factors():
                graph.add(f)
            batches[kind] = batch
    return _Graph(graph, values, pose_var, batches, base)


# ---- state in numpy --------------------------------------------------------------------------


@dataclass
class _State:
    T: np.ndarray
    xyz: np.ndarray  # (P', 3)
    axes: np.ndarray  # (A, 3)
    lines: dict[str, np.ndarray]  # kind -> (n, 6) world Pluecker of the line's main axis
    inv_depth: dict[str, np.ndarray]  # kind -> (n,) inverse depths (anchored and temporary-VP)


def _state(
    m: Map, pb: Problem, values: gtsam.Values, batches: dict | None = None, config: BAConfig | None = None
) -> _State:
    config = config or BAConfig()
    T = m.keyframes.T_wc.copy()
    held = pb.kf_fixed.copy()  # held poses keep their exact input values (the prior lets them drift 1e-14)
    if pb.gauge is not None:
        held[pb.gauge[0]] = True
    for i in np.flatnonzero(pb.kf_in & ~held):
        T[i] = values.atPose3(X(i)).matrix()
    xyz = np.array([values.atPoint3(P(j)) for j in range(len(pb.pt_rows))]).reshape(-1, 3)
    axes = m.axes.directions.copy()
    for a in np.flatnonzero(pb.axis_var):
        v = values.atUnit3(AX(a)).point3()
        axes[a] = v if v @ m.axes.directions[a] >= 0 else -v
    lines, inv = {}, {}
    for kind, grp in pb.lines.items():
        n = len(grp)
        if batches and KIND_FIXDIR in batches and kind == KIND_ANCHORED:
            ab = np.array([values.atVector(F(i)) for i in range(n)]).reshape(n, 2)
            L, _ = batches[KIND_FIXDIR].lines_from(ab, np.arange(n))
            inv[kind], _ = geo.ray_inverse_depth(grp.bearing, T[grp.ref_kf], L)
        elif kind == KIND_ORTHO:
            Us = np.array([values.atRot3(U(i)).matrix() for i in range(n)]).reshape(n, 3, 3)
            phi = np.array([values.atVector(W(i))[0] for i in range(n)])
            L = geo.plucker_from_ortho(Us, phi, geo.local_to_world(grp.frame_origin, grp.frame_scale))
        else:
            if kind == KIND_TVP:
                v = np.array([values.atUnit3(D(i)).point3() for i in range(n)]).reshape(-1, 3)
            else:
                v = axes[np.argmax(grp.weights, axis=1)] if n else np.zeros((0, 3))
            if config is not None and uses_offset(config, kind):
                rs = np.array([values.atVector(RS(kind, i)) for i in range(n)]).reshape(n, 2)
                r = rs[:, 0]
                L = (
                    geo.anchored_offset_plucker(v, rs, grp.bearing, grp.offset_dir, T[grp.ref_kf])
                    if n
                    else []
                )
            else:
                r = np.array([values.atVector(R(kind, i))[0] for i in range(n)])
                L = geo.anchored_plucker(v, r, grp.bearing, T[grp.ref_kf]) if n else []
            # what the Map stores: 1/z of the point of the observed-midpoint ray closest to the line (the
            # anchor's own 1/z where that ray does not meet the line in front)
            r_obs, _ = geo.ray_inverse_depth(grp.obs_bearing, T[grp.ref_kf], np.asarray(L).reshape(-1, 6))
            inv[kind] = np.where(np.isfinite(r_obs) & (r_obs > 0), r_obs, r)
        lines[kind] = geo.normalize_plucker(np.asarray(L).reshape(-1, 6)) if n else np.zeros((0, 6))
    return _State(T, xyz, axes, lines, inv)


def _rms(m: Map, pb: Problem, st: _State) -> dict[str, float]:
    out = {}
    if len(pb.pt_obs_pt):
        uv, _ = geo.project_points(m.camera.K, st.T[pb.pt_obs_kf], st.xyz[pb.pt_obs_pt])
        out["points_px"] = float(np.sqrt(np.mean(np.sum((uv - pb.pt_obs_uv) ** 2, axis=1))))
    errs = []
    for kind, grp in pb.lines.items():
        if len(grp.obs_kf):
            owner = np.repeat(np.arange(len(grp)), np.diff(grp.obs_start))
            Lc = geo.plucker_to_camera(st.lines[kind][owner], st.T[grp.obs_kf])
            e = geo.endpoint_errors(m.camera.K, Lc, grp.obs_xy)
            out[f"lines_{kind}_px"] = float(np.sqrt(np.mean(e**2)))
            errs.append(e.ravel())
    if errs:
        out["lines_px"] = float(np.sqrt(np.mean(np.concatenate(errs) ** 2)))
    return out


# ---- run -----------------------------------------------------------------------------------------


def _lm_stage(
    optimizer: LevenbergMarquardt,
    config: BAConfig,
    progress: ProgressFn | None,
    history: list[float],
    iteration_s: list[float],
    iteration_cpu_s: list[float],
) -> bool:
    """Levenberg-Marquardt iterations until convergence or max_iterations; True if converged."""
    cost = optimizer.error
    for it in range(config.max_iterations):
        ti, ci = time.perf_counter(), time.process_time()
        try:
            accepted = optimizer.iterate()
        except RuntimeError as exc:
            raise OptimizationError(f"BA: gtsam failed in iteration {it + 1}: {exc}") from exc
        iteration_s.append(time.perf_counter() - ti)
        iteration_cpu_s.append(time.process_time() - ci)
        new = optimizer.error
        if not np.isfinite(new):
            raise OptimizationError(f"BA: the cost became {new} in iteration {it + 1}")
        history.append(new)
        if progress is not None:
            progress(it + 1, config.max_iterations, new)
        decrease = cost - new
        cost = new
        if decrease <= config.absolute_error_tol or decrease <= config.relative_error_tol * max(
            history[-2], 1e-300
        ):
            return True
        if not accepted:
            return True  # no decrease found even with heavy damping: a minimum to solver precision
    return False


def _multifrontal(n_keyframes: int, config: BAConfig) -> bool:
    """Whether to eliminate multifrontally: a large map, whose dense camera front still fits the budget."""
    front_mib = (6 * n_keyframes) ** 2 * 8 / 2**20
    return (
        n_keyframes >= config.multifrontal_from_keyframes and front_mib <= config.multifrontal_max_front_mib
    )


def _run(
    m: Map,
    pb: Problem,
    config: BAConfig,
    progress: ProgressFn | None,
    t0: float,
    hold_rotations: bool = False,
) -> BAResult:
    g = _build_graph(m, pb, config, hold_rotations)
    setup_s = time.perf_counter() - t0
    init_state = _state(m, pb, g.values, g.batches, config)
    initial_rms = _rms(m, pb, init_state)
    initial_cost = g.error(g.values)
    if not np.isfinite(initial_cost):
        raise OptimizationError("BA: the initial cost is not finite; check the map for degenerate geometry")
    history = [initial_cost]
    iteration_s: list[float] = []
    iteration_cpu_s: list[float] = []
    optimizer = LevenbergMarquardt(
        g.graph,
        g.values,
        config.lambda_initial,
        error=g.error,
        relative_tol=config.relative_error_tol,
        halve_rejected=config.halve_rejected_steps,
        multifrontal=_multifrontal(int(pb.kf_in.sum()), config),
    )
    converged = _lm_stage(optimizer, config, progress, history, iteration_s, iteration_cpu_s)
    cost = optimizer.error
    time_s = time.perf_counter() - t0
    values = optimizer.values
    linearize_s = optimizer.linearize_s / max(optimizer.n_linearize, 1)
    solve_s = optimizer.solve_s / optimizer.n_solve if optimizer.n_solve else float("nan")
    st = _state(m, pb, values, g.batches, config)
    final_rms = _rms(m, pb, st)
    out = _write_back(m, pb, st, config)
    _check_finite(out, pb)
    n_lines = {k: len(v) for k, v in pb.lines.items()}
    n_axes_var = int(pb.axis_var.sum())
    result = BAResult(
        map=out,
        initial_cost=initial_cost,
        final_cost=cost,
        iterations=len(iteration_s),
        converged=converged,
        time_s=time_s,
        setup_s=setup_s,
        linearize_s=linearize_s,
        solve_s=solve_s,
        initial_rms_px=initial_rms,
        final_rms_px=final_rms,
        n_variables={
            "poses": int(g.pose_var.sum()),
            "points": len(pb.pt_rows),
            "axes": n_axes_var,
            **{f"lines_{k}": v for k, v in n_lines.items()},
        },
        n_observations={
            "points": len(pb.pt_obs_pt),
            **{f"lines_{k}": len(v.obs_kf) for k, v in pb.lines.items()},
        },
        line_params={
            KIND_ANCHORED: (
                2 * n_lines[KIND_ANCHORED]
                if config.structural_lines == KIND_FIXDIR
                else (2 if uses_offset(config, KIND_ANCHORED) else 1) * n_lines[KIND_ANCHORED]
                + 2 * n_axes_var
            ),
            KIND_TVP: (4 if uses_offset(config, KIND_TVP) else 3) * n_lines[KIND_TVP],
            KIND_ORTHO: 4 * n_lines[KIND_ORTHO],
        },
        dropped=dict(pb.dropped),
        cost_history=history,
        iteration_s=iteration_s,
        iteration_cpu_s=iteration_cpu_s,
        lm_linearize_s=optimizer.linearize_s,
        lm_solve_s=optimizer.solve_s,
        lm_error_s=optimizer.error_s,
        n_solves=optimizer.n_solve,
    )
    out.metadata.setdefault("timings", {})["ba_s"] = time_s
    log.debug(
        "BA: cost %.6g -> %.6g in %d iterations (%.2f s); rms %s",
        initial_cost,
        cost,
        result.iterations,
        time_s,
        {k: round(v, 3) for k, v in final_rms.items()},
    )
    return result


def _write_back(m: Map, pb: Problem, st: _State, config: BAConfig | None = None) -> Map:
    config = config or BAConfig()
    out = copy.deepcopy(m)
    K = m.camera.K
    out.keyframes.T_wc[pb.kf_in] = st.T[pb.kf_in]
    out.points.xyz[pb.pt_rows] = st.xyz
    out.axes.directions[:] = st.axes
    centres = st.T[pb.kf_in, :3, 3]
    scale = max(float(np.ptp(centres, axis=0).max()) if len(centres) else 0.0, 1.0)
    for kind, grp in pb.lines.items():
        if not len(grp):
            continue
        L = st.lines[kind].copy()
        # a line driven to infinity (orthonormal phi -> 0) or to NaN keeps its input geometry, with a reason
        bad = ~np.isfinite(L).all(axis=1) | (np.linalg.norm(np.nan_to_num(L[:, :3]), axis=1) > 1e4 * scale)
        if bad.any():
            log.warning("BA: %d %s lines went to infinity; kept as they were", int(bad.sum()), kind)
            pb.dropped["lines_degenerate_after_ba"] = pb.dropped.get("lines_degenerate_after_ba", 0) + int(
                bad.sum()
            )
            e0 = m.lines.endpoints_w[grp.rows[bad]]
            L[bad] = geo.normalize_plucker(geo.plucker_from_endpoints(e0[:, 0], e0[:, 1]))
        owner = np.repeat(np.arange(len(grp)), np.diff(grp.obs_start))
        flat = np.zeros(len(grp), bool)
        need = float(min_parallax_deg(config, kind == KIND_ORTHO))
        if need > 0:
            par = line_parallax_deg(L, owner, st.T[grp.obs_kf, :3, 3], len(grp))
            flat = par < need
            flat &= ~bad
            if flat.any():
                log.info(
                    "BA: %d %s lines span less than %.2f deg of parallax after BA (depth unobservable); "
                    "kept as they were",
                    int(flat.sum()),
                    kind,
                    need,
                )
                pb.dropped["lines_low_parallax_after_ba"] = pb.dropped.get(
                    "lines_low_parallax_after_ba", 0
                ) + int(flat.sum())
                e0 = m.lines.endpoints_w[grp.rows[flat]]
                L[flat] = geo.normalize_plucker(geo.plucker_from_endpoints(e0[:, 0], e0[:, 1]))
        ends, ok = geo.clip_to_observations(L, owner, st.T[grp.obs_kf], K, grp.obs_xy, len(grp))
        # a single usable endpoint ray gives a zero-length segment, which has no direction: old extent too
        ok &= np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1) > 1e-9 * scale
        if not ok.all():  # keep the old extent, projected onto the new line
            P0, d = geo.line_point_dir(L[~ok])
            old = m.lines.endpoints_w[grp.rows[~ok]]
            s = np.einsum("nkj,nj->nk", old - P0[:, None], d)
            ends[~ok] = P0[:, None] + s[..., None] * d[:, None]
        out.lines.endpoints_w[grp.rows] = ends
        if kind != KIND_ORTHO:
            inv = st.inv_depth[kind].copy()
            kept = bad | flat  # their stored inverse depth must describe the kept line
            if kept.any():
                r, _ = geo.ray_inverse_depth(grp.obs_bearing[kept], st.T[grp.ref_kf[kept]], L[kept])
                old_r = m.lines.inverse_depth[grp.rows[kept]]
                fallback = np.where(np.isfinite(old_r), old_r, inv[kept])
                inv[kept] = np.where(np.isfinite(r) & (r > 0), r, fallback)
            out.lines.ref_keyframe_id[grp.rows] = m.keyframes.ids[grp.ref_kf]
            out.lines.inverse_depth[grp.rows] = inv
    return out


def _check_finite(out: Map, pb: Problem) -> None:
    bad = []
    if not np.isfinite(out.keyframes.T_wc).all():
        bad.append("keyframe poses")
    if not np.isfinite(out.points.xyz).all():
        bad.append("points")
    if not np.isfinite(out.lines.endpoints_w).all():
        bad.append("line endpoints")
    if not np.isfinite(out.axes.directions).all():
        bad.append("axes")
    for grp in pb.lines.values():
        if grp is not pb.lines[KIND_ORTHO] and not np.isfinite(out.lines.inverse_depth[grp.rows]).all():
            bad.append("inverse depths")
    if bad:
        raise OptimizationError(f"BA produced non-finite {', '.join(bad)}; the input geometry is degenerate")


__all__ = ["BAConfig", "BAResult", "LineGroup", "global_ba", "local_ba"]
