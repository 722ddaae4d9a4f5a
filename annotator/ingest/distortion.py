"""Lens distortion models recorders use, as OpenCV's.

RealSense describes some of its cameras (a D455's colour camera, for one) with the *inverse*
Brown-Conrady model: its coefficients take a distorted point to the undistorted one, the
reverse of OpenCV's. :func:`forward_brown_conrady` finds OpenCV's coefficients of the same
lens.
"""

from __future__ import annotations

import numpy as np


def forward_brown_conrady(K: np.ndarray, coeffs: np.ndarray, w: int, h: int) -> np.ndarray:
    """OpenCV's (forward) distortion coefficients of a camera that RealSense describes with
    its *inverse* Brown-Conrady model, whose coefficients take a distorted point to its
    undistorted one: OpenCV's rational model (k1, k2, p1, p2, k3, k4, k5, k6), fitted by
    least squares over the image (its denominator inverts the polynomial closely).

    >>> K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    >>> bool(np.abs(forward_brown_conrady(K, np.zeros(5), 640, 480)).max() < 1e-9)
    True
    """
    from scipy.optimize import least_squares

    u, v = np.meshgrid(np.linspace(0, w - 1, 32), np.linspace(0, h - 1, 24))
    xd = ((u - K[0, 2]) / K[0, 0]).ravel()
    yd = ((v - K[1, 2]) / K[1, 1]).ravel()
    k1, k2, p1, p2, k3 = np.asarray(coeffs, np.float64)[:5]
    xu, yu = distort(xd, yd, np.array([k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]))

    def residual(c: np.ndarray) -> np.ndarray:
        x, y = distort(xu, yu, c)
        return np.concatenate([x - xd, y - yd])

    start = np.array([-k1, -k2, -p1, -p2, -k3, 0.0, 0.0, 0.0])
    fit = least_squares(residual, start, xtol=1e-14, ftol=1e-14, gtol=1e-14)
    return np.asarray(fit.x, np.float64)


def distort(x: np.ndarray, y: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's rational distortion (k1, k2, p1, p2, k3, k4, k5, k6) of normalised points;
    with k4..k6 zero, the Brown-Conrady polynomial RealSense uses either way round."""
    k1, k2, p1, p2, k3, k4, k5, k6 = c
    r2 = x * x + y * y
    f = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    return (
        x * f + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
        y * f + 2 * p2 * x * y + p1 * (r2 + 2 * y * y),
    )
