"""The zoom: one instance cropped at full resolution in every camera and in the depth
pictures, each pixel magnified to a square block of screen pixels, so that a pose one pixel
off can be seen.

The selected instance's silhouette (the pixels its rendering covers) is drawn either as an
outline one screen pixel wide, just inside the silhouette's edge, or as a translucent fill.
:func:`zoom` also returns the same crops with the rendered part painted over the image (a
shaded rendering at the proposed pose); showing the two alternately ("blink") makes an
offset of one pixel jump to the eye.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from viewer.mosaic import Tile, grid, locate
from viewer.overlays import Panel, Prepared
from viewer.style import (
    UNEXPLAINED_COLOUR,
    Look,
    draw_missing,
    put_title,
    tint,
)

MARGIN_PX = 6  # full-resolution pixels kept around the instance
MIN_MAGNIFICATION = 2  # a one-pixel offset is hard to see at 1:1
MAX_MAGNIFICATION = 12


@dataclass
class Zoom:
    """The zoom pictures of one instance, RGB, with the tiles mapping them to camera pixels."""

    key: str
    image: np.ndarray  # the crops with the outline (or fill)
    tiles: list[Tile]
    #: draws :attr:`rendered`: only blinking needs it, so a repair does not wait for it
    paint: Callable[[], np.ndarray] = field(repr=False)
    _rendered: np.ndarray | None = field(default=None, init=False, repr=False)

    @property
    def rendered(self) -> np.ndarray:
        """The same crops with the rendered part painted over the image."""
        if self._rendered is None:
            self._rendered = self.paint()
        return self._rendered

    def locate(self, u: float, v: float) -> tuple[Tile, float, float] | None:
        """The tile under picture position (u, v) and the full-resolution pixel there."""
        return locate(self.tiles, u, v)


def _crop(
    panel: Panel, box: tuple[int, int, int, int], cell_w: int, cell_h: int
) -> tuple[int, int, int, int, int]:
    """(x0, y0, width, height, magnification) of the crop shown in a cell."""
    h, w = panel.image.shape[:2]
    bw, bh = box[2] - box[0] + 2 * MARGIN_PX, box[3] - box[1] + 2 * MARGIN_PX
    fit = min(cell_w // max(bw, 1), cell_h // max(bh, 1))
    m = int(max(1, min(MAX_MAGNIFICATION, max(MIN_MAGNIFICATION, fit), cell_w, cell_h)))
    cw, ch = min(w, cell_w // m), min(h, cell_h // m)
    cx, cy = (box[0] + box[2]) / 2.0, (box[1] + box[3]) / 2.0
    x0 = int(np.clip(round(cx - cw / 2.0), 0, w - cw))
    y0 = int(np.clip(round(cy - ch / 2.0), 0, h - ch))
    return x0, y0, cw, ch, m


def _magnify(img: np.ndarray, m: int) -> np.ndarray:
    """Each pixel as an m x m block (what ``np.repeat`` on both axes gives, several times
    faster)."""
    if m == 1:
        return img.copy()
    h, w = img.shape[:2]
    if img.dtype == bool:
        return _magnify(img.view(np.uint8), m).view(bool)
    return cv2.resize(img, (w * m, h * m), interpolation=cv2.INTER_NEAREST_EXACT)


def inner_outline(mask: np.ndarray) -> np.ndarray:
    """The pixels of ``mask`` with a 4-neighbour outside it: an outline one pixel wide. The
    border of the array is not an edge (the silhouette may go on beyond a crop)."""
    m8 = mask.astype(np.uint8)
    cross = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)
    eroded = cv2.erode(m8, cross, borderType=cv2.BORDER_REPLICATE)
    return mask & (eroded == 0)


def zoom(
    prep: Prepared, key: str, look: Look, width: int, height: int, *, fill: bool = False
) -> Zoom | None:
    """The zoom pictures of instance ``key``, ``width`` x ``height``; None if it is not in
    ``prep``. The rendered part (for blinking) is drawn when it is first asked for."""
    if key not in prep.keys:
        return None
    k = prep.keys.index(key)
    colour = look.colour(key)
    base = np.zeros((height, width, 3), np.uint8)
    tiles: list[Tile] = []
    crops: list[_Crop] = []
    for panel, cx0, cy0, cell_w, cell_h in _cells(prep, width, height):
        box = panel.layer.boxes[k]
        if box is None:
            _not_visible(base, f"{panel.name}: {key} not visible", cx0, cy0)
            continue
        x0, y0, cw, ch, m = _crop(panel, box, cell_w, cell_h)
        img = panel.image[y0 : y0 + ch, x0 : x0 + cw]
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
        mask = panel.layer.instance[y0 : y0 + ch, x0 : x0 + cw] == k
        if panel.is_depth and prep.unexplained is not None:
            tint(img, prep.unexplained[y0 : y0 + ch, x0 : x0 + cw], UNEXPLAINED_COLOUR, 0.6)
        crop = _Crop(panel, x0, y0, m, img.copy(), mask)
        if fill:
            tint(img, mask, colour, 0.35)
        big = _magnify(img, m)
        if not fill:
            # One screen pixel wide, just inside the magnified silhouette's edge.
            big[inner_outline(_magnify(mask, m))] = colour
        tile = Tile(
            panel.name,
            panel.camera,
            cx0 + (cell_w - cw * m) // 2,
            cy0 + (cell_h - ch * m) // 2,
            cw * m,
            ch * m,
            float(m),
            (float(x0), float(y0)),
        )
        _decorate(big, panel, tile, look)
        base[tile.y0 : tile.y0 + tile.height, tile.x0 : tile.x0 + tile.width] = big
        tiles.append(tile)
        crops.append(crop)
    image = cv2.cvtColor(base, cv2.COLOR_BGR2RGB)
    return Zoom(key, image, tiles, lambda: _rendered(image, crops, tiles, look, colour))


@dataclass
class _Crop:
    """What a tile of the zoom shows: its panel's crop (BGR, before any outline) and the
    instance's pixels there."""

    panel: Panel
    x0: int
    y0: int
    magnification: int
    image: np.ndarray
    mask: np.ndarray


