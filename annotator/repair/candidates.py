"""Other candidate poses of an instance, and a start pose for a part that has none.

annotation.json does not record the candidates ``annotate`` weighed, so they are made again
here from the markers as detected, the way :mod:`annotator.annotation.scene` makes them
(:func:`annotator.pnp.iter_candidate_poses`: SQPnP per camera, both IPPE solutions of every
lone marker), each refined on the markers it explains; the *support* of a candidate is how
many marker views it explains within ``inlier_px``.

A part without a pose is started where a reviewer clicked: from its own markers if any were
read, else from unread marker squares near the click (each square tried on each of the
part's marker sites and corner orders, both IPPE solutions), else at the depth under the
click, in the 24 rotations of the axes; each start is scored by how many measured points
near the click lie on its surface, then refined (:mod:`annotator.refinement`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from annotator.dataset import Dataset
from annotator.dataset.figures import MarkerUse
from annotator.detection.aruco import ImageReading
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.geometry.transforms import make_transform
from annotator.pnp import Observation, iter_candidate_poses, refine_pose, reprojection_errors
from annotator.pnp.multiview import lone_marker_poses
from annotator.refinement import DepthTerm, RefineSettings, measured_points
from annotator.rendering.raycast import PlacedMesh

INLIER_PX = 2.5
#: Two candidates closer than this share of the diameter (RMS surface displacement) are one.
SAME_FRACTION = 0.01


@dataclass(frozen=True)
class Candidate:
    """A pose ``rig_T_model`` and what supports it."""

    T: np.ndarray
    support: int  # marker views within INLIER_PX (or measured points, for a start pose)
    reprojection_px: float | None
    source: str  # how it was made, in words

    def text(self) -> str:
        px = "" if self.reprojection_px is None else f", {self.reprojection_px:.2f} px"
        return f"{self.source}: support {self.support}{px}"


def instance_observations(
    ds: Dataset, readings: Sequence[ImageReading], obj: str, instance: str
) -> list[Observation]:
    """The markers of one instance in every camera's reading (thresholded and soft)."""
    model = ds.objects[obj]
    inst = model.instance(instance)
    sites = model.site_corners(instance)
    site_of = {int(m): k for k, m in enumerate(inst.marker_ids)}
    out = []
    for j, reading in enumerate(readings):
        for d in reading.markers:
            k = site_of.get(int(d.id))
            if k is not None:
                out.append(Observation(j, int(d.id), sites[k], d.corners, soft=d.soft))
    return out


def pose_distance(mesh: Mesh, T1: np.ndarray, T2: np.ndarray) -> float:
    """RMS surface displacement (mm) between two poses of a part."""
    R1 = T1[:3, :3]
    return mesh.moments.rms_displacement(R1.T @ T2[:3, :3], R1.T @ (T2[:3, 3] - T1[:3, 3]))


def alternatives(
    cameras: Sequence[Camera],
    mesh: Mesh,
    obs: Sequence[Observation],
    *,
    limit: int = 8,
) -> list[Candidate]:
    """Distinct candidate poses from the markers, the best supported first."""
    out: list[Candidate] = []
    if not obs:
        return out
    same = SAME_FRACTION * mesh.moments.diameter
    for T in iter_candidate_poses(cameras, obs):
        err = reprojection_errors(cameras, obs, T)
        inl = [k for k in range(len(obs)) if err[k] < 2 * INLIER_PX]
        if not inl:
            continue
        T = refine_pose(cameras, [obs[k] for k in inl], T).T
        err = reprojection_errors(cameras, obs, T)
        ok = err < INLIER_PX
        if not ok.any():
            continue
        if any(pose_distance(mesh, c.T, T) < same for c in out):
            continue
        used = err[ok]
        source = "consensus" if len(inl) > 1 else "one marker (IPPE)"
        out.append(Candidate(T, int(ok.sum()), float(np.sqrt(np.mean(used**2))), source))
        if len(out) >= 4 * limit:
            break
    out.sort(key=lambda c: (-c.support, c.reprojection_px or 0.0))
    return out[:limit]


