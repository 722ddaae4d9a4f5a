"""Early duplicate removal by the paper's distance (section 4.2, "Filtering duplicates").

A pose estimator proposes many hypotheses, several for the same instance: the same pose found
from different votes or windows, and, for a symmetric part, poses that differ only by a
symmetry of the part (a brick turned by half a turn, a gear by one tooth, a cylinder by any
turn about its axis). These are *the same pose* (Brégier et al.: a pose is a class of rigid
transforms up to the symmetry group), so they are duplicates: the evaluation counts every one
but the first as a false positive. Removing them raises the precision, and doing it early,
before refinement and verification, saves their cost, or equivalently, for a fixed number of
hypotheses kept, lets more *truly different* hypotheses in, which raises the recall.

"Too similar" is measured by the paper's distance, the RMS displacement of the surface
minimised over the symmetry group, which a metric of SE(3) cannot express. Because that
distance is the Euclidean distance between a pose's representative and the other pose's
nearest representative, every neighbourhood query is a radius search in a KD-tree of the
representatives, instead of comparing all pairs.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from annotator.symmetry.embedding import poses_and_values


def filter_duplicates(poses: Any, scores: Any, part: Any, radius: float) -> np.ndarray:
    """Greedy suppression of duplicate pose hypotheses: the indices of the poses kept.

    In decreasing score order (ties: the earlier pose first), a pose is kept unless it lies
    within ``radius`` (mm, inclusive, as the evaluation's match threshold) of a pose already
    kept; so the best-scored pose of each neighbourhood survives and no two kept poses are
    within ``radius`` of each other.

    Args:
        poses: (N, 4, 4) model-to-camera transforms (mm).
        scores: (N,) scores, higher is better.
        part: A :class:`~annotator.symmetry.PoseSpace`, or a part with ``mesh`` and
            ``symmetry`` (see :func:`~annotator.symmetry.embedding.as_space`).
        radius: The distance (mm, the paper's) under which two poses are the same.

    Returns:
        Indices into ``poses`` of the poses kept, best score first.

    Cost: one KD-tree of the N x G representatives (G per pose: the size of a finite group,
    2 for revolution with flip, else 1) and one radius query per pose, so 10^4 hypotheses take
    a fraction of a second where all pairs would be 10^8 distances.

    Example: eight poses of the gear, one tooth (45 degrees) apart, are one pose; without the
    symmetry they are eight.

    >>> import numpy as np
    >>> from annotator.dataset.model import Symmetry
    >>> from annotator.geometry.transforms import axis_angle
    >>> from annotator.parts import build_part
    >>> from annotator.symmetry import PoseSpace, filter_duplicates
    >>> gear = build_part("gear")
    >>> poses = np.tile(np.eye(4), (8, 1, 1))
    >>> poses[:, :3, :3] = [axis_angle([0, 0, 1], k * np.pi / 4) for k in range(8)]
    >>> poses[:, :3, 3] = [0, 0, 500]
    >>> scores = np.arange(8.0)
    >>> filter_duplicates(poses, scores, gear, radius=5.0).tolist()
    [7]
    >>> rigid = PoseSpace.from_moments(gear.mesh.moments, Symmetry("none"))
    >>> len(filter_duplicates(poses, scores, rigid, radius=5.0))
    8
    """
    from scipy.spatial import cKDTree

    space, R, t, scores = poses_and_values(poses, scores, part, "scores")
    n = len(R)
    if not radius >= 0:
        raise ValueError(f"radius must be a non-negative distance, got {radius!r}")
    if n == 0:
        return np.zeros(0, dtype=int)
    order = np.argsort(-scores, kind="stable")
    reps = space.representatives(R, t)  # (N, G, dim)
    tree = cKDTree(reps.reshape(-1, space.dim))
    owner = np.repeat(np.arange(n), space.count)
    # Every pose's neighbours at once (one C call): the query point may be any of a pose's
    # representatives, the distance to another pose being to that pose's nearest one.
    neighbours = tree.query_ball_point(reps[:, 0], r=radius)
    alive = np.ones(n, dtype=bool)
    kept = []
    for i in order:
        if not alive[i]:
            continue
        kept.append(i)
        alive[owner[neighbours[i]]] = False
    return np.asarray(kept, dtype=int)
