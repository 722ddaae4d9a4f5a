"""The physics check of a dataset's scene: its posed parts as bodies, the support fitted to
the empty bin's depth (``rig.depth.background``) or to the scene's own depth away from the
parts, then :func:`~annotator.physics.check.check_bodies` (see :mod:`annotator.physics` for
the conventions). Poses are a fixed rig's in its reference camera, a sequence's in its scene
frame (its first posed frame's depth gives the support)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from annotator.dataset import Dataset, InstancePose
from annotator.dataset.flags import Flag, sort_flags
from annotator.dataset.frames import Shot
from annotator.dataset.records import InstanceAnnotation
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert
from annotator.physics.check import InstancePhysics, PhysicsSettings, check_bodies
from annotator.physics.contact import Body, signed_distance
from annotator.physics.support import (
    INLIER_MM,
    Support,
    SupportPlane,
    depth_grid,
    fit_support_plane,
    grid_surface,
)

#: Depth points this close (mm) to a posed part are the part's, not the support's (small:
#: the support next to a part leaning on it must stay).
PART_MARGIN_MM = 2.0
#: A measured floor may be this far (mm) off the parts resting on it, and is then moved.
FLOOR_BIAS_MM = 3.0
#: How many parts must rest on the floor for it to be moved to them.
RESTING_PARTS = 3
#: Planes of a scene's depth weighed as the floor of its pile, and the share of the points
#: the ones before left that each after the first must hold (the floor seen between the
#: parts of a full bin is a small part of the view).
CANDIDATE_PLANES = 4
NEXT_PLANE_SHARE = 0.1
#: A floor's normal lies within this angle (degrees) of the line of sight of a camera
#: looking into the bin; a wall's is further off.
FLOOR_VIEW_DEG = 60.0

# The empty bin's support, by dataset, background file and depth camera.
_EMPTY_BIN: dict[tuple[str, str, object], Support | None] = {}


def bodies_of(ds: Dataset, poses: Sequence[InstancePose]) -> list[Body]:
    """The posed parts as bodies (poses of objects the dataset does not have are left out)."""
    return [Body(p.key, ds.objects[p.object].mesh, p.T) for p in poses if p.object in ds.objects]


def shot_support(
    ds: Dataset, shot: Shot, bodies: Sequence[Body], depth: np.ndarray | None = None
) -> Support | None:
    """What the parts rest on, in the scene's frame: from the empty bin's depth for a fixed
    rig that has one, else from ``shot``'s depth (read if not given) away from the posed
    ``bodies``; None without depth, or where no floor's plane holds."""
    spec = ds.rig.depth
    if spec is None:
        return None
    cam = ds.rig.camera(spec.camera)
    if shot.frame is None and spec.background is not None:
        found = empty_bin(ds)  # every scene's: the floor's offset is the scene's own
    else:
        if depth is None:
            depth = shot.capture.read_depth(ds.rig)
        found = _measured_support(depth, cam, invert(shot.rig_T_scene), bodies)
    return None if found is None else found.lowered(floor_offset(found.plane, bodies))


def empty_bin(ds: Dataset) -> Support | None:
    """The support the empty bin's depth (``rig.depth.background``) measures, fitted once
    per process (None: no such depth, or no floor in it)."""
    spec = ds.rig.depth
    if spec is None or spec.background is None:
        return None
    cam = ds.rig.camera(spec.camera)
    key = (str(ds.root), spec.background, cam.grid_key)
    if key not in _EMPTY_BIN:
        _EMPTY_BIN[key] = _measured_support(ds.background_depth, cam, np.eye(4))
    return _EMPTY_BIN[key]


def _measured_support(
    depth: np.ndarray | None,
    cam: Camera,
    scene_T_rig: np.ndarray,
    bodies: Sequence[Body] = (),
) -> Support | None:
    """The support a depth map of ``cam`` measures, in the scene's frame, away from the
    ``bodies`` (none: an empty bin); None without depth or a floor's plane."""
    if depth is None:
        return None
    grid = depth_grid(depth, cam)  # the depth camera's frame
    scene_T_cam = scene_T_rig @ cam.rig_T_cam
    grid = grid @ scene_T_cam[:3, :3].T + scene_T_cam[:3, 3]
    if bodies:  # the parts' own surfaces are not the support
        pts = grid.reshape(-1, 3)
        for b in bodies:
            lo, hi = b.box
            near = np.all((pts >= lo - PART_MARGIN_MM) & (pts <= hi + PART_MARGIN_MM), axis=1)
            idx = np.flatnonzero(near)
            if len(idx):
                d = signed_distance(b.mesh, b.to_model(pts[idx].T))
                pts[idx[d < PART_MARGIN_MM]] = np.nan
        grid = pts.reshape(grid.shape)
    flat = grid.reshape(-1, 3)
    view = scene_T_cam[:3, 2]
    plane = floor_of_pile(flat, bodies, view=view) if bodies else fit_support_plane(flat)
    return None if plane is None else Support(plane, grid_surface(grid))


