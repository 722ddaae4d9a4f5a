"""Poses that cannot be right in a dataset, whatever file they come from (gt.json,
annotation.json, review.json's repaired and added poses).

A pose is impossible when it names an object the dataset does not have, an instance its
object.yaml does not list (a name typed by hand, an instance removed since ``annotate``), or
when the part's surface centroid lies behind the reference camera (z <= 0): no camera of
the rig could have seen it there. Two instances of one object whose centres coincide
(:data:`SAME_PLACE_MM`) cannot both be right either: solid parts do not share their room
(a pose copied onto another instance, or one part annotated twice). ``check`` lists every such pose; ``export`` leaves its
scene out and says why; ``sites`` leaves out a scene whose annotation names an unknown
instance.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from annotator.dataset.model import Dataset
from annotator.dataset.review import Posed
from annotator.errors import UserError


def unknown_name(ds: Dataset, object_name: str, instance: str) -> str | None:
    """Why ``object_name/instance`` is not an instance of ``ds`` (None: it is one)."""
    obj = ds.objects.get(object_name)
    if obj is None:
        known = ", ".join(sorted(ds.objects)) or "none"
        return f"unknown object {object_name!r} (objects: {known})"
    if instance not in {i.name for i in obj.instances}:
        return (
            f"unknown instance '{object_name}/{instance}' "
            f"({obj.folder.name}/object.yaml does not list it)"
        )
    return None


def pose_problem(ds: Dataset, pose: Posed) -> str | None:
    """Why ``pose`` cannot be right in ``ds`` (see the module docstring), or None."""
    unknown = unknown_name(ds, pose.object, pose.instance)
    if unknown is not None:
        return unknown
    try:
        centre = ds.objects[pose.object].mesh.moments.centroid
    except UserError:  # an unreadable mesh is reported for its own file
        centre = np.zeros(3)
    z = float((np.asarray(pose.R, float) @ centre + np.asarray(pose.t, float))[2])
    if not z > 0:
        return (
            f"'{pose.object}/{pose.instance}' lies behind the reference camera "
            f"(its centre at z = {z:.1f} mm)"
        )
    return None


#: Two instances of one object closer than this (mm, their surface centroids) share a place.
SAME_PLACE_MM = 1.0


def same_place(ds: Dataset, poses: Sequence[Posed]) -> list[str]:
    """Why pairs of ``poses`` cannot both be right: instances of one object whose centres
    lie within :data:`SAME_PLACE_MM` of each other (one line per pair)."""
    centres: dict[str, list[tuple[str, np.ndarray]]] = {}
    for p in poses:
        try:
            c = ds.objects[p.object].mesh.moments.centroid
        except (KeyError, UserError):  # unknown objects and bad meshes are named elsewhere
            continue
        at = np.asarray(p.R, float) @ c + np.asarray(p.t, float)
        centres.setdefault(p.object, []).append((p.instance, at))
    out = []
    for obj, placed in sorted(centres.items()):
        for i, (a, ca) in enumerate(placed):
            for b, cb in placed[i + 1 :]:
                d = float(np.linalg.norm(ca - cb))
                if d < SAME_PLACE_MM:
                    out.append(
                        f"'{obj}/{a}' and '{obj}/{b}' are at the same place (centres {d:.2f} mm "
                        "apart): one part posed twice, or a pose copied onto another instance"
                    )
    return out
