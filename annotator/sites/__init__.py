"""Markers glued by hand: each instance's real marker sites, measured from its scenes.

``annotator sites DATASET`` reads the annotated scenes, finds every instance's markers again
in every camera, and solves per instance for its poses and its markers' corrections within
their sites' planes (:mod:`annotator.sites.solve`); the measured sites go into object.yaml
as the instance's own ``sites`` (:mod:`annotator.sites.measure`), which ``annotate`` then
uses instead of the layout.
"""

from __future__ import annotations

from annotator.sites.solve import InstanceData, MarkerView, SiteSettings, SiteSolution, solve_sites

__all__ = ["InstanceData", "MarkerView", "SiteSettings", "SiteSolution", "solve_sites"]
