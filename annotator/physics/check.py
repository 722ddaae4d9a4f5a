"""The physics check of one pile: per instance, its deepest penetration (into which part, or
the support), its gap to what is below it, and the flags a reviewer should see (see
:mod:`annotator.physics` for the conventions).

A figure is flagged only beyond what the poses' own uncertainty explains: three times the
combined 1-sigma ``uncertainty_mm`` of the two parties (one for the support), and never
below a floor that covers touching parts (contacts are never exact, even in a physics
engine's piles).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from annotator.dataset.figures import SUPPORT, PhysicsCheck
from annotator.dataset.flags import Flag
from annotator.physics.contact import (
    Body,
    boxes_overlap,
    least_hull_distance,
    overlapping_boxes,
    penetration,
)
from annotator.physics.support import Support

#: About how many of a body's lower points its gap is measured from.
GAP_POINTS = 600
#: A gap this small (mm) is a touch: nothing else need be looked at.
TOUCHING_MM = 0.05


@dataclass(frozen=True)
class PhysicsSettings:
    """Thresholds of the physics check.

    Attributes:
        sigmas: How many combined 1-sigma uncertainties a figure may reach unflagged.
        penetration_floor_mm: Penetrations up to this are never flagged.
        gap_floor_mm: Gaps up to this are never flagged.
        fall_floor_mm: With the stability check, moves up to this are never flagged.

    >>> PhysicsSettings() == PhysicsSettings()
    True
    """

    sigmas: float = 3.0
    penetration_floor_mm: float = 1.0
    gap_floor_mm: float = 1.5
    fall_floor_mm: float = 15.0


@dataclass
class InstancePhysics:
    """One body's physics: its figures and its physics flags (:data:`PHYSICS_FLAGS`)."""

    key: str
    check: PhysicsCheck = field(default_factory=PhysicsCheck)
    flags: list[Flag] = field(default_factory=list)

    def describe(self) -> str:
        """One line: the instance, what is wrong, with whom."""
        return f"{self.key}: {self.check.describe(list(self.flags))}"


def check_bodies(
    bodies: Sequence[Body],
    support: Support | None,
    *,
    uncertainty: Mapping[str, float | None] | None = None,
    settings: PhysicsSettings | None = None,
) -> list[InstancePhysics]:
    """The physics figures and flags of every body of one pile (in the order given).

    ``uncertainty``: each key's 1-sigma ``uncertainty_mm`` (missing or None: 0, exact poses
    such as gt.json's); ``support``: what the pile rests on, None if unknown (then no gap
    is measured and nothing is flagged ``floats``). Penetrating the support is going below
    its floor's plane; the gap to it is to the plane or its measured surface.
    """
    settings = settings or PhysicsSettings()
    u = {b.key: float((uncertainty or {}).get(b.key) or 0.0) for b in bodies}
    out = [InstancePhysics(b.key) for b in bodies]
    # Overlaps between parts: only pairs whose bounds meet can overlap.
    for i, j in overlapping_boxes(bodies):
        a, b = bodies[i], bodies[j]
        depth = penetration(a, b)
        for k, other in ((i, b.key), (j, a.key)):
            if depth > out[k].check.penetration_mm:
                out[k].check.penetration_mm, out[k].check.penetrates = depth, other
        limit = _limit(settings.penetration_floor_mm, settings, u[a.key], u[b.key])
        if depth > limit:
            _flag(out[i], Flag.PENETRATES, b.key)
            _flag(out[j], Flag.PENETRATES, a.key)
    if support is not None:
        for i, rec in enumerate(out):
            _on_support(rec, i, bodies, support, u, settings)
    return out


