"""The HTML report: self-contained (no external references), complete, graceful on missing parts."""

from __future__ import annotations

import base64
import json
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from papl_mapper.errors import BackendUnavailableError, InputError
from papl_mapper.gui import ReportOptions, build_report_html, preview, write_report
from papl_mapper.gui.plots import stereonet_xy
from papl_mapper.gui.preview import PreviewOptions
from papl_mapper.map import Camera, Map

from .test_gui_preview import building_map

SMALL = PreviewOptions(width=400, height=300)


class _Collect(HTMLParser):
    """Collects tags, every URL-bearing attribute and the visible text."""

    def __init__(self) -> None:
        super().__init__()
        self.tags: list[str] = []
        self.urls: list[tuple[str, str, str]] = []
        self.text: list[str] = []
        self.styles: list[str] = []
        self._in_style = False

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        self._in_style = tag == "style"
        for k, v in attrs:
            if k in ("src", "href", "srcset", "data", "action", "poster", "background") or k.startswith(
                "xlink"
            ):
                self.urls.append((tag, k, v or ""))

    def handle_endtag(self, tag):
        if tag == "style":
            self._in_style = False

    def handle_data(self, data):
        (self.styles if self._in_style else self.text).append(data)


def _parse(text: str) -> _Collect:
    p = _Collect()
    p.feed(text)
    p.close()
    return p


def _assert_self_contained(p: _Collect) -> None:
    assert "script" not in p.tags and "link" not in p.tags and "iframe" not in p.tags
    for tag, attr, url in p.urls:
        assert url.startswith(("data:", "#")), f"<{tag} {attr}={url[:60]!r}> is an external reference"
    css = " ".join(p.styles)
    assert "@import" not in css and "url(" not in css


def _run_folder(tmp_path: Path, m: Map | None = None) -> Path:
    run = tmp_path / "run"
    run.mkdir()
    m = m or building_map()
    m.save(run / "map.papl")
    summary = {
        "recording": {
            "path": "walk.mp4",
            "frames": 120,
            "fps": 30.0,
            "width": 640,
            "height": 480,
            "sha256": "ab" * 32,
        },
        "timings_s": {"decode": 1.5, "frontend": 4.25, "mapping": 9.0, "global_ba": 3.125},
        "ba": {
            "initial_cost": 5000.0,
            "final_cost": 125.0,
            "iterations": 17,
            "time_s": 3.125,
            "rms": {"points_px": 0.61, "lines_px": 0.93},
        },
        "frames_lost": 3,
        "per_frame": {"frame": list(range(10)), "points": [50 + i for i in range(10)], "lines": [20] * 10},
    }
    (run / "summary.json").write_text(json.dumps(summary))
    c = m.keyframes.T_wc[:, :3, 3]
    rows = [
        f"{t:.6f} {x:.6f} {y:.6f} {z:.6f} 0 0 0 1"
        for t, (x, y, z) in zip(m.keyframes.timestamp, c, strict=True)
    ]
    (run / "trajectory.tum").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n")
    (run / "config.toml").write_text("[frontend]\nmax_features = 1500\n")
    (run / "log.txt").write_text("decoding <video>\nmapping done & saved\n")
    return run


def test_full_run_report_is_self_contained_and_complete(tmp_path):
    run = _run_folder(tmp_path)
    out = write_report(run, tmp_path / "report.html", options=ReportOptions(preview=SMALL))
    text = out.read_text()
    p = _parse(text)
    _assert_self_contained(p)
    body = " ".join(p.text)
    # four previews + three plots embedded as PNG data
    pngs = [u for _, a, u in p.urls if u.startswith("data:image/png;base64,")]
    assert len(pngs) == 7
    for heading in (
        "Previews",
        "Summary",
        "Axes and lines per axis",
        "Bundle adjustment",
        "Timings per stage",
        "Plots",
        "Ground truth comparison",
        "How to open the exports",
        "Configuration",
    ):
        assert heading in body
    m = building_map()
    per_axis = m.summary()["lines_per_axis"]
    assert per_axis == [40, 30, 25, 20]
    for name, n in zip(("vertical", "horizontal 1", "horizontal 2", "horizontal 3"), per_axis, strict=True):
        assert name in body and f"{n:,}" in body
    assert "walk.mp4" in body and "frames lost" in body
    assert "5,000" in body and "125" in body and "97.5 %" in body  # BA cost before/after and its reduction
    assert "global_ba" in body and "17.875" in body  # timings and their total
    assert "90.00°" in body and "30.00°" in body and "60.00°" in body  # angles between the axes
    assert "max_features = 1500" in body and "mapping done & saved" in body  # escaped, shown verbatim
    assert "not available" in body  # no --gt given
    assert "CloudCompare" in body and "usdview" in body


