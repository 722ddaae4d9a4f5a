"""Scene warnings from annotation.json, as the viewer shows them.

``warnings`` is a list. Older files hold plain strings; newer ones hold objects with a
``kind`` and a ``message``, and for ``unexplained_depth`` (measured depth that no posed part
explains: often a part without a pose) a list of ``regions``::

    {"kind": "unexplained_depth", "message": "...",
     "regions": [{"box": [x0, y0, x1, y1], "pixels": 812, "depth_mm": [431.0, 447.5]}]}

Boxes are on the depth camera's pixel grid, end exclusive. The matching per-pixel mask is
``scenes/<id>/unexplained.png`` (nonzero = unexplained). Any warning makes a scene *flagged*.
Entries that are neither strings nor objects with a message are shown as their JSON text:
a warning is never dropped.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

UNEXPLAINED_DEPTH = "unexplained_depth"


@dataclass(frozen=True)
class DepthRegion:
    """A region of unexplained measured depth."""

    box: tuple[int, int, int, int]
    pixels: int | None = None
    depth_mm: tuple[float, float] | None = None

    def describe(self) -> str:
        x0, y0, x1, y1 = self.box
        out = f"x {x0}-{x1}, y {y0}-{y1}"
        if self.pixels is not None:
            out += f", {self.pixels} px"
        if self.depth_mm is not None:
            out += f", depth {self.depth_mm[0]:.0f}-{self.depth_mm[1]:.0f} mm"
        return out


@dataclass(frozen=True)
class SceneWarning:
    """One entry of annotation.json's ``warnings``."""

    kind: str
    message: str
    regions: tuple[DepthRegion, ...] = ()


def _region(rec: Any) -> DepthRegion | None:
    if not isinstance(rec, dict):
        return None
    try:
        box = tuple(int(round(float(v))) for v in rec["box"])
    except (KeyError, TypeError, ValueError):
        return None
    if len(box) != 4:
        return None
    pixels = rec.get("pixels")
    depth = rec.get("depth_mm")
    try:
        depth_mm = None if depth is None else (float(depth[0]), float(depth[1]))
    except (TypeError, ValueError, IndexError):
        depth_mm = None
    return DepthRegion(
        box,  # type: ignore[arg-type]
        int(pixels) if isinstance(pixels, (int, float)) and not isinstance(pixels, bool) else None,
        depth_mm,
    )


def parse_warnings(value: Any) -> tuple[SceneWarning, ...]:
    """The warnings of an annotation.json (its ``warnings`` value; None or absent: none)."""
    if not isinstance(value, list):
        return ()
    out = []
    for rec in value:
        if isinstance(rec, str):
            out.append(SceneWarning("note", rec))
        elif isinstance(rec, dict) and isinstance(rec.get("message") or rec.get("kind"), str):
            kind = str(rec.get("kind") or "note")
            regions = rec.get("regions") if isinstance(rec.get("regions"), list) else []
            out.append(
                SceneWarning(
                    kind,
                    str(rec.get("message") or kind.replace("_", " ")),
                    tuple(r for r in map(_region, regions) if r is not None),
                )
            )
        else:
            out.append(SceneWarning("note", json.dumps(rec)))
    return tuple(out)


def depth_regions(warnings: tuple[SceneWarning, ...]) -> tuple[DepthRegion, ...]:
    """Every unexplained-depth region of the warnings."""
    return tuple(r for w in warnings if w.kind == UNEXPLAINED_DEPTH for r in w.regions)
