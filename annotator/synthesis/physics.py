"""Dropping parts into a bin with MuJoCo (mesh collisions use convex hulls).

Physics runs in metres and kilograms (gravity 9.81 m/s^2); poses are returned in mm in the
world (bin) frame. A fixed simulated duration is used rather than waiting for rest: MuJoCo's
soft contacts creep slowly forever (NOTES.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from annotator.geometry import MM_PER_M
from annotator.geometry.mesh import Mesh
from annotator.physics.stability import FRICTION, add_mesh_body, body_pose


@dataclass(frozen=True)
class Bin:
    """An open box: inner size (mm), wall height and thickness; floor top at z = 0."""

    inner: tuple[float, float] = (300.0, 240.0)
    height: float = 120.0
    wall: float = 20.0

    def meshes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The floor and four walls as (centre (3,), full size (3,)) boxes, mm."""
        ix, iy = self.inner
        w, h = self.wall, self.height
        return [
            (np.array([0.0, 0.0, -w / 2]), np.array([ix + 2 * w, iy + 2 * w, w])),
            (np.array([(ix + w) / 2, 0.0, h / 2]), np.array([w, iy + 2 * w, h])),
            (np.array([-(ix + w) / 2, 0.0, h / 2]), np.array([w, iy + 2 * w, h])),
            (np.array([0.0, (iy + w) / 2, h / 2]), np.array([ix, w, h])),
            (np.array([0.0, -(iy + w) / 2, h / 2]), np.array([ix, w, h])),
        ]


def drop_parts(
    meshes: Sequence[Mesh],
    *,
    bin: Bin,
    rng: np.random.Generator,
    duration: float = 2.5,
    timestep: float = 0.002,
) -> list[np.ndarray | None]:
    """Drop one copy of each mesh into ``bin``, one after the other from random poses above it.

    Returns:
        The settled ``world_T_part`` 4x4 poses (mm), in the order of ``meshes``; None for a
        part that left the bin (it bounced out or tunnelled through a wall).
    """
    spec = mujoco.MjSpec()
    spec.option.timestep = timestep
    spec.option.gravity = [0.0, 0.0, -9.81]
    _add_bin(spec, bin)
    for k, mesh in enumerate(meshes):
        _add_part(spec, k, mesh, bin, rng)
    model = spec.compile()
    data = mujoco.MjData(model)
    for _ in range(int(round(duration / timestep))):
        mujoco.mj_step(model, data)
    ix, iy = bin.inner
    poses: list[np.ndarray | None] = []
    for k in range(len(meshes)):
        T = body_pose(model, data, f"part{k}")
        t = T[:3, 3]
        inside = abs(t[0]) < ix / 2 and abs(t[1]) < iy / 2 and -1.0 < t[2] < bin.height * 3
        poses.append(T if inside else None)
    return poses


def _add_bin(spec: mujoco.MjSpec, bin: Bin) -> None:
    """The bin's floor and walls, fixed boxes in the world."""
    for k, (centre, size) in enumerate(bin.meshes()):
        g = spec.worldbody.add_geom()
        g.name = f"bin{k}"
        g.type = mujoco.mjtGeom.mjGEOM_BOX
        g.size = size / 2000.0
        g.pos = centre / MM_PER_M
        g.friction = FRICTION


def _add_part(spec: mujoco.MjSpec, k: int, mesh: Mesh, bin: Bin, rng: np.random.Generator) -> None:
    """Part ``k``, free, at a random pose above the bin (every third one a layer higher, so
    that parts dropped together do not start interpenetrating)."""
    ix, iy = bin.inner
    margin = 0.3
    r = mesh.moments.radius
    pos = [
        rng.uniform(-ix / 2 * (1 - margin), ix / 2 * (1 - margin)) / MM_PER_M,
        rng.uniform(-iy / 2 * (1 - margin), iy / 2 * (1 - margin)) / MM_PER_M,
        (bin.height + r + (k // 3) * 1.6 * r) / MM_PER_M,
    ]
    q = Rotation.random(random_state=rng).as_quat()  # x, y, z, w
    add_mesh_body(spec, f"part{k}", mesh, pos, [q[3], q[0], q[1], q[2]])
