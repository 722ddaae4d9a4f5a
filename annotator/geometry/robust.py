"""Robust statistics every solver shares: the Huber weights of residuals and the noise that
residuals show, from their median absolute deviation (a Gaussian's sigma is
:data:`MAD_TO_SIGMA` times it), so that a few outliers neither steer a fit nor inflate the
noise it reports."""

from __future__ import annotations

import numpy as np

__all__ = ["MAD_TO_SIGMA", "huber_cost", "huber_weights", "robust_sigma"]

#: A Gaussian's standard deviation over its median absolute deviation (1 / Phi^-1(3/4)).
MAD_TO_SIGMA = 1.4826


def huber_weights(r: np.ndarray, k: float) -> np.ndarray:
    """The weights that make least squares minimise Huber's loss of threshold ``k``: 1 within
    ``k``, ``k / |r|`` beyond (iteratively reweighted least squares).

    >>> huber_weights(np.array([0.5, -2.0, 4.0]), 1.0).tolist()
    [1.0, 0.5, 0.25]
    """
    a = np.abs(r)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def huber_cost(r: np.ndarray, k: float) -> float:
    """Huber's loss of the residuals ``r``: quadratic within ``k``, linear beyond.

    >>> huber_cost(np.array([1.0, 3.0]), 2.0)
    4.5
    """
    a = np.abs(r)
    return float(np.sum(np.where(a <= k, 0.5 * a**2, k * a - 0.5 * k**2)))


def robust_sigma(x: np.ndarray, centre: float = 0.0) -> float:
    """The standard deviation ``x`` would have about ``centre`` were it Gaussian, from its
    median absolute deviation (0 for no values).

    >>> round(robust_sigma(np.random.default_rng(0).normal(0, 2, 100_000)), 2)
    2.0
    """
    x = np.asarray(x, np.float64)
    return MAD_TO_SIGMA * float(np.median(np.abs(x - centre))) if x.size else 0.0
