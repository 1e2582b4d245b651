"""Where line recall and precision are lost, stage by stage, on synthetic recordings with ground truth.

Every ground-truth segment is sampled along its length (each sample stands for its share of length)
and each sample is followed through the stages:

  visible       in front, inside the image and not behind a scene quad in >= --min-frames GT frames
                (papl_mapper.eval.visibility, as eval's line_recall_visible)
  detected      a frontend segment of that frame lies on the sample's projected GT line (angle and
                distance gates) and its extent, carried back onto the 3D line, spans the sample
  tracked       ... by a segment whose track has >= min_views registered observations whose
                back-projection planes span >= min_plane_angle_deg (what triangulation needs)
  triangulated  ... whose track got a 3D line from `triangulate_lines`
  in map        ... whose track's line survived culling, BA and stray-line removal
  3D (tau)      within tau of a final map line after the Sim(3) (the metric's recall)
  line (tau)    within tau of the infinite 3D line of a final map line whose track detected it
                (placement right; "in map" minus this is misplacement, this minus 3D is extent)

Precision: every final line is called structural when most of its observations lie on a projected
GT segment (2D gates as above), texture otherwise; the table gives each class's share of the map's
line length and its precision. A counterfactual also triangulates the same tracks with GT poses.
The same stages are also given as shares of the visible GT length: where the visible length is lost.

    .venv/bin/python benchmarks/line_diagnosis.py \
        /tmp/papl_accuracy/corridor_noise0_10s=/tmp/s10/corridor0.npz \
        /tmp/papl_accuracy/atlanta_noise0_10s=/tmp/s10/atlanta0.npz
Writes benchmarks/results/line_diagnosis.json.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
from machine import machine_info

import papl_mapper.mapping.adjust as adjust_mod
import papl_mapper.mapping.structure as structure_mod
import papl_mapper.pipelines.run as run_mod
from papl_mapper.config import load_config
from papl_mapper.eval import evaluate
from papl_mapper.eval.evaluate import load_ground_truth
from papl_mapper.eval.lines import nearest_segment_distance
from papl_mapper.eval.visibility import DEFAULT_MIN_FRAMES, NEAR, scene_occluders, segment_visibility
from papl_mapper.geometry.similarity import umeyama
from papl_mapper.geometry.triangulation import observation_planes
from papl_mapper.mapping.assemble import vp_directions_w
from papl_mapper.mapping.lines import _plane_angle_deg
from papl_mapper.pipelines.config import RunConfig
from papl_mapper.tracks import Tracks
from papl_mapper.trajectory_io import write_tum

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "line_diagnosis.json"
REL_TAUS = (0.005, 0.01, 0.02)
MAX_ANGLE_DEG = 2.0  # detection vs projected GT segment
MAX_DIST_PX = 2.0  # mean endpoint distance of a detection to the projected GT line


def _clip_segments(K, T_cw, ends):
    """Projected GT segments clipped to z > NEAR: (S, 4) pixels and (S, 2) 3D params of the ends."""
    a = ends[:, 0] @ T_cw[:3, :3].T + T_cw[:3, 3]
    b = ends[:, 1] @ T_cw[:3, :3].T + T_cw[:3, 3]
    za, zb = a[:, 2], b[:, 2]
    ok = (za > NEAR) | (zb > NEAR)
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = (NEAR - za) / (zb - za)
    t0 = np.where(za > NEAR, 0.0, tc)
    t1 = np.where(zb > NEAR, 1.0, tc)
    pa = a + t0[:, None] * (b - a)
    pb = a + t1[:, None] * (b - a)
    f = np.array([K[0, 0], K[1, 1]])
    with np.errstate(divide="ignore", invalid="ignore"):
        ua = pa[:, :2] / pa[:, 2:3] * f + K[:2, 2]
        ub = pb[:, :2] / pb[:, 2:3] * f + K[:2, 2]
    return np.concatenate([ua, ub], axis=1), np.stack([t0, t1], 1), ok


def _ray_param(K, T_wc, uv, p0, d):
    """3D parameter along the line p0 + t d of the point closest to each pixel's ray."""
    r = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(K).T @ T_wc[:3, :3].T
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    c = T_wc[:3, 3]
    w0 = p0 - c
    b = r @ d
    den = np.maximum(d @ d - b**2, 1e-12)
    return (b * (r @ w0) - w0 @ d) / den


