"""Scene completeness: is every visible part explained by a pose, and are the images usable?

**Background.** What lies behind the parts: the dataset's background depth map (the empty bin
or support, captured once per rig and declared as ``rig.depth.background`` in dataset.yaml;
``annotator synth`` writes one), or else the support found in the scene's own depth
(:func:`fit_support`): the floor plane, and the other large planes (a bin's rim and walls).

**Unexplained depth.** A measured depth pixel is *unexplained* when it lies in front of the
background (by more than ``max(3 mm, 0.5%)``) and in front of every posed instance rendered at
its pose (by more than ``max(5 mm, 1%)``; where no instance is rendered, in front of nothing):
something is there that no pose accounts for. The mask is opened by one sample (thin slivers
along depth edges are sensor artefacts) and cut into 8-connected regions.

**The rule.** A region is reported (warning ``unexplained_depth``) when it covers at least
``min_region_fraction`` (0.3) of the smallest part's mean silhouette: the mean projected area
of its convex hull (a quarter of the hull's surface, Cauchy's formula) seen at the scene's
median depth. So a part at least a third visible is never left silent.

**Unread markers.** Candidate squares that could not be read, of a marker's size at their
depth, lying on a reported region, are listed with it: a part is there, its markers are
unreadable.

**Image quality**, per camera: ``edge_blur_px``, the blur (Gaussian sigma, px) that best
explains the candidate marker squares under a blur model
(:func:`annotator.detection.deblur.estimate_blur`), ``median``/``saturated``, the median
grey level (8-bit) and the fraction of saturated pixels, and ``marker_white``/``marker_black``,
the grey levels of the detected markers' printed white and black (:func:`marker_exposure`).
Warnings: ``blurred`` when the edge blur exceeds ``blur_warn_px`` (2.5 px: cells of 20 px
markers then merge); ``under_exposed`` judged on the markers where some were read — their
white below ``dark_marker_white`` (40) or their white-to-black contrast below
``min_marker_contrast`` (25): the corners drown in the noise — and on the image's median
(below 25) only where none was read (a dark bin floor filling the frame is no fault when the
markers on the parts are well exposed); ``over_exposed`` when more than 5% of the pixels are
saturated.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from annotator.dataset import Dataset
from annotator.dataset.figures import DepthRegion, ImageQuality, SceneWarning
from annotator.dataset.flags import WarningKind
from annotator.detection.aruco import ImageReading


@dataclass(frozen=True)
class CompletenessSettings:
    """Thresholds of the completeness checks (see the module docstring)."""

    background_tolerance_mm: float = 3.0
    background_tolerance_rel: float = 0.005
    pose_tolerance_mm: float = 5.0
    pose_tolerance_rel: float = 0.01
    min_region_fraction: float = 0.3
    blur_warn_px: float = 2.5
    dark_median: float = 25.0
    dark_marker_white: float = 40.0
    min_marker_contrast: float = 25.0
    saturated_fraction: float = 0.05


# ------------------------------------------------------------------------- background


def fit_support_plane(
    points: np.ndarray, *, inlier_mm: float = 3.0, far_share: float = 0.3, seed: int = 0
) -> tuple[np.ndarray, float] | None:
    """The plane the parts rest on, ``n . x = d`` (unit ``n``, ``d > 0``, camera frame), from
    the measured points (..., 3) (NaN where none); None with too few points.

    In a bin the floor is mostly hidden by the parts and the most populated plane is often
    the bin's rim, in front of them. So the plane is fitted by RANSAC to the farthest
    ``far_share`` of the points only, among planes facing the camera (within 45 degrees).
    """
    pts = points.reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 50:
        return None
    far = pts[pts[:, 2] >= np.quantile(pts[:, 2], 1.0 - far_share)]
    rng = np.random.default_rng(seed)
    sample = far[rng.choice(len(far), min(len(far), 8000), replace=False)]
    return _ransac_plane(sample, inlier_mm, rng, min_facing=np.cos(np.radians(45.0)))


def _ransac_plane(
    sample: np.ndarray,
    inlier_mm: float,
    rng: np.random.Generator,
    *,
    iterations: int = 150,
    min_facing: float = 0.0,
) -> tuple[np.ndarray, float] | None:
    """The plane with the most inliers whose normal makes at least ``min_facing`` (cosine)
    with the optical axis, refined by least squares on its inliers."""
    best, best_count = None, -1
    trio = rng.integers(0, len(sample), (iterations, 3))
    for i, j, k in trio:
        n = np.cross(sample[j] - sample[i], sample[k] - sample[i])
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        n /= norm
        if abs(n[2]) < min_facing:
            continue
        count = int(np.sum(np.abs(sample @ n - n @ sample[i]) < inlier_mm))
        if count > best_count:
            best, best_count = (n, float(n @ sample[i])), count
    if best is None:
        return None
    n, d = best
    inl = sample[np.abs(sample @ n - d) < inlier_mm]
    c = inl.mean(axis=0)
    n = np.linalg.svd(inl - c, full_matrices=False)[2][-1]
    d = float(n @ c)
    return (n, d) if d > 0 else (-n, -d)


def support_pixels(
    points: np.ndarray,
    floor: tuple[np.ndarray, float] | None,
    *,
    inlier_mm: float = 3.0,
    min_share: float = 0.02,
    seed: int = 0,
) -> np.ndarray:
    """Pixels of a grid of measured points (H, W, 3) that belong to the setting rather than
    to parts: large planes other than the floor (a bin's rim and walls), found one after the
    other by RANSAC, of which only the connected pieces that come within 12% of the image
    border and span at least 30% of the image count (after an opening that cuts the thin lines
    where planes cross parts). Parts do not reach across 30% of the image; faces of several parts
    that happen to lie in one plane are not connected to the border."""
    h, w = points.shape[:2]
    ok = np.isfinite(points).all(axis=2)
    out = np.zeros((h, w), bool)
    idx = np.flatnonzero(ok.ravel())
    if len(idx) < 50:
        return out
    rng = np.random.default_rng(seed)
    sample = points.reshape(-1, 3)[idx[rng.choice(len(idx), min(len(idx), 8000), replace=False)]]
    if floor is not None:
        sample = sample[np.abs(sample @ floor[0] - floor[1]) >= inlier_mm]
    kernel = np.ones((5, 5), np.uint8)
    for _ in range(6):
        if len(sample) < 50:
            break
        plane = _ransac_plane(sample, inlier_mm, rng)
        if plane is None:
            break
        n, d = plane
        on_sample = np.abs(sample @ n - d) < inlier_mm
        if on_sample.sum() < min_share * 8000:
            break
        sample = sample[~on_sample]
        with np.errstate(invalid="ignore"):
            on = (np.abs(points @ n - d) < inlier_mm).astype(np.uint8)
        on = cv2.morphologyEx(on, cv2.MORPH_OPEN, kernel)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(on, connectivity=8)
        for k in range(1, count):
            x, y, bw, bh = (int(v) for v in stats[k, :4])
            if _border_band(x, y, bw, bh, w, h):
                out |= labels == k
    return out


def plane_depth(plane: tuple[np.ndarray, float], rays: np.ndarray) -> np.ndarray:
    """z-depth where rays ``(x, y, 1)`` (..., 3) meet the plane (inf where they miss it)."""
    n, d = plane
    denom = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(denom > 1e-9, d / denom, np.inf)
    return z


def support_depth(measured: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """The setting's depth (mm) where no background capture exists: the support plane found
    in ``measured`` (inf where there is none), with the bin's rim and walls, which are
    setting and not parts, at their measured depth. ``rays``: the pixels' ``(x, y, 1)``."""
    points = rays * measured[..., None]
    plane = fit_support_plane(points)
    background = plane_depth(plane, rays) if plane is not None else np.full(measured.shape, np.inf)
    return np.where(support_pixels(points, plane), measured, background)


# ------------------------------------------------------------------- unexplained depth


def unexplained_mask(
    measured: np.ndarray,
    background: np.ndarray,
    rendered: np.ndarray,
    settings: CompletenessSettings = CompletenessSettings(),
) -> np.ndarray:
    """Pixels whose measured depth (mm, NaN = none) lies in front of the background and of
    every posed instance (``rendered``: the nearest rendered depth, inf where none)."""
    s = settings
    bg_tol = np.maximum(s.background_tolerance_mm, s.background_tolerance_rel * measured)
    pose_tol = np.maximum(s.pose_tolerance_mm, s.pose_tolerance_rel * measured)
    with np.errstate(invalid="ignore"):
        mask = (
            np.isfinite(measured)
            & (measured < background - bg_tol)
            & (measured < rendered - pose_tol)
        )
    return cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0


def mean_silhouette_mm2(vertices: np.ndarray) -> float:
    """Mean projected area (mm^2) of a part over all viewing directions: a quarter of its
    convex hull's surface area (Cauchy's formula)."""
    from scipy.spatial import ConvexHull

    return float(ConvexHull(vertices).area) / 4.0


def find_regions(
    mask: np.ndarray,
    measured: np.ndarray,
    *,
    step: int,
    min_pixels: float,
    skip_border_bands: bool = False,
    owned: np.ndarray | None = None,
) -> tuple[list[DepthRegion], np.ndarray]:
    """Connected regions of ``mask`` (on a grid of every ``step``-th pixel) with at least
    ``min_pixels`` full-resolution pixels. With ``skip_border_bands``, pieces of a bin's wall
    are dropped: regions within 12% of the image border that reach across 30% of the image
    or run along that border (parts in the bin do not reach there). Regions with more than half their pixels in ``owned`` are dropped (they
    belong to an instance already flagged). Returns the regions and the mask of the kept
    ones."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    area = step * step
    kept = np.zeros(mask.shape, bool)
    out = []
    for k in range(1, n):
        px = int(stats[k, cv2.CC_STAT_AREA]) * area
        if px < min_pixels:
            continue
        sel = labels == k
        z = measured[sel]
        x, y, w, h = (int(v) for v in stats[k, :4])
        if skip_border_bands and _border_band(x, y, w, h, *mask.shape[::-1]):
            continue
        if owned is not None and owned[sel].mean() > 0.5:
            continue
        kept |= sel
        lo, hi = np.percentile(z, [5, 95])
        out.append(
            DepthRegion(
                (x * step, y * step, (x + w) * step, (y + h) * step),
                px,
                (round(float(lo), 1), round(float(hi), 1)),
            )
        )
    return out, kept


def _border_band(x: int, y: int, w: int, h: int, width: int, height: int) -> bool:
    """A box within 12% of the image border that reaches across 30% of the image, or lies
    along that border at least 2.5 times longer than wide: a piece of a bin's wall."""
    top_bottom = y <= 0.12 * height or y + h >= 0.88 * height
    left_right = x <= 0.12 * width or x + w >= 0.88 * width
    if not (top_bottom or left_right):
        return False
    if max(w / width, h / height) >= 0.3:
        return True
    return (top_bottom and w >= 2.5 * h) or (left_right and h >= 2.5 * w)


# ------------------------------------------------------------------------ image quality


def exposure(gray: np.ndarray) -> tuple[float, float]:
    """Median grey level and fraction of saturated pixels (>= 250) of an 8-bit image.

    Both from the histogram (what ``np.median`` gives: the mean of the two middle levels of
    an even count; it sorted a million pixels for it), OpenCV's: numpy's ``bincount`` takes
    twice as long. (Its float32 counts are exact up to 2**24 pixels.)"""
    hist = cv2.calcHist([np.ascontiguousarray(gray)], [0], None, [256], [0, 256])
    counts = np.cumsum(hist.ravel().astype(np.int64))
    n = int(counts[-1])
    lower = int(np.searchsorted(counts, (n - 1) // 2, side="right"))
    upper = int(np.searchsorted(counts, n // 2, side="right"))
    saturated = n - int(counts[249])
    return (lower + upper) / 2.0, saturated / n


def quality_warnings(
    quality: dict[str, ImageQuality], settings: CompletenessSettings = CompletenessSettings()
) -> list[SceneWarning]:
    """``blurred`` / ``under_exposed`` / ``over_exposed`` warnings from per-camera figures."""
    out = []
    blurred = {
        c: q.edge_blur_px
        for c, q in quality.items()
        if q.edge_blur_px is not None and q.edge_blur_px > settings.blur_warn_px
    }
    if blurred:
        message = (
            "images blurred (edge blur "
            + ", ".join(f"{c} {v:.1f} px" for c, v in blurred.items())
            + f", above {settings.blur_warn_px} px): markers may be unreadable"
        )
        out.append(SceneWarning(WarningKind.BLURRED, message, cameras=tuple(sorted(blurred))))
    dark = {c: why for c, q in quality.items() if (why := _too_dark(q, settings))}
    if dark:
        message = "images too dark: " + ", ".join(f"{c} ({why})" for c, why in dark.items())
        out.append(SceneWarning(WarningKind.UNDER_EXPOSED, message, cameras=tuple(dark)))
    bright = [
        c
        for c, q in quality.items()
        if q.saturated is not None and q.saturated > settings.saturated_fraction
    ]
    if bright:
        message = (
            f"images over-exposed (more than {settings.saturated_fraction:.0%} "
            "of the pixels saturated): " + ", ".join(bright)
        )
        out.append(SceneWarning(WarningKind.OVER_EXPOSED, message, cameras=tuple(bright)))
    return out


def _too_dark(q: ImageQuality, settings: CompletenessSettings) -> str | None:
    """Why ``q``'s image is under-exposed (the markers' levels where it has them, else its
    median), or None."""
    if q.marker_white is not None and q.marker_black is not None:
        if q.marker_white < settings.dark_marker_white:
            return f"markers' white at grey level {q.marker_white:.0f}, below {settings.dark_marker_white:g}"
        contrast = q.marker_white - q.marker_black
        if contrast < settings.min_marker_contrast:
            return (
                f"markers' contrast {contrast:.0f} grey levels, below "
                f"{settings.min_marker_contrast:g}"
            )
        return None
    if q.median is not None and q.median < settings.dark_median:
        return f"median grey level {q.median:.0f}, below {settings.dark_median:g}, no marker read"
    return None


def marker_exposure(gray: np.ndarray, quads: list[np.ndarray]) -> tuple[float, float] | None:
    """The printed white and black of the markers (8-bit grey levels): each quad (4, 2) is
    warped to a square of its cells, its outer ring (the black border) gives the black,
    the brightest quarter of its inner cells the white; the medians over the markers. None
    without a quad.

    >>> import numpy as np
    >>> img = np.full((40, 40), 10, np.uint8); img[12:28, 12:28] = 200
    >>> white, black = marker_exposure(img, [np.array([[6, 6], [33, 6], [33, 33], [6, 33.0]])])
    >>> round(white), round(black)
    (200, 10)
    """
    if not quads:
        return None
    side = 48  # px of the warped square: 8 px a cell of a 4x4 marker with its border
    ring = side // 6
    square = np.array([[0, 0], [side, 0], [side, side], [0, side]], np.float32)
    patches = np.stack(
        [
            cv2.warpPerspective(
                gray,
                cv2.getPerspectiveTransform(np.asarray(q, np.float32) + 0.5, square),
                (side, side),
                flags=cv2.INTER_LINEAR,
            )
            for q in quads
        ]
    )
    # The cell edges blur into their neighbours: keep each ring's middle. Every marker's
    # levels in one call (each row's percentile is the one it had alone).
    inner = patches[:, ring + 2 : side - ring - 2, ring + 2 : side - ring - 2]
    border = np.concatenate(
        [patches[:, 1 : ring - 1], patches[:, side - ring + 1 : side - 1]], axis=1
    )
    whites = np.percentile(inner.reshape(len(quads), -1), 85, axis=1)
    blacks = np.median(border.reshape(len(quads), -1), axis=1)
    return float(np.median(whites)), float(np.median(blacks))


def image_quality(
    ds: Dataset, readings: list[ImageReading], grays: list[np.ndarray]
) -> dict[str, ImageQuality]:
    """Per camera, the blur the detector measured and the exposure of the image and of its
    markers."""
    out = {}
    for cam, reading, gray in zip(ds.rig.cameras, readings, grays):
        median, saturated = exposure(gray)
        blur = None if reading.blur_px is None else round(reading.blur_px, 2)
        levels = marker_exposure(gray, [m.corners for m in reading.markers if not m.soft])
        out[cam.name] = ImageQuality(
            blur,
            round(median, 4),
            round(saturated, 4),
            marker_white=None if levels is None else round(levels[0], 2),
            marker_black=None if levels is None else round(levels[1], 2),
        )
    return out
