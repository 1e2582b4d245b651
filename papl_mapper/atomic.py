"""Atomic output files: write under a temporary name beside the target, then rename over it.

`tempfile.mkstemp` creates files readable by the owner only; outputs get the mode a plain
`open(path, "w")` would give (the existing file's mode, else 0666 minus the umask).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def output_mode(path: Path) -> int:
    """The permission bits a new (or rewritten) output file at `path` should have."""
    return path.stat().st_mode & 0o7777 if path.exists() else 0o666 & ~_umask()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success it replaces `path`, on failure it is removed."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=suffix, dir=path.parent if str(path.parent) else "."
    )
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, output_mode(path))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
