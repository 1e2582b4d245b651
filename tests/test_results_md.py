"""benchmarks/RESULTS.md is what benchmarks/results_md.py builds from benchmarks/results/*.json."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _results_md():
    spec = importlib.util.spec_from_file_location("results_md", ROOT / "benchmarks" / "results_md.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("results_md", module)  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_results_md_is_up_to_date_and_covers_every_results_file():
    r = _results_md()
    text = r.build()
    assert (ROOT / "benchmarks" / "RESULTS.md").read_text() == text, "run benchmarks/results_md.py"
    for path in (ROOT / "benchmarks" / "results").glob("*.json"):
        assert f"`benchmarks/results/{path.name}`" in text


def test_numbers_come_from_the_json(tmp_path: Path):
    """A changed value in a results file changes the table, and nothing else is invented."""
    r = _results_md()
    (tmp_path / "map_io.json").write_text(
        '{"lines": 123, "save_s": 4.56789, "machine": {"git_commit": "abc"}}'
    )
    text = r.build(tmp_path)
    assert "| `lines` | 123 |" in text and "| `save_s` | 4.568 |" in text and "commit abc" in text
    (tmp_path / "new_benchmark.json").write_text('{"rows": [{"case": "a", "ms": 1.5}], "seconds": 2}')
    text = r.build(tmp_path)
    assert "## Other results" in text and "| a | 1.5 |" in text and "| `seconds` | 2 |" in text