def test_bare_map_report_shows_not_available(tmp_path):
    path = building_map().save(tmp_path / "b.papl")
    text = build_report_html(path, options=ReportOptions(previews=False))
    p = _parse(text)
    _assert_self_contained(p)
    body = " ".join(p.text)
    assert body.count("not available") >= 5  # recording, BA, timings, config, log, previews, gt
    assert "horizontal 3" in body


def test_empty_map_report_says_so(tmp_path):
    m = Map(Camera(640, 480, 500.0, 500.0, 319.5, 239.5))
    out = write_report(m, tmp_path / "empty.html", options=ReportOptions(preview=SMALL))
    p = _parse(out.read_text())
    _assert_self_contained(p)
    body = " ".join(p.text)
    assert "This map is empty" in body
    assert "no principal axes" in body


def test_huge_map_decimation_is_reported(tmp_path):
    m = building_map(n_per_axis=(1500, 1000, 1000), length_per_axis=(1.0, 1.0, 1.0), n_unanchored=500)
    opts = ReportOptions(preview=PreviewOptions(width=400, height=300, max_lines=800))
    body = " ".join(_parse(build_report_html(m, options=opts)).text)
    assert "800 of 4,000 lines shown" in body


def test_broken_summary_and_trajectory_are_notes_not_failures(tmp_path):
    run = _run_folder(tmp_path)
    (run / "summary.json").write_text("{not json")
    (run / "trajectory.tum").write_text("0 1 2 3\n")
    (run / "keyframes.tum").unlink(missing_ok=True)
    body = " ".join(_parse(build_report_html(run, options=ReportOptions(previews=False))).text)
    assert "summary.json unreadable" in body
    assert "trajectory.tum: line 1" in body
    assert "no BA statistics" in body and "no timings" in body


def test_no_backend_still_writes_the_report(tmp_path, monkeypatch):
    def broken(env=None):
        raise BackendUnavailableError("no off-screen OpenGL backend works (simulated); install libegl1")

    monkeypatch.setattr(preview, "find_offscreen_backend", broken)
    out = write_report(building_map(), tmp_path / "r.html", options=ReportOptions(preview=SMALL))
    body = " ".join(_parse(out.read_text()).text)
    assert "previews were not rendered" in body and "libegl1" in body


def test_bad_sources_are_input_errors(tmp_path):
    with pytest.raises(InputError, match="no such run folder"):
        write_report(tmp_path / "nothing", tmp_path / "r.html")
    (tmp_path / "emptyrun").mkdir()
    with pytest.raises(InputError, match="no map.papl"):
        write_report(tmp_path / "emptyrun", tmp_path / "r.html")
    assert not (tmp_path / "r.html").exists()


def test_per_keyframe_counts_from_map_observations():
    """Without summary.json, counts per keyframe come from the map's observations."""
    from papl_mapper.gui.report import load_run, per_frame_counts

    from .conftest import make_map

    m = make_map(n_kf=5, n_pts=50, n_lines=30)  # points seen in keyframes 0 and 1, lines in keyframe 0
    x, series, label = per_frame_counts(load_run(m))
    np.testing.assert_array_equal(x, m.keyframes.frame_index)
    np.testing.assert_array_equal(series["points"], [50, 50, 0, 0, 0])
    np.testing.assert_array_equal(series["lines"], [30, 0, 0, 0, 0])
    assert "keyframe" in label


def test_stereonet_projection_known_values():
    xy = stereonet_xy(np.array([[0, 0, 1.0], [1, 0, 0], [0, -1, 0], [1, 0, -1], [-1, 0, 1]]))
    np.testing.assert_allclose(xy[0], [0, 0], atol=1e-12)  # vertical at the centre
    np.testing.assert_allclose(xy[1], [1, 0], atol=1e-12)  # horizontal on the rim
    np.testing.assert_allclose(xy[2], [0, -1], atol=1e-12)
    r45 = np.sqrt(1 - np.cos(np.pi / 4))  # equal area: r = sqrt(1 - cos(plunge from vertical))
    np.testing.assert_allclose(xy[3], [r45, 0], atol=1e-12)
    np.testing.assert_allclose(xy[4], [r45, 0], atol=1e-12)  # undirected: the opposite direction coincides
    # equal area: uniform directions fill the disc uniformly (half the points inside r = 1/sqrt(2))
    d = np.random.default_rng(0).normal(size=(20000, 3))
    r = np.linalg.norm(stereonet_xy(d), axis=1)
    assert abs((r < np.sqrt(0.5)).mean() - 0.5) < 0.02