def floor_of_pile(
    points: np.ndarray, bodies: Sequence[Body], *, view: np.ndarray | None = None
) -> SupportPlane | None:
    """The plane of ``points`` (N, 3; NaN: none) that the ``bodies`` rest on; ``view``: the
    direction the camera that measured them looks along (default +z, the points' frame
    being the camera's).

    The dominant plane is the floor when the bin is seen from above and the parts leave
    some of it bare; close by, or at a slant, a wall or the bin's rim may hold more points.
    So up to :data:`CANDIDATE_PLANES` planes are found in turn, each among the points the
    ones before did not hold. The one kept faces the camera (a floor is seen from above,
    a wall edge-on: its normal within :data:`FLOOR_VIEW_DEG` of the line of sight, when
    any does) and has the most parts resting on it and the fewest through it (the first,
    on a tie).

    >>> rng = np.random.default_rng(0)
    >>> rim = np.c_[rng.uniform(-150, 150, (3000, 2)), np.full(3000, 500.0)]
    >>> floor = np.c_[rng.uniform(-100, 100, (800, 2)), np.full(800, 620.0)]
    >>> round(fit_support_plane(np.r_[rim, floor]).d, 1)  # the rim, 500 mm away, holds most
    500.0
    """
    look = np.array([0.0, 0.0, 1.0]) if view is None else np.asarray(view, float)
    pts = points.copy()
    best: tuple[tuple[bool, int], SupportPlane] | None = None
    for k in range(CANDIDATE_PLANES):
        plane = fit_support_plane(pts, min_share=0.25 if k == 0 else NEXT_PLANE_SHARE)
        if plane is None:
            break
        lowest = np.array([float(plane.height(b.points).min()) for b in bodies])
        resting = int(np.sum(np.abs(lowest) < FLOOR_BIAS_MM))
        through = int(np.sum(lowest < -FLOOR_BIAS_MM))
        facing = abs(float(plane.n @ look)) >= np.cos(np.radians(FLOOR_VIEW_DEG))
        score = (facing, resting - 2 * through)
        if best is None or score > best[0]:
            best = (score, plane)
        if facing and through == 0 and resting >= min(RESTING_PARTS, len(bodies)):
            break  # a floor, surely: nothing need be looked at beyond it
        with np.errstate(invalid="ignore"):
            pts[np.abs(plane.height(pts.T)) < 2 * INLIER_MM] = np.nan
    return None if best is None else best[1]


def floor_offset(plane: SupportPlane, bodies: Sequence[Body]) -> float:
    """How far (mm) the measured floor lies above the parts resting on it: the median of
    their lowest points' depth below it, when at least :data:`RESTING_PARTS` parts lie
    within :data:`FLOOR_BIAS_MM` of it (a depth sensor's offset of a millimetre or two);
    0 otherwise. One part sunk into the floor does not move the median."""
    lowest = np.array([float(plane.height(b.points).min()) for b in bodies])
    resting = lowest[np.abs(lowest) < FLOOR_BIAS_MM]
    if len(resting) < RESTING_PARTS:
        return 0.0
    return float(-np.median(resting))


def shot_physics(
    ds: Dataset,
    shot: Shot,
    poses: Sequence[InstancePose],
    *,
    uncertainty: Mapping[str, float | None] | None = None,
    settings: PhysicsSettings | None = None,
    stability: bool = False,
    depth: np.ndarray | None = None,
) -> tuple[list[InstancePhysics], Support | None]:
    """The physics of the parts ``poses`` places in ``shot``'s scene (the scene frame), and
    the support found; with ``stability``, each part's fall when left to gravity too."""
    settings = settings or PhysicsSettings()
    bodies = bodies_of(ds, poses)
    support = shot_support(ds, shot, bodies, depth)
    out = check_bodies(bodies, support, uncertainty=uncertainty, settings=settings)
    if stability and support is not None and bodies:
        # MuJoCo only for --stability: annotate's and check's physics check runs without it,
        # and every worker process would pay its import.
        from annotator.physics.stability import falls

        u = uncertainty or {}
        for rec, fall in zip(out, falls(bodies, support)):
            rec.check.fall_mm = fall
            limit = max(settings.fall_floor_mm, settings.sigmas * float(u.get(rec.key) or 0.0))
            if fall > limit:
                rec.flags.append(Flag.UNSTABLE)
    return out, support


def record_physics(
    ds: Dataset,
    shot: Shot,
    instances: Sequence[InstanceAnnotation],
    depth: np.ndarray | None = None,
) -> None:
    """Each annotated instance's physics in its pile (``instance.physics``), its physics
    flags added to its flags: what ``annotate`` records. ``shot``: the scene's (a
    sequence's first posed frame, whose depth gives the support)."""
    uncertainty = {r.key: r.uncertainty_mm for r in instances}
    found, _ = shot_physics(
        ds, shot, [r.pose for r in instances], uncertainty=uncertainty, depth=depth
    )
    for r, rec in zip(instances, found):
        r.physics = rec.check
        r.flags = sort_flags([*r.flags, *rec.flags])
