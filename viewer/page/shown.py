"""What one page shows, kept so that a render remakes only what changed: the scene's
prepared overlays, the mosaic and the zoom made from them, what each was made for (scene,
poses, look, size), and which of them is on the canvas."""

from __future__ import annotations

from dataclasses import dataclass

from viewer.drawing.mosaic import Picture
from viewer.drawing.overlays import Prepared
from viewer.drawing.zoom import Zoom


@dataclass
class Shown:
    """A page's pictures (see the module docstring); its session's lock guards it."""

    prep: Prepared | None = None
    mosaic: tuple[str, Picture] | None = None  # (scene, picture)
    zoom: tuple[str, Zoom] | None = None  # (scene, zoom)
    mosaic_for: tuple | None = None  # what the mosaic was made for
    zoom_for: tuple | None = None  # what the zoom was made for
    on_canvas: tuple | None = None  # ("mosaic" | "zoom" | "none", what it was made for)

    def clear(self, on_canvas: tuple | None = None) -> None:
        """Forget every picture (a scene that cannot be shown, a page that closed)."""
        self.prep = self.mosaic = self.zoom = None
        self.mosaic_for = self.zoom_for = None
        self.on_canvas = on_canvas

    @property
    def zoomed(self) -> bool:
        """Whether the zoom is the picture on the canvas."""
        return self.on_canvas is not None and self.on_canvas[0] == "zoom"

    def on_screen(self) -> tuple[str, Picture | Zoom] | None:
        """(scene, picture) of the picture on the canvas, the mosaic or the zoom."""
        return self.zoom if self.zoomed else self.mosaic
