"""How well a hypothesis agrees with the measured depth: the part rendered at the pose.

The part is ray cast alone at the pose in the depth camera (pixel-exact, lens distortion
included, as annotate's depth agreement; every ``step``-th pixel of every ``step``-th row),
and each rendered pixel with a measurement is one of:

- *agreeing*: measured and rendered depth within ``max(3 mm, 1%)`` (annotate's tolerance);
- *contradicting*: the measurement lies behind the rendered surface: the camera sees
  through where the part would be, so it is not there;
- *occluded*: the measurement lies in front; something hides the part (neutral).

The score is ``(agreeing - contradicting) / rendered pixels``: 1 for a part fully seen where
the pose puts it, about 0.5 for one half hidden, negative for a pose in thin air. A pose and
its symmetric equivalents render the same, so they score the same.
"""

from __future__ import annotations

import numpy as np

from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.occlusion import AGREEMENT_TOLERANCE_MM
from annotator.rendering.raycast import cast_alone, projected_bbox


def depth_consistency(
    camera: Camera,
    depth: np.ndarray,
    mesh: Mesh,
    cam_T_model: np.ndarray,
    *,
    step: int = 2,
    tolerance_rel: float = 0.01,
) -> float:
    """The score of the module docstring, in [-1, 1]; -1 for a pose rendered nowhere in the
    image. ``depth`` is the full-resolution map (mm, NaN = none) of ``camera``."""
    box = projected_bbox(camera, mesh, cam_T_model)
    if box is None:
        return -1.0
    x0, y0, x1, y1 = (-(-v // step) for v in box)
    if x0 >= x1 or y0 >= y1:
        return -1.0
    rays = camera.pixel_rays(step)[y0:y1, x0:x1]
    rendered = cast_alone(mesh, cam_T_model, rays).depth
    measured = depth[::step, ::step][y0:y1, x0:x1]
    on = np.isfinite(rendered)
    n = int(on.sum())
    if n == 0:
        return -1.0
    r, m = rendered[on], measured[on]
    tol = np.maximum(AGREEMENT_TOLERANCE_MM, tolerance_rel * r)
    with np.errstate(invalid="ignore"):
        agree = int(np.sum(np.abs(m - r) < tol))
        behind = int(np.sum(m > r + tol))
    return (agree - behind) / n
