"""Which corners and views of a rig calibration's joint fit are outliers (:mod:`.rig`, steps
4-5): corners far beyond their camera's noise, views that lose many of them or fit far worse
than their camera's others, and views of another moment than their shot's others."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from annotator.calibration.records import CalibrationSettings

#: A view whose RMS in the joint fit is over this many times its camera's RMS alone ...
MOMENT_FACTOR = 2.0
#: ... and this many pixels more is of another moment than its shot (:class:`_Moments`).
MOMENT_MARGIN_PX = 0.25


def inliers(
    err: np.ndarray,
    keep: np.ndarray,
    view_index: np.ndarray,
    n_views: int,
    opts: CalibrationSettings,
    view_camera: np.ndarray | None = None,
    moments: Moments | None = None,
) -> tuple[np.ndarray, dict[int, str]]:
    """Corners to keep after a refinement with residual norms ``err``, and the views dropped
    as a whole (index -> reason). Each camera is judged by its own noise (``view_camera``:
    the camera of each view), never below the rig's nor above three times it: a camera
    whose corners are noisier (a board seen through the paper) keeps its good corners, and
    one that runs off is not excused."""
    if view_camera is None:
        view_camera = np.zeros(n_views, np.int64)
    corner_camera = view_camera[view_index]
    # The norm of a 2D Gaussian residual has median 1.1774 sigma.
    rig_sigma = float(np.median(err[keep])) / 1.1774
    sigma = np.full(int(view_camera.max(initial=0)) + 1, rig_sigma)
    for c in np.unique(corner_camera[keep]).tolist():
        own = float(np.median(err[keep & (corner_camera == c)])) / 1.1774
        sigma[c] = min(max(own, rig_sigma), 3.0 * rig_sigma)
    limits = np.maximum(opts.outlier_sigmas * sigma, opts.min_outlier_px)
    ok = err <= limits[corner_camera]
    counts = np.bincount(view_index, minlength=n_views)
    good = np.bincount(view_index, weights=ok, minlength=n_views)
    sq = np.bincount(view_index, weights=np.where(ok, err**2, 0.0), minlength=n_views)
    rms = np.sqrt(sq / np.maximum(good, 1))
    present = counts > 0
    view_limits = {}
    for c in np.unique(view_camera[present]).tolist():
        mine = present & (good > 0) & (view_camera == c)
        median_rms = float(np.median(rms[mine])) if np.any(mine) else 0.0
        view_limits[c] = max(3.0 * median_rms, 1.0)
    dropped: dict[int, str] = {}
    for i in np.flatnonzero(present).tolist():
        lost = counts[i] - good[i]
        limit = float(limits[view_camera[i]])
        view_limit = view_limits[int(view_camera[i])]
        if good[i] < opts.min_corners or lost > 0.25 * counts[i]:
            dropped[i] = (
                f"outlier residuals: {int(lost)} of its {counts[i]} corners off by more than "
                f"{limit:.2f} px"
            )
            if lost == counts[i]:
                dropped[i] += " (an image of another moment, or the board moved during the shot?)"
        elif rms[i] > view_limit:
            dropped[i] = (
                f"outlier residuals: RMS {rms[i]:.2f} px, over {view_limit:.2f} px "
                "(three times the median view's of its camera)"
            )
    if moments is not None:
        was_kept = np.bincount(view_index, weights=keep, minlength=n_views) > 0
        fitted = present & (good > 0)
        dropped.update(
            moments.other_moments(rms, fitted, was_kept, dropped, view_camera, opts.min_shots)
        )
    ok &= ~np.isin(view_index, list(dropped))
    return ok, dropped


@dataclass(frozen=True)
class Moments:
    """Views of a shot taken at another moment than the rest of the shot's (webcams that are
    not synchronised, a board held by hand): such a view fits its own camera as well as any,
    and the rig only with the board moved. A view whose RMS in the joint fit exceeds
    ``MOMENT_FACTOR`` times its camera's RMS alone (``calibrateCamera``: its own corner
    noise), and ``MOMENT_MARGIN_PX`` more, disagrees with its shot; of a shot's views that
    do, only the one furthest over its limit is left out in a round (it pulls the shot's
    board pose towards itself, and so the others' residuals up), and one left out stays out
    while it still disagrees; never so many that a camera keeps fewer than ``min_shots``
    views (a rig whose views disagree that much is one the checks refuse, naming why).

    Attributes:
        view_shot: The shot of each view.
        camera_rms: Each camera's RMS alone, px.
    """

    view_shot: np.ndarray
    camera_rms: np.ndarray

    def other_moments(
        self,
        rms: np.ndarray,
        fitted: np.ndarray,
        was_kept: np.ndarray,
        dropped: Mapping[int, str],
        view_camera: np.ndarray,
        min_shots: int,
    ) -> dict[int, str]:
        """Index -> why of the views left out as of another moment (see the class), among
        the ``fitted`` views not already ``dropped`` (``was_kept``: the views the last fit
        used)."""
        own = self.camera_rms[view_camera]
        limit = np.maximum(MOMENT_FACTOR * own, own + MOMENT_MARGIN_PX)
        over = rms / limit
        candidates = fitted & (over > 1.0)
        candidates[list(dropped)] = False
        # Left out before and still off: out again. Of the views the fit used, the worst of
        # each shot, unless it is the shot's last view (nothing to disagree with).
        chosen = set(np.flatnonzero(candidates & ~was_kept).tolist())
        used = fitted & was_kept
        used[list(dropped)] = False
        views_in_shot = np.bincount(self.view_shot[used], minlength=int(self.view_shot.max()) + 1)
        for s in np.unique(self.view_shot[candidates & was_kept]).tolist():
            mine = np.flatnonzero(candidates & was_kept & (self.view_shot == s))
            if views_in_shot[s] >= 2:
                chosen.add(int(mine[np.argmax(over[mine])]))
        left = np.bincount(view_camera[used], minlength=len(self.camera_rms))
        out: dict[int, str] = {}
        for i in sorted(chosen, key=lambda i: (-over[i], i)):
            if was_kept[i]:
                if left[view_camera[i]] <= min_shots:
                    continue
                left[view_camera[i]] -= 1
            out[i] = (
                f"disagrees with the shot's other views: RMS {rms[i]:.2f} px in the rig, "
                f"against {own[i]:.2f} px for its camera alone (limit {limit[i]:.2f} px): an "
                "image of another moment (the board moved between the cameras' images)?"
            )
        return out