def _cells(prep: Prepared, width: int, height: int) -> list[tuple[Panel, int, int, int, int]]:
    """Each panel with the cell of the grid it is shown in: (panel, x0, y0, width, height)."""
    panels = prep.panels
    aspect = max(p.image.shape[1] / p.image.shape[0] for p in panels)
    cols, rows = grid(len(panels), width, height, aspect)
    cell_w, cell_h = width // cols, height // rows
    return [
        (panel, (i % cols) * cell_w, (i // cols) * cell_h, cell_w, cell_h)
        for i, panel in enumerate(panels)
    ]


def _not_visible(img: np.ndarray, text: str, x0: int, y0: int) -> None:
    cv2.putText(
        img,
        text,
        (x0 + 10, y0 + 40),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.55,
        (200, 200, 200),
        1,
        cv2.LINE_AA,
    )


def _decorate(pic: np.ndarray, panel: Panel, tile: Tile, look: Look) -> None:
    """The unexplained regions or "no pose here" marks, and the title, on a tile's picture."""
    local = Tile(tile.name, tile.camera, 0, 0, tile.width, tile.height, tile.scale, tile.origin)
    if panel.is_depth:
        for r in look.regions:
            p0 = local.to_picture(r.box[0] - 0.5, r.box[1] - 0.5)
            p1 = local.to_picture(r.box[2] - 0.5, r.box[3] - 0.5)
            cv2.rectangle(
                pic, (int(p0[0]), int(p0[1])), (int(p1[0]), int(p1[1])), UNEXPLAINED_COLOUR, 1
            )
    else:
        for mk in look.missing:
            if mk.camera == panel.camera:
                draw_missing(pic, *local.to_picture(*mk.pixel))
    put_title(
        pic, f"{panel.name} x{int(tile.scale)}  ({int(tile.origin[0])}, {int(tile.origin[1])})"
    )


def _rendered(
    image: np.ndarray,
    crops: list[_Crop],
    tiles: list[Tile],
    look: Look,
    colour: tuple[int, int, int],
) -> np.ndarray:
    """The zoom's picture with the rendered part painted over each crop (RGB): the shaded
    rendering at the pose, in the instance's colour."""
    out = image.copy()  # the cells without a tile ("not visible") are the same
    for crop, tile in zip(crops, tiles):
        small = crop.image.copy()
        h, w = crop.mask.shape
        shade = crop.panel.layer.shade[crop.y0 : crop.y0 + h, crop.x0 : crop.x0 + w]
        small[crop.mask] = (shade[crop.mask, None] * (np.asarray(colour) / 255.0)).astype(np.uint8)
        paint = _magnify(small, crop.magnification)
        _decorate(paint, crop.panel, tile, look)
        ys, xs = slice(tile.y0, tile.y0 + tile.height), slice(tile.x0, tile.x0 + tile.width)
        out[ys, xs] = cv2.cvtColor(paint, cv2.COLOR_BGR2RGB)
    return out
