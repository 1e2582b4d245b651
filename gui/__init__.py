"""Off-screen previews, the HTML map report and the desktop viewer; import as papl_mapper.gui.

Public surface:
- `render_views(map, out_dir, options=None) -> PreviewResult`: isometric/top/front/side PNGs coloured by axis.
- `write_report(run_dir_or_map, out_path, gt_dir=None, options=None, previews=None) -> Path`: one
  self-contained HTML file (`previews`: already rendered ones to embed).
- The desktop viewer (`papl-map view`): `viewer_window.open_viewer`, with its data path in
  `viewer_scene`, the 2D panel in `viewer_walk`, picking in `viewer_pick` and the scripted-control
  hook in `viewer_control`; Qt is imported only when a window opens.
pyvista/VTK and matplotlib are imported only when rendering, so importing this package is cheap.
"""

from .preview import PreviewOptions, PreviewResult, find_offscreen_backend, render_views
from .report import ReportOptions, build_report_html, load_run, write_report

__all__ = [
    "PreviewOptions",
    "PreviewResult",
    "ReportOptions",
    "build_report_html",
    "find_offscreen_backend",
    "load_run",
    "render_views",
    "write_report",
]
