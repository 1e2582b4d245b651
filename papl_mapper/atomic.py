"""Atomic output files and the output-path policy: write under a temporary name beside the target,
then rename over it.

Policy (`output_target`): only a regular file is ever replaced. A symbolic link is followed and its
real target is written (the link stays a link); a name held by a folder, FIFO, device or socket is
refused with an OutputError, as is a missing or read-only folder, and a write that fails (disk full)
leaves the old file whole.

`tempfile.mkstemp` creates files readable by the owner only; outputs get the mode a plain
`open(path, "w")` would give (the existing file's mode, else 0666 minus the umask).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

from papl_mapper.errors import OutputError

_KINDS = {
    stat.S_IFDIR: "a folder",
    stat.S_IFIFO: "a FIFO (named pipe)",
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
    stat.S_IFSOCK: "a socket",
}


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def output_mode(path: Path) -> int:
    """The permission bits a new (or rewritten) output file at `path` should have."""
    return path.stat().st_mode & 0o7777 if path.exists() else 0o666 & ~_umask()


def output_target(path: str | os.PathLike) -> Path:
    """The file an output named `path` is written to (a link's real target), checked against the policy.

    Raises OutputError naming `path` when the target is not a regular file or its folder is missing
    or not writable.
    """
    path = Path(path)
    target = Path(os.path.realpath(path)) if path.is_symlink() else path
    try:
        mode = target.stat().st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:
        raise OutputError(f"{path}: cannot be written ({exc.strerror or exc})") from exc
    if mode is not None and not stat.S_ISREG(mode):
        kind = _KINDS.get(stat.S_IFMT(mode), "not a regular file")
        hint = "give a file name" if stat.S_ISDIR(mode) else "papl-map only replaces regular files"
        raise OutputError(f"{path}: is {kind}; {hint}")
    parent = target.parent if str(target.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"{path}: the folder {parent} does not exist; create it first")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{path}: the folder {parent} is not writable")
    return target


def check_output_dir(path: str | os.PathLike) -> Path:
    """`path` as an output folder: an existing writable folder, or a name that can be created."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{path}: exists and is not a folder; give an output folder")
    existing = path
    while not existing.exists():
        existing = existing.parent if existing != existing.parent else Path(".")
    if not existing.is_dir():
        raise OutputError(f"{path}: {existing} is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise OutputError(f"{path}: cannot write in {existing} (read-only or no permission)")
    return path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path beside `path`'s target; on success it replaces the target, on failure it
    is removed. OSErrors while writing it (disk full) become an OutputError naming `path`."""
    path = Path(path)
    target = output_target(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix, dir=target.parent)
    except OSError as exc:
        raise OutputError(f"{path}: cannot write in {target.parent} ({exc.strerror or exc})") from exc
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, output_mode(target))
        os.replace(tmp, target)
    except OutputError as exc:  # a nested atomic write into our temporary file: name the real output
        Path(tmp).unlink(missing_ok=True)
        if tmp in str(exc):
            raise OutputError(str(exc).replace(tmp, str(path))) from exc
        raise
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        if exc.filename not in (None, tmp, str(target)):
            raise  # about another file (an input read while writing this one)
        raise OutputError(f"{path}: could not write the file ({exc.strerror or exc})") from exc
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def move_into_place(source: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Rename the finished file `source` (on the same file system) over the output `path`, under the same
    policy as `atomic_path` (a link's target is replaced; a folder, FIFO or device is refused)."""
    target = output_target(path)
    try:
        os.replace(source, target)
    except OSError as exc:
        raise OutputError(f"{path}: could not write the file ({exc.strerror or exc})") from exc
    return Path(path)


def move_dir_into_place(source: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Rename the finished folder `source` (on the same file system) over the folder `path`, replacing
    an earlier one; a file, link or device at `path` is refused."""
    target = Path(path)
    if target.is_symlink() or (target.exists() and not target.is_dir()):
        raise OutputError(f"{path}: is not a folder; refusing to replace it")
    try:
        if target.exists():
            shutil.rmtree(target)
        os.replace(source, target)
    except OSError as exc:
        raise OutputError(f"{path}: could not write the folder ({exc.strerror or exc})") from exc
    return target
