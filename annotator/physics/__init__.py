"""Is a pile of posed parts physically possible? Parts that pass through each other or
through their support, parts that rest on nothing, piles that would not stand still, and the
pick-ready labels that follow from the same geometry.

Conventions (stated once, followed by every module here):

- Poses are ``cam_T_model`` (4x4, mm) in one camera frame, the scene's reference camera.
- The **support** is a plane in that frame, ``n . x + d = 0`` with the unit normal ``n``
  pointing *up*, away from the support and towards the camera; gravity is ``-n``. A point's
  **height** is ``n . x + d`` (mm, negative below the support).
- A **penetration** is how deep (mm) one body's surface reaches inside another solid: the
  deepest surface point of either inside the other, measured as the exact signed distance of
  points sampled on the surface (every vertex included) to the other's triangle mesh as it
  is (not its convex hull).
- A **gap** is how far (mm) a body's lower half is from what could hold it: the support
  (the floor's plane below it, or a wall it leans on), or another body's convex hull in any
  direction (a part wedged between others rests on their sides; one bridging a concave
  neighbour's opening rests on its rims, which the hull shares).
"""

from __future__ import annotations

from annotator.physics.check import InstancePhysics, PhysicsSettings, check_bodies
from annotator.physics.contact import Body
from annotator.physics.support import Support, SupportPlane, fit_support_plane

__all__ = [
    "Body",
    "InstancePhysics",
    "PhysicsSettings",
    "Support",
    "SupportPlane",
    "check_bodies",
    "fit_support_plane",
]