def match_detections(K, T_wc, gt_ends, det_xy):
    """(det index, GT index) pairs where a detection lies on a projected GT segment, and the 3D params."""
    T_cw = np.linalg.inv(T_wc)
    proj, _, ok = _clip_segments(K, T_cw, gt_ends)
    g = np.flatnonzero(ok & np.isfinite(proj).all(1))
    if len(g) == 0 or len(det_xy) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros((0, 2))
    pa, pb = proj[g, :2], proj[g, 2:]
    dg = pb - pa
    Lg = np.linalg.norm(dg, axis=1)
    keep = Lg > 1.0
    g, pa, dg, Lg = g[keep], pa[keep], dg[keep], Lg[keep]
    ug = dg / Lg[:, None]
    ng = np.stack([-ug[:, 1], ug[:, 0]], 1)
    da = det_xy[:, 2:] - det_xy[:, :2]
    Ld = np.linalg.norm(da, axis=1)
    ud = da / np.maximum(Ld, 1e-9)[:, None]
    cosang = np.abs(ud @ ug.T)  # (D, G)
    d1 = np.abs(np.einsum("dgi,gi->dg", det_xy[:, None, :2] - pa[None], ng))
    d2 = np.abs(np.einsum("dgi,gi->dg", det_xy[:, None, 2:] - pa[None], ng))
    s1 = np.einsum("dgi,gi->dg", det_xy[:, None, :2] - pa[None], ug) / Lg
    s2 = np.einsum("dgi,gi->dg", det_xy[:, None, 2:] - pa[None], ug) / Lg
    lo, hi = np.minimum(s1, s2), np.maximum(s1, s2)
    overlap = (np.minimum(hi, 1) - np.maximum(lo, 0)) * Lg
    good = (
        (cosang > np.cos(np.radians(MAX_ANGLE_DEG)))
        & (0.5 * (d1 + d2) < MAX_DIST_PX)
        & (overlap > 0.5 * np.minimum(Ld[:, None], Lg[None]))
    )
    di, gj = np.nonzero(good)
    gi = g[gj]
    p0 = gt_ends[gi, 0]
    d = gt_ends[gi, 1] - gt_ends[gi, 0]
    t = np.empty((len(di), 2))
    for k in range(len(di)):
        t[k] = _ray_param(K, T_wc, det_xy[di[k]].reshape(2, 2), p0[k], d[k])
    return di, gi, np.sort(t, axis=1)


