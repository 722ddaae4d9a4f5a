"""What a sequence's observations are trusted to: the noise of each marker's corners (a
sharp image's, a motion streak's, what each frame's residuals show), where on its streak a
blurred frame's pose may lie, how far each part's markers sit from their layout (glued by
hand, measured by ``annotator sites``) and what that does to a frame's pose, and the depth
of each marker (for the scale, :mod:`.depth_scale`). Pure functions of the solve's arrays;
:mod:`.sequence` weighs its bundle adjustment and states its uncertainties with them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from annotator.annotation.depth_scale import surface_under
from annotator.dataset import Dataset
from annotator.dataset.model import ObjectModel
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert
from annotator.noise import NOISE
from annotator.pnp.bundle import BundleObservations, BundleResult
from annotator.pnp.uncertainty import site_covariance

__all__ = [
    "MOTION_BLUR_PX",
    "FrameBlur",
    "corner_sigma",
    "frame_sigma",
    "frame_site_covariance",
    "glue_spread",
    "marker_depths",
    "median_by",
    "site_sigma",
    "surface_centres",
]


def corner_sigma(streak_px: np.ndarray) -> np.ndarray:
    """Each corner's noise (px) in an image smeared by a streak ``streak_px`` long: the sharp
    image's, plus the spread of a point uniformly anywhere along the streak."""
    return np.sqrt(NOISE.corner_px**2 + np.asarray(streak_px, float) ** 2 / 12)


def frame_sigma(
    obs: BundleObservations, err: np.ndarray, keep: np.ndarray, sigma: np.ndarray
) -> np.ndarray:
    """Each observation's corner noise raised to what its frame's kept residuals show: their
    RMS per coordinate, widened for the frame's six unknowns (a frame fitted on few corners
    looks better than it is)."""
    out = sigma.copy()
    for f in np.unique(obs.frame[keep]):
        mine = (obs.frame == f) & keep
        n = 8 * int(mine.sum())
        rms = float(np.sqrt(np.mean(err[mine] ** 2) / 2))  # per coordinate
        if n > 6:
            rms *= np.sqrt(n / (n - 6))
        out[obs.frame == f] = np.maximum(out[obs.frame == f], rms)
    return out


def marker_depths(
    cams: Sequence[Camera],
    obs: BundleObservations,
    frames: np.ndarray,
    models: np.ndarray,
    centre: np.ndarray | None = None,
) -> np.ndarray:
    """(N,) the depth (mm) of each observation's marker centre in its camera (``centre``,
    (N, 3) model frame: the mean of its corners unless given)."""
    M = np.einsum("nij,njk->nik", invert(frames[obs.frame]), models[obs.instance])
    centre = obs.model_corners.mean(axis=1) if centre is None else centre
    z = np.empty(len(obs))
    for j, cam in enumerate(cams):
        sel = obs.camera == j
        C = cam.cam_T_rig @ M[sel]
        z[sel] = np.einsum("nj,nj->n", C[:, 2, :3], centre[sel]) + C[:, 2, 3]
    return z


def surface_centres(
    ds: Dataset, keys: list[tuple[str, str]], obs: BundleObservations
) -> np.ndarray:
    """(N, 3) the point of its part's surface under each observation's marker centre (model
    frame), worked out once per marker."""
    centre = obs.model_corners.mean(axis=1)
    out = centre.copy()
    for i, (obj, _) in enumerate(keys):
        mine = obs.instance == i
        if not mine.any():
            continue
        sites, back = np.unique(centre[mine].round(6), axis=0, return_inverse=True)
        on = surface_under(ds.objects[obj].mesh.triangles, sites)
        out[mine] = on[back.reshape(-1)]
    return out


def median_by(index: np.ndarray, values: np.ndarray, size: int) -> np.ndarray:
    """(size,) the median of ``values`` per ``index`` (NaN: none)."""
    out = np.full(size, np.nan)
    for k in np.unique(index):
        out[k] = float(np.median(values[index == k]))
    return out


@dataclass(frozen=True)
class FrameBlur:
    """Per posed frame, its longest motion streak (px) and its markers' median depth (mm):
    which instant of the exposure its pose stands for is not known."""

    streak_px: np.ndarray
    depth_mm: np.ndarray

    def uncertainty(self, n: int, focal_px: float) -> tuple[float, float]:
        """Frame ``n``'s pose uncertainty (1-sigma, mm and degrees) from its streak alone:
        the rig anywhere along it, as a shift across the view or as a turn."""
        spread = float(self.streak_px[n]) / np.sqrt(12) / focal_px  # radians
        depth = float(self.depth_mm[n]) if np.isfinite(self.depth_mm[n]) else 0.0
        return spread * depth, float(np.degrees(spread))


#: A frame whose motion streak is at least this long (px) is flagged ``motion_blur``: where
#: on the streak its pose lies is not known to the 2 mm a posed frame promises.
MOTION_BLUR_PX = 3.0


def frame_site_covariance(
    obs: BundleObservations,
    mine: np.ndarray,
    result: BundleResult,
    scene_T_rig: np.ndarray,
    sigma: np.ndarray,
) -> np.ndarray:
    """The ``(w, v)`` covariance of a frame's pose from the errors of the sites it was posed
    on (``mine``: its kept observations; ``sigma``: each instance's site error, mm): its
    corners in the scene frame, about its camera centre, each off by its part's."""
    idx = np.flatnonzero(mine)
    M = result.scene_T_model[obs.instance[idx]]
    pts = np.einsum("nij,nkj->nki", M[:, :3, :3], obs.model_corners[idx]) + M[:, None, :3, 3]
    cov = site_covariance(
        np.eye(3), (pts - scene_T_rig[:3, 3]).reshape(-1, 3), np.repeat(sigma[obs.instance[idx]], 4)
    )
    return cov if np.isfinite(cov).all() else np.zeros((6, 6))


def site_sigma(
    obs: BundleObservations,
    err: np.ndarray,
    keep: np.ndarray,
    depth: np.ndarray,
    focal_px: float,
    n_instances: int,
) -> np.ndarray:
    """(instances,) how far each instance's marker corners sit from where its layout puts
    them (mm, 1-sigma), as its kept residuals show: their RMS per coordinate carried to the
    part at its median depth. Markers glued by hand disagree with the layout the same way in
    every frame, so more frames do not average it out: it goes with the sites' own error."""
    out = np.zeros(n_instances)
    for i in np.unique(obs.instance[keep]):
        mine = keep & (obs.instance == i)
        rms = float(np.sqrt(np.mean(err[mine] ** 2) / 2))
        out[i] = rms * float(np.median(depth[mine])) / focal_px
    return out


def glue_spread(model: ObjectModel, instance: str) -> float:
    """How far an instance's measured sites (``annotator sites``) moved from the layout (mm,
    1-sigma per axis of the face, RMS over its corners), 0 without measured sites. Sites are
    measured against the part's own pose, so what its markers moved by on average is in
    neither: the gluing's spread stays in its uncertainty after ``sites`` too."""
    sites = model.instance(instance).sites
    if sites is None or model.markers is None:
        return 0.0
    moved = np.linalg.norm(sites - model.markers.corners, axis=-1)  # (S, 4)
    measured = moved.max(axis=1) > 1e-6
    if not measured.any():
        return 0.0
    return float(np.sqrt(np.mean(moved[measured] ** 2) / 2))
