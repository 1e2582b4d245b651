"""The CLI: help everywhere, one error line and a non-zero exit for bad input."""

from __future__ import annotations

import subprocess
import sys

import pytest

from papl_mapper.cli import COMMANDS, main


def test_help_for_every_command(capsys):
    for name in COMMANDS:
        with pytest.raises(SystemExit) as exc:
            main([name, "--help"])
        assert exc.value.code == 0
        assert name in capsys.readouterr().out


def test_info_prints_summary(tmp_path, small_map, capsys):
    path = small_map.save(tmp_path / "m.papl")
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "vertical" in out and "keyframes      5" in out


def test_bad_map_is_one_line_and_nonzero(tmp_path):
    bad = tmp_path / "bad.papl"
    bad.write_bytes(b"\x00" * 100)
    proc = subprocess.run(
        [sys.executable, "-m", "papl_mapper.cli", "info", str(bad)], capture_output=True, text=True
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0
    assert "bad.papl" in proc.stderr and "Traceback" not in proc.stderr


def test_run_help_names_every_preset():
    """The preset list in `run --help` is written out (the parser does not import the pipeline)."""
    import argparse

    from papl_mapper.cli import run as run_cli
    from papl_mapper.pipelines.config import PRESETS

    parser = argparse.ArgumentParser()
    run_cli.add_parser(parser.add_subparsers())
    # argparse wraps long help at hyphens: compare without whitespace
    help_text = "".join(parser._subparsers._group_actions[0].choices["run"].format_help().split())
    for name in PRESETS:
        assert name in help_text, name
