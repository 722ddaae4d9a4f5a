"""Whether a pile stands still: its parts left to gravity on their support for a moment in
MuJoCo (the engine ``annotator synth`` drops parts with), and how far each moved (see
:mod:`annotator.physics` for the conventions).

MuJoCo collides meshes by their convex hulls and its contacts are soft: a pile that stands
still moves by a fraction of a millimetre in the moment simulated, a part resting on nothing
falls by centimetres.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from annotator.geometry import MM_PER_M
from annotator.geometry.mesh import Mesh
from annotator.geometry.transforms import invert, make_transform
from annotator.physics.contact import Body
from annotator.physics.support import Support, SupportPlane

#: How long the pile is left to gravity (s).
SECONDS = 0.2
FRICTION = [0.6, 0.005, 0.0001]


def add_mesh_body(
    spec: mujoco.MjSpec,
    name: str,
    mesh: Mesh,
    pos: Sequence[float],
    quat: Sequence[float],
    *,
    damping: float = 0.002,
    density: float = 1200.0,
) -> None:
    """A free body ``name`` of ``mesh`` (mm) at ``pos`` (m) turned by ``quat`` (w, x, y, z):
    the body's frame is the mesh's own (MuJoCo collides its convex hull)."""
    m = spec.add_mesh()
    m.name = f"{name}-mesh"
    m.uservert = (mesh.vertices / MM_PER_M).astype(np.float32).ravel().tolist()
    m.userface = mesh.faces.astype(np.int32).ravel().tolist()
    body = spec.worldbody.add_body()
    body.name = name
    body.pos = list(pos)
    body.quat = list(quat)
    j = body.add_freejoint()
    j.damping = [damping, 0.0, 0.0]
    g = body.add_geom()
    g.type = mujoco.mjtGeom.mjGEOM_MESH
    g.meshname = m.name
    g.density = density
    g.friction = FRICTION


def body_pose(model: mujoco.MjModel, data: mujoco.MjData, name: str) -> np.ndarray:
    """Body ``name``'s pose (4x4, mm) in the simulation's world."""
    bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
    w, x, y, z = data.xquat[bid]
    return make_transform(Rotation.from_quat([x, y, z, w]).as_matrix(), data.xpos[bid] * MM_PER_M)


def world_of(support: SupportPlane) -> np.ndarray:
    """``world_T_cam`` (4x4): the support is the plane z = 0, up is +z."""
    R = Rotation.align_vectors([[0.0, 0.0, 1.0]], [support.n])[0].as_matrix()
    return make_transform(R, R @ (support.d * support.n))


def falls(
    bodies: Sequence[Body],
    support: Support,
    *,
    seconds: float = SECONDS,
    timestep: float = 0.002,
) -> list[float]:
    """How far (mm) each body's farthest vertex moves when the pile is left to gravity for
    ``seconds`` on its support: an endless floor, and the measured surface (the bin's walls)
    as a height field where there is one."""
    world_T_cam = world_of(support.plane)
    spec = mujoco.MjSpec()
    spec.option.timestep = timestep
    spec.option.gravity = [0.0, 0.0, -9.81]
    floor = spec.worldbody.add_geom()
    floor.type = mujoco.mjtGeom.mjGEOM_BOX
    floor.size = [2.0, 2.0, 0.01]
    floor.pos = [0.0, 0.0, -0.01]
    floor.friction = FRICTION
    before = [world_T_cam @ b.T for b in bodies]
    if support.surface is not None and bodies:
        _add_surface(spec, support.surface, world_T_cam, before)
    for k, (b, T) in enumerate(zip(bodies, before)):
        x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
        add_mesh_body(spec, f"part{k}", b.mesh, T[:3, 3] / MM_PER_M, [w, x, y, z])
    model = spec.compile()
    data = mujoco.MjData(model)
    for _ in range(int(round(seconds / timestep))):
        mujoco.mj_step(model, data)
    out = []
    for k, (b, T) in enumerate(zip(bodies, before)):
        moved = body_pose(model, data, f"part{k}") @ invert(T)
        v = b.T[:3, :3] @ b.mesh.vertices.T + b.T[:3, 3:4]  # camera frame
        w = world_T_cam[:3, :3] @ v + world_T_cam[:3, 3:4]
        shift = moved[:3, :3] @ w + moved[:3, 3:4] - w
        out.append(float(np.linalg.norm(shift, axis=0).max()))
    return out


#: The height field's cell (mm) and margin around the parts (mm).
CELL_MM = 2.0
MARGIN_MM = 40.0
#: Measured support this high (mm) above the floor's plane is a wall, not the floor.
WALL_MM = 4.0


def _add_surface(
    spec: mujoco.MjSpec, surface: Mesh, world_T_cam: np.ndarray, poses: Sequence[np.ndarray]
) -> None:
    """The measured support around the parts as a height field: each cell the highest
    point measured in it (the floor where nothing was: under the parts)."""
    centres = np.array([T[:3, 3] for T in poses])
    lo = centres[:, :2].min(axis=0) - MARGIN_MM - 100.0
    hi = centres[:, :2].max(axis=0) + MARGIN_MM + 100.0
    v = surface.vertices @ world_T_cam[:3, :3].T + world_T_cam[:3, 3]
    inside = np.all((v[:, :2] >= lo) & (v[:, :2] < hi), axis=1)
    v = v[inside]
    ncol, nrow = (np.ceil((hi - lo) / CELL_MM).astype(int) + 1).tolist()
    height = np.zeros((nrow, ncol))
    if len(v):
        col = ((v[:, 0] - lo[0]) / CELL_MM).astype(int)
        row = ((v[:, 1] - lo[1]) / CELL_MM).astype(int)
        np.maximum.at(height, (row, col), v[:, 2])
    height[height < WALL_MM] = 0.0  # the floor is the floor's box: measured, it is bumpy
    top = float(height.max())
    if top <= 1.0:  # a floor and nothing more: the floor's box holds
        return
    field = spec.add_hfield()
    field.name = "support"
    field.nrow, field.ncol = nrow, ncol
    half = (hi - lo) / 2 / MM_PER_M
    field.size = [float(half[0]), float(half[1]), top / MM_PER_M, 0.005]
    field.userdata = (height / top).ravel().tolist()
    g = spec.worldbody.add_geom()
    g.type = mujoco.mjtGeom.mjGEOM_HFIELD
    g.hfieldname = "support"
    g.pos = [*((lo + hi) / 2 / MM_PER_M).tolist(), 0.0]
    g.friction = FRICTION
