"""Optional libraries: which extra of pyproject.toml installs each, and the one way the product imports them.

The core (mapping, the map file, PLY/glTF/OBJ/COLMAP/TUM exports) needs none of these; rendering, USD,
DXF, the viewer and Ray import them when used, so a missing one is a BackendUnavailableError naming the
extra to install, at the moment the feature is asked for.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from papl_mapper.errors import BackendUnavailableError

EXTRAS: dict[str, tuple[str, str]] = {
    "pyvista": ("render", "pyvista"),
    "vtkmodules": ("render", "vtk"),
    "matplotlib": ("render", "matplotlib"),
    "PIL": ("render", "pillow"),
    "pxr": ("usd", "usd-core"),
    "ezdxf": ("dxf", "ezdxf"),
    "PySide6": ("viewer", "pyside6-essentials"),
    "pyvistaqt": ("viewer", "pyvistaqt"),
    "ray": ("ray", "ray"),
}
"""Top-level module -> (extra, pip package)."""


def install_hint(module: str) -> str:
    """What to install for `module` (a top-level name in EXTRAS)."""
    extra, package = EXTRAS[module]
    return f"{package} (the '{extra}' extra), which is not installed: pip install 'papl-mapper[{extra}]'"


def require(module: str, feature: str) -> ModuleType:
    """Import `module` (or a submodule of one in EXTRAS) for `feature`, e.g. "USD export".

    A missing library raises BackendUnavailableError naming the extra; a library that is installed
    but fails to load (a missing system library) raises it with the loader's message.
    """
    top = module.split(".")[0]
    if top not in EXTRAS:
        raise KeyError(f"{top} is not an optional library of papl-mapper")
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        missing = (exc.name or "").split(".")[0]
        if missing not in EXTRAS:  # something the library itself needs
            raise BackendUnavailableError(f"{feature}: {module} could not be imported ({exc})") from exc
        raise BackendUnavailableError(f"{feature} needs {install_hint(missing)}") from exc
    except ImportError as exc:
        raise BackendUnavailableError(f"{feature}: {module} is installed but does not load ({exc})") from exc
