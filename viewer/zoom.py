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

from dataclasses import dataclass

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
    rendered: np.ndarray  # the same crops with the rendered part painted over the image
    tiles: list[Tile]

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
    return np.repeat(np.repeat(img, m, axis=0), m, axis=1)


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
    ``prep``."""
    if key not in prep.keys:
        return None
    k = prep.keys.index(key)
    panels = prep.panels
    colour = look.colour(key)
    base = np.zeros((height, width, 3), np.uint8)
    rendered = base.copy()
    tiles: list[Tile] = []
    aspect = max(p.image.shape[1] / p.image.shape[0] for p in panels)
    cols, rows = grid(len(panels), width, height, aspect)
    cell_w, cell_h = width // cols, height // rows
    for i, panel in enumerate(panels):
        cx0, cy0 = (i % cols) * cell_w, (i // cols) * cell_h
        box = panel.layer.boxes[k]
        if box is None:
            cv2.putText(
                base,
                f"{panel.name}: {key} not visible",
                (cx0 + 10, cy0 + 40),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.55,
                (200, 200, 200),
                1,
                cv2.LINE_AA,
            )
            rendered[cy0 : cy0 + cell_h, cx0 : cx0 + cell_w] = base[
                cy0 : cy0 + cell_h, cx0 : cx0 + cell_w
            ]
            continue
        x0, y0, cw, ch, m = _crop(panel, box, cell_w, cell_h)
        img = panel.image[y0 : y0 + ch, x0 : x0 + cw]
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
        mask = panel.layer.instance[y0 : y0 + ch, x0 : x0 + cw] == k
        if panel.is_depth and prep.unexplained is not None:
            tint(img, prep.unexplained[y0 : y0 + ch, x0 : x0 + cw], UNEXPLAINED_COLOUR, 0.6)
        big = _magnify(img, m)
        big_mask = _magnify(mask, m)
        paint = big.copy()
        shade = _magnify(panel.layer.shade[y0 : y0 + ch, x0 : x0 + cw], m)
        paint[big_mask] = (shade[big_mask, None] * (np.asarray(colour) / 255.0)).astype(np.uint8)
        if fill:
            tint(big, big_mask, colour, 0.35)
        else:
            big[inner_outline(big_mask)] = colour
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
        local = Tile(tile.name, tile.camera, 0, 0, tile.width, tile.height, tile.scale, tile.origin)
        for pic in (big, paint):
            if panel.is_depth:
                for r in look.regions:
                    p0 = local.to_picture(r.box[0] - 0.5, r.box[1] - 0.5)
                    p1 = local.to_picture(r.box[2] - 0.5, r.box[3] - 0.5)
                    cv2.rectangle(
                        pic,
                        (int(p0[0]), int(p0[1])),
                        (int(p1[0]), int(p1[1])),
                        UNEXPLAINED_COLOUR,
                        1,
                    )
            else:
                for mk in look.missing:
                    if mk.camera == panel.camera:
                        draw_missing(pic, *local.to_picture(*mk.pixel))
            put_title(pic, f"{panel.name} x{m}  ({x0}, {y0})")
        ys, xs = slice(tile.y0, tile.y0 + tile.height), slice(tile.x0, tile.x0 + tile.width)
        base[ys, xs] = big
        rendered[ys, xs] = paint
        tiles.append(tile)
    return Zoom(
        key, cv2.cvtColor(base, cv2.COLOR_BGR2RGB), cv2.cvtColor(rendered, cv2.COLOR_BGR2RGB), tiles
    )
