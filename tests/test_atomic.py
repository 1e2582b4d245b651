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


def test_move_dir_into_place_replaces_a_folder_and_refuses_a_file(tmp_path):
    """A finished staging folder takes the place of the earlier folder (whose files go with it); a file
    where the folder should be is refused with an OutputError naming it, and nothing moves."""
    from papl_mapper.atomic import move_dir_into_place

    target = tmp_path / "frames"
    target.mkdir()
    (target / "old.png").write_bytes(b"old")
    staged = tmp_path / ".frames.tmp"
    staged.mkdir()
    (staged / "new.png").write_bytes(b"new")
    assert move_dir_into_place(staged, target) == target
    assert sorted(p.name for p in target.iterdir()) == ["new.png"] and not staged.exists()
    blocker = tmp_path / "taken"
    blocker.write_text("a file")
    staged.mkdir()
    with pytest.raises(OutputError, match="taken"):
        move_dir_into_place(staged, blocker)
    assert staged.is_dir() and blocker.read_text() == "a file"
