"""Printable marker sheets at true scale (PNG pages at a stated DPI, and one PDF).

Each marker is drawn as its printed square (black border included) of side ``size`` mm,
labelled with its id, instance and site, on A4 pages with 8 mm margins; every page carries a
50 mm scale bar to check the printer did not rescale.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from annotator.io.atomic import write_bytes
from annotator.io.images import write_png
from annotator.markers.texture import marker_image

A4_MM = (210.0, 297.0)


@dataclass(frozen=True)
class SheetMarker:
    marker_id: int
    label: str


def render_pages(
    dictionary: str, markers: Sequence[SheetMarker], *, size_mm: float, dpi: int
) -> list[np.ndarray]:
    """Render A4 pages (uint8 grey, portrait) holding every marker at true scale."""
    px_per_mm = dpi / 25.4
    w, h = (round(A4_MM[0] * px_per_mm), round(A4_MM[1] * px_per_mm))
    margin = round(8 * px_per_mm)
    side = round(size_mm * px_per_mm)
    cell_w = side + round(6 * px_per_mm)
    cell_h = side + round(9 * px_per_mm)
    cols = max(1, (w - 2 * margin) // cell_w)
    rows = max(1, (h - 2 * margin - round(14 * px_per_mm)) // cell_h)
    per_page = cols * rows
    font = 0.25 * px_per_mm / 11.8 * 2.0
    pages = []
    for start in range(0, max(len(markers), 1), per_page):
        page = np.full((h, w), 255, np.uint8)
        for k, m in enumerate(markers[start : start + per_page]):
            r, c = divmod(k, cols)
            x, y = margin + c * cell_w, margin + r * cell_h
            page[y : y + side, x : x + side] = marker_image(dictionary, m.marker_id, side)
            cv2.putText(
                page,
                m.label,
                (x, y + side + round(4 * px_per_mm)),
                cv2.FONT_HERSHEY_SIMPLEX,
                font,
                0,
                max(1, dpi // 150),
                cv2.LINE_AA,
            )
        # Scale bar: 50 mm with 10 mm ticks.
        y0 = h - margin - round(4 * px_per_mm)
        x0 = margin
        bar = round(50 * px_per_mm)
        cv2.line(page, (x0, y0), (x0 + bar, y0), 0, max(1, dpi // 100))
        for t in range(6):
            xt = x0 + round(t * 10 * px_per_mm)
            cv2.line(page, (xt, y0 - round(2 * px_per_mm)), (xt, y0), 0, max(1, dpi // 150))
        cv2.putText(
            page,
            f"50 mm  (print at 100%, {size_mm:g} mm markers, {dictionary})",
            (x0 + bar + round(3 * px_per_mm), y0),
            cv2.FONT_HERSHEY_SIMPLEX,
            font,
            0,
            max(1, dpi // 150),
            cv2.LINE_AA,
        )
        pages.append(page)
    return pages


def write_sheets(folder: Path, pages: Sequence[np.ndarray], *, dpi: int) -> None:
    """``sheet_NN.png`` per page and ``markers.pdf`` with all pages at true scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.backends.backend_pdf import PdfPages

    for k, page in enumerate(pages, start=1):
        write_png(folder / f"sheet_{k:02d}.png", page)
    buf = io.BytesIO()
    with PdfPages(buf) as pdf:
        for page in pages:
            fig = plt.figure(figsize=(A4_MM[0] / 25.4, A4_MM[1] / 25.4), dpi=dpi)
            ax = fig.add_axes((0, 0, 1, 1))
            ax.imshow(page, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
            ax.set_axis_off()
            pdf.savefig(fig, dpi=dpi)
            plt.close(fig)
    write_bytes(folder / "markers.pdf", buf.getvalue())
