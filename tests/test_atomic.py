"""papl_mapper.atomic: the one way outputs are put in place."""

from __future__ import annotations

from pathlib import Path

import pytest

from papl_mapper.atomic import move_into_place
from papl_mapper.errors import OutputError


def test_move_into_place_replaces_a_file_and_follows_a_link(tmp_path: Path):
    src = tmp_path / "running.log"
    src.write_text("new")
    (tmp_path / "old.txt").write_text("old")
    (tmp_path / "log.txt").symlink_to(tmp_path / "old.txt")
    assert move_into_place(src, tmp_path / "log.txt") == tmp_path / "log.txt"
    assert (tmp_path / "log.txt").is_symlink() and (tmp_path / "old.txt").read_text() == "new"
    assert not src.exists()


def test_move_into_place_refuses_a_folder(tmp_path: Path):
    src = tmp_path / "running.log"
    src.write_text("new")
    (tmp_path / "log.txt").mkdir()
    with pytest.raises(OutputError, match="is a folder"):
        move_into_place(src, tmp_path / "log.txt")
    assert src.read_text() == "new"
