"""Poses as points of the pose space's Euclidean embedding, and back (paper section 4.1).

:meth:`PoseSpace.representatives` maps a pose to its representatives; the distance between two
poses is the Euclidean distance from any representative of one to the nearest representative
of the other. This module adds what neighbourhood queries and averages over *many* poses
need: the poses of a stack of 4x4 transforms, a pose space from a part, and the inverse map,
from any point of the ambient space to the nearest pose (:func:`nearest_poses`), which is how
a mean of representatives becomes a pose again.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from annotator.symmetry.space import PoseSpace


def as_space(part: Any) -> PoseSpace:
    """The pose space of ``part``: a :class:`PoseSpace` itself, or anything with a ``mesh``
    (its surface moments) and a ``symmetry`` (a built-in :class:`~annotator.parts.Part`, a
    dataset's :class:`~annotator.dataset.ObjectModel`)."""
    if isinstance(part, PoseSpace):
        return part
    try:
        moments, symmetry = part.mesh.moments, part.symmetry
    except AttributeError:
        raise TypeError(
            f"expected a PoseSpace or a part with .mesh and .symmetry, got {type(part).__name__}"
        ) from None
    return PoseSpace.from_moments(moments, symmetry)


def split_poses(poses: Any) -> tuple[np.ndarray, np.ndarray]:
    """``R`` (N, 3, 3) and ``t`` (N, 3) of model-to-camera transforms (N, 4, 4) (or (N, 3, 4))."""
    T = np.asarray(poses, float)
    if T.size == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"poses must be (N, 4, 4) transforms, got shape {T.shape}")
    return T[:, :3, :3], T[:, :3, 3]


def stack_poses(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 4, 4) transforms from ``R`` (N, 3, 3) and ``t`` (N, 3)."""
    n = len(R)
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    return T


def nearest_poses(
    space: PoseSpace, points: np.ndarray, *, fallback_R: np.ndarray | None = None
) -> np.ndarray:
    """For each point (N, dim) of the ambient space, the pose whose representative is nearest
    to it, as (N, 4, 4) transforms.

    - none / finite: the rotation part ``A`` of the point (``vec(R' G L)``, row-major) gives
      the rotation ``argmin ||R L - A||_F = polar(A L)`` (orthogonal Procrustes; exact even
      for a flat part, whose ``L`` is singular), in the canonical frame; a finite group's
      element is absorbed (every ``R' G`` is the same pose);
    - revolution classes: the axis is the normalised first three coordinates, the rotation
      about it any (a fixed completion of the axis to a frame);
    - spherical: only the position counts; the rotation is ``fallback_R`` (N, 3, 3), e.g. a
      vote's own, or the identity.

    The centroid position is the translation part of the point; the returned ``t`` puts the
    model's origin where that centroid position requires.
    """
    P = np.asarray(points, float).reshape(-1, space.dim)
    n = len(P)
    if space.kind in ("none", "finite"):
        A = P[:, :9].reshape(n, 3, 3) @ space.L
        U, _, Vt = np.linalg.svd(A)
        d = np.sign(np.linalg.det(U @ Vt))
        U[:, :, 2] *= d[:, None]
        Rc = U @ Vt
        tc = P[:, 9:]
    elif space.kind == "spherical":
        Rc = (
            np.repeat(np.eye(3)[None], n, 0)
            if fallback_R is None
            else np.asarray(fallback_R, float).reshape(n, 3, 3) @ space.B
        )
        tc = P
    else:
        z = P[:, :3] / np.maximum(np.linalg.norm(P[:, :3], axis=1, keepdims=True), 1e-300)
        Rc = frames_with_z(z)
        tc = P[:, 3:]
    R = Rc @ space.B.T
    t = tc - R @ space.centroid
    return stack_poses(R, t)


def frames_with_z(z: np.ndarray) -> np.ndarray:
    """Rotations (N, 3, 3) whose third column is the unit vector ``z`` (N, 3), a smooth
    completion away from the reference axis used (x, or y near x)."""
    ref = np.where(np.abs(z[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    x = np.cross(ref, z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    return np.stack([x, np.cross(z, x), z], axis=2)


def poses_and_values(
    poses: Any, values: Any, part: Any, name: str
) -> tuple[PoseSpace, np.ndarray, np.ndarray, np.ndarray]:
    """The pose space of ``part``, ``R`` and ``t`` of ``poses`` and one value per pose
    (``name``: what the values are, for the error), checked to match in number."""
    space = as_space(part)
    R, t = split_poses(poses)
    v = np.asarray(values, float).reshape(-1)
    if len(v) != len(R):
        raise ValueError(f"{len(R)} poses but {len(v)} {name}")
    return space, R, t, v
