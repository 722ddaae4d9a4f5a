"""The main picture: every panel of a scene (cameras, depth, disagreement) in one image of
exactly the browser's viewport size, with the proposed poses' silhouette contours coloured by
decision, and the way back from a pixel of that image to a full-resolution camera pixel.

Sizing the picture to the viewport (not to the images) keeps the JPEG small and lets the
page show it one screen pixel per image pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from viewer.drawing.overlays import Panel, Prepared
from viewer.drawing.style import (
    FLAG_COLOUR,
    SELECTED_COLOUR,
    UNEXPLAINED_COLOUR,
    Look,
    draw_missing,
    label,
    put_label,
    put_title,
    tint,
)

_SHIFT = 4  # cv2 fixed-point bits: contours are drawn to 1/16 px


@dataclass(frozen=True)
class Tile:
    """Where a panel's pixels sit in a picture: full-resolution pixel ``origin + (u - x0 +
    0.5) / scale - 0.5`` is shown at picture column ``u`` (pixel centres at integers)."""

    name: str
    camera: str
    x0: int
    y0: int
    width: int
    height: int
    scale: float
    origin: tuple[float, float] = (0.0, 0.0)

    def contains(self, u: float, v: float) -> bool:
        return self.x0 - 0.5 <= u < self.x0 + self.width - 0.5 and (
            self.y0 - 0.5 <= v < self.y0 + self.height - 0.5
        )

    def to_full(self, u: float, v: float) -> tuple[float, float]:
        """Picture position to full-resolution pixel of ``camera``."""
        return (
            self.origin[0] + (u - self.x0 + 0.5) / self.scale - 0.5,
            self.origin[1] + (v - self.y0 + 0.5) / self.scale - 0.5,
        )

    def to_picture(self, x: float, y: float) -> tuple[float, float]:
        """Full-resolution pixel of ``camera`` to picture position."""
        return (
            self.x0 + (x - self.origin[0] + 0.5) * self.scale - 0.5,
            self.y0 + (y - self.origin[1] + 0.5) * self.scale - 0.5,
        )


@dataclass
class Picture:
    """An RGB picture made of tiles."""

    image: np.ndarray
    tiles: list[Tile]

    @property
    def nbytes(self) -> int:
        return int(self.image.nbytes)

    def locate(self, u: float, v: float) -> tuple[Tile, float, float] | None:
        """The tile under picture position (u, v) and the full-resolution pixel there."""
        return locate(self.tiles, u, v)


def locate(tiles: list[Tile], u: float, v: float) -> tuple[Tile, float, float] | None:
    """The tile of ``tiles`` under picture position (u, v) and the full-resolution pixel
    there, or None."""
    for t in tiles:
        if t.contains(u, v):
            x, y = t.to_full(u, v)
            return t, x, y
    return None


def grid(count: int, width: int, height: int, aspect: float) -> tuple[int, int]:
    """Columns and rows for ``count`` panels of ``aspect`` (w/h) that make them largest in
    ``width`` x ``height``."""
    best, best_scale = (1, max(count, 1)), -1.0
    for cols in range(1, max(count, 1) + 1):
        rows = -(-count // cols)
        cell_w, cell_h = width / cols, height / rows
        s = min(cell_w / aspect, cell_h)
        if s > best_scale + 1e-9:
            best, best_scale = (cols, rows), s
    return best


def _contour_points(c: np.ndarray, tile: Tile) -> np.ndarray:
    pts = (c + 0.5) * tile.scale - 0.5
    return np.round(pts * (1 << _SHIFT)).astype(np.int32)


def draw_panel(img: np.ndarray, panel: Panel, tile: Tile, prep: Prepared, look: Look) -> None:
    """Contours, labels, unexplained depth and "no pose here" marks on a scaled panel."""
    layer = panel.layer
    if panel.is_depth and prep.unexplained is not None:
        small = cv2.resize(
            prep.unexplained.astype(np.float32),
            (img.shape[1], img.shape[0]),
            interpolation=cv2.INTER_AREA,
        )
        tint(img, np.clip(small * 2.0, 0.0, 1.0), UNEXPLAINED_COLOUR, 0.85)
    if panel.is_depth:
        for r in look.regions:
            x0, y0 = tile.to_picture(r.box[0] - 0.5, r.box[1] - 0.5)
            x1, y1 = tile.to_picture(r.box[2] - 0.5, r.box[3] - 0.5)
            p0 = (int(x0 - tile.x0), int(y0 - tile.y0))
            p1 = (int(x1 - tile.x0), int(y1 - tile.y0))
            cv2.rectangle(img, p0, p1, UNEXPLAINED_COLOUR, 2)
    local = Tile(tile.name, tile.camera, 0, 0, tile.width, tile.height, tile.scale)
    for k, key in enumerate(prep.keys):
        if not layer.contours[k]:
            continue
        pts = [_contour_points(c, local) for c in layer.contours[k]]
        colour = look.colour(key)
        if key in look.flagged:
            cv2.polylines(img, pts, True, FLAG_COLOUR, 4, cv2.LINE_AA, _SHIFT)
        cv2.polylines(
            img,
            pts,
            True,
            SELECTED_COLOUR if key == look.selected else colour,
            2,
            cv2.LINE_AA,
            _SHIFT,
        )
    for k, key in enumerate(prep.keys):
        centre = layer.centres[k]
        if centre is not None:
            x, y = local.to_picture(*centre)
            text = label(key, key in look.flagged) + ("*" if key in look.edited else "")
            put_label(img, text, int(x) - 12, int(y), look.colour(key))
    if not panel.is_depth:
        for m in look.missing:
            if m.camera == panel.camera:
                draw_missing(img, *local.to_picture(*m.pixel))
    put_title(img, panel.name)


def layout(prep: Prepared, width: int, height: int) -> list[tuple[Panel, Tile]]:
    """Where each panel of ``prep`` goes in a ``width`` x ``height`` picture."""
    panels = prep.panels
    if not panels:
        return []
    aspect = max(p.image.shape[1] / p.image.shape[0] for p in panels)
    cols, rows = grid(len(panels), width, height, aspect)
    cell_w, cell_h = width // cols, height // rows
    out = []
    for i, panel in enumerate(panels):
        h, w = panel.image.shape[:2]
        s = min(cell_w / w, cell_h / h)
        tw, th = max(1, int(w * s)), max(1, int(h * s))
        x0 = (i % cols) * cell_w + (cell_w - tw) // 2
        y0 = (i // cols) * cell_h + (cell_h - th) // 2
        out.append((panel, Tile(panel.name, panel.camera, x0, y0, tw, th, tw / w)))
    return out


def compose(prep: Prepared, look: Look, width: int, height: int) -> Picture:
    """All panels of ``prep`` in one ``width`` x ``height`` RGB picture (kept in ``prep``
    for the last looks and sizes, within its bytes: made ahead of time, a switch only looks
    it up)."""
    key = (width, height, look)
    picture = prep.pictures.get(key)
    if picture is None:
        picture = _compose(prep, look, width, height)
        prep.pictures.put(key, picture)
    return picture


def forget(prep: Prepared, keep: set[tuple[int, int]]) -> None:
    """Drop what was drawn in ``prep`` for canvases of sizes other than ``keep`` (pages that
    have closed): their mosaics and their resized panels."""
    prep.pictures.drop(lambda key: (key[0], key[1]) not in keep)
    needed = {(p.name, t.width, t.height) for w, h in keep for p, t in layout(prep, w, h)}
    prep.resized.drop(lambda key: key not in needed)


def _compose(prep: Prepared, look: Look, width: int, height: int) -> Picture:
    out = np.zeros((height, width, 3), np.uint8)
    tiles: list[Tile] = []
    for panel, tile in layout(prep, width, height):
        img = prep.scaled(panel, tile.width, tile.height).copy()
        draw_panel(img, panel, tile, prep, look)
        out[tile.y0 : tile.y0 + tile.height, tile.x0 : tile.x0 + tile.width] = img
        tiles.append(tile)
    return Picture(cv2.cvtColor(out, cv2.COLOR_BGR2RGB), tiles)
