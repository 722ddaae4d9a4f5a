"""Markers glued by hand: a site moved within its own plane.

A printed sticker lands beside the place the layout gives it, flat on the same face: shifted
along the face and turned about the face's normal. That is three numbers per site, its
*correction* ``(du, dv, dtheta)``: ``du`` along the site's top edge (top-left to top-right),
``dv`` along its left edge (top-left to bottom-left), both mm, and ``dtheta`` (radians) a
turn about the outward normal ``(BL - TL) x (TR - TL)`` through the site's centre, positive
counter-clockwise seen from outside. A tilt out of the face is not modelled: a sticker
pressed on a face follows it, and a tilt of a few degrees moves a corner of an 8 mm marker
by a tenth of a millimetre along the view, which the images hardly see.

:func:`apply_corrections` moves sites by corrections (the measured sites of an instance);
:func:`random_glue` draws them as gluing does (``annotator synth --glue``).
"""

from __future__ import annotations

import numpy as np

from annotator.geometry.transforms import axis_angle


def site_frames(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per site (S, 4, 3): its centre (S, 3) and unit axes ``u`` (along the top edge), ``v``
    (in the plane, towards the bottom edge) and outward normal ``n`` (S, 3 each)."""
    c = np.asarray(corners, float)
    centre = c.mean(axis=1)
    u = (c[:, 1] - c[:, 0]) + (c[:, 2] - c[:, 3])
    v = (c[:, 3] - c[:, 0]) + (c[:, 2] - c[:, 1])
    n = np.cross(v, u)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    u -= (u * n).sum(1, keepdims=True) * n
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(n, u)
    return centre, u, v, n


def apply_corrections(corners: np.ndarray, corrections: np.ndarray) -> np.ndarray:
    """``corners`` (S, 4, 3) moved by ``corrections`` (S, 3): ``(du, dv, dtheta)`` each.

    >>> import numpy as np
    >>> square = np.array([[[-4, 4, 0], [4, 4, 0], [4, -4, 0], [-4, -4, 0.0]]])
    >>> moved = apply_corrections(square, np.array([[1.0, 0.0, 0.0]]))
    >>> (moved - square)[0, 0].round(6).tolist()
    [1.0, 0.0, 0.0]
    """
    corners = np.asarray(corners, float)
    corrections = np.asarray(corrections, float).reshape(-1, 3)
    centre, u, v, n = site_frames(corners)
    out = np.empty_like(corners)
    for k in range(len(corners)):
        du, dv, dtheta = corrections[k]
        R = axis_angle(n[k], dtheta)
        out[k] = (corners[k] - centre[k]) @ R.T + centre[k] + du * u[k] + dv * v[k]
    return out


def random_glue(
    corners: np.ndarray, *, sigma_mm: float, sigma_deg: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Sites as glued by hand: each moved by N(0, ``sigma_mm``) along both of its axes and
    turned by N(0, ``sigma_deg``) about its normal. Returns the glued corners and the
    corrections drawn (S, 3; mm, mm, rad)."""
    n = len(corners)
    corrections = np.column_stack(
        [rng.normal(0, sigma_mm, (n, 2)), np.radians(rng.normal(0, sigma_deg, n))]
    )
    return apply_corrections(corners, corrections), corrections