def _depth_at(
    camera: Camera, depth_camera: Camera, depth: np.ndarray, pixel: tuple[float, float]
) -> np.ndarray | None:
    """The measured point (reference frame) along the ray through ``pixel`` of ``camera``:
    the nearest to that ray of the depth map's points, the nearer ones preferred."""
    step = 2
    rays = depth_camera.pixel_rays(step)
    d = depth[::step, ::step]
    ok = np.isfinite(d) & (d > 0)
    pts = rays[ok] * d[ok][:, None]
    pts = pts @ depth_camera.rig_T_cam[:3, :3].T + depth_camera.rig_T_cam[:3, 3]
    if not len(pts):
        return None
    ray = camera.undistort_pixels(np.array([pixel], float))[0]
    direction = camera.rig_T_cam[:3, :3] @ np.array([ray[0], ray[1], 1.0])
    direction /= np.linalg.norm(direction)
    rel = pts - camera.rig_T_cam[:3, 3]
    along = rel @ direction
    off = np.linalg.norm(rel - along[:, None] * direction, axis=1)
    near = off < max(1.0, float(off.min()) + 0.5)
    k = np.flatnonzero(near)[np.argmin(along[near])]
    return pts[k]


def _axis_rotations() -> list[np.ndarray]:
    """The 24 rotations that map the axes onto the axes."""
    out = []
    for perm in ([0, 1, 2], [1, 2, 0], [2, 0, 1], [1, 0, 2], [0, 2, 1], [2, 1, 0]):
        for signs in np.ndindex(2, 2, 2):
            R = np.zeros((3, 3))
            R[np.arange(3), perm] = np.where(np.array(signs) == 0, 1.0, -1.0)
            if np.linalg.det(R) > 0:
                out.append(R)
    return out


def start_pose(
    ds: Dataset,
    obj: str,
    instance: str,
    *,
    camera: Camera,
    pixel: tuple[float, float],
    readings: Sequence[ImageReading],
    depth: np.ndarray | None,
    others: Sequence[PlacedMesh] = (),
    radius_px: float = 120.0,
) -> Candidate | None:
    """A start pose for ``obj/instance``, which has none, at ``pixel`` of ``camera`` (see the
    module docstring); None when there is neither a marker nor depth to start from."""
    model = ds.objects[obj]
    mesh = model.mesh
    cams = ds.rig.cameras
    own = alternatives(cams, mesh, instance_observations(ds, readings, obj, instance), limit=1)
    if own:
        return own[0]
    dcam = ds.rig.depth_camera
    if depth is None or dcam is None:
        return None
    p = _depth_at(camera, dcam, depth, pixel)
    if p is None:
        return None
    # The part's centre lies behind the surface point clicked, by about half its size.
    view = p - camera.rig_T_cam[:3, 3]
    centre = p + 0.3 * mesh.moments.radius * view / np.linalg.norm(view)
    starts: list[tuple[np.ndarray, str]] = []
    j = [c.name for c in cams].index(camera.name)
    unread = readings[j].unread if j < len(readings) else np.zeros((0, 4, 2))
    sites = model.site_corners(instance)
    for quad in unread:
        if np.linalg.norm(quad.mean(axis=0) - np.asarray(pixel)) > radius_px:
            continue
        for X in sites:
            for m in range(4):
                o = Observation(j, -1, X, np.roll(quad, m, axis=0))
                starts += [
                    (camera.rig_T_cam @ T, "an unread marker square")
                    for T in lone_marker_poses(camera, o)
                ]
    c = mesh.moments.centroid
    starts += [
        (make_transform(R, centre - R @ c), "the depth under the click") for R in _axis_rotations()
    ]
    settings = RefineSettings()
    pts = measured_points(dcam, depth, mesh, starts[-1][0], others, settings)
    if len(pts) < settings.min_points:
        return None
    term = DepthTerm(mesh, pts, dcam.rig_T_cam[:3, 3])
    best: Candidate | None = None
    for T, source in starts:
        r, _, _ = term.residuals(T, settings.start_gate_mm / 2)
        score = int(np.sum(np.abs(r) < settings.end_gate_mm))
        if best is None or score > best.support:
            best = Candidate(T, score, None, source)
    return best


def used_observations(
    cameras: Sequence[Camera],
    mesh: Mesh,
    obs: Sequence[Observation],
    used: dict[str, MarkerUse] | None,
) -> list[Observation]:
    """The observations a refinement may rely on: those ``annotate`` used (``used``:
    annotation.json's ``markers``), or, for an instance it did not pose, those the best
    supported candidate explains (a misread or stray marker must not pull the pose)."""
    if used:
        names = [c.name for c in cameras]
        keep = {(names.index(c), int(i)) for c, m in used.items() if c in names for i in m.used}
        return [o for o in obs if (o.camera, o.marker_id) in keep]
    best = alternatives(cameras, mesh, obs, limit=1)
    if not best:
        return []
    err = reprojection_errors(cameras, obs, best[0].T)
    return [o for o, e in zip(obs, err) if e < INLIER_PX]