def check_one(
    body: Body,
    others: Sequence[Body],
    support: Support | None,
    *,
    uncertainty: float = 0.0,
    settings: PhysicsSettings | None = None,
) -> InstancePhysics:
    """The physics of ``body`` alone among ``others`` (taken as they are: a pose estimate
    among the true parts): its deepest penetration and its gap, flagged as
    :func:`check_bodies` flags them."""
    settings = settings or PhysicsSettings()
    rec = InstancePhysics(body.key)
    limit = _limit(settings.penetration_floor_mm, settings, uncertainty)
    for other in others:
        if boxes_overlap(body, other):
            depth = penetration(body, other)
            if depth > rec.check.penetration_mm:
                rec.check.penetration_mm, rec.check.penetrates = depth, other.key
            if depth > limit:
                _flag(rec, Flag.PENETRATES, other.key)
    if support is not None:  # the others' uncertainty is not the estimate's to carry
        _on_support(rec, 0, [body, *others], support, {body.key: uncertainty}, settings)
    return rec


def _on_support(
    rec: InstancePhysics,
    i: int,
    bodies: Sequence[Body],
    support: Support,
    u: Mapping[str, float],
    settings: PhysicsSettings,
) -> None:
    """Body ``i``'s depth below the support's floor and its gap to what could hold it,
    flagged beyond their thresholds, into ``rec``."""
    a = bodies[i]
    heights = support.plane.height(a.points)
    below = max(0.0, -float(heights.min()))
    if below > rec.check.penetration_mm:
        rec.check.penetration_mm, rec.check.penetrates = below, SUPPORT
    if below > _limit(settings.penetration_floor_mm, settings, u.get(a.key, 0.0)):
        _flag(rec, Flag.PENETRATES, SUPPORT)
    gap, rests_on = _gap(i, bodies, support, heights)
    rec.check.gap_mm, rec.check.rests_on = gap, rests_on
    limit = _limit(settings.gap_floor_mm, settings, u.get(a.key, 0.0), u.get(rests_on, 0.0))
    if gap > limit:
        _flag(rec, Flag.FLOATS, rests_on)


def _gap(
    i: int, bodies: Sequence[Body], support: Support, heights: np.ndarray
) -> tuple[float, str]:
    """How far body ``i``'s lower half is from what could hold it: the support (the floor
    below it, a wall it leans on) or another body's hull (in any direction: a part wedged
    between others rests on their sides); the nearest of them."""
    a = bodies[i]
    lower = np.flatnonzero(heights < float(support.plane.height(a.centroid[:, None])[0]))
    # A gap is no needle: fewer points will do (picked before they are gathered).
    low = a.points[:, lower[:: max(1, len(lower) // GAP_POINTS)]]
    floor = max(0.0, float(heights.min()))
    if low.shape[1] == 0 or floor <= TOUCHING_MM:  # on the floor: nothing is nearer
        return floor, SUPPORT
    best, rests_on = support.least_distance(low), SUPPORT
    for j, b in enumerate(bodies):
        if best <= TOUCHING_MM:
            break
        if j == i or not boxes_overlap(a, b, margin=best):
            continue
        # The hull lies in b's box: a point further than ``best`` from the box is further
        # from the hull, and cannot be the nearest.
        lo, hi = b.box
        near = np.all((low >= lo[:, None] - best) & (low <= hi[:, None] + best), axis=0)
        if not near.any():
            continue
        d = least_hull_distance(low[:, near], b, best)
        if d < best:
            best, rests_on = d, b.key
    return best, rests_on


def _limit(floor: float, settings: PhysicsSettings, *uncertainties: float) -> float:
    return max(floor, settings.sigmas * float(np.sqrt(sum(x * x for x in uncertainties))))


def _flag(rec: InstancePhysics, flag: Flag, partner: str) -> None:
    """Flag ``rec`` naming ``partner`` (for a penetration, the deepest one flagged)."""
    if flag not in rec.flags:
        rec.flags.append(flag)
    if flag == Flag.PENETRATES:
        rec.check.partners[str(flag)] = rec.check.penetrates or partner
    else:
        rec.check.partners.setdefault(str(flag), partner)
