"""Exporters: one module per file format, registered by suffix; import as papl_mapper.exporters.

    from papl_mapper.exporters import export, ExportOptions
    export(map, "out.glb", parts=("lines", "points"))

Every format is a pure function `(Map, ExportOptions) -> bytes` (a folder format such as COLMAP
text returns `{file name: bytes}`), listed in `REGISTRY` by suffix; `export` writes atomically.
"""

from .registry import (
    FOLDER_FORMATS,
    REGISTRY,
    check_available,
    check_target,
    export,
    suffix_of,
    supported_suffixes,
    write_atomic,
)
from .scene import PARTS, ExportOptions, ExportScene, prepare

__all__ = [
    "FOLDER_FORMATS",
    "PARTS",
    "REGISTRY",
    "check_available",
    "ExportOptions",
    "ExportScene",
    "check_target",
    "export",
    "prepare",
    "suffix_of",
    "supported_suffixes",
    "write_atomic",
]
