"""The self-contained HTML map report: previews, summary, axes, BA statistics, timings, plots,
ground-truth metrics and how to open the exports, in one file with every image embedded.

Reads a run folder (`map.papl`, `trajectory.tum`, `summary.json`, `config.toml`, `log.txt`; any
of them may be absent except the map) or a bare map. Missing parts show "not available"; the
report never fetches anything (no external scripts, styles, fonts or images).
"""

from __future__ import annotations

import base64
import dataclasses
import datetime as _dt
import html
import json
import logging
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from papl_mapper.atomic import atomic_path
from papl_mapper.errors import BackendUnavailableError, InputError, PaplError
from papl_mapper.map import Map
from papl_mapper.palette import UNANCHORED_RGB, axis_colors, axis_names, hex_color
from papl_mapper.scale.estimate import units_note
from papl_mapper.trajectory_io import Trajectory, read_tum

from . import plots
from .preview import PreviewOptions, PreviewResult, prepare_scene, render_views

log = logging.getLogger(__name__)

NA = "not available"

#: What reads which export well (from the exporters' notes, shared/EXPORTS.md).
EXPORT_GUIDE: tuple[tuple[str, str, str], ...] = (
    (
        "map.ply",
        "PLY vertices + edges, coloured per segment",
        "Open3D (read_line_set), CloudCompare; MeshLab shows edges white and drops them on re-save",
    ),
    (
        "map.glb / map.gltf",
        "glTF 2.0 LINES, one primitive per axis, unlit",
        "three.js and web viewers "
        "(LineSegments), Khronos glTF validator; Blender imports lines as loose edges that do not render",
    ),
    ("map.usda / map.usdc", "USD BasisCurves per axis, Z up", "usdview, Omniverse, Maya, Houdini"),
    (
        "map.dxf",
        "DXF LINE entities on one layer per axis (BYLAYER colours)",
        "FreeCAD, LibreCAD, AutoCAD, BricsCAD; ezdxf audit",
    ),
    ("map.obj", "OBJ `l` lines grouped per axis", "CloudCompare; MeshLab ignores OBJ lines"),
    ("map_tubes.glb / .ply", "lines as thin tube meshes", "any mesh viewer, Blender renders"),
    (
        "trajectory.tum / .kitti",
        "camera path (TUM has timestamps)",
        "evo (evo_traj, evo_ape -as), most SLAM tools",
    ),
    (
        "colmap/",
        "COLMAP text model (cameras, images, points3D)",
        "COLMAP GUI, line mappers that start from COLMAP poses",
    ),
)


@dataclass
class ReportOptions:
    """What the report holds and how large its images are."""

    title: str = ""
    """Report title; empty uses the run folder or map file name."""
    previews: bool = True
    """Render the four off-screen previews (needs an off-screen OpenGL backend)."""
    preview: PreviewOptions = field(default_factory=lambda: PreviewOptions(width=1200, height=900))
    """Options of the embedded previews."""
    stereonet_max_lines: int = 20_000
    """Lines drawn in the direction stereonet (seeded subset beyond this)."""
    log_tail_lines: int = 40
    """Lines of log.txt shown at the end of the report."""


@dataclass
class RunFolder:
    """What was found in a run folder (or beside a bare map); absent parts are None with a note why."""

    name: str
    map: Map
    map_path: Path | None = None
    summary: dict[str, Any] | None = None
    trajectory_tum: Path | None = None
    trajectory: Trajectory | None = None
    config_text: str | None = None
    log_text: str | None = None
    notes: list[str] = field(default_factory=list)


