"""Which frames of a source become the sequence's frames: every N-th, less the frames too
blurred to read.

Sharpness is the variance of the Laplacian of the grey image (after a light 3x3 smoothing,
so that sensor noise does not count as detail). What is "too blurred" depends on the scene,
the lens and the light, so each frame is compared with its own sequence: a frame is dropped
when its sharpness is below ``threshold`` times the running median of the candidates around
it (a centred window of :data:`WINDOW` candidates, itself included). Motion blur of a hand
moving the camera comes and goes within a few frames, which the median of a window that wide
does not follow.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from annotator.io.images import to_gray8

#: Default: a frame with less than half the sharpness of its neighbours' median is dropped.
BLUR_THRESHOLD = 0.5
#: Candidates in the running median's window (odd: centred on the frame).
WINDOW = 15


def sharpness(img: np.ndarray) -> float:
    """Variance of the Laplacian of the image (grey, 8-bit, lightly smoothed): high for a
    sharp image, low for a blurred one (any size, grey or colour, 8/16-bit)."""
    grey = cv2.GaussianBlur(to_gray8(img), (3, 3), 0)
    lap = cv2.Laplacian(grey, cv2.CV_32F)
    return float(np.var(lap, dtype=np.float64))


def running_median(values: Sequence[float], window: int = WINDOW) -> np.ndarray:
    """The median of each value's centred window of ``window`` values (fewer at the ends:
    the window is moved inside the sequence, or the whole sequence when shorter).

    >>> running_median([1.0, 9.0, 2.0, 3.0, 100.0], window=3).tolist()
    [2.0, 2.0, 3.0, 3.0, 3.0]
    """
    v = np.asarray(values, np.float64)
    n = len(v)
    w = min(window, n)
    out = np.empty(n)
    for i in range(n):
        lo = min(max(i - w // 2, 0), n - w)
        out[i] = np.median(v[lo : lo + w])
    return out


@dataclass(frozen=True)
class Selection:
    """What was kept of the candidates (source frames ``0, every, 2 * every...``).

    Attributes:
        candidates: The source indices looked at.
        sharpness: Each candidate's sharpness.
        reference: Each candidate's running median.
        kept: The source indices kept, in order.
        blurred: The source indices dropped as too blurred.
    """

    candidates: tuple[int, ...]
    sharpness: tuple[float, ...]
    reference: tuple[float, ...]
    kept: tuple[int, ...]
    blurred: tuple[int, ...]

    def of(self, index: int) -> float:
        """The sharpness of candidate ``index`` (a source index)."""
        return self.sharpness[self.candidates.index(index)]


def candidates(count: int, every: int) -> list[int]:
    """The source indices looked at: every ``every``-th of ``count`` frames, from the first."""
    return list(range(0, count, every))


def select(
    indices: Sequence[int],
    values: Sequence[float],
    *,
    threshold: float = BLUR_THRESHOLD,
    window: int = WINDOW,
) -> Selection:
    """Keep the candidates ``indices`` whose sharpness ``values`` is at least ``threshold``
    times their running median (``threshold`` 0 keeps them all).

    >>> s = select([0, 2, 4, 6, 8], [10.0, 11.0, 2.0, 9.0, 12.0], window=5)
    >>> s.kept, s.blurred
    ((0, 2, 6, 8), (4,))
    """
    ref = running_median(values, window) if len(values) else np.zeros(0)
    keep = [v >= threshold * r for v, r in zip(values, ref)]
    return Selection(
        tuple(int(i) for i in indices),
        tuple(float(v) for v in values),
        tuple(float(r) for r in ref),
        tuple(int(i) for i, k in zip(indices, keep) if k),
        tuple(int(i) for i, k in zip(indices, keep) if not k),
    )
