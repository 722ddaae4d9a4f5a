"""Mode finding over pose votes by mean shift in the pose space (paper section 4.2, "Finding
modes").

Vote-based estimators (PPF, Drost et al. 2010; Hough forests...) turn many weak pose votes
into a few strong hypotheses by finding where the votes concentrate. How close two votes are
is a choice of metric: a metric of SE(3) treats a gear turned by one tooth as a different
pose, so the votes for one gear scatter over 8 places (for a cylinder, over a whole circle of
turns about its axis), each gathering a fraction of the support, and each producing its own
hypothesis, a duplicate. With the paper's distance (RMS surface displacement minimised over
the symmetry group) those votes are *the same pose* and add up.

The distance is the Euclidean distance from a representative of one pose to the nearest
representative of the other, which makes mean shift straightforward: neighbourhoods are
radius searches in a KD-tree of every vote's representatives, and the mean of the
neighbours' representatives nearest to the current estimate (which resolves the symmetry),
mapped back to the nearest pose, is the next estimate (the extrinsic mean of Brégier et al.
2016).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from annotator.symmetry.duplicates import filter_duplicates
from annotator.symmetry.embedding import nearest_poses, poses_and_values, stack_poses


@dataclass(frozen=True)
class Modes:
    """Modes of weighted pose votes, heaviest first.

    Attributes:
        poses: (M, 4, 4) model-to-camera transforms of the modes.
        weights: (M,) the summed weight of the votes assigned to each mode.
        labels: (N,) the mode each vote is assigned to (index into ``poses``), -1 for a vote
            farther than the bandwidth from every mode.
    """

    poses: np.ndarray
    weights: np.ndarray
    labels: np.ndarray


def find_modes(
    poses: Any,
    weights: Any,
    part: Any,
    bandwidth: float,
    *,
    max_iterations: int = 30,
    tolerance: float | None = None,
    seeds: str = "cover",
) -> Modes:
    """Modes of the density of weighted pose votes, by mean shift in the pose space.

    The kernel is flat: every vote within ``bandwidth`` (the paper's distance, mm) of the
    current estimate counts with its weight (the mean shift of the Epanechnikov kernel
    density, which converges in finitely many steps). Each step averages, for every
    neighbouring vote, its representative nearest to the current estimate, and projects the
    mean back to the nearest pose (:func:`~annotator.symmetry.embedding.nearest_poses`).

    Seeds: with ``seeds="cover"`` (default), the votes kept by
    :func:`~annotator.symmetry.filter_duplicates` at ``bandwidth / 2``, heaviest first, so
    that every vote is within half a bandwidth of a seed (binned seeding: the same modes as
    seeding from every vote, for far fewer trajectories); ``"all"``: every vote.
    Converged seeds closer than ``bandwidth`` are one mode (the densest kept). Every vote is
    then assigned to its nearest mode within ``bandwidth``, and a mode's weight is the sum of
    the weights assigned to it, so weights add up to at most the total.

    Args:
        poses: (N, 4, 4) model-to-camera transforms (mm), the votes.
        weights: (N,) positive vote weights.
        part: A :class:`~annotator.symmetry.PoseSpace`, or a part with ``mesh`` and
            ``symmetry``; a space built with ``Symmetry("none")`` gives mean shift in SE(3)
            under the same metric otherwise.
        bandwidth: Kernel radius, mm.
        max_iterations: Mean-shift steps per seed at most.
        tolerance: A seed has converged when a step moves it less than this (mm; default
            ``bandwidth / 1000``).
        seeds: ``"cover"`` or ``"all"`` (above).

    Returns:
        The :class:`Modes`, heaviest first. For a revolution part a mode's rotation about the
        axis is arbitrary (all are the same pose); for a spherical part its rotation is that
        of its seed.

    Example: two bricks, 40 noisy votes each; half of the votes are for the brick turned by
    its half-turn symmetry. With the symmetry the votes add up in two modes; in SE(3) they
    split into four of half the weight.

    >>> import numpy as np
    >>> from annotator.dataset.model import Symmetry
    >>> from annotator.geometry.transforms import axis_angle, random_rotations
    >>> from annotator.parts import build_part
    >>> from annotator.symmetry import PoseSpace, find_modes
    >>> rng = np.random.default_rng(0)
    >>> brick = build_part("brick")
    >>> truth = np.tile(np.eye(4), (2, 1, 1))
    >>> truth[:, :3, :3] = random_rotations(2, rng)
    >>> truth[:, :3, 3] = [[0, 0, 500], [60, 0, 520]]
    >>> votes = np.repeat(truth, 40, axis=0)
    >>> half = axis_angle([0, 0, 1], np.pi)
    >>> votes[::2, :3, :3] = votes[::2, :3, :3] @ half
    >>> votes[:, :3, 3] += rng.normal(0, 1.0, (80, 3))
    >>> modes = find_modes(votes, np.ones(80), brick, bandwidth=10.0)
    >>> modes.weights.tolist()
    [40.0, 40.0]
    >>> rigid = PoseSpace.from_moments(brick.mesh.moments, Symmetry("none"))
    >>> find_modes(votes, np.ones(80), rigid, bandwidth=10.0).weights.tolist()
    [20.0, 20.0, 20.0, 20.0]

    Over 80 lines: the method and its worked example; the steps are each a function.
    """
    space, R, t, w = poses_and_values(poses, weights, part, "weights")
    _check_arguments(w, bandwidth, seeds)
    n = len(R)
    if n == 0:
        return Modes(np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0, dtype=int))
    votes = _Votes.of(space, R, t, w)
    T = np.asarray(stack_poses(R, t))
    start = filter_duplicates(T, w, space, 0.5 * bandwidth) if seeds == "cover" else np.arange(n)
    tol = bandwidth * 1e-3 if tolerance is None else float(tolerance)
    seed_R = R[start].copy()  # the rotation a spherical part's estimate keeps
    current = _shift(votes, votes.reps[start, 0].copy(), seed_R, bandwidth, max_iterations, tol)
    _, density = _neighbour_means(space, votes.tree, votes.flat, votes.owner, w, current, bandwidth)
    estimates = nearest_poses(space, current, fallback_R=seed_R)
    mode_poses = estimates[filter_duplicates(estimates, density, space, bandwidth)]
    return _assign(votes, mode_poses, bandwidth)


def _check_arguments(w: np.ndarray, bandwidth: float, seeds: str) -> None:
    if not bandwidth > 0:
        raise ValueError(f"bandwidth must be a positive distance, got {bandwidth!r}")
    if np.any(w < 0) or not np.all(np.isfinite(w)):
        raise ValueError("weights must be finite and non-negative")
    if seeds not in ("cover", "all"):
        raise ValueError(f"seeds must be 'cover' or 'all', got {seeds!r}")


@dataclass(frozen=True)
class _Votes:
    """The votes in the pose space: their representatives (N, G, dim), flattened with the
    vote each belongs to, in a KD-tree; and their weights."""

    space: Any
    reps: np.ndarray
    flat: np.ndarray
    owner: np.ndarray
    tree: Any
    w: np.ndarray

    @classmethod
    def of(cls, space: Any, R: np.ndarray, t: np.ndarray, w: np.ndarray) -> _Votes:
        from scipy.spatial import cKDTree

        reps = space.representatives(R, t)
        flat = reps.reshape(-1, space.dim)
        owner = np.repeat(np.arange(len(R)), space.count)
        return cls(space, reps, flat, owner, cKDTree(flat), w)


def _shift(
    votes: _Votes,
    current: np.ndarray,
    seed_R: np.ndarray,
    bandwidth: float,
    max_iterations: int,
    tol: float,
) -> np.ndarray:
    """Mean-shift the seeds (their first representatives, (S, dim)) until each moves less
    than ``tol`` in a step, or ``max_iterations``: the converged representatives."""
    space = votes.space
    active = np.arange(len(current))
    for _ in range(max_iterations):
        if not len(active):
            break
        mean, mass = _neighbour_means(
            space, votes.tree, votes.flat, votes.owner, votes.w, current[active], bandwidth
        )
        moved = nearest_poses(space, mean, fallback_R=seed_R[active])
        new = space.representatives(moved[:, :3, :3], moved[:, :3, 3])[:, 0]
        lost = mass <= 0  # no vote in reach: stay (cannot happen from a vote, kept for safety)
        new[lost] = current[active][lost]
        shift = np.linalg.norm(new - current[active], axis=1)
        current[active] = new
        active = active[shift >= tol]
    return current


def _assign(votes: _Votes, mode_poses: np.ndarray, bandwidth: float) -> Modes:
    """Each vote to its nearest mode within the bandwidth; the modes, heaviest first."""
    from scipy.spatial import cKDTree

    space, w = votes.space, votes.w
    mode_reps = space.representatives(mode_poses[:, :3, :3], mode_poses[:, :3, 3])
    mode_tree = cKDTree(mode_reps.reshape(-1, space.dim))
    mode_owner = np.repeat(np.arange(len(mode_poses)), space.count)
    d, j = mode_tree.query(votes.reps[:, 0], k=1, distance_upper_bound=bandwidth)
    found = np.isfinite(d)
    labels = np.full(len(w), -1, dtype=int)
    labels[found] = mode_owner[j[found]]
    mode_w = np.bincount(labels[found], weights=w[found], minlength=len(mode_poses))
    order = np.argsort(-mode_w, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    labels[found] = rank[labels[found]]
    return Modes(mode_poses[order], mode_w[order], labels)


def _neighbour_means(
    space: Any,
    tree: Any,
    flat: np.ndarray,
    owner: np.ndarray,
    w: np.ndarray,
    queries: np.ndarray,
    bandwidth: float,
) -> tuple[np.ndarray, np.ndarray]:
    """For each query point (Q, dim): the weighted mean of the representatives, one per vote
    (its nearest to the query), of the votes within ``bandwidth``, and their total weight."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(queries).sparse_distance_matrix(tree, bandwidth, output_type="ndarray")
    q, j, dist = pairs["i"], pairs["j"], pairs["v"]
    if space.count > 1 and len(q):
        # Several representatives of one vote in reach (a small group element, a wide
        # bandwidth): only the nearest counts, so that a vote weighs once.
        key = q.astype(np.int64) * len(w) + owner[j]
        first = np.lexsort((dist, key))
        _, uniq = np.unique(key[first], return_index=True)
        sel = first[uniq]
        q, j = q[sel], j[sel]
    wj = w[owner[j]]
    m = len(queries)
    mass = np.bincount(q, weights=wj, minlength=m)
    sums = np.stack(
        [np.bincount(q, weights=wj * flat[j, k], minlength=m) for k in range(flat.shape[1])],
        axis=1,
    )
    mean = np.divide(sums, mass[:, None], out=queries.copy(), where=mass[:, None] > 0)
    return mean, mass
