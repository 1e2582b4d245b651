"""Typed errors of papl-mapper. Library code raises these; only the CLI turns them into one line.

Every message names the file or object at fault and, where possible, what to do next.
"""

from __future__ import annotations


class PaplError(Exception):
    """Base of every error papl-mapper raises on purpose."""

    exit_code = 1


class InputError(PaplError):
    """A user-supplied file or argument is missing, unreadable or malformed."""

    exit_code = 2


class UnmappableError(InputError):
    """The recording holds no geometry to map (no parallax, no texture, too few frames).

    `T_cw_frames` holds the poses that could still be found (frame row -> T_cw; for a camera that
    only turns in place, its orientations), which the pipeline writes before reporting the error.
    """

    def __init__(self, message: str, T_cw_frames: dict | None = None):
        super().__init__(message)
        self.T_cw_frames = T_cw_frames or {}


class MapFormatError(InputError):
    """A map file is corrupt, truncated, of another version, or holds invalid values."""


class ConfigError(InputError):
    """A configuration file or --set override names an unknown key or holds a bad value."""


class OutputError(InputError):
    """An output cannot be written: its folder is missing or read-only, the disk is full, or the name
    is taken by something that is not a regular file (a folder, FIFO, device or socket)."""


class GeometryError(PaplError):
    """Degenerate geometry: a line parallel to the viewing ray, a zero-length segment, and the like."""

    exit_code = 3


class OptimizationError(PaplError):
    """An optimiser failed or produced non-finite values."""

    exit_code = 3


class BackendUnavailableError(PaplError):
    """A system facility (an off-screen renderer, a codec, an external tool) is not installed."""

    exit_code = 4
