"""open3d imported without its plotly drawing.

``open3d.visualization`` imports ``draw_plotly`` unconditionally, and with it plotly, dash, IPython, werkzeug,
pydantic and requests: about 600 modules, 0.35-0.4 of the import's 0.63-0.69 CPU s beside numpy, scipy and OpenCV
(0.28-0.30 without them), paid on every densify run. fullview never draws with plotly, so that one submodule is
replaced by a stand-in whose functions say so.
"""

from __future__ import annotations

import sys
import types
from typing import Any, Callable

PLOTLY_DRAWING = "open3d.visualization.draw_plotly"
PLOTLY_FUNCTIONS = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def open3d() -> types.ModuleType:
    """The open3d module (imported now if it is not yet), without its plotly drawing unless something imported
    open3d before."""
    if "open3d" not in sys.modules and PLOTLY_DRAWING not in sys.modules:
        stand_in = types.ModuleType(PLOTLY_DRAWING, "open3d's plotly drawing, not loaded by fullview")
        for name in PLOTLY_FUNCTIONS:
            setattr(stand_in, name, _not_loaded(name))
        sys.modules[PLOTLY_DRAWING] = stand_in
    import open3d as o3d
    return o3d


def _not_loaded(name: str) -> Callable[..., Any]:
    def call(*args: Any, **kwargs: Any) -> Any:
        raise RuntimeError(f"open3d.visualization.{name}: open3d's plotly drawing is not loaded in fullview "
                           "(fullview.sfm.open3d_module)")
    return call
