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

from dataclasses import dataclass, field

import cv2
import numpy as np

from viewer.drawing.mosaic import Tile, grid, locate
from viewer.drawing.overlays import Panel, Prepared
from viewer.drawing.style import (
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
class ZoomTile:
    """One panel's crop in the zoom: its camera pixels as shown, where they are shown and
    the instance's pixels there (what the outline follows)."""

    tile: Tile
    panel: Panel
    x0: int  # the crop's corner, full-resolution pixels
    y0: int
    magnification: int
    plain: np.ndarray  # BGR crop, before the fill (what the rendered part is painted on)
    shown: np.ndarray  # BGR crop as shown: tinted where the instance is, in fill mode
    mask: np.ndarray  # the instance's pixels in the crop


@dataclass
class Zoom:
    """The zoom pictures of one instance: the crops of every panel at full resolution, the
    outline over them, and where the tiles map to camera pixels.

    The page gets them as layers (:func:`viewer.page.pictures.zoom_html`): each crop at its own
    resolution, magnified by the browser, and the outline and marks as vector shapes, so
    that a repair sends a few kilobytes where a picture of the whole zoom is hundreds.
    :attr:`image` is the same drawn in one picture: what the page shows."""

    key: str
    width: int
    height: int
    tiles: list[Tile]
    parts: list[ZoomTile]
    notes: list[tuple[str, int, int]]  # "not visible" texts and where they start
    look: Look
    colour: tuple[int, int, int]  # the instance's outline, BGR
    fill: bool  # a translucent fill instead of the outline
    _image: np.ndarray | None = field(default=None, init=False, repr=False)
    _rendered: np.ndarray | None = field(default=None, init=False, repr=False)

    @property
    def image(self) -> np.ndarray:
        """The zoom in one RGB picture: the crops magnified, with the outline (or fill)."""
        if self._image is None:
            self._image = _composite(self)
        return self._image

    @property
    def rendered(self) -> np.ndarray:
        """The same crops with the rendered part painted over the image (blinking)."""
        if self._rendered is None:
            self._rendered = _rendered(self)
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


def _kept_crop(
    part: ZoomTile | None, crop: tuple[int, int, int, int, int]
) -> tuple[int, int, int, int, int]:
    """``crop``, or ``part``'s crop where it is of the same size and magnification and its
    corner is within half the margin of ``crop``'s (the instance moved a pixel or two)."""
    if part is None:
        return crop
    x0, y0, cw, ch, m = crop
    h, w = part.mask.shape
    same = (cw, ch, m) == (w, h, part.magnification)
    if same and max(abs(x0 - part.x0), abs(y0 - part.y0)) <= MARGIN_PX // 2:
        return part.x0, part.y0, cw, ch, m
    return crop


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
    prep: Prepared,
    key: str,
    look: Look,
    width: int,
    height: int,
    *,
    fill: bool = False,
    keep: Zoom | None = None,
) -> Zoom | None:
    """The zoom pictures of instance ``key``, ``width`` x ``height``; None if it is not in
    ``prep``. Only the crops are made here; the picture in one piece and the rendered part
    (for blinking) are drawn when first asked for.

    ``keep``: the zoom shown before. Where it was on the same instance at the same size and
    a crop would move by a few pixels only (a repaired pose), its crop is kept: the
    reviewer sees the outline move over the image, not the image under the outline, and
    the page gets the same crop again."""
    if key not in prep.keys:
        return None
    k = prep.keys.index(key)
    colour = look.colour(key)
    parts: list[ZoomTile] = []
    notes: list[tuple[str, int, int]] = []
    before = {}
    if keep is not None and keep.key == key and (keep.width, keep.height) == (width, height):
        before = {p.panel.name: p for p in keep.parts}
    for panel, cx0, cy0, cell_w, cell_h in _cells(prep, width, height):
        box = panel.layer.boxes[k]
        if box is None:
            notes.append((f"{panel.name}: {key} not visible", cx0 + 10, cy0 + 40))
            continue
        crop = _crop(panel, box, cell_w, cell_h)
        x0, y0, cw, ch, m = _kept_crop(before.get(panel.name), crop)
        img = panel.image[y0 : y0 + ch, x0 : x0 + cw]
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img.copy()
        mask = panel.layer.instance[y0 : y0 + ch, x0 : x0 + cw] == k
        if panel.is_depth and prep.unexplained is not None:
            tint(img, prep.unexplained[y0 : y0 + ch, x0 : x0 + cw], UNEXPLAINED_COLOUR, 0.6)
        shown = img.copy()
        if fill:
            tint(shown, mask, colour, 0.35)
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
        parts.append(ZoomTile(tile, panel, x0, y0, m, img, shown, mask))
    tiles = [p.tile for p in parts]
    return Zoom(key, width, height, tiles, parts, notes, look, colour, fill)