def _gt_folder(tmp_path: Path, m: Map) -> Path:
    """A ground-truth folder in the agreed layout, made from the map itself."""
    gt = tmp_path / "gt_scene"
    (gt / "gt").mkdir(parents=True)
    m.save(gt / "gt" / "map.papl")
    c = m.keyframes.T_wc[:, :3, 3]
    rows = [
        f"{t:.6f} {x:.6f} {y:.6f} {z:.6f} 0 0 0 1"
        for t, (x, y, z) in zip(m.keyframes.timestamp, c, strict=True)
    ]
    (gt / "gt" / "trajectory.tum").write_text("\n".join(rows) + "\n")
    seg = m.lines.endpoints_w.reshape(-1, 6)
    lab = m.lines.axis_of_line()
    (gt / "gt" / "segments.txt").write_text(
        "# x1 y1 z1 x2 y2 z2 axis\n"
        + "\n".join(" ".join(f"{v:.6f}" for v in s) + f" {a}" for s, a in zip(seg, lab, strict=True))
    )
    (gt / "gt" / "axes.json").write_text(
        json.dumps(
            {
                "directions": m.axes.directions.tolist(),
                "vertical_index": 0,
                "names": ["vertical", "horizontal 1", "horizontal 2", "horizontal 3"],
            }
        )
    )
    (gt / "camera.json").write_text(json.dumps(m.camera.to_dict()))
    (gt / "scene.json").write_text(
        json.dumps({"scene": "test-building", "seed": 1, "command": "made by the test"})
    )
    (gt / "timestamps.txt").write_text("\n".join(f"{t:.6f}" for t in m.keyframes.timestamp) + "\n")
    return gt


def test_ground_truth_section_with_eval(tmp_path):
    m = building_map()
    run = _run_folder(tmp_path, m)
    gt = _gt_folder(tmp_path, m)
    text = build_report_html(run, gt_dir=gt, options=ReportOptions(previews=False))
    p = _parse(text)
    _assert_self_contained(p)
    body = " ".join(p.text)
    assert "ATE RMSE" in body and "matched poses" in body
    assert any(u.startswith("data:image/png") for _, _, u in p.urls)


def test_cli_report(tmp_path, capsys):
    from papl_mapper.cli import main

    run = _run_folder(tmp_path)
    assert main(["report", str(run), "--no-previews"]) == 0
    assert (run / "report.html").exists()
    assert main(["report", str(tmp_path / "missing")]) == 2
    assert "missing" in capsys.readouterr().err


def test_ground_truth_section_renders_the_agreed_eval_api(tmp_path, monkeypatch):
    """The report's use of `papl_mapper.eval.evaluate` per the agreed API, with a stand-in result."""
    import dataclasses

    import papl_mapper.eval as eval_pkg

    @dataclasses.dataclass
    class FakeResult:
        ate_rmse: float = 0.0123
        ate_rmse_rel_path: float = 0.0042
        rpe_trans: float = 0.0031
        rpe_rot_deg: float = 0.21
        scale: float = 1.75
        sim3: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(4))
        ate_per_pose: tuple = (np.linspace(10, 20, 11), np.linspace(0.0, 0.02, 11))
        line_recall: dict = dataclasses.field(default_factory=lambda: {"0.05": 0.81, "0.10": 0.93})
        line_precision: dict = dataclasses.field(default_factory=lambda: {"0.05": 0.77, "0.10": 0.9})
        axis_errors_deg: list = dataclasses.field(default_factory=lambda: [0.12, 0.34, 0.56])
        n_matched_poses: int = 11

        def table(self) -> str:
            return "ATE RMSE  0.0123 <aligned>"

    calls = []

    def fake_evaluate(gt_dir, result, trajectory_tum=None, config=None):
        calls.append((gt_dir, result, trajectory_tum))
        return FakeResult()

    monkeypatch.setattr(eval_pkg, "evaluate", fake_evaluate, raising=False)
    run = _run_folder(tmp_path)
    text = build_report_html(run, gt_dir=tmp_path / "gt", options=ReportOptions(previews=False))
    p = _parse(text)
    _assert_self_contained(p)
    body = " ".join(p.text)
    assert calls and calls[0][0] == tmp_path / "gt" and calls[0][2] == run / "trajectory.tum"
    assert isinstance(calls[0][1], Map)
    for s in (
        "0.0123",
        "0.0042",
        "1.75",
        "line recall @ 0.05",
        "0.81",
        "line precision @ 0.10",
        "0.34",
        "ATE RMSE  0.0123 <aligned>",
    ):
        assert s in body, s
    assert len([u for _, _, u in p.urls if u.startswith("data:image/png")]) == 4  # 3 plots + ATE over time

    def failing(*a, **k):
        raise InputError(f"{tmp_path / 'gt'}: gt/trajectory.tum missing")

    monkeypatch.setattr(eval_pkg, "evaluate", failing, raising=False)
    body = " ".join(
        _parse(build_report_html(run, gt_dir=tmp_path / "gt", options=ReportOptions(previews=False))).text
    )
    assert "gt/trajectory.tum missing" in body


