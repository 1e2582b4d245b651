"""index.html of a `papl-map batch`: totals, then one row per recording, in one self-contained file
(inline styles, no scripts, nothing fetched). Links are relative: to each recording's report.html
(or its summary.json / log when there is no report), so the folder can be moved or served as is."""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

from papl_mapper.atomic import atomic_path
from papl_mapper.palette import UNANCHORED_RGB, axis_colors, hex_color

STATUS_COLOURS = {
    "ok": "#0a7d38",
    "failed": "#b3261e",
    "interrupted": "#a15c00",
    "pending": "#666",
    "running": "#0059b3",
    "submitted": "#0059b3",
}

_CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:1.5em;color:#222}
h1{font-size:1.4em;margin:0 0 .3em}
.totals{display:flex;flex-wrap:wrap;gap:.6em 1.6em;margin:.6em 0 1.2em;padding:.7em 1em;
 background:#f3f4f6;border-radius:6px}
.totals b{font-size:1.2em}
table{border-collapse:collapse;width:100%}
th,td{padding:.35em .55em;border-bottom:1px solid #ddd;text-align:left;vertical-align:top}
th{background:#fafafa;position:sticky;top:0}
td.num{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
.status{font-weight:600}
.err{color:#b3261e;font-size:.92em;max-width:40em}
.chip{display:inline-block;min-width:1.6em;padding:0 .25em;margin-right:.15em;border-radius:3px;
 color:#fff;text-align:center}
.stages{font-size:.85em;color:#555}
.small{font-size:.85em;color:#555}
"""


def _e(v: Any) -> str:
    return html.escape("" if v is None else str(v))


def _num(v: Any, fmt: str = "{}") -> str:
    return "" if v is None else fmt.format(v)


def _lines(row: dict[str, Any]) -> str:
    per_axis = row.get("lines_per_axis") or []
    if not per_axis and not row.get("lines"):
        return ""
    colours = axis_colors(len(per_axis), row.get("vertical_index"))
    chips = "".join(
        f'<span class="chip" style="background:{hex_color(tuple(int(x) for x in c))}" '
        f'title="axis {a}">{n}</span>'
        for a, (n, c) in enumerate(zip(per_axis, colours, strict=True))
    )
    grey = hex_color(UNANCHORED_RGB)
    un = row.get("unanchored_lines") or 0
    chips += f'<span class="chip" style="background:{grey}" title="unanchored">{un}</span>'
    return f"{row.get('lines', '')} {chips}"


def _link(row: dict[str, Any]) -> str:
    name = _e(row["name"])
    base = row.get("out") or row["name"]
    if row.get("report"):
        return f'<a href="{_e(base)}/report.html">{name}</a>'
    if row.get("status") == "ok":
        return f'<a href="{_e(base)}/summary.json">{name}</a>'
    return name


def _stages(row: dict[str, Any]) -> str:
    t = row.get("timings_s") or {}
    main = {k: v for k, v in t.items() if v >= 0.05}
    return " · ".join(f"{_e(k)} {v:.1f}" for k, v in main.items())


def _ate(row: dict[str, Any]) -> str:
    if row.get("ate_rmse") is None:
        return ""
    rel = row.get("ate_rmse_rel_path")
    return f"{row['ate_rmse']:.4g}" + (f" ({100 * rel:.2f}%)" if rel is not None else "")


def render_index(doc: dict[str, Any]) -> str:
    t = doc.get("totals", {})
    eng = doc.get("engine", {})
    rows = doc.get("recordings", [])
    engine = (
        f"local pool, {eng.get('workers')} workers × {eng.get('threads_per_worker')} threads"
        if eng.get("engine") == "local"
        else f"Ray {eng.get('address')}, {eng.get('num_cpus_per_task')} CPUs and "
        f"{eng.get('memory_gib_per_task')} GiB per task"
    )
    rate = t.get("recordings_per_minute")
    totals = [
        ("recordings", t.get("recordings")),
        ("ok", t.get("ok")),
        ("failed", t.get("failed")),
        ("interrupted", t.get("interrupted")),
        ("not started", t.get("pending")),
        ("reused from an earlier run", t.get("reused")),
        ("frames posed", f"{t.get('frames_posed', 0)} / {t.get('frames', 0)}"),
        ("keyframes", t.get("keyframes")),
        ("lines", t.get("lines")),
        ("wall time", f"{t.get('wall_s', 0):.1f} s"),
        ("recordings per minute", f"{rate:.2f}" if rate else "–"),
        ("largest worker", f"{t.get('peak_rss_mib_max', 0):.0f} MiB"),
    ]
    head = "".join(f"<div>{_e(k)}<br><b>{_e(v)}</b></div>" for k, v in totals)
    body = []
    for i, r in enumerate(rows, 1):
        status = r.get("status", "")
        colour = STATUS_COLOURS.get(status, "#222")
        err = f'<div class="err">{_e(r.get("error"))}</div>' if r.get("error") else ""
        reused = ' <span class="small">(reused)</span>' if r.get("reused") else ""
        frames = f"{r['frames_posed']} / {r['frames']}" if r.get("frames") is not None else ""
        anchored = _num(r.get("anchored_fraction"), "{:.0%}") if status == "ok" else ""
        wall = r.get("worker_s") or r.get("wall_s")
        body.append(
            "<tr>"
            f'<td class="num">{i}</td>'
            f'<td>{_link(r)}<div class="small">{_e(r.get("source"))}</div></td>'
            f'<td><span class="status" style="color:{colour}">{_e(status)}</span>{reused}{err}</td>'
            f'<td class="num">{_e(frames)}</td>'
            f'<td class="num">{_e(r.get("keyframes", ""))}</td>'
            f"<td>{_lines(r)}</td>"
            f'<td class="num">{_e(anchored)}</td>'
            f'<td class="num">{_e(_ate(r))}</td>'
            f'<td class="stages">{_stages(r)}</td>'
            f'<td class="num">{_e(_num(wall, "{:.1f} s"))}</td>'
            f'<td class="num">{_e(_num(r.get("peak_rss_mib"), "{:.0f}"))}</td>'
            f'<td class="num">{_e(r.get("attempts", ""))}</td>'
            "</tr>"
        )
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>papl-map batch: {_e(Path(str(doc.get('out', ''))).name)}</title>"
        f"<style>{_CSS}</style></head><body>"
        f'<h1>papl-map batch</h1><div class="small">{_e(doc.get("out"))} · {_e(engine)} · '
        f"{_e(doc.get('software'))} · updated {_e(doc.get('updated'))}"
        f"{'' if doc.get('finished') else ' · <b>not finished</b>'}</div>"
        f'<div class="totals">{head}</div>'
        "<table><thead><tr><th>#</th><th>recording</th><th>status</th><th>frames posed</th>"
        "<th>keyframes</th><th>lines per axis (unanchored grey)</th><th>anchored</th><th>ATE (of path)</th>"
        "<th>seconds per stage</th><th>wall</th><th>peak MiB</th><th>attempts</th></tr></thead><tbody>"
        + "".join(body)
        + "</tbody></table></body></html>\n"
    )


def write_index(doc: dict[str, Any], path: Path) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(render_index(doc), encoding="utf-8")
    return path