def load_run(source: str | os.PathLike | Map) -> RunFolder:
    """Read a run folder, a bare `.papl` file, or take a Map; raise InputError if there is no map."""
    if isinstance(source, Map):
        return RunFolder(name=str(source.metadata.get("name", "map")), map=source)
    path = Path(source)
    if path.is_dir():
        map_path = path / "map.papl"
        if not map_path.exists():
            raise InputError(f"{path}: run folder has no map.papl; give a run folder or a .papl map file")
        run = RunFolder(name=path.resolve().name, map=Map.load(map_path), map_path=map_path)
        folder = path
    elif path.exists():
        run = RunFolder(name=path.stem, map=Map.load(path), map_path=path)
        folder = None
    else:
        raise InputError(f"{path}: no such run folder or map file")
    if folder is None:
        return run
    s = folder / "summary.json"
    if s.exists():
        try:
            data = json.loads(s.read_text())
            if not isinstance(data, dict):
                raise ValueError("top level is not an object")
            run.summary = data
        except (ValueError, UnicodeDecodeError) as exc:
            run.notes.append(f"{s.name} unreadable ({exc}); its sections show '{NA}'")
    for name in ("trajectory.tum", "keyframes.tum"):
        t = folder / name
        if t.exists():
            try:
                run.trajectory = read_tum(t)
                run.trajectory_tum = t
                break
            except InputError as exc:
                run.notes.append(str(exc))
    for attr, name in (("config_text", "config.toml"), ("log_text", "log.txt")):
        p = folder / name
        if p.exists():
            setattr(run, attr, p.read_text(errors="replace"))
    return run


# ---- HTML helpers ---------------------------------------------------------------------------

_CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',Roboto,Helvetica,Arial,sans-serif;margin:0;
background:#fafafa;color:#1b1b1b;line-height:1.4}
main{max-width:1250px;margin:0 auto;padding:1em 1.5em 3em}
h1{font-size:1.6em;margin:.4em 0 .1em}h2{font-size:1.25em;border-bottom:1px solid #ccc;margin-top:1.8em}
.sub{color:#555;margin-bottom:1em}
table{border-collapse:collapse;margin:.5em 0;font-size:.93em}
th,td{border:1px solid #ddd;padding:.25em .6em;text-align:left;vertical-align:top}
th{background:#f0f0f0}td.num{text-align:right;font-variant-numeric:tabular-nums}
.na{color:#999;font-style:italic}.note{background:#fff7e0;border-left:4px solid #e69f00;padding:.4em .8em;
margin:.4em 0}
.grid{display:grid;grid-template-columns:repeat(auto-fit,minmax(520px,1fr));gap:12px}
.grid img,.plot img{width:100%;height:auto;border:1px solid #ddd;background:#fff}
.plots{display:grid;grid-template-columns:repeat(auto-fit,minmax(420px,1fr));gap:12px}
.sw{display:inline-block;width:.9em;height:.9em;border:1px solid #333;vertical-align:-.1em;margin-right:.3em}
.bar{display:inline-block;height:.8em;background:#0072b2;vertical-align:middle}
pre{background:#f3f3f3;padding:.6em;overflow:auto;font-size:.85em;max-height:30em}
figure{margin:0}figure.plot{max-width:760px}figcaption{font-size:.85em;color:#555}
"""


def _e(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _na(what: str = "") -> str:
    return f'<span class="na">{NA}{_e(" (" + what + ")") if what else ""}</span>'


def _img(png: bytes, alt: str) -> str:
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode("ascii")}">'


def _num(v: Any, fmt: str = "{:,.4g}") -> str:
    if isinstance(v, bool) or v is None:
        return _na() if v is None else _e(v)
    if isinstance(v, (int, np.integer)):
        return f"{int(v):,}"
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if not np.isfinite(v):
            return _e(v)
        if 1e3 <= abs(v) < 1e12:  # thousands separated, 4 significant digits at least
            return f"{v:,.0f}"
        return f"{v:.4g}"
    return _e(v)


def _table(rows: list[tuple[str, str]], header: tuple[str, str] | None = None) -> str:
    head = f"<tr><th>{_e(header[0])}</th><th>{_e(header[1])}</th></tr>" if header else ""
    body = "".join(f"<tr><th>{_e(k)}</th><td>{v}</td></tr>" for k, v in rows)
    return f"<table>{head}{body}</table>"


def _get(d: Any, *keys: str) -> Any:
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


# ---- sections -------------------------------------------------------------------------------


def run_warnings(summary: dict[str, Any] | None) -> list[str]:
    """What a reader must know before trusting the map: a guessed camera, a doubtful focal length,
    parts of the recording mapped apart from it."""
    out = []
    if _get(summary, "camera", "guessed") is True:
        out.append(
            "No camera file was given: the intrinsics were guessed from a horizontal field of view. "
            "Give the real intrinsics with --camera FILE for a metric-shape map."
        )
    if _get(summary, "focal_check", "plausible") is False:
        out.append(str(_get(summary, "focal_check", "message")))
    for seg in _get(summary, "segment_maps") or []:
        first, last = seg["frames"]
        out.append(
            f"Frames {first}-{last} could not be joined to this map (a stretch with too little to track "
            f"between them): they were mapped on their own, in their own frame and scale, in "
            f"{seg['folder']}/ ({seg['frames_posed']} frames posed, {seg['points']} points, "
            f"{seg['lines']} lines)."
        )
    return out


def _section_summary(run: RunFolder, s: dict[str, Any]) -> str:
    m = run.map
    names = axis_names(len(m.axes), m.axes.vertical_index)
    colors = axis_colors(len(m.axes), m.axes.vertical_index)
    rec = _get(run.summary, "recording")
    rows: list[tuple[str, str]] = []
    if isinstance(rec, dict):
        rows.append(("recording", _e(rec.get("path", NA))))
        for k in ("frames", "fps", "width", "height"):
            rows.append((k, _num(rec.get(k))))
        rows.append(("recording sha256", f"<code>{_e(rec.get('sha256', NA))}</code>"))
    else:
        rows.append(("recording", _na("no summary.json recording entry")))
    rows.append(("map file", _e(run.map_path) if run.map_path else _na("map given in memory")))
    rows += [
        ("keyframes", _num(s["keyframes"])),
        ("points", f"{_num(s['points'])} ({_num(s['point_observations'])} observations)"),
        ("lines", f"{_num(s['lines'])} ({_num(s['line_observations'])} observations)"),
        ("anchored fraction", f"{100 * s['anchored_fraction']:.1f} %" if s["lines"] else _na("no lines")),
        ("units", _e(units_note(m.metadata))),
    ]
    if "trajectory_length" in s:
        rows.append(("keyframe path length", f"{s['trajectory_length']:.3f} {_e(s['units'])}"))
        rows.append(("duration", f"{s['duration_s']:.2f} s"))
    cam = m.camera
    rows.append(
        (
            "camera",
            _e(
                f"{cam.model} {cam.width}x{cam.height} fx={cam.fx:.2f} fy={cam.fy:.2f} "
                f"cx={cam.cx:.2f} cy={cam.cy:.2f}"
            ),
        )
    )
    if run.summary is not None and "frames_lost" in run.summary:
        rows.append(("frames lost", _num(run.summary.get("frames_lost"))))
    focal = _get(run.summary, "focal_check")
    if isinstance(focal, dict) and focal.get("message"):
        rows.append(("focal check", _e(focal["message"])))
    revisits = _get(run.summary, "revisits")
    if isinstance(revisits, list):
        rows.append(("revisits (loops closed)", _num(len(revisits))))
    rows += _start_checks(run.summary)
    out = "".join(f"<p class='note'><b>Warning:</b> {_e(w)}</p>" for w in run_warnings(run.summary))
    out += "<h2>Summary</h2>" + _table(rows)
    # lines per axis and the axes
    ax_rows = []
    lengths = m.lines.lengths() if len(m.lines) else np.zeros(0)
    axis = m.lines.axis_of_line()
    for a, name in enumerate(names):
        d = m.axes.directions[a]
        sel = axis == a
        ax_rows.append(
            f"<tr><td>{a}</td><td><span class='sw' style='background:{hex_color(colors[a])}'></span>"
            f"{_e(name)}</td><td><code>({d[0]:+.4f}, {d[1]:+.4f}, {d[2]:+.4f})</code></td>"
            f"<td class='num'>{int(sel.sum()):,}</td><td class='num'>{lengths[sel].sum():.3f}</td></tr>"
        )
    sel = axis < 0
    ax_rows.append(
        f"<tr><td>-</td><td><span class='sw' style='background:{hex_color(UNANCHORED_RGB)}'></span>"
        f"unanchored</td><td>-</td><td class='num'>{int(sel.sum()):,}</td>"
        f"<td class='num'>{lengths[sel].sum():.3f}</td></tr>"
    )
    out += "<h2>Axes and lines per axis</h2>"
    if not len(m.axes):
        out += f"<p>{_na('no principal axes in this map')}</p>"
    out += (
        "<table><tr><th>#</th><th>axis</th><th>direction (world, +Z up)</th><th>lines</th>"
        f"<th>total length [{_e(s['units'])}]</th></tr>" + "".join(ax_rows) + "</table>"
    )
    if len(m.axes) > 1:
        ang = m.axes.angles_deg()
        head = "".join(f"<th>{_e(n)}</th>" for n in names)
        body = "".join(
            f"<tr><th>{_e(names[i])}</th>"
            + "".join(
                f"<td class='num'>{'-' if i == j else f'{ang[i, j]:.2f}°'}</td>" for j in range(len(names))
            )
            + "</tr>"
            for i in range(len(names))
        )
        out += f"<p>Angles between the axes:</p><table><tr><th></th>{head}</tr>{body}</table>"
    return out


def _start_checks(summary: dict[str, Any] | None) -> list[tuple[str, str]]:
    """Rows saying which start the global BA kept: the rotation check's and the backward registration's."""
    rows = []
    rot = _get(summary, "rotation_check")
    if isinstance(rot, dict) and rot.get("pairs"):
        said = (
            f"median pair missed by {rot.get('residual_ba_deg', 0):.3f}° (BA) and "
            f"{rot.get('residual_averaged_deg', 0):.3f}° (averaged rotations)"
        )
        if rot.get("second_start"):
            said += f"; a second BA from the averaged rotations ran, the {rot.get('kept')} start kept"
        rows.append(("rotation check", _e(said)))
    rev = _get(summary, "reverse_check")
    if isinstance(rev, dict):
        where = " in a worker process" if rev.get("in_worker") else ""
        took = (
            f" ({rev['registration_s']:.1f} s{where})" if isinstance(rev.get("registration_s"), float) else ""
        )
        if rev.get("z") is None:
            said = (
                f"registered backwards{took}: {_num(rev.get('posed_backward'))} of the "
                f"{_num(rev.get('keyframes'))} keyframes posed, not compared"
            )
        else:
            said = (
                f"registered backwards{took}: {rev.get('kept')} poses kept (paired test over the tracks: "
                f"z {rev['z']:.1f}, negative favours the backward poses)"
            )
        rows.append(("second start", _e(said)))
    return rows


def _section_ba(summary: dict[str, Any] | None) -> str:
    ba = _get(summary, "ba")
    out = "<h2>Bundle adjustment</h2>"
    if not isinstance(ba, dict) or not ba:
        return out + f"<p>{_na('no BA statistics in summary.json')}</p>"
    rows = "<tr><th>quantity</th><th>before</th><th>after</th></tr>"
    rows += f"<tr><th>cost</th><td class='num'>{_num(ba.get('initial_cost'))}</td>"
    rows += f"<td class='num'>{_num(ba.get('final_cost'))}</td></tr>"
    rms = ba.get("rms")
    if isinstance(rms, dict):
        for k, v in rms.items():
            if isinstance(v, dict):
                before, after = v.get("before", v.get("initial")), v.get("after", v.get("final"))
            else:
                before, after = None, v
            rows += f"<tr><th>RMS reprojection error {_e(k)}</th><td class='num'>{_num(before)}</td>"
            rows += f"<td class='num'>{_num(after)}</td></tr>"
    rest = [
        (k, _num(v))
        for k, v in ba.items()
        if k not in ("initial_cost", "final_cost", "rms") and not isinstance(v, (dict, list))
    ]
    ic, fc = ba.get("initial_cost"), ba.get("final_cost")
    if isinstance(ic, (int, float)) and isinstance(fc, (int, float)) and ic > 0:
        rest.append(("cost reduction", f"{100 * (1 - fc / ic):.1f} %"))
    return out + f"<table>{rows}</table>" + (_table(rest) if rest else "")


def _section_timings(summary: dict[str, Any] | None) -> str:
    t = _get(summary, "timings_s")
    out = "<h2>Timings per stage</h2>"
    if not isinstance(t, dict) or not t:
        return out + f"<p>{_na('no timings in summary.json')}</p>"
    vals = {k: float(v) for k, v in t.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    top = max(vals.values(), default=0.0) or 1.0
    total = sum(vals.values())
    rows = "".join(
        f"<tr><th>{_e(k)}</th><td class='num'>{v:.3f}</td><td class='num'>{100 * v / (total or 1):.1f} %</td>"
        f"<td><span class='bar' style='width:{300 * v / top:.0f}px'></span></td></tr>"
        for k, v in vals.items()
    )
    rows += f"<tr><th>total</th><td class='num'>{total:.3f}</td><td></td><td></td></tr>"
    return out + f"<table><tr><th>stage</th><th>seconds</th><th>share</th><th></th></tr>{rows}</table>"


def per_frame_counts(run: RunFolder) -> tuple[np.ndarray, dict[str, np.ndarray], str] | None:
    """(x, {series: counts}, x label): summary.json `per_frame`, else observations per keyframe of the map."""
    pf = _get(run.summary, "per_frame")
    if isinstance(pf, dict) and isinstance(pf.get("frame"), list) and pf["frame"]:
        n = len(pf["frame"])
        try:
            series = {
                k: np.asarray(v, np.float64)
                for k, v in pf.items()
                if k != "frame" and isinstance(v, list) and len(v) == n
            }
            return np.asarray(pf["frame"], np.float64), series, "frame"
        except (TypeError, ValueError):
            run.notes.append("summary.json per_frame holds non-numbers; counts per frame not shown")
            return None
    m = run.map
    if not len(m.keyframes):
        return None
    order = np.argsort(m.keyframes.ids)
    kf_sorted = m.keyframes.ids[order]

    def per_keyframe(obs_kf: np.ndarray) -> np.ndarray:  # observations per keyframe, in keyframe order
        counts = np.bincount(np.searchsorted(kf_sorted, obs_kf), minlength=len(kf_sorted))
        out = np.empty(len(kf_sorted))
        out[order] = counts[: len(kf_sorted)]
        return out

    by_frame = np.argsort(m.keyframes.frame_index, kind="stable")
    pts = per_keyframe(m.points.obs_ids[:, 1])[by_frame]
    lns = per_keyframe(m.lines.obs_ids[:, 1])[by_frame]
    frames = m.keyframes.frame_index[by_frame].astype(np.float64)
    return frames, {"points": pts, "lines": lns}, "keyframe (frame index)"


def _section_plots(run: RunFolder, options: ReportOptions) -> str:
    m = run.map
    scene = prepare_scene(m, dataclasses.replace(options.preview, show_points=False))
    centres = run.trajectory.positions if run.trajectory is not None else m.keyframes.T_wc[:, :3, 3]
    label = run.trajectory_tum.name if run.trajectory_tum else "keyframes"
    figs = [
        _img(
            plots.trajectory_top(
                centres,
                scene.endpoints_w,
                scene.line_rgb,
                units=m.metadata.get("units", "arbitrary"),
                label=label,
            ),
            "trajectory top view",
        ),
        _img(
            plots.direction_stereonet(
                m.lines.endpoints_w,
                m.lines.axis_of_line(),
                m.axes.directions,
                m.axes.vertical_index,
                options.preview.palette,
                options.stereonet_max_lines,
                options.preview.seed,
            ),
            "line direction stereonet",
        ),
    ]
    pf = per_frame_counts(run)
    if pf is not None and pf[1] and any(np.any(v != 0) for v in pf[1].values()):
        figs.append(_img(plots.per_frame_counts(pf[0], pf[1], pf[2]), "counts per frame"))
    else:
        figs.append(
            f"<p>counts per frame: {_na('no per-frame data in summary.json, no observations in the map')}</p>"
        )
    return (
        "<h2>Plots</h2><div class='plots'>"
        + "".join(f"<figure class='plot'>{f}</figure>" for f in figs)
        + "</div>"
    )


def _section_gt(run: RunFolder, gt_dir: Path | None) -> str:
    out = "<h2>Ground truth comparison</h2>"
    if gt_dir is None:
        return out + f"<p>{_na('no --gt folder given')}</p>"
    try:
        from papl_mapper.eval import evaluate
    except ImportError as exc:
        return out + f"<p>{_na(f'papl_mapper.eval.evaluate cannot be imported: {exc}')}</p>"
    try:
        res = evaluate(Path(gt_dir), run.map, run.trajectory_tum)
    except PaplError as exc:
        return out + f"<p>{_na(str(exc))}</p>"
    units = run.map.metadata.get("units", "arbitrary")
    out += f"<p>Ground truth: <code>{_e(gt_dir)}</code></p>"
    rows = [
        ("matched poses", _num(getattr(res, "n_matched_poses", None))),
        (f"ATE RMSE [{units}] (Sim(3) aligned)", _num(getattr(res, "ate_rmse", None))),
        ("ATE RMSE / path length", _num(getattr(res, "ate_rmse_rel_path", None))),
        ("RPE translation", _num(getattr(res, "rpe_trans", None))),
        ("RPE rotation [deg]", _num(getattr(res, "rpe_rot_deg", None))),
        ("Sim(3) scale", _num(getattr(res, "scale", None))),
    ]
    recall = getattr(res, "line_recall", None)
    recall_vis = getattr(res, "line_recall_visible", None) or {}
    precision = getattr(res, "line_precision", None)
    frac = getattr(res, "gt_visible_fraction", None)
    if frac is not None:
        n_min = getattr(res, "line_visible_min_frames", "?")
        rows.append((f"share of the GT line length seen in >= {n_min} frames", _num(frac)))
    for thr in dict.fromkeys([*(recall or {}), *(precision or {})]):  # recall, recall of seen GT, precision
        if isinstance(recall, dict) and thr in recall:
            rows.append((f"line recall @ {thr}", _num(recall[thr])))
        if thr in recall_vis:
            rows.append((f"line recall of the seen GT @ {thr}", _num(recall_vis[thr])))
        if isinstance(precision, dict) and thr in precision:
            rows.append((f"line precision @ {thr}", _num(precision[thr])))
    ae = getattr(res, "axis_errors_deg", None)
    if ae is not None:
        rows.append(("axis errors [deg]", _e(", ".join(f"{float(v):.3f}" for v in ae)) or _na()))
    out += _table(rows, ("metric", "value"))
    try:
        out += f"<pre>{_e(res.table())}</pre>"
    except Exception as exc:  # noqa: BLE001 - the table is a convenience; the metrics above stand
        log.debug("EvalResult.table() failed: %s", exc)
    per = getattr(res, "ate_per_pose", None)
    if per is not None:
        try:
            t, e = (np.asarray(x, np.float64) for x in per)
            if len(t):
                out += (
                    f"<figure class='plot'>{_img(plots.ate_over_time(t, e, units), 'ATE over time')}</figure>"
                )
        except (TypeError, ValueError) as exc:
            out += f"<p>ATE over time: {_na(str(exc))}</p>"
    return out


def _section_exports() -> str:
    rows = "".join(
        f"<tr><td><code>{_e(f)}</code></td><td>{_e(w)}</td><td>{_e(t)}</td></tr>" for f, w, t in EXPORT_GUIDE
    )
    return (
        "<h2>How to open the exports</h2><p>Write them with <code>papl-map export MAP OUT.ext</code>. "
        "Line primitives are poorly supported by many viewers; where a tool drops them, use the tubes "
        "export.</p><table><tr><th>file</th><th>what it holds</th><th>reads it well</th></tr>"
        + rows
        + "</table>"
    )


# ---- public ---------------------------------------------------------------------------------


def build_report_html(
    source: str | os.PathLike | Map,
    gt_dir: str | os.PathLike | None = None,
    options: ReportOptions | None = None,
    previews: PreviewResult | None = None,
) -> str:
    """The report as one HTML string (see `write_report`)."""
    options = options or ReportOptions()
    t0 = time.perf_counter()
    run = load_run(source)
    m = run.map
    s = m.summary()
    title = options.title or f"papl-mapper report: {run.name}"
    notes = list(run.notes)
    if len(m.lines) == 0 and len(m.points) == 0 and len(m.keyframes) == 0:
        notes.insert(0, "This map is empty: no keyframes, points or lines.")
    parts = [f"<h1>{_e(title)}</h1>"]
    from papl_mapper import __version__

    parts.append(
        f"<div class='sub'>papl-mapper {_e(__version__)}, generated "
        f"{_dt.datetime.now(_dt.UTC).strftime('%Y-%m-%d %H:%M UTC')}</div>"
    )
    # previews
    prev = "<h2>Previews</h2>"
    if options.previews:
        try:
            with tempfile.TemporaryDirectory() as tmp:
                res = previews or render_views(m, tmp, options.preview)
                notes += res.notes
                prev += (
                    "<div class='grid'>"
                    + "".join(
                        f"<figure>{_img(p.read_bytes(), f'{v} view')}"
                        f"<figcaption>{_e(v)} view</figcaption></figure>"
                        for v, p in zip(res.views, res.paths, strict=True)
                    )
                    + "</div>"
                )
        except BackendUnavailableError as exc:
            prev += f"<p>{_na(str(exc))}</p>"
            notes.append("previews were not rendered: no off-screen OpenGL backend")
    else:
        prev += f"<p>{_na('previews switched off')}</p>"
    parts.append("".join(f"<div class='note'>{_e(n)}</div>" for n in dict.fromkeys(notes)))
    parts.append(prev)
    parts.append(_section_summary(run, s))
    parts.append(_section_ba(run.summary))
    parts.append(_section_timings(run.summary))
    parts.append(_section_plots(run, options))
    parts.append(_section_gt(run, Path(gt_dir) if gt_dir is not None else None))
    parts.append(_section_exports())
    parts.append("<h2>Configuration</h2>")
    parts.append(
        f"<pre>{_e(run.config_text)}</pre>" if run.config_text else f"<p>{_na('no config.toml')}</p>"
    )
    parts.append("<h2>Log (last lines)</h2>")
    if run.log_text:
        tail = "\n".join(run.log_text.splitlines()[-options.log_tail_lines :])
        parts.append(f"<pre>{_e(tail)}</pre>")
    else:
        parts.append(f"<p>{_na('no log.txt')}</p>")
    parts.append(f"<p class='sub'>Report built in {time.perf_counter() - t0:.1f} s.</p>")
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<title>{_e(title)}</title><style>{_CSS}</style></head><body><main>"
        + "\n".join(parts)
        + "</main></body></html>\n"
    )


def write_report(
    run_dir_or_map: str | os.PathLike | Map,
    out_path: str | os.PathLike,
    gt_dir: str | os.PathLike | None = None,
    options: ReportOptions | None = None,
    previews: PreviewResult | None = None,
) -> Path:
    """Write the self-contained HTML report of a run folder, a `.papl` file or a Map; returns the path.
    `previews`: the map's previews already rendered (by the run), embedded instead of rendered again."""
    out_path = Path(out_path)
    text = build_report_html(run_dir_or_map, gt_dir, options, previews)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return out_path