def outline_rects(mask: np.ndarray, m: int) -> list[tuple[int, int, int, int]]:
    """The outline :func:`inner_outline` finds in ``mask`` magnified ``m`` times, as
    rectangles (x, y, width, height) of the magnified picture: one screen pixel wide along
    each edge between the mask and the rest, on the mask's side, runs of edges merged. The
    border of the array is not an edge."""
    mk = np.asarray(mask, bool)
    up = np.zeros_like(mk)  # an edge above the pixel
    up[1:] = mk[1:] & ~mk[:-1]
    down = np.zeros_like(mk)
    down[:-1] = mk[:-1] & ~mk[1:]
    left = np.zeros_like(mk)
    left[:, 1:] = mk[:, 1:] & ~mk[:, :-1]
    right = np.zeros_like(mk)
    right[:, :-1] = mk[:, :-1] & ~mk[:, 1:]
    rects = [(x * m, y * m, n * m, 1) for y, x, n in _runs(up)]
    rects += [(x * m, y * m + m - 1, n * m, 1) for y, x, n in _runs(down)]
    rects += [(x * m, y * m, 1, n * m) for x, y, n in _runs(left.T)]
    rects += [(x * m + m - 1, y * m, 1, n * m) for x, y, n in _runs(right.T)]
    return rects


def _runs(edges: np.ndarray) -> list[tuple[int, int, int]]:
    """(row, first column, length) of each run of True along the rows of ``edges``."""
    h, w = edges.shape
    # A zero after each row keeps runs from joining across rows; then runs start and end
    # at alternate changes of the flattened array.
    padded = np.zeros((h, w + 1), np.int8)
    padded[:, :w] = edges
    change = np.flatnonzero(np.diff(padded.ravel(), prepend=np.int8(0)))
    starts, ends = change[0::2], change[1::2]
    rows, cols = np.divmod(starts, w + 1)
    return list(zip(rows.tolist(), cols.tolist(), (ends - starts).tolist()))


def _composite(z: Zoom) -> np.ndarray:
    """The zoom in one RGB picture (see :attr:`Zoom.image`)."""
    base = np.zeros((z.height, z.width, 3), np.uint8)
    for text, x, y in z.notes:
        _not_visible(base, text, x, y)
    for part in z.parts:
        big = _magnify(part.shown, part.magnification)
        if not z.fill:
            # One screen pixel wide, just inside the magnified silhouette's edge.
            big[inner_outline(_magnify(part.mask, part.magnification))] = z.colour
        _decorate(big, part.panel, part.tile, z.look)
        t = part.tile
        base[t.y0 : t.y0 + t.height, t.x0 : t.x0 + t.width] = big
    return cv2.cvtColor(base, cv2.COLOR_BGR2RGB)


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


@dataclass(frozen=True)
class TileMarks:
    """What a zoom tile shows over its crop besides the outline, in the tile's own picture
    pixels (drawn into :attr:`Zoom.image` and sent to the page as SVG alike)."""

    title: str
    regions: list[tuple[int, int, int, int]]  # unexplained depth: x0, y0, x1, y1 inclusive
    missing: list[tuple[float, float]]  # "no pose here" marks' centres


def tile_marks(panel: Panel, tile: Tile, look: Look) -> TileMarks:
    """The title, unexplained regions (depth panels) or "no pose here" marks of a tile."""
    local = Tile(tile.name, tile.camera, 0, 0, tile.width, tile.height, tile.scale, tile.origin)
    regions: list[tuple[int, int, int, int]] = []
    missing: list[tuple[float, float]] = []
    if panel.is_depth:
        for r in look.regions:
            p0 = local.to_picture(r.box[0] - 0.5, r.box[1] - 0.5)
            p1 = local.to_picture(r.box[2] - 0.5, r.box[3] - 0.5)
            regions.append((int(p0[0]), int(p0[1]), int(p1[0]), int(p1[1])))
    else:
        missing = [local.to_picture(*mk.pixel) for mk in look.missing if mk.camera == panel.camera]
    title = f"{panel.name} x{int(tile.scale)}  ({int(tile.origin[0])}, {int(tile.origin[1])})"
    return TileMarks(title, regions, missing)


def _decorate(pic: np.ndarray, panel: Panel, tile: Tile, look: Look) -> None:
    """The unexplained regions or "no pose here" marks, and the title, on a tile's picture."""
    marks = tile_marks(panel, tile, look)
    for x0, y0, x1, y1 in marks.regions:
        cv2.rectangle(pic, (x0, y0), (x1, y1), UNEXPLAINED_COLOUR, 1)
    for x, y in marks.missing:
        draw_missing(pic, x, y)
    put_title(pic, marks.title)


def _rendered(z: Zoom) -> np.ndarray:
    """The zoom's picture with the rendered part painted over each crop (RGB): the shaded
    rendering at the pose, in the instance's colour."""
    out = z.image.copy()  # the cells without a tile ("not visible") are the same
    for part in z.parts:
        small = part.plain.copy()
        h, w = part.mask.shape
        shade = part.panel.layer.shade[part.y0 : part.y0 + h, part.x0 : part.x0 + w]
        paint_colour = np.asarray(z.colour) / 255.0
        small[part.mask] = (shade[part.mask, None] * paint_colour).astype(np.uint8)
        paint = _magnify(small, part.magnification)
        _decorate(paint, part.panel, part.tile, z.look)
        t = part.tile
        out[t.y0 : t.y0 + t.height, t.x0 : t.x0 + t.width] = cv2.cvtColor(paint, cv2.COLOR_BGR2RGB)
    return out
