"""Point pair voting (Drost et al. 2010): one pose vote per scene reference point.

Every ``reference_step``-th scene point is a reference. It is paired with every scene point
within the model's largest extent; each pair's feature key selects the model pairs with the
same key, and each of those votes for (the model sample matched to the reference, the angle
``alpha_scene - alpha_model`` about the aligned normal), in an accumulator of
(samples x ``angle_bins``) cells per reference. The best cell of each reference is its vote,
the pose ``P = A_s^-1 R_x(alpha) A_m`` (``A`` the alignments of the scene reference and the
model sample), weighted by its count.

What happens to the votes next is the point of the paper's section 4.2: they are clustered
into hypotheses, in SE(3) or in the pose space of the part's symmetry
(:mod:`annotator.estimation.estimator`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from annotator.estimation.cloud import OrientedCloud
from annotator.estimation.features import (
    alignments,
    feature_keys,
    pair_angles,
    pair_features,
    rotations_about_x,
)
from annotator.estimation.model import PPFModel
from annotator.symmetry.embedding import stack_poses


@dataclass(frozen=True)
class Votes:
    """Pose votes: (N, 4, 4) model-to-camera transforms (the cloud's frame) and their
    weights (N,), the accumulator counts."""

    poses: np.ndarray
    weights: np.ndarray

    def __len__(self) -> int:
        return len(self.weights)


def vote(
    model: PPFModel,
    cloud: OrientedCloud,
    *,
    reference_step: int = 5,
    max_pairs: int = 4_000_000,
) -> Votes:
    """The votes of every ``reference_step``-th point of ``cloud`` (see the module
    docstring); ``max_pairs`` bounds the model pairs expanded at once (memory)."""
    pts = cloud.points
    if len(pts) < 2 or len(model.points) == 0:
        return Votes(np.zeros((0, 4, 4)), np.zeros(0))
    refs = np.arange(0, len(pts), max(1, int(reference_step)))
    pairs = _matched_pairs(model, cloud, refs)
    Rs, ts = alignments(pts[refs], cloud.normals[refs])
    alpha_s = pair_angles(Rs[pairs.ref], ts[pairs.ref], pts[pairs.other]).astype(np.float32)
    best_cell, best_count = _best_cells(model, pairs, alpha_s, len(refs), max_pairs)
    voted = best_count > 0
    sample = best_cell[voted] // model.angle_bins
    angle = (best_cell[voted] % model.angle_bins + 0.5) * model.angle_step
    Rs, ts = Rs[voted], ts[voted]
    Rx = rotations_about_x(angle)
    Rm, tm = model.align_R[sample], model.align_t[sample]
    # P = A_s^-1 R_x A_m, with A x = R x + t.
    RsT = np.swapaxes(Rs, 1, 2)
    R = RsT @ Rx @ Rm
    t = np.einsum("nij,nj->ni", RsT @ Rx, tm) - np.einsum("nij,nj->ni", RsT, ts)
    return Votes(stack_poses(R, t), best_count[voted])


@dataclass(frozen=True)
class _Pairs:
    """Scene pairs whose feature is in the model: the reference (index into ``refs``), the
    other point (index into the cloud), and the feature's position in the model's table."""

    ref: np.ndarray
    other: np.ndarray
    pos: np.ndarray


def _matched_pairs(model: PPFModel, cloud: OrientedCloud, refs: np.ndarray) -> _Pairs:
    """Every pair of a reference point and another point within the model's largest
    distance whose quantised feature the model has."""
    from scipy.spatial import cKDTree

    pts, nrm = cloud.points, cloud.normals
    pairs = cKDTree(pts[refs]).sparse_distance_matrix(
        cKDTree(pts), model.max_distance, output_type="ndarray"
    )
    r_local, other = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    keep = refs[r_local] != other
    r_local, other = r_local[keep], other[keep]
    ref = refs[r_local]
    keys = feature_keys(
        pair_features(pts[ref], nrm[ref], pts[other], nrm[other]),
        model.distance_step,
        model.angle_step,
    )
    pos = np.searchsorted(model.unique_keys, keys)
    pos = np.minimum(pos, len(model.unique_keys) - 1)
    found = model.unique_keys[pos] == keys
    return _Pairs(r_local[found], other[found], pos[found])


def _best_cells(
    model: PPFModel, pairs: _Pairs, alpha_s: np.ndarray, n_refs: int, max_pairs: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per reference, the accumulator cell (model point x angle bin) with the most votes and
    its count, accumulating chunks of whole references of at most ``max_pairs`` expanded
    model pairs."""
    counts = model.counts[pairs.pos]
    # Pairs are grouped by reference (the tree returns them so; sort to be sure), so that
    # chunks of whole references bound the expanded model pairs.
    order = np.argsort(pairs.ref, kind="stable")
    r_local, pos, alpha_s, counts = (
        pairs.ref[order],
        pairs.pos[order],
        alpha_s[order],
        counts[order],
    )
    per_ref = np.bincount(r_local, weights=counts, minlength=n_refs)
    cells = len(model.points) * model.angle_bins
    best_cell = np.zeros(n_refs, dtype=np.int64)
    best_count = np.zeros(n_refs)
    bounds = np.searchsorted(r_local, np.arange(n_refs + 1))
    lo = 0
    while lo < n_refs:
        # As many references as fit in max_pairs expanded model pairs (at least one).
        total = np.cumsum(per_ref[lo:])
        hi = lo + max(1, int(np.searchsorted(total, max_pairs, side="right")))
        hi = min(hi, lo + max(1, 4_000_000 // max(cells, 1)))  # accumulator memory
        a, b = bounds[lo], bounds[hi]
        _accumulate(
            model,
            r_local[a:b] - lo,
            pos[a:b],
            alpha_s[a:b],
            counts[a:b],
            hi - lo,
            best_cell[lo:hi],
            best_count[lo:hi],
        )
        lo = hi
    return best_cell, best_count


def _accumulate(
    model: PPFModel,
    ref: np.ndarray,
    pos: np.ndarray,
    alpha_s: np.ndarray,
    counts: np.ndarray,
    n_refs: int,
    best_cell: np.ndarray,
    best_count: np.ndarray,
) -> None:
    """Vote for a chunk of references (``ref`` local to it) and write each one's best cell
    and its count into ``best_cell`` / ``best_count``."""
    total = int(counts.sum())
    if total == 0:
        return
    # Expand every scene pair into its run of model pairs; values are repeated rather than
    # gathered through a pair index (half the memory traffic).
    cells = len(model.points) * model.angle_bins
    offset = model.starts[pos] - (np.cumsum(counts) - counts)
    entry = np.arange(total, dtype=np.int64)
    entry += np.repeat(offset, counts)
    alpha = np.repeat(alpha_s + np.float32(2 * np.pi), counts)
    alpha -= model.alpha[entry]  # in (0, 4 pi): truncation is floor
    alpha *= np.float32(1.0 / model.angle_step)
    index = alpha.astype(np.int64)
    index %= model.angle_bins
    index += np.repeat(ref.astype(np.int64) * cells, counts)
    index += model.cell_base[entry]
    acc = np.bincount(index, minlength=n_refs * cells).reshape(n_refs, cells)
    best_cell[:] = acc.argmax(axis=1)
    best_count[:] = acc[np.arange(n_refs), best_cell]
