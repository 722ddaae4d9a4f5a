"""Pick-ready labels of a pile: which parts lie on top (nothing above them within their
footprint) and how much free height there is above each, for a gripper coming from above
(see :mod:`annotator.physics` for the conventions)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from annotator.geometry.open3d_lib import o3d
from annotator.physics.contact import Body
from annotator.physics.support import Support
from annotator.rendering.raycast import get_threads

#: Up in a camera frame where no support is known: towards the camera, which looks down.
CAMERA_UP = np.array([0.0, 0.0, -1.0])
#: A surface faces up when its normal is this close to up (cosine).
FACING_UP = 0.2


@dataclass(frozen=True)
class PickLabel:
    """``on_top``: nothing lies above the part within its footprint; ``free_height_mm``:
    the clearance above its upward-facing surface to the nearest part over it (None when
    it is on top)."""

    on_top: bool
    free_height_mm: float | None

    def to_json(self) -> dict[str, Any]:
        h = self.free_height_mm
        return {"on_top": self.on_top, "free_height_mm": None if h is None else round(h, 2)}


def pick_labels(bodies: Sequence[Body], support: Support | None) -> list[PickLabel]:
    """Each body's :class:`PickLabel`: rays cast up (against gravity: the support's normal,
    else towards the camera) from its upward-facing surface against every other body."""
    up = support.plane.n if support is not None else CAMERA_UP
    out = []
    for i, body in enumerate(bodies):
        pts, normals = body.samples
        facing = normals.T @ up > FACING_UP
        others = [b for j, b in enumerate(bodies) if j != i]
        if not facing.any() or not others:
            out.append(PickLabel(True, None))
            continue
        scene = o3d.t.geometry.RaycastingScene(nthreads=get_threads())
        for b in others:
            v = b.T[:3, :3] @ b.mesh.vertices.T + b.T[:3, 3:4]
            scene.add_triangles(
                o3d.core.Tensor(np.ascontiguousarray(v.T, dtype=np.float32)),
                o3d.core.Tensor(b.mesh.faces.astype(np.uint32)),
            )
        origins = pts[:, facing].T
        rays = np.hstack([origins, np.broadcast_to(up, origins.shape)]).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays), nthreads=get_threads())["t_hit"].numpy()
        hit = hit[np.isfinite(hit)]
        out.append(PickLabel(False, float(hit.min())) if len(hit) else PickLabel(True, None))
    return out
