"""Poses on markers whose sites are known only so well.

A marker's site on its part (its four corners in the model frame) may be off by a shift in
its plane and a turn about its normal (:mod:`annotator.markers.glue`): the same error in every
camera that sees it, which the pose follows. Given each site's 1-sigma (shifts in mm, each of
two, and turn in rad, per marker id), :func:`site_jacobian` gives how the corner residuals
move with those errors: what a pose's covariance needs to count them
(:func:`annotator.refinement.depth.pose_covariance`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from annotator.geometry.camera import Camera
from annotator.pnp.multiview import Observation, corner_residuals

#: Site sigmas per marker id: (each shift in its plane, mm; turn about its normal, rad).
SiteSigmas = dict[int, tuple[float, float]]


def site_jacobian(
    cameras: Sequence[Camera], obs: Sequence[Observation], T: np.ndarray, sigmas: SiteSigmas
) -> tuple[np.ndarray, np.ndarray]:
    """The corner residuals' derivatives (8 len(obs), 3 M) with respect to the M markers'
    site errors (shift along the top edge, along the left edge, turn about the normal through
    the site's centre), and each column's 1-sigma (3 M,; 0 for an id not in ``sigmas``)."""
    obs = list(obs)
    ids = sorted({o.marker_id for o in obs})
    x = np.stack([o.image_corners for o in obs])
    r0 = corner_residuals(cameras, obs, T, x)
    J = np.zeros((r0.size, 3 * len(ids)))
    scale = np.zeros(3 * len(ids))
    eps = 1e-3  # mm, rad: the projection is smooth at this scale
    for m, mid in enumerate(ids):
        shift, turn = sigmas.get(mid, (0.0, 0.0))
        scale[3 * m : 3 * m + 3] = (shift, shift, turn)
        X = next(o.model_corners for o in obs if o.marker_id == mid)
        u = (X[1] - X[0]) / np.linalg.norm(X[1] - X[0])
        v = (X[3] - X[0]) / np.linalg.norm(X[3] - X[0])
        n = np.cross(v, u)
        c = X.mean(axis=0)
        moves = (np.broadcast_to(u, X.shape), np.broadcast_to(v, X.shape), np.cross(n, X - c))
        for k, d in enumerate(moves):
            moved = [
                Observation(o.camera, o.marker_id, o.model_corners + eps * d, o.image_corners)
                if o.marker_id == mid
                else o
                for o in obs
            ]
            r1 = corner_residuals(cameras, moved, T, x)
            J[:, 3 * m + k] = (r1 - r0) / eps
    return J, scale
