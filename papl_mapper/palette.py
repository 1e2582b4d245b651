"""The one axis palette: every exporter, preview and report colours axes from here.

Okabe-Ito colours (colour-blind safe). The vertical axis is always blue, horizontal axes
take the remaining colours in order, unanchored lines are grey.
"""

from __future__ import annotations

import numpy as np

VERTICAL_RGB: tuple[int, int, int] = (0, 114, 178)  # blue
UNANCHORED_RGB: tuple[int, int, int] = (150, 150, 150)  # grey
HORIZONTAL_RGB: tuple[tuple[int, int, int], ...] = (
    (230, 159, 0),  # orange
    (0, 158, 115),  # bluish green
    (213, 94, 0),  # vermillion
    (204, 121, 167),  # reddish purple
    (240, 228, 66),  # yellow
    (86, 180, 233),  # sky blue
    (0, 0, 0),  # black
)
#: A second palette for users who ask for strongly saturated colours.
VIVID_HORIZONTAL_RGB: tuple[tuple[int, int, int], ...] = (
    (228, 26, 28),
    (77, 175, 74),
    (152, 78, 163),
    (255, 127, 0),
    (166, 86, 40),
    (247, 129, 191),
)
PALETTES = {"okabe-ito": HORIZONTAL_RGB, "vivid": VIVID_HORIZONTAL_RGB}


def axis_colors(n_axes: int, vertical_index: int | None, palette: str = "okabe-ito") -> np.ndarray:
    """RGB uint8 colours (n_axes, 3): the vertical axis blue, the others in palette order."""
    try:
        horizontal = PALETTES[palette]
    except KeyError as exc:
        raise ValueError(f"unknown palette {palette!r}; choose one of {sorted(PALETTES)}") from exc
    colors = np.empty((n_axes, 3), dtype=np.uint8)
    k = 0
    for a in range(n_axes):
        if a == vertical_index:
            colors[a] = VERTICAL_RGB
        else:
            colors[a] = horizontal[k % len(horizontal)]
            k += 1
    return colors


def line_colors(
    axis_of_line: np.ndarray, n_axes: int, vertical_index: int | None, palette: str = "okabe-ito"
) -> np.ndarray:
    """RGB uint8 colours (M, 3) for lines labelled with an axis index, or -1 for unanchored."""
    table = np.vstack([axis_colors(n_axes, vertical_index, palette), np.array([UNANCHORED_RGB])])
    idx = np.where(axis_of_line < 0, n_axes, axis_of_line)
    return table[idx.astype(np.int64)]


def axis_names(n_axes: int, vertical_index: int | None) -> list[str]:
    """Human names: 'vertical' and 'horizontal 1..k' in axis order."""
    names, k = [], 0
    for a in range(n_axes):
        if a == vertical_index:
            names.append("vertical")
        else:
            k += 1
            names.append(f"horizontal {k}")
    return names


def hex_color(rgb) -> str:
    """'#rrggbb' for an RGB triple of 0..255 integers."""
    r, g, b = (int(c) for c in rgb)
    return f"#{r:02x}{g:02x}{b:02x}"
