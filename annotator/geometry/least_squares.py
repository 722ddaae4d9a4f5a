"""Damped least squares (Levenberg-Marquardt): the one iteration every solver of the project
runs, the multi-camera PnP (:mod:`annotator.pnp.multiview`), the sequences' bundle adjustment
(:mod:`annotator.pnp.bundle`), the rig calibration (:mod:`annotator.calibration.bundle`) and
the depth refinement (:mod:`annotator.refinement.depth`).

A solver brings what is its own: how to linearise its problem at a state (the normal
equations, dense or sparse, robust weights or not) and how to try a step from it with a given
damping (solve the damped system, move the state with :func:`~annotator.geometry.lie.perturb`,
evaluate the cost). :func:`levenberg_marquardt` keeps the schedule: a step that lowers the
cost is taken and the damping divided (:class:`Damping`), one that does not is refused and
the damping multiplied; the iteration stops when a step taken is small enough (the solver's
``small``), when the damping passes its ceiling (no step lowers the cost: a minimum, as well
as the problem can be solved), when the solver cannot solve its system, or after
``max_iterations``. A solver whose problem changes from one iteration to the next (the depth
refinement, :mod:`annotator.refinement.depth`, narrows the gate its matches are sought
within) gives ``cost_at``: a state's cost under the next iteration's problem, against which
the next steps are judged.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import Generic, TypeVar

import numpy as np

__all__ = ["Damping", "Minimum", "Stop", "levenberg_marquardt"]

S = TypeVar("S")  # a solver's state (its unknowns and what it keeps of them)
L = TypeVar("L")  # its linearisation at a state
D = TypeVar("D")  # its step


@dataclass(frozen=True)
class Damping:
    """Levenberg's damping: ``start``, divided by ``factor`` after a step taken (never below
    ``floor``), multiplied by it after a step refused; past ``ceiling`` the iteration stops."""

    start: float
    floor: float
    ceiling: float
    factor: float = 10.0


class Stop(StrEnum):
    """Why the iteration stopped."""

    SMALL_STEP = "small_step"  # the last step taken was small enough: converged
    NO_DESCENT = "no_descent"  # the damping passed its ceiling: no step lowers the cost
    SINGULAR = "singular"  # the solver could not solve its system
    ITERATIONS = "iterations"  # max_iterations reached


@dataclass(frozen=True)
class Minimum(Generic[S]):
    """Where the iteration stopped: the state, its cost, how many iterations it made and
    why it stopped."""

    state: S
    cost: float
    iterations: int
    stop: Stop


def levenberg_marquardt(
    state: S,
    cost: float,
    linearise: Callable[[S], L],
    trial: Callable[[S, L, float], tuple[S, float, D] | None],
    *,
    damping: Damping,
    small: Callable[[float, float, D], bool],
    max_iterations: int,
    refused_count: bool = True,
    cost_at: Callable[[S], float] | None = None,
) -> Minimum[S]:
    """Minimise from ``state`` (whose cost is ``cost``).

    Args:
        linearise: The state's linearisation (its normal equations), made once per state.
        trial: ``(state, linearisation, damping)`` -> the state a damped step reaches, its
            cost and the step; None when the system cannot be solved.
        small: ``(cost, new cost, step)`` -> whether a step taken is small enough to stop.
        refused_count: Whether a refused step counts as an iteration (else an iteration is
            one linearisation, with as many trials as it takes to lower the cost).
        cost_at: A state taken -> its cost under the next iteration's problem, for a problem
            that changes between iterations (None: the cost its trial gave stands).

    >>> # f(x) = (x - 3)^2 from x = 0: one Gauss-Newton step, then a step of nothing.
    >>> def trial(x, lin, lam):
    ...     J, r = lin
    ...     step = -J * r / (J * J * (1 + lam))
    ...     return x + step, float((x + step - 3.0) ** 2), np.array([step])
    >>> m = levenberg_marquardt(0.0, 9.0, lambda x: (1.0, x - 3.0), trial,
    ...     damping=Damping(1e-9, 1e-12, 1e8), max_iterations=50,
    ...     small=lambda c, c_new, step: abs(step).max() < 1e-6)
    >>> round(m.state, 6), m.stop
    (3.0, <Stop.SMALL_STEP: 'small_step'>)
    """
    lam = damping.start
    lin = linearise(state)
    iterations = 0
    while iterations < max_iterations:
        iterations += 1
        while True:
            tried = trial(state, lin, lam)
            if tried is None:
                return Minimum(state, cost, iterations, Stop.SINGULAR)
            new, new_cost, step = tried
            if np.isfinite(new_cost) and new_cost < cost:
                done = small(cost, new_cost, step)
                state, cost = new, new_cost
                lam = max(lam / damping.factor, damping.floor)
                if done:
                    return Minimum(state, cost, iterations, Stop.SMALL_STEP)
                if cost_at is not None:
                    cost = cost_at(state)
                if iterations < max_iterations:  # else it would go unused
                    lin = linearise(state)
                break
            lam *= damping.factor
            if lam > damping.ceiling:
                return Minimum(state, cost, iterations, Stop.NO_DESCENT)
            if refused_count:
                break
    return Minimum(state, cost, iterations, Stop.ITERATIONS)
