"""The small motions of rigid transforms, the one convention every solver linearises with.

A pose is moved by a 6-vector ``d = (w, v)``: its rotation turned by ``exp([w]x)`` on the
left (about the origin of the frame the pose maps into) and its translation shifted by ``v``,

    R -> exp([w]x) R,    t -> t + v,

so that a point ``x`` of the moved frame goes, to first order, to ``x + w x (R x0) + v``
where ``R x0`` is the point before the move. Jacobians of residuals are with respect to
``d`` at ``d = 0`` (:mod:`annotator.pnp.multiview`, :mod:`annotator.pnp.bundle`,
:mod:`annotator.refinement.depth`), and covariances of poses are of ``d``
(:mod:`annotator.pnp.uncertainty`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["cross", "matrix_to_rotvec", "norms", "perturb", "rotvec_to_matrix", "skew"]


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of ``(..., 3)`` vectors (broadcast), with the same arithmetic and so the
    same bits: the Jacobians of the solvers take it thousands of times a scene on a few
    dozen vectors, where ``np.cross``'s generality (axis moves, type casts) costs more than
    the products.

    >>> cross(np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    array([0., 0., 1.])
    """
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def norms(v: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(v, axis=1)`` of (N, 3) vectors, with the same bits (its sum of
    squares, in its order), written out: the refinement takes it on thousands of points at
    every step, where the general reduction over a stride-3 axis costs several times more.

    >>> norms(np.array([[3.0, 4.0, 12.0]]))
    array([13.])
    """
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    return np.sqrt(x * x + y * y + z * z)


def skew(w: np.ndarray) -> np.ndarray:
    """The cross-product matrix ``[w]x`` of a vector (or of each of ``(..., 3)`` vectors):
    ``skew(w) @ x == np.cross(w, x)``.

    >>> skew(np.array([1.0, 2.0, 3.0])) @ np.array([0.0, 0.0, 1.0])
    array([ 2., -1.,  0.])
    """
    w = np.asarray(w, dtype=float)
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    return K


def perturb(T: np.ndarray, d: np.ndarray) -> np.ndarray:
    """``T`` (4x4, or (N, 4, 4)) moved by ``d = (w, v)`` (6, or (N, 6)): ``R -> exp([w]x) R``,
    ``t -> t + v`` (see the module). A new array; ``T`` is left as it is.

    >>> T = perturb(np.eye(4), np.array([0.0, 0.0, np.pi / 2, 1.0, 0.0, 0.0]))
    >>> np.round(T[:3, :3] @ [1.0, 0.0, 0.0], 6).tolist(), T[:3, 3].tolist()
    ([0.0, 1.0, 0.0], [1.0, 0.0, 0.0])
    """
    out = np.array(T, dtype=float, copy=True)
    d = np.asarray(d, dtype=float)
    out[..., :3, :3] = rotvec_to_matrix(d[..., :3]) @ out[..., :3, :3]
    out[..., :3, 3] = out[..., :3, 3] + d[..., 3:]
    return out


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, shape (..., 3)) to rotation matrices (..., 3, 3), by
    Rodrigues' formula (series near zero)."""
    r = np.asarray(rotvec, dtype=float)
    theta = np.linalg.norm(r, axis=-1)[..., None, None]
    t2 = theta**2
    if r.ndim == 1:  # one vector (every solver's step): only the branch it takes
        if theta[0, 0] < 1e-4:
            a, b = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
        else:
            a, b = np.sin(theta) / theta, (1.0 - np.cos(theta)) / t2
    else:
        small = theta < 1e-4
        with np.errstate(invalid="ignore", divide="ignore"):
            a = np.where(small, 1.0 - t2 / 6.0, np.sin(theta) / theta)
            b = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(theta)) / t2)
    K = skew(r)
    return np.eye(3) + a * K + b * (K @ K)


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) to rotation vectors (..., 3), angles in [0, pi], through
    the quaternion (Shepperd: from its largest component, for accuracy)."""
    q = _quaternion(np.asarray(R, dtype=float))
    v = q[..., :3]
    s = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(s, q[..., 3])
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(s < 1e-12, 2.0, angle / s)
    return v * scale[..., None]


def _quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) ``(x, y, z, w)`` with ``w >= 0`` of rotation matrices
    (..., 3, 3), each from the candidate of its largest component (Shepperd's method)."""
    r = {(i, j): R[..., i, j] for i in range(3) for j in range(3)}
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    big = np.stack(
        [1.0 + 2.0 * r[0, 0] - tr, 1.0 + 2.0 * r[1, 1] - tr, 1.0 + 2.0 * r[2, 2] - tr, 1.0 + tr], -1
    )
    h = np.sqrt(np.maximum(big, 1e-300)) / 2.0  # each candidate's largest component
    d = 4.0 * h
    xy, xz, yz = r[0, 1] + r[1, 0], r[0, 2] + r[2, 0], r[1, 2] + r[2, 1]
    wx, wy, wz = r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]
    rows = (  # (x, y, z, w) from x, from y, from z, from w
        (h[..., 0], xy / d[..., 0], xz / d[..., 0], wx / d[..., 0]),
        (xy / d[..., 1], h[..., 1], yz / d[..., 1], wy / d[..., 1]),
        (xz / d[..., 2], yz / d[..., 2], h[..., 2], wz / d[..., 2]),
        (wx / d[..., 3], wy / d[..., 3], wz / d[..., 3], h[..., 3]),
    )
    candidates = np.stack([np.stack(row, -1) for row in rows], -2)
    pick = np.argmax(big, axis=-1)[..., None, None]
    q = np.take_along_axis(candidates, pick, axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)  # w >= 0: angles up to pi
