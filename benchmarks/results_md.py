"""Build benchmarks/RESULTS.md from benchmarks/results/*.json: one table per results file with its
headline numbers, under a heading per area.

Every number in RESULTS.md is read from a JSON file the benchmark wrote; this script only chooses which
keys are headlines (AREAS) and prints them as they are (floats to four significant digits). Docstrings
cite RESULTS.md or the JSON instead of quoting measurements, so a re-run benchmark updates one place.
A results file no area names still gets a table (under "Other results"), built from its top level.

    .venv/bin/python benchmarks/results_md.py           # rewrite benchmarks/RESULTS.md
    .venv/bin/python benchmarks/results_md.py --check   # exit 1 if it is out of date
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
OUT = ROOT / "benchmarks" / "RESULTS.md"
NOTES = ROOT / "benchmarks" / "results" / "notes.md"  # hand-written: why defaults are what they are
NOISE = ("machine", "commit", "all_runs", "load_average", "loadavg", "date")
"""Keys never shown as headlines (provenance is printed once per file)."""


@dataclass(frozen=True)
class Rows:
    """A table with one row per entry of the list or dict at `path` (dotted; "" is the top level) and
    the given columns (dotted keys inside an entry); `only` keeps the entries of a dict with these keys."""

    path: str
    columns: tuple[str, ...]
    only: tuple[str, ...] = ()


@dataclass(frozen=True)
class Keys:
    """A two-column table of the leaves whose dotted path matches one of the fnmatch patterns."""

    patterns: tuple[str, ...]


SEEDED_ACCURACY_ROWS = Rows(
    "rows",
    ("scene", "noise", "seed", "variant", "ate_rel_path", "line_recall_1pct", "line_precision_1pct", "map_s"),
)
"""The table of an accuracy.py run over several walk seeds."""

AREAS: list[tuple[str, dict[str, list[Rows | Keys]]]] = [
    (
        "Frontend",
        {
            "frontend_throughput.json": [
                Rows(
                    "",
                    (
                        "default.fps",
                        "default.ms_per_frame",
                        "default.cpu_ms_per_frame",
                        "default.main_thread_cpu_ms_per_frame",
                        "default.step_ms_per_frame.points",
                        "default.step_ms_per_frame.lines",
                        "default.accuracy.vertical_err_deg_median",
                        "realtime_preset.fps",
                    ),
                    only=("1280x720", "640x480"),
                )
            ],
            "features.json": [
                Rows(
                    "rows",
                    (
                        "sequence",
                        "detector",
                        "verified_median",
                        "inlier_sampson_px_median",
                        "detect_ms_per_image",
                        "match_verify_ms_per_pair",
                    ),
                )
            ],
            "track_accuracy.json": [
                Rows(
                    "rows",
                    (
                        "case",
                        "setting",
                        "tracks_measured",
                        "reprojection_median_px",
                        "tracks_over_3px",
                        "epipolar_median_px",
                    ),
                )
            ],
            "vanishing_yud.json": [
                Rows(
                    "results",
                    ("median_err_deg", "directions_under_2deg", "gt_segment_label_accuracy", "ms_per_image"),
                )
            ],
        },
    ),
    (
        "Mapping and bundle adjustment",
        {
            "ba_scale.json": [
                Keys(
                    (
                        "figures.n_keyframes",
                        "figures.n_points",
                        "figures.n_anchored_lines",
                        "figures.n_observations",
                        "figures.lm_iterations",
                        "figures.s_per_iteration_median",
                        "figures.lm_*_s_per_iteration",
                        "figures.n_line_factors_*",
                        "figures.line_linearize_*",
                        "figures.total_ba_s",
                        "figures.peak_rss_mib",
                    )
                )
            ],
            "keyframe_culling.json": [
                Rows(
                    "runs",
                    (
                        "recording",
                        "variant",
                        "keyframes",
                        "mapping_wall_s",
                        "timings_s.ba_full",
                        "ate_rmse_rel_path_pct",
                        "line_recall_1pct",
                        "line_precision_1pct",
                    ),
                )
            ],
            "line_diagnosis.json": [
                Rows(
                    "results",
                    (
                        "scene",
                        "ate_rel_path",
                        "eval_recall.1%",
                        "eval_precision.1%",
                        "recall_stages.visible",
                        "recall_stages.tracked",
                        "recall_stages.in map",
                    ),
                )
            ],
            "registration_lines.json": [
                Rows("rows", ("scene", "variant", "perturbation", "ate_pct_path", "rpe_rot_deg", "map_s"))
            ],
        },
    ),
    (
        "Line representations",
        {
            "line_representations.json": [
                Keys(("product_default", "ratios.*")),
                Rows("synthetic.small", ("time_cpu_s", "error_l", "error_l_median", "trans", "line_params")),
                Rows("synthetic.large", ("time_cpu_s", "error_l", "error_l_median", "trans", "line_params")),
                Rows("xu_line_sim.1.5", ("accuracy_cm", "time_cpu_s", "line_params")),
            ]
        },
    ),
    (
        "Accuracy",
        {
            "accuracy.json": [
                Rows(
                    "rows",
                    (
                        "scene",
                        "noise",
                        "variant",
                        "ate_rel_path",
                        "line_recall_1pct",
                        "line_precision_1pct",
                        "vertical_err_deg",
                        "map_s",
                    ),
                )
            ],
            "accuracy_final_completion.json": [SEEDED_ACCURACY_ROWS],
            "accuracy_frames.json": [SEEDED_ACCURACY_ROWS],
            "accuracy_video.json": [SEEDED_ACCURACY_ROWS],
            "handheld.json": [
                Rows("rows", ("scene", "seed", "variant", "ate_rel_path", "posed", "map_s", "reverse_kept"))
            ],
            **{
                name: [
                    Rows(
                        "sequences",
                        (
                            "papl.ate_rmse_m",
                            "papl.ate_rmse_pct_path",
                            "papl.wall_s",
                            "colmap.status",
                            "glomap.ate_rmse_m",
                            "glomap.wall_s",
                        ),
                    )
                ]
                for name in (
                    "real.json",
                    "real_step2.json",
                    "real_step2_offset1.json",
                    "real_step3.json",
                    "real_step3_offset1.json",
                    "real_step3_offset2.json",
                    "real_step4.json",
                )
            },
            "synthetic_peers.json": [
                Rows(
                    "sequences",
                    (
                        "papl.frames_posed",
                        "papl.ate_rmse_pct_path",
                        "papl_ablation.points-only.ate_rmse_pct_path",
                        "colmap.frames_posed",
                        "colmap.ate_rmse_pct_path",
                        "papl_on_colmap_frames.ate_rmse_pct_path",
                        "glomap.frames_posed",
                        "glomap.ate_rmse_pct_path",
                        "papl_on_glomap_frames.ate_rmse_pct_path",
                    ),
                )
            ],
            "real_shuffled.json": [
                Rows(
                    "sequences",
                    ("papl.frames_posed", "papl.ate_rmse_m", "colmap.ate_rmse_m", "glomap.ate_rmse_m"),
                )
            ],
            "scale.json": [
                Rows(
                    "synthetic",
                    ("scene", "noise", "marker_err_pct", "camera_height_err_pct", "length_err_pct"),
                )
            ],
        },
    ),
    (
        "Exports, map file and rendering",
        {
            "export.json": [Rows("formats", ("seconds", "peak_rss_mb", "file_size_mb"))],
            "export_libraries.json": [
                Keys(("segments", "points", "product.*")),
                *(
                    Rows(
                        f"writers.{w}",
                        ("seconds", "size_mb", "same_bytes_as_hand_written", "seconds_over_hand_written"),
                    )
                    for w in ("ply", "ply_ascii", "tubes_ply", "glb")
                ),
            ],
            "map_io.json": [
                Keys(("lines", "points", "save_s", "load_s", "validate_s", "file_mb", "*process_peak_rss_mb"))
            ],
            "render.json": [
                Keys(("segments", "points", "four_views_s", "four_views_peak_rss_mb", "report_s", "huge_*"))
            ],
            "viewer.json": [
                Rows(
                    "sizes",
                    (
                        "data_path.load_s",
                        "viewer_vtk_qt.first_frame_from_launch_s",
                        "viewer_vtk_qt.orbit_frame_median_s",
                        "viewer_vtk_qt.peak_rss_mib",
                        "open3d_gui.first_frame_from_launch_s",
                        "open3d_gui.orbit_frame_median_s",
                        "open3d_gui.error",
                    ),
                )
            ],
            "synth_render.json": [
                Rows("render", ("scene", "width", "height", "supersample", "msaa", "render_fps_cpu"))
            ],
        },
    ),
    (
        "Batch, memory and resume",
        {
            "batch.json": [
                Rows(
                    "results.corridor3s", ("recordings", "wall_s", "recordings_per_min", "peak_rss_MiB_max")
                ),
                Rows("results.engine_overhead_8_failing_recordings", ("recordings", "wall_s_per_recording")),
            ],
            "memory_long.json": [
                Rows("runs", ("variant", "seconds", "frames", "keyframes", "peak_rss_MiB", "wall_s"))
            ],
            "registration_scale.json": [
                Rows(
                    "runs",
                    (
                        "seconds",
                        "keyframes",
                        "revisits",
                        "registration_s",
                        "baseline_s",
                        "ratio",
                        "ms_per_keyframe",
                        "max_pose_difference",
                    ),
                )
            ],
            "resume.json": [
                Keys(
                    (
                        "fresh_run_s",
                        "resumed_from",
                        "resumed_run_s",
                        "checkpoints_total_MiB",
                        "checkpoints_write_share_of_stage_time_pct",
                    )
                )
            ],
        },
    ),
]
"""Area heading -> results file -> its headline tables, in order."""


def get(data: Any, dotted: str) -> Any:
    """The value at a dotted path (keys may themselves hold dots: the longest matching key wins)."""
    if dotted == "":
        return data
    if isinstance(data, dict):
        for k in sorted(
            (k for k in data if dotted == k or dotted.startswith(k + ".")), key=len, reverse=True
        ):
            rest = dotted[len(k) + 1 :]
            value = get(data[k], rest)
            if value is not None:
                return value
    return None


def flatten(data: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """(dotted path, leaf) of every scalar in `data`, lists indexed as `key[i]`."""
    if isinstance(data, dict):
        return [kv for k, v in data.items() for kv in flatten(v, f"{prefix}.{k}" if prefix else str(k))]
    if isinstance(data, list):
        return [kv for i, v in enumerate(data) for kv in flatten(v, f"{prefix}[{i}]")]
    return [(prefix, data)]


def fmt(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.4g}"
    if isinstance(value, list):
        return ", ".join(fmt(v) for v in value)
    return str(value).replace("|", "/").replace("\n", " ")


def table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + [
        "| " + " | ".join(r) + " |" for r in rows
    ]


def render(data: dict, spec: Rows | Keys) -> list[str]:
    if isinstance(spec, Keys):
        rows = [
            [f"`{k}`", fmt(v)]
            for k, v in flatten(data)
            if any(fnmatch.fnmatchcase(k, p) for p in spec.patterns) and not any(n in k for n in NOISE)
        ]
        return table(["key", "value"], rows) if rows else []
    entries = get(data, spec.path)
    if isinstance(entries, dict):
        items = [
            (k, v) for k, v in entries.items() if isinstance(v, dict) and (not spec.only or k in spec.only)
        ]
    elif isinstance(entries, list):
        items = [("", v) for v in entries if isinstance(v, dict)]
    else:
        return []
    keyed = any(k for k, _ in items)
    header = ([f"`{spec.path or 'key'}`"] if keyed else []) + [f"`{c}`" for c in spec.columns]
    rows = [([k] if keyed else []) + [fmt(get(v, c)) for c in spec.columns] for k, v in items]
    return table(header, rows)


def default_specs(data: dict) -> list[Rows | Keys]:
    """Headlines of a file no area names: its top-level numbers and lists of records (8 columns)."""
    specs: list[Rows | Keys] = []
    scalars = [k for k, v in data.items() if isinstance(v, int | float) and not any(n in k for n in NOISE)]
    if scalars:
        specs.append(Keys(tuple(scalars)))
    for k, v in data.items():
        if isinstance(v, list) and v and isinstance(v[0], dict):
            cols = [c for c, x in v[0].items() if not isinstance(x, dict | list)][:8]
            specs.append(Rows(k, tuple(cols)))
    return specs


def provenance(name: str, data: dict) -> str:
    machine = data.get("machine") if isinstance(data.get("machine"), dict) else {}
    commit = machine.get("git_commit") or data.get("commit") or data.get("git_commit")
    parts = [f"`benchmarks/results/{name}`"]
    script = ROOT / "benchmarks" / f"{Path(name).stem}.py"
    if script.exists():
        parts.append(f"written by `benchmarks/{script.name}`")
    if commit:
        parts.append(f"commit {str(commit)[:10]}")
    if data.get("date_utc"):
        parts.append(str(data["date_utc"]))
    if machine.get("cpu_model"):
        parts.append(f"{machine['cpu_model']}, {machine.get('nproc', '?')} cores")
    return "; ".join(parts)


def build(results: Path = RESULTS, notes: Path = NOTES) -> str:
    files = {p.name: json.loads(p.read_text()) for p in sorted(results.glob("*.json"))}
    named = [f for _, area in AREAS for f in area]
    if len(named) != len(set(named)):
        raise SystemExit("a results file is named in two areas of AREAS")
    out = [
        "# Benchmark results",
        "",
        "Generated by `benchmarks/results_md.py` from `benchmarks/results/*.json`; do not edit by hand.",
        "Each table holds headline numbers of one results file, as the benchmark wrote them (floats to four",
        "significant digits); the JSON has the rest, the settings and the machine. Re-run a benchmark, then",
        "this script.",
    ]
    other = {k: v for k, v in files.items() if k not in named}
    for heading, area in [*AREAS, ("Other results", {k: default_specs(v) for k, v in other.items()})]:
        present = [(f, specs) for f, specs in area.items() if f in files]
        if not present:
            continue
        out += ["", f"## {heading}"]
        for name, specs in present:
            data = files[name]
            out += ["", f"### {Path(name).stem}", "", provenance(name, data)]
            for spec in specs:
                lines = render(data, spec)
                if lines:
                    out += [""] + lines
    if notes.exists():  # measurements no results file holds (one-off runs, removed options), with sources
        out += ["", f"<!-- from benchmarks/results/{notes.name}, written by hand -->", ""]
        out.append(notes.read_text().rstrip())
    return "\n".join(out) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if RESULTS.md is not what the JSON gives")
    args = ap.parse_args()
    text = build()
    if args.check:
        if not OUT.exists() or OUT.read_text() != text:
            print(f"{OUT} is out of date: run benchmarks/results_md.py", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text)
    print("wrote", OUT)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