def test_report_warns_of_guessed_camera_and_wrong_focal_length():
    from papl_mapper.gui.report import run_warnings

    assert run_warnings({"camera": {"guessed": False}, "focal_check": {"plausible": True}}) == []
    focal = {"plausible": False, "message": "focal length looks wrong"}
    w = run_warnings({"camera": {"guessed": True}, "focal_check": focal})
    assert len(w) == 2 and "guessed" in w[0] and w[1] == "focal length looks wrong"
    assert run_warnings(None) == []


def test_report_names_the_segments_mapped_apart_from_the_map():
    from papl_mapper.gui.report import run_warnings

    seg = {"frames": [0, 103], "folder": "segments/000000-000103", "frames_posed": 103, "points": 1434}
    (w,) = run_warnings({"segment_maps": [{**seg, "lines": 25}]})
    assert w.startswith("Frames 0-103 could not be joined to this map")
    assert "segments/000000-000103/ (103 frames posed, 1434 points, 25 lines)" in w
    assert run_warnings({"segment_maps": []}) == []


def test_the_summary_says_which_start_the_global_ba_kept() -> None:
    from papl_mapper.gui.report import _start_checks

    summary = {
        "rotation_check": {
            "pairs": 40,
            "residual_ba_deg": 0.41,
            "residual_averaged_deg": 0.05,
            "second_start": True,
            "kept": "averaged",
        },
        "reverse_check": {
            "keyframes": 20,
            "posed_backward": 20,
            "z": -12.26,
            "kept": "backward",
            "registration_s": 6.4,
            "in_worker": True,
        },
    }
    rows = dict(_start_checks(summary))
    assert (
        "0.410° (BA) and 0.050°" in rows["rotation check"] and "averaged start kept" in rows["rotation check"]
    )
    assert rows["second start"] == (
        "registered backwards (6.4 s in a worker process): backward poses kept (paired test over the "
        "tracks: z -12.3, negative favours the backward poses)"
    )
    summary["reverse_check"] = {
        "keyframes": 20,
        "posed_backward": 12,
        "z": None,
        "kept": "forward",
        "registration_s": 1.5,
        "in_worker": False,
    }
    assert dict(_start_checks(summary))["second start"] == (
        "registered backwards (1.5 s): 12 of the 20 keyframes posed, not compared"
    )
    assert _start_checks({}) == [] and _start_checks(None) == []


def test_previews_already_rendered_are_embedded_not_rendered_again(tmp_path, monkeypatch):
    """The run renders its previews once: the report embeds those files, with their notes."""
    m = building_map()
    res = preview.render_views(m, tmp_path / "previews", SMALL)
    res.notes.append("a note of the rendered previews")

    def no_render(*args, **kwargs):
        raise AssertionError("rendered again")

    monkeypatch.setattr("papl_mapper.gui.report.render_views", no_render)
    text = write_report(m, tmp_path / "r.html", previews=res).read_text()
    embedded = [url for tag, attr, url in _parse(text).urls if tag == "img"]
    for path in res.paths:
        assert any(base64.b64encode(path.read_bytes()).decode("ascii") in url for url in embedded)
    assert "a note of the rendered previews" in " ".join(_parse(text).text)
