"""summary.json from the typed RunSummary: the keys the report, batch rows and benchmarks read."""

from __future__ import annotations

import pytest

from papl_mapper.pipelines.summary import MappingStats, RecordingInfo, RunSummary


def test_mapped_summary_is_one_flat_table():
    stats = MappingStats(frames_unregistered=2, keyframes_registered=9, ba_points={"iterations": 3})
    s = RunSummary(
        recording=RecordingInfo("v.mp4", "abc", 75, fps=30.0, width=640, height=480, stopped_early=False),
        frontend={"frames": 75},
        camera={"fx": 1.0},
        counts={"keyframes": 9},
        frames_lost=0,
        mapping=stats,
        timings_s={"frontend": 1.0},
        checkpoints_written={},
        per_frame={"frame": [0]},
    ).to_dict()
    assert s["status"] == "mapped" and s["resumed"] is None  # null, not missing, when not resumed
    assert s["recording"] == {
        "path": "v.mp4",
        "sha256": "abc",
        "frames": 75,
        "fps": 30.0,
        "width": 640,
        "height": 480,
        "stopped_early": False,
    }
    assert s["keyframes_registered"] == 9 and s["ba_points"] == {"iterations": 3}
    assert "ba" not in s and "focal_check" not in s and "error" not in s  # stages that did not run


def test_unmapped_summary_says_why():
    s = RunSummary(
        recording=RecordingInfo("v.mp4", "abc", 40),
        frontend={},
        status="unmapped",
        error="no motion",
        frames_posed=40,
    ).to_dict()
    assert list(s) == ["status", "error", "recording", "frames_posed", "frontend"]


def test_mapping_stats_round_trip_through_a_checkpoint():
    stats = MappingStats(completion={"merged": 1}, axis_update=["axis 2 merged"])
    assert MappingStats.from_dict(stats.as_dict()) == stats
    with pytest.raises(ValueError, match="unknown keys"):
        MappingStats.from_dict({"bogus": 1})
