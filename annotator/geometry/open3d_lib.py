"""open3d, as the tool imports it: without its plotly/dash notebook viewer.

``import open3d`` also imports ``open3d.visualization.draw_plotly``, which loads plotly and
dash, the larger part of open3d's start-up, for a notebook viewer this tool never uses. Every
module takes open3d from here (``from annotator.geometry.open3d_lib import o3d``), so that
viewer is replaced by a stand-in whose functions say it is not loaded. When open3d was already
imported (by the user's own code), it is left as it is.
"""

from __future__ import annotations

import sys
import types
from typing import Any, NoReturn

_VIEWER = "open3d.visualization.draw_plotly"

if "open3d" not in sys.modules and _VIEWER not in sys.modules:

    def _not_loaded(*_: Any, **__: Any) -> NoReturn:
        raise RuntimeError(
            "open3d's plotly viewer is not loaded in a process that imported annotator first; "
            "import open3d before annotator to use it"
        )

    _stand_in = types.ModuleType(_VIEWER)
    for _name in ("get_plotly_fig", "draw_plotly", "draw_plotly_server"):
        setattr(_stand_in, _name, _not_loaded)
    sys.modules[_VIEWER] = _stand_in

import open3d as _open3d  # noqa: E402  (after the stand-in, on purpose)

#: open3d, typed as Any: its stubs describe its C++ overloads, not what it takes from numpy.
o3d: Any = _open3d

__all__ = ["o3d"]
