"""The trained model of a part for point pair voting: its oriented samples and the table of
every sample pair by feature (Drost et al. 2010, "global model description").

Samples: points drawn on the surface in proportion to area (seeded: the same model every
time), with their faces' outward normals, then one per cube of ``distance_step`` mm, as the
scene is subsampled (:func:`~annotator.estimation.cloud.voxel_subsample`). The table holds,
for every ordered pair of samples, its feature key, its first sample and the angle ``alpha``
of the second about the first's aligned normal, sorted by key so that a scene pair's matches
are one contiguous run found by binary search.

Training builds all N^2 pairs with numpy (a few hundred thousand for the built-in parts) and
is cached per part (by mesh content and settings) in the process; batch commands train in the
parent before forking, so workers share it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from annotator.estimation.cloud import voxel_subsample
from annotator.estimation.features import alignments, feature_keys, pair_angles, pair_features
from annotator.geometry.mesh import Mesh, surface_samples


@dataclass(frozen=True, eq=False)
class PPFModel:
    """A part trained for voting.

    Attributes:
        points: (M, 3) samples, model frame, mm.
        normals: (M, 3) their unit outward normals.
        align_R: (M, 3, 3), align_t (M, 3): each sample's alignment (see
            :func:`~annotator.estimation.features.alignments`).
        keys: (P,) sorted feature keys of the sample pairs; first (P,) their first sample;
            alpha (P,) the angle of their second sample.
        unique_keys: (K,) the distinct keys; starts, counts (K,) their run in ``keys``.
        distance_step: mm; angle_bins: the number of angle cells in a full turn.
        max_distance: The largest distance between two samples (a scene pair farther apart
            cannot belong to one part).
    """

    points: np.ndarray
    normals: np.ndarray
    align_R: np.ndarray
    align_t: np.ndarray
    keys: np.ndarray
    first: np.ndarray
    alpha: np.ndarray
    unique_keys: np.ndarray
    starts: np.ndarray
    counts: np.ndarray
    distance_step: float
    angle_bins: int
    max_distance: float

    @property
    def cell_base(self) -> np.ndarray:
        """(P,) each model pair's first accumulator cell: ``first * angle_bins``."""
        base = self.__dict__.get("_cell_base")
        if base is None:
            base = self.first.astype(np.int64) * self.angle_bins
            object.__setattr__(self, "_cell_base", base)
        return base

    @property
    def angle_step(self) -> float:
        return 2 * np.pi / self.angle_bins


_CACHE: dict[tuple, PPFModel] = {}


def train_model(mesh: Mesh, *, distance_step: float, angle_bins: int = 30) -> PPFModel:
    """Train (or fetch from the cache) the model of a part: samples ``distance_step`` mm
    apart, angles in ``angle_bins`` cells per turn."""
    key = (mesh.digest, round(float(distance_step), 9), int(angle_bins))
    model = _CACHE.get(key)
    if model is None:
        if len(_CACHE) >= 16:
            _CACHE.clear()
        model = _CACHE[key] = _train(mesh, float(distance_step), int(angle_bins))
    return model


def _train(mesh: Mesh, distance_step: float, angle_bins: int) -> PPFModel:
    pts, nrm = surface_samples(mesh, distance_step)
    cloud = voxel_subsample(pts, nrm, distance_step)
    p, n = cloud.points, cloud.normals
    m = len(p)
    R, t = alignments(p, n)
    i, j = np.nonzero(~np.eye(m, dtype=bool))
    features = pair_features(p[i], n[i], p[j], n[j])
    angle_step = 2 * np.pi / angle_bins
    keys = feature_keys(features, distance_step, angle_step)
    alpha = pair_angles(R[i], t[i], p[j])
    order = np.argsort(keys, kind="stable")
    keys, first, alpha = keys[order], i[order].astype(np.int32), alpha[order]
    unique_keys, starts, counts = np.unique(keys, return_index=True, return_counts=True)
    return PPFModel(
        points=p,
        normals=n,
        align_R=R,
        align_t=t,
        keys=keys,
        first=first,
        alpha=alpha.astype(np.float32),
        unique_keys=unique_keys,
        starts=starts,
        counts=counts,
        distance_step=distance_step,
        angle_bins=angle_bins,
        max_distance=float(features[:, 0].max()) if len(features) else 0.0,
    )
