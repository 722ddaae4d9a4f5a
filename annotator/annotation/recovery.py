"""Marker recovery: once an instance is posed, each of its markers that should be visible in
a camera where it was not read is looked for among the unread candidate squares.

A square within the settings' ``final_inlier_px`` (or 12% of its side) of the projected marker, whose bits differ from
the marker's in at most :data:`RECOVER_MAX_BIT_ERRORS`, is *recovered*: it joins the
instance's observations as a soft reading, held to the support of the others by the
consensus (:mod:`annotator.annotation.consensus`).
"""

from __future__ import annotations

import functools

import numpy as np

from annotator.dataset import Dataset
from annotator.detection import MarkerDetector
from annotator.detection.aruco import ImageReading
from annotator.geometry.camera import Camera
from annotator.geometry.lie import cross
from annotator.markers.texture import marker_bits
from annotator.pnp import Observation

#: Markers are looked for when seen within 75 degrees of face-on.
RECOVER_COS = float(np.cos(np.radians(75.0)))
#: At most this many of a marker's inner bits may differ from what was read.
RECOVER_MAX_BIT_ERRORS = 2


def recover_markers(
    ds: Dataset,
    obj: str,
    inst: str,
    T: np.ndarray,
    obs: list[Observation],
    readings: list[ImageReading],
    grays: list[np.ndarray],
    detector: MarkerDetector,
    *,
    within_px: float,
) -> bool:
    """Add to ``obs`` the markers of instance ``obj/inst``, posed at ``T`` (rig frame), found
    among the unread candidate squares where the pose puts them (within ``within_px`` or 12%
    of the marker's side); True if any was."""
    seen = {(o.camera, o.marker_id) for o in obs}
    added = False
    for j, (cam, reading) in enumerate(zip(ds.rig.cameras, readings)):
        if len(reading.unread) == 0:
            continue
        read = {mid for c, mid in seen if c == j}
        for mid, X, corners in _found_in(ds, obj, inst, T, cam, reading, read, within_px):
            obs.append(
                Observation(j, mid, X, detector.refine(grays[j], corners[None])[0], soft=True)
            )
            seen.add((j, mid))
            added = True
    return added


def _found_in(
    ds: Dataset,
    obj: str,
    inst: str,
    T: np.ndarray,
    cam: Camera,
    reading: ImageReading,
    read: set[int],
    within_px: float,
) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """(marker id, model corners, image corners) of the instance's markers facing ``cam``,
    not among the ids already ``read``, that one of its unread squares matches."""
    model = ds.objects[obj]
    instance = model.instance(inst)
    X_all = model.site_corners(inst)[: len(instance.marker_ids)]
    cam_T = cam.cam_T_rig @ T
    C_all = X_all @ cam_T[:3, :3].T + cam_T[:3, 3]  # (S, 4, 3), all sites at once
    sites = [s for s in np.flatnonzero(_facing(C_all)) if instance.marker_ids[s] not in read]
    if not sites:
        return []
    projected = cam.project(C_all[sites])  # one projection for all (each point is its own)
    # Each projected marker's mean side, and the unread squares whose centres lie within
    # 35% of it of its centre: for every site at once.
    sides = np.linalg.norm(projected - np.roll(projected, 1, axis=1), axis=2).mean(axis=1)
    centres = reading.unread.mean(axis=1)
    apart = np.linalg.norm(centres[None] - projected.mean(axis=1)[:, None], axis=2)
    near = apart < 0.35 * sides[:, None]
    out = []
    for site, uv, side, candidates in zip(sites, projected, sides, near):
        mid = instance.marker_ids[site]
        squares = np.flatnonzero(candidates)
        match = _matching_square(ds.dictionary, mid, uv, float(side), squares, reading, within_px)
        if match is not None:
            out.append((mid, X_all[site], match))
    return out


def _facing(C_all: np.ndarray) -> np.ndarray:
    """Which sites (corners in the camera frame, (S, 4, 3)) are in front of the camera and
    seen within 75 degrees of face-on."""
    normal = cross(C_all[:, 3] - C_all[:, 0], C_all[:, 1] - C_all[:, 0])
    centre = C_all.mean(axis=1)
    cos = -(normal * centre).sum(1)
    limit = RECOVER_COS * np.linalg.norm(normal, axis=1) * np.linalg.norm(centre, axis=1)
    return (C_all[..., 2].min(axis=1) > 0) & (cos >= limit)


def _matching_square(
    dictionary: str,
    mid: int,
    uv: np.ndarray,
    side: float,
    near: np.ndarray,
    reading: ImageReading,
    within_px: float,
) -> np.ndarray | None:
    """Of the unread squares ``near`` (indices), the one (its corners in the marker's order)
    on the projected corners ``uv`` (whose mean side is ``side``) whose bits are marker
    ``mid``'s, or None."""
    for k in near:
        quads = [np.roll(reading.unread[k], m, axis=0) for m in range(4)]
        m = int(np.argmin([np.abs(q - uv).max() for q in quads]))
        if np.linalg.norm(quads[m] - uv, axis=1).max() > max(within_px, 0.12 * side):
            continue
        expected = np.rot90(_inner_bits(dictionary, mid), m)
        if int(np.sum(reading.unread_bits[k] != expected)) <= RECOVER_MAX_BIT_ERRORS:
            return quads[m]
    return None


@functools.lru_cache(maxsize=4096)
def _inner_bits(dictionary: str, marker_id: int) -> np.ndarray:
    """The marker's inner bits (True = white), rows and columns as printed."""
    return marker_bits(dictionary, marker_id)[1:-1, 1:-1] > 127