def diagnose(
    folder: Path,
    tracks_path: Path,
    overrides: list[str],
    dump: Path | None = None,
    min_frames: int = DEFAULT_MIN_FRAMES,
) -> dict:
    """Run the mapping with probes and follow every GT sample through the stages."""
    tracks = Tracks.load(tracks_path)
    gt = load_ground_truth(folder)
    gt_ends = gt.segments.endpoints[gt.segments.lengths() > 0]
    diag = float(np.ptp(gt_ends.reshape(-1, 3), axis=0).__pow__(2).sum() ** 0.5)
    taus = np.array(REL_TAUS) * diag
    K = tracks.camera.K
    # GT pose of each tracks frame
    ti = np.searchsorted(gt.trajectory.timestamps, tracks.timestamp)
    ti = np.clip(ti, 0, len(gt.trajectory) - 1)
    prev = np.clip(ti - 1, 0, None)
    closer = np.abs(gt.trajectory.timestamps[prev] - tracks.timestamp) < np.abs(
        gt.trajectory.timestamps[ti] - tracks.timestamp
    )
    ti = np.where(closer, prev, ti)
    T_gt = gt.trajectory.T_wc[ti]

    # --- run the mapping with probes on the stages it calls
    cfg = load_config(RunConfig, None, overrides)
    probe: dict = {"cull": []}
    orig_tri, orig_cull, orig_stray, orig_fp = (
        structure_mod.triangulate_lines,
        adjust_mod.cull_observations,
        run_mod.drop_stray_lines,
        run_mod.frame_poses,
    )

    def tri(track, T_obs, xy, vp_w, K_, c, seed=0):
        est = orig_tri(track, T_obs, xy, vp_w, K_, c, seed)
        probe["tri_in"] = (track.copy(), T_obs.copy(), xy.copy(), vp_w.copy())
        probe["est"] = est
        return est

    def cull(m, *a, **kw):
        before = set(m.lines.ids.tolist())
        out = orig_cull(m, *a, **kw)
        if before:
            probe["cull"].append(before - set(m.lines.ids.tolist()))
        return out

    def stray(m, *a, **kw):
        before = set(m.lines.ids.tolist())
        n = orig_stray(m, *a, **kw)
        probe["stray"] = before - set(m.lines.ids.tolist())
        return n

    def fp(tr, m, c):
        out = orig_fp(tr, m, c)
        probe.setdefault("frame_poses", out)  # the first call: the poses lines are triangulated with
        return out

    structure_mod.triangulate_lines, adjust_mod.cull_observations = tri, cull
    run_mod.drop_stray_lines, run_mod.frame_poses = stray, fp
    t0 = time.perf_counter()
    try:
        m, _ = run_mod.map_tracks(tracks, cfg)
        traj = run_mod.frame_trajectory(tracks, m, cfg)
    finally:
        structure_mod.triangulate_lines, adjust_mod.cull_observations = orig_tri, orig_cull
        run_mod.drop_stray_lines, run_mod.frame_poses = orig_stray, orig_fp
    t_map = time.perf_counter() - t0
    tum = Path(f"/tmp/line_diag_{folder.name}.tum")
    write_tum(tum, traj)
    ev = evaluate(folder, m, tum)
    S = ev.sim3
    est_final = m.lines.endpoints_w @ S[:3, :3].T + S[:3, 3]
    final_ids = m.lines.ids

    # --- the triangulation input: which tracks were tracked well enough, which triangulated
    tr_track, tr_T, tr_xy, tr_vp = probe["tri_in"]
    est = probe["est"]
    lcfg = cfg.lines
    order = np.argsort(tr_track, kind="stable")
    starts = np.flatnonzero(np.r_[True, tr_track[order][1:] != tr_track[order][:-1]])
    ends_ = np.r_[starts[1:], len(order)]
    planes = observation_planes(tr_T[order], K, tr_xy[order])
    tracked = set()
    why_not: dict[int, str] = {}
    for s, e in zip(starts, ends_, strict=True):
        tid = int(tr_track[order][s])
        if e - s < lcfg.min_views:
            why_not[tid] = "too few views"
        elif _plane_angle_deg(planes[s:e, :3]) < lcfg.min_plane_angle_deg:
            why_not[tid] = "too little parallax"
        else:
            tracked.add(tid)
    triangulated = set(est.track.tolist())
    in_map = set(final_ids.tolist())

    # --- GT samples: the pieces of the visibility clip (eval's), seen in >= min_frames GT frames
    spacing = 0.5 * taus[0]
    quads, occ_src = scene_occluders(gt.folder, gt_ends)
    if quads is None:
        print(f"warning: {occ_src}", file=sys.stderr)
    vis = segment_visibility(gt_ends, tracks.camera, T_gt, spacing, quads)
    owner = vis.owner
    frac = 0.5 * (vis.t0 + vis.t1)
    pieces = np.bincount(owner, minlength=len(gt_ends))
    X = gt_ends[owner, 0] + frac[:, None] * (gt_ends[owner, 1] - gt_ends[owner, 0])
    w = vis.piece_lengths()
    seg_start = np.cumsum(pieces) - pieces
    visible = vis.visible(min_frames)

    # per-stage 2D coverage, and the (sample, final line) pairs for the placement test
    stage_names = ("detected", "tracked", "triangulated", "in map")
    covered = {n: np.zeros(len(X), bool) for n in stage_names}
    line_pairs: set[tuple[int, int]] = set()  # (GT segment, final line row)
    final_row = {int(t): i for i, t in enumerate(final_ids)}
    gt_tracks: set[int] = set()  # tracks with a detection on a GT segment
    obs_structural = np.zeros(len(tracks.line_track), bool)
    for f in range(len(tracks)):
        rows = np.flatnonzero(tracks.line_frame == f)
        if len(rows) == 0:
            continue
        di, gi, t = match_detections(K, T_gt[f], gt_ends, tracks.line_xy[rows])
        if len(di) == 0:
            continue
        obs_structural[rows[np.unique(di)]] = True
        for d_, g_, (t0_, t1_) in zip(di, gi, t, strict=True):
            tid = int(tracks.line_track[rows[d_]])
            gt_tracks.add(tid)
            a = seg_start[g_]
            fr = frac[a : a + pieces[g_]]
            hit = np.flatnonzero((fr >= t0_ - 1e-3) & (fr <= t1_ + 1e-3)) + a
            flags = (True, tid in tracked, tid in triangulated, tid in in_map)
            for n, on in zip(stage_names, flags, strict=True):
                if on:
                    covered[n][hit] = True
            if tid in final_row:
                line_pairs.add((int(g_), final_row[tid]))

    # 3D: distance of samples to the final lines (aligned), and to their track's infinite line
    d3 = nearest_segment_distance(X, est_final, float(taus.max()), levels=taus)
    on_line = np.zeros((len(taus), len(X)), bool)
    for g_, r in line_pairs:
        a = seg_start[g_]
        sl = slice(a, a + pieces[g_])
        p0, p1 = est_final[r]
        u = (p1 - p0) / max(np.linalg.norm(p1 - p0), 1e-12)
        v = X[sl] - p0
        dist = np.linalg.norm(v - np.outer(v @ u, u), axis=1)
        on_line[:, sl] |= (dist[None] <= taus[:, None]) & covered["in map"][sl][None]
    # the same with the lines triangulated before BA (aligned by their own frames' poses)
    fposes = probe.get("frame_poses") or {}
    frames = np.array(sorted(fposes), int)
    pre = {}
    if len(frames) >= 3:
        sim = umeyama(
            np.array([fposes[int(f)][:3, 3] for f in frames]),
            T_gt[frames][:, :3, 3],
            R_x=np.array([fposes[int(f)][:3, :3] for f in frames]),
            R_y=T_gt[frames][:, :3, :3],
        )
        est_pre = sim.apply(est.endpoints_w)
        dpre = nearest_segment_distance(X, est_pre, float(taus.max()), levels=taus)
        pre = {
            f"{100 * r:g}%": float(w[dpre <= t].sum() / w.sum()) for r, t in zip(REL_TAUS, taus, strict=True)
        }
    # counterfactual: triangulate the same observations with GT poses
    frame_of_obs = tracks.line_frame[np.isin(tracks.line_frame, frames)] if len(frames) else []
    gt_pose_recall = {}
    if len(frame_of_obs) == len(tr_track):
        T_obs_gt = T_gt[frame_of_obs]
        labels = tracks.line_vp[np.isin(tracks.line_frame, frames)]
        vp_gt = vp_directions_w(tracks, frame_of_obs, labels, T_obs_gt)
        est_gt = orig_tri(tr_track, T_obs_gt, tr_xy, vp_gt, K, lcfg)
        dg = nearest_segment_distance(X, est_gt.endpoints_w, float(taus.max()), levels=taus)
        pg, _, _ = _prec(est_gt.endpoints_w, gt_ends, taus, spacing)
        gt_pose_recall = {
            f"{100 * r:g}%": {"recall": float(w[dg <= t].sum() / w.sum()), "precision": float(pv)}
            for r, t, pv in zip(REL_TAUS, taus, pg, strict=True)
        }

    total = float(w.sum())
    table = {"visible": float(w[visible].sum() / total)}
    for n in stage_names:
        table[n] = float(w[covered[n]].sum() / total)
    for r, row in zip(REL_TAUS, on_line, strict=True):
        table[f"line placed ({100 * r:g}%)"] = float(w[row].sum() / total)
    for r, t in zip(REL_TAUS, taus, strict=True):
        table[f"3D recall ({100 * r:g}%)"] = float(w[d3 <= t].sum() / total)
    for r, t in zip(REL_TAUS, taus, strict=True):  # the recall a metric over the seen GT would give
        table[f"3D recall of visible ({100 * r:g}%)"] = float(w[visible & (d3 <= t)].sum() / w[visible].sum())
    # the same stages as shares of the visible length: where the length the camera saw is lost
    wv = w[visible].sum()
    table_vis = {"visible": 1.0}
    for n in stage_names:
        table_vis[n] = float(w[visible & covered[n]].sum() / wv)
    for r, row in zip(REL_TAUS, on_line, strict=True):
        table_vis[f"line placed ({100 * r:g}%)"] = float(w[visible & row].sum() / wv)
    for r, t in zip(REL_TAUS, taus, strict=True):
        table_vis[f"3D recall ({100 * r:g}%)"] = float(w[visible & (d3 <= t)].sum() / wv)
    by_axis = {}
    for a in np.unique(gt.segments.axis[gt.segments.lengths() > 0]):
        sel = gt.segments.axis[gt.segments.lengths() > 0][owner] == a
        by_axis[int(a)] = {
            "length": float(w[sel].sum()),
            "visible": float(w[sel & visible].sum() / w[sel].sum()),
            "detected": float(w[sel & covered["detected"]].sum() / w[sel].sum()),
            "in map": float(w[sel & covered["in map"]].sum() / w[sel].sum()),
            "3D recall (1%)": float(w[sel & (d3 <= taus[1])].sum() / w[sel].sum()),
        }

    # --- precision: structural (its observations lie on GT segments) vs texture lines
    sel_obs = np.isin(tracks.line_track, final_ids)
    frac_struct = np.zeros(len(final_ids))
    if sel_obs.any():
        rows = np.searchsorted(final_ids, tracks.line_track[sel_obs])
        n_all = np.bincount(rows, minlength=len(final_ids))
        n_on = np.bincount(rows, weights=obs_structural[sel_obs], minlength=len(final_ids))
        frac_struct = n_on / np.maximum(n_all, 1)
    structural = frac_struct >= 0.5
    anchored = (
        m.lines.axis_weights.sum(axis=1) > 0 if m.lines.axis_weights.size else np.zeros(len(m.lines), bool)
    )
    lengths = np.linalg.norm(est_final[:, 1] - est_final[:, 0], axis=1)
    prec = {}
    for name, mask in (
        ("all", np.ones(len(final_ids), bool)),
        ("structural", structural),
        ("texture", ~structural),
        ("anchored", anchored),
        ("unanchored", ~anchored),
    ):
        p, length, _ = _prec(est_final[mask], gt_ends, taus, spacing)
        prec[name] = {
            "lines": int(mask.sum()),
            "length_share": float(lengths[mask].sum() / max(lengths.sum(), 1e-12)),
            **{f"precision {100 * r:g}%": float(v) for r, v in zip(REL_TAUS, p, strict=True)},
        }
    # structural lines: how much of their length lies beyond the GT segment they sit on (extent)
    over = _overshoot(est_final[structural], gt_ends, taus[1])
    prec["structural"]["length beyond GT ends (1%)"] = over
    lost = {}
    for tid in gt_tracks - tracked:
        r = why_not.get(tid, "unregistered frames only")
        lost[r] = lost.get(r, 0) + 1
    lost["triangulation rejected"] = len((gt_tracks & tracked) - triangulated)
    lost["culled or stray"] = len((gt_tracks & triangulated) - in_map)
    if dump is not None:
        rows = np.searchsorted(est.track, final_ids)
        d_each = [_prec(est_final[i : i + 1], gt_ends, taus, spacing)[0][1] for i in range(len(final_ids))]
        views = np.bincount(np.searchsorted(final_ids, m.lines.obs_ids[:, 0]), minlength=len(final_ids))
        np.savez(
            dump,
            length=lengths,
            structural=structural,
            anchored=anchored,
            from_vp=est.from_vp[rows],
            rms_px=est.rms_px[rows],
            kf_views=views,
            n_obs=np.bincount(
                np.searchsorted(final_ids, tracks.line_track[sel_obs]), minlength=len(final_ids)
            ),
            precision_1=np.array(d_each),
            frac_struct=frac_struct,
            track=final_ids,
            px_len=_median_px_length(tracks, final_ids),
        )
        # the triangulation input with each observation's "lies on a GT segment" flag, to try filters
        sel_in = np.isin(tracks.line_frame, frames)
        np.savez(
            dump.with_name(dump.stem + "_tri.npz"),
            track=tr_track,
            T_wc=tr_T,
            xy=tr_xy,
            vp_w=tr_vp,
            on_gt=obs_structural[sel_in],
            K=K,
        )
    return {
        "scene": folder.name,
        "gt_tracks_lost": lost,
        "tracks": str(tracks_path),
        "overrides": overrides,
        "map_s": round(t_map, 2),
        "ate_rel_path": ev.ate_rmse_rel_path,
        "eval_recall": ev.line_recall,
        "eval_precision": ev.line_precision,
        "scene_diagonal": diag,
        "gt_length": total,
        "n_lines": {
            "tracks": int(len(np.unique(tr_track))),
            "tracked": len(tracked),
            "triangulated": len(triangulated),
            "culled": int(sum(len(c) for c in probe["cull"])),
            "stray": len(probe.get("stray", ())),
            "in map": len(in_map),
        },
        "recall_stages": table,
        "visible_min_frames": min_frames,
        "eval_recall_visible": ev.line_recall_visible,
        "recall_stages_of_visible": table_vis,
        "recall_by_axis": by_axis,
        "recall_pre_ba_lines": pre,
        "gt_pose_triangulation": gt_pose_recall,
        "precision": prec,
    }


