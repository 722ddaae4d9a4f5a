"""How well each marker's site is known on its part, as a pose's uncertainty counts it.

A pose rests on its markers' sites: where they really are on the part is an error shared by
every camera that sees them, which the pose's reprojection residuals cannot show (the pose
follows the sites). So a pose's stated uncertainty adds what its sites' errors do to it
(:func:`annotator.refinement.depth.pose_covariance`), per marker id a 1-sigma of the site's
shifts in its plane (mm, each of two) and of its turn about its normal (rad):

- no site of the object measured (``annotator sites`` never ran, or the markers were placed
  exactly): the layout is exact, nothing is added;
- a site ``annotator sites`` measured from ``n`` scenes: each shift to
  ``AnnotateSettings.one_scene_site_mm / n``, never below ``measured_site_mm`` (the turn to
  what that shift is at the corners, never below ``measured_site_deg``); an object.yaml
  that does not say from how many scenes (written before ``site_scenes``): to
  ``measured_site_mm`` and ``measured_site_deg``;
- one it measured from a single scene was fitted to that scene's pose: where that scene is
  annotated again the pose and the site are off together, with residuals that show nothing,
  so its error is an unknown the pose shares, not one it follows: the marker only tells the
  pose what is left once its site may move (:class:`SiteErrors`' ``fitted``);
- one it could not measure (left on the layout): the spread of the object's measured sites
  about their layout (how far gluing moves a marker), split between the two shifts and the
  turn's reach at the corners; no site is less known than that (where gluing moved the
  markers little, one fitted to a single scene cannot be far off either).

A pose none of whose sites is known well (measured from :data:`MIN_SCENES` scenes or more,
or to ``measured_site_mm`` anyway) is flagged ``unchecked_sites``: its uncertainty may be
honest, but nothing independent of it places its markers (more scenes of the part would).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from annotator.annotation.settings import AnnotateSettings
from annotator.dataset.model import ObjectModel
from annotator.pnp import Observation

#: A site of an instance within this of the layout's (mm, RMS over its corners) was not moved
#: by ``annotator sites``: it could not measure it.
UNMOVED_MM = 0.01
#: A site measured from fewer scenes than this was fitted to the one pose it was seen in.
MIN_SCENES = 2


@dataclass(frozen=True)
class SiteErrors:
    """The 1-sigma of each marker's site, shifts in its plane (mm, each of two) and turn
    about its normal (rad), per marker id, in two kinds.

    Attributes:
        taken: Sites a pose takes as they are: their errors move it.
        fitted: Sites measured from one scene only, fitted to that scene's pose: their
            errors are unknowns the pose shares (see
            :func:`annotator.refinement.depth.pose_covariance`'s ``fitted_sites``).
        checked: The ids whose sites are known well: measured from :data:`MIN_SCENES`
            scenes or more, or to ``measured_site_mm`` anyway.
    """

    taken: dict[int, tuple[float, float]]
    fitted: dict[int, tuple[float, float]]
    checked: frozenset[int] = frozenset()

    @property
    def unchecked(self) -> bool:
        """The sites are not exact and none is known well (``checked``): the pose rests on
        markers nothing independent places (``unchecked_sites``)."""
        return not self.exact and not self.checked

    @property
    def exact(self) -> bool:
        """Every site is exact: a pose's uncertainty has nothing to add."""
        sigmas = [*self.taken.values(), *self.fitted.values()]
        return not any(shift > 0 or turn > 0 for shift, turn in sigmas)


def site_errors(
    model: ObjectModel, instance: str, used: Sequence[Observation], s: AnnotateSettings
) -> SiteErrors:
    """How well the site of each marker of ``used`` is known: see the module docstring.

    >>> from annotator import load_dataset
    >>> brick = load_dataset("sample_scenes").objects["brick"]
    >>> first = brick.instances[0]
    >>> o = Observation(0, first.marker_ids[0], np.zeros((4, 3)), np.zeros((4, 2)))
    >>> site_errors(brick, first.name, [o], AnnotateSettings()).exact  # the layout is exact
    True
    """
    taken: dict[int, tuple[float, float]] = {}
    fitted: dict[int, tuple[float, float]] = {}
    checked: set[int] = set()
    if model.markers is None:
        return SiteErrors(taken, fitted)
    moved_by = _moved(model)
    shift = _spread(moved_by) / np.sqrt(2.0)
    reach = model.markers.size / np.sqrt(2.0)  # a corner's distance from the site's centre
    unmeasured = (shift, shift / reach)
    measured = (s.measured_site_mm, float(np.radians(s.measured_site_deg)))
    inst = model.instance(instance)
    ids = [int(m) for m in inst.marker_ids]
    scenes = inst.site_scenes
    for o in used:
        k = ids.index(o.marker_id)
        n = None if scenes is None else scenes[k]
        if moved_by[instance][k] <= UNMOVED_MM:
            n, sigma = 0, unmeasured
        elif n is None:
            sigma = measured
        else:
            shift_n = max(s.measured_site_mm, s.one_scene_site_mm / max(n, 1))
            sigma = (shift_n, max(measured[1], shift_n / reach))
        # Never less known than a site nobody measured: where gluing moved the markers
        # little, a site fitted to one scene cannot be far off either.
        sigma = (min(sigma[0], unmeasured[0]), min(sigma[1], unmeasured[1]))
        if n is not None and 0 < n < MIN_SCENES:
            fitted[o.marker_id] = sigma
        else:
            taken[o.marker_id] = sigma
        if n is None or n >= MIN_SCENES or sigma[0] <= s.measured_site_mm:
            checked.add(o.marker_id)
    return SiteErrors(taken, fitted, frozenset(checked))


def _moved(model: ObjectModel) -> dict[str, np.ndarray]:
    """Per instance, how far each of its sites is from the layout's (mm, RMS over corners;
    zeros without its own sites)."""
    assert model.markers is not None
    layout = model.markers.corners
    out = {}
    for inst in model.instances:
        if inst.sites is None:
            out[inst.name] = np.zeros(len(layout))
        else:
            out[inst.name] = np.sqrt(np.mean(np.sum((inst.sites - layout) ** 2, -1), axis=1))
    return out


def _spread(moved_by: dict[str, np.ndarray]) -> float:
    """The RMS corner distance of the object's measured sites from the layout (mm): how far
    one nobody measured may be; 0 when none was measured."""
    moved = np.concatenate([v[v > UNMOVED_MM] for v in moved_by.values()] or [np.zeros(0)])
    return float(np.sqrt(np.mean(moved**2))) if len(moved) else 0.0
