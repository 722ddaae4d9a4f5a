"""Whether a marker reading the solve left out is worth a reviewer's look.

A reading that disagrees with its instance's pose (``rejected_markers``) matters when it may
be a sticker glued off its site, on another face or on another copy. It does not when it is
a misreading: small, slanted markers of a dictionary of 1000 differ by few bits, so another
marker, of this part or of another, is read as one of this part's ids, exactly where that
marker's site is and its own id is read in other frames or cameras; nor when the marker is
seen almost edge-on, where its corners are too uncertain to agree with anything. The
consensus rightly left those out; nothing about the pose to check.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from annotator.dataset.flags import Flag
from annotator.dataset.records import InstanceAnnotation
from annotator.geometry.camera import Camera
from annotator.pnp.multiview import Observation

__all__ = [
    "EDGE_ON_SQUARENESS",
    "forgive_misreadings",
    "rays_meet",
    "squareness",
    "worth_a_look",
]

#: A quad whose area is under this share of its longest side squared is a square seen
#: more than about 70 degrees off its normal.
EDGE_ON_SQUARENESS = 0.35
#: A reading this close (px, or this share of its longest side, the larger) to another
#: site's image is that marker, misread (sites do not overlap: a sticker glued off its own
#: site by a millimetre or two is nowhere near this close to another's).
SAME_PLACE_PX = 4.0
SAME_PLACE_SHARE = 0.3
#: Two lines of sight passing this close (mm) may see one sticker.
RAYS_MEET_MM = 5.0


def squareness(quad: np.ndarray) -> float:
    """The area of ``quad`` (4, 2) over the square of its longest side: 1 for a square seen
    face on, about the cosine of the slant for one seen at a slant, 0 edge-on.

    >>> squareness(np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float))
    1.0
    >>> round(squareness(np.array([[0, 0], [10, 0], [10, 5], [0, 5]], float)), 2)
    0.5
    """
    x, y = quad[:, 0], quad[:, 1]
    area = 0.5 * abs(float(x @ np.roll(y, -1) - y @ np.roll(x, -1)))
    side = float(np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1).max())
    return area / side**2 if side > 0 else 0.0


def worth_a_look(
    camera: Camera, cam_T_frame: np.ndarray, kept_sites: np.ndarray, image_corners: np.ndarray
) -> bool:
    """Whether a left-out reading (``image_corners``, (4, 2) px, in ``camera``) may be a
    marker off its site: not edge-on, and not on the image of one of ``kept_sites`` ((M, 4, 3),
    in the frame ``cam_T_frame`` maps into the camera's): the sites, of any posed part,
    whose own markers the solve kept (that marker, misread).

    >>> K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    >>> cam = Camera("c", 640, 480, K)
    >>> site = np.array([[[-5, -5, 300], [5, -5, 300], [5, 5, 300], [-5, 5, 300]]], float)
    >>> there = cam.project(site[0])  # the kept marker's own image: a misreading of it
    >>> worth_a_look(cam, np.eye(4), site, there), worth_a_look(cam, np.eye(4), site, there + 50)
    (False, True)
    >>> worth_a_look(cam, np.eye(4), site, there * [1, 0.1] + 50)  # a sliver: edge-on
    False
    """
    if squareness(image_corners) < EDGE_ON_SQUARENESS:
        return False
    if len(kept_sites) == 0:
        return True
    pts = np.asarray(kept_sites, float).reshape(-1, 3) @ cam_T_frame[:3, :3].T + cam_T_frame[:3, 3]
    projected = camera.project(pts).reshape(-1, 4, 2)
    side = float(np.linalg.norm(image_corners - np.roll(image_corners, -1, axis=0), axis=1).max())
    near = max(SAME_PLACE_PX, SAME_PLACE_SHARE * side)
    turns = np.stack([np.roll(image_corners, r, axis=0) for r in range(4)])  # (4, 4, 2)
    with np.errstate(invalid="ignore"):
        gaps = np.abs(projected[:, None] - turns[None]).max(axis=(2, 3))  # (M, 4)
    return not bool(np.any(gaps <= near))


def forgive_misreadings(
    cameras: Sequence[Camera],
    instances: Sequence[InstanceAnnotation],
    observations: Mapping[tuple[str, str], Sequence[Observation]],
) -> None:
    """A fixed rig's: drop ``rejected_markers`` from each of ``instances`` whose every
    rejected sharp reading (of ``observations``, per ``(object, instance)``) is not
    :func:`worth_a_look` among the sites whose markers any of ``instances`` kept."""
    names = [c.name for c in cameras]
    kept = [
        o.model_corners @ r.R.T + r.t
        for r in instances
        for o in observations.get((r.object, r.instance), ())
        if r.markers.get(names[o.camera]) and o.marker_id in r.markers[names[o.camera]].used
    ]
    kept_sites = np.array(kept).reshape(-1, 4, 3)
    for r in instances:
        if Flag.REJECTED_MARKERS not in r.flags:
            continue
        rejected = [
            o
            for o in observations.get((r.object, r.instance), ())
            if not o.soft
            and r.markers.get(names[o.camera])
            and o.marker_id in r.markers[names[o.camera]].rejected
        ]
        if rejected and not any(
            worth_a_look(
                cameras[o.camera], cameras[o.camera].cam_T_rig, kept_sites, o.image_corners
            )
            for o in rejected
        ):
            r.flags = [f for f in r.flags if f != Flag.REJECTED_MARKERS]


def rays_meet(origins: np.ndarray, directions: np.ndarray, *, gap_mm: float = RAYS_MEET_MM) -> bool:
    """Whether two of the lines of sight (``origins``, ``directions``: (N, 3)) pass within
    ``gap_mm`` of each other in front of both cameras: readings of one id from several
    frames that may be one sticker (a static scene holds it in one place), not several
    markers misread as that id.

    >>> o = np.array([[0.0, 0, 0], [100, 0, 0]])
    >>> rays_meet(o, np.array([[0.0, 0, 1], [-0.2, 0, 1]]))  # both through (0, 0, 500)
    True
    >>> rays_meet(o, np.array([[0.0, 0, 1], [0.2, 0, 1]]))
    False
    """
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    for a in range(len(d)):
        for b in range(a + 1, len(d)):
            w = origins[a] - origins[b]
            c = float(d[a] @ d[b])
            if 1.0 - c * c < 1e-9:  # parallel: the same line, or none met
                if np.linalg.norm(np.cross(w, d[a])) <= gap_mm:
                    return True
                continue
            s = (c * float(d[b] @ w) - float(d[a] @ w)) / (1.0 - c * c)
            t = (float(d[b] @ w) - c * float(d[a] @ w)) / (1.0 - c * c)
            if s > 0 and t > 0 and np.linalg.norm(w + s * d[a] - t * d[b]) <= gap_mm:
                return True
    return False