def _median_px_length(tracks: Tracks, ids: np.ndarray) -> np.ndarray:
    """Median image length (px) of each track's observations."""
    out = np.zeros(len(ids))
    px = np.linalg.norm(tracks.line_xy[:, 2:] - tracks.line_xy[:, :2], axis=1)
    for i, t in enumerate(ids):
        out[i] = np.median(px[tracks.line_track == t])
    return out


def _prec(est, gt_ends, taus, spacing):
    from papl_mapper.eval.lines import covered_fraction

    if len(est) == 0:
        return np.full(len(taus), np.nan), 0.0, {}
    return covered_fraction(est, gt_ends, taus, spacing)


def _overshoot(est, gt_ends, tau):
    """Share of the lines' length whose samples are within tau of a GT *infinite* line but not its segment."""
    if len(est) == 0:
        return float("nan")
    from papl_mapper.eval.lines import sample_segments

    pts, _, w = sample_segments(est, 0.25 * tau, include_ends=False)
    dseg = nearest_segment_distance(pts, gt_ends, tau)
    # extend GT segments far along their line: near the infinite line but off the segment = overshoot
    d = gt_ends[:, 1] - gt_ends[:, 0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    long = np.stack([gt_ends[:, 0] - 5.0 * d, gt_ends[:, 1] + 5.0 * d], 1)
    dlong = nearest_segment_distance(pts, long, tau)
    return float(w[(dlong <= tau) & ~(dseg <= tau)].sum() / w.sum())


def _print(res: dict) -> None:
    print(f"\n== {res['scene']}  (ATE {100 * res['ate_rel_path']:.3f}% of path, map {res['map_s']} s)")
    print("GT-detecting tracks lost:", res["gt_tracks_lost"])
    print("line counts:", ", ".join(f"{k} {v}" for k, v in res["n_lines"].items()))
    print(f"{'recall stage':<30}{'GT length share':>16}{'visible share':>15}")
    for k, v in res["recall_stages"].items():
        vis = res["recall_stages_of_visible"].get(k)
        print(f"{k:<30}{v:>16.3f}" + (f"{vis:>15.3f}" if vis is not None else ""))
    if res["recall_pre_ba_lines"]:
        print("recall of the lines before BA:", res["recall_pre_ba_lines"])
    if res["gt_pose_triangulation"]:
        print("triangulated with GT poses:", res["gt_pose_triangulation"])
    print("recall by GT axis:")
    for a, v in res["recall_by_axis"].items():
        print(f"  axis {a:>2}: " + "  ".join(f"{k} {x:.3f}" for k, x in v.items()))
    print(f"{'precision class':<14}{'lines':>7}{'len share':>10}{'p0.5%':>8}{'p1%':>8}{'p2%':>8}")
    for k, v in res["precision"].items():
        print(
            f"{k:<14}{v['lines']:>7}{v['length_share']:>10.3f}"
            f"{v['precision 0.5%']:>8.3f}{v['precision 1%']:>8.3f}{v['precision 2%']:>8.3f}"
        )
    print(
        "structural line length beyond GT segment ends (1%):",
        res["precision"]["structural"].get("length beyond GT ends (1%)"),
    )


#: The line triangulation settings before the structural-lines change (commit 737daa0), for --before.
BEFORE = ["lines.min_vp_fraction=0", "lines.min_views=2", "lines.min_plane_angle_deg=2"]


def _summary_table(pairs: list[tuple[dict, dict | None]]) -> None:
    """Recall / precision / ATE per scene, before and after, at every threshold."""
    print(
        f"\n{'scene':<22}{'run':<8}{'ATE %path':>10}"
        + "".join(f"{'R' + k:>8}{'P' + k:>8}" for k in ("0.5%", "1%", "2%"))
    )
    for after, before in pairs:
        for name, r in (("before", before), ("after", after)):
            if r is None:
                continue
            row = f"{r['scene']:<22}{name:<8}{100 * r['ate_rel_path']:>10.3f}"
            for k in ("0.5%", "1%", "2%"):
                row += f"{r['eval_recall'][k]:>8.3f}{r['eval_precision'][k]:>8.3f}"
            print(row)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("pairs", nargs="+", help="GT_FOLDER=TRACKS.npz")
    ap.add_argument("--set", action="append", default=[], help="RunConfig override key=value")
    ap.add_argument("--before", action="store_true", help=f"also run each scene with {' '.join(BEFORE)}")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument("--dump", help="folder for per-line arrays (npz) for further analysis")
    ap.add_argument(
        "--min-frames",
        type=int,
        default=DEFAULT_MIN_FRAMES,
        help="GT frames a part of a segment must be seen in to count as visible (as eval)",
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    results, befores, pairs = [], [], []
    for pair in args.pairs:
        folder, tracks = pair.split("=", 1)
        if not Path(folder).is_dir() or not Path(tracks).is_file():
            print(f"skip {pair}: missing", file=sys.stderr)
            continue
        before = None
        if args.before:
            before = diagnose(Path(folder), Path(tracks), BEFORE + args.set)
            print("\n-- before:", " ".join(BEFORE))
            _print(before)
            befores.append(before)
        dump = Path(args.dump) / f"{Path(folder).name}.npz" if args.dump else None
        res = diagnose(Path(folder), Path(tracks), args.set, dump, args.min_frames)
        print("\n-- after (defaults)" + (f" with {' '.join(args.set)}" if args.set else ""))
        _print(res)
        results.append(res)
        pairs.append((res, before))
    _summary_table(pairs)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = {"machine": machine_info(), "results": results}
    if befores:
        doc["before"] = {"overrides": BEFORE, "results": befores}
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
