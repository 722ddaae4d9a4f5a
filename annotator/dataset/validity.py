"""Poses that cannot be right in a dataset, whatever file they come from (gt.json,
annotation.json, review.json's repaired and added poses).

A pose is impossible when it names an object the dataset does not have, an instance its
object.yaml does not list (a name typed by hand, an instance removed since ``annotate``), or
when the part's surface centroid lies behind the reference camera (z <= 0): no camera of
the rig could have seen it there. ``check`` lists every such pose; ``export`` leaves its
scene out and says why; ``sites`` leaves out a scene whose annotation names an unknown
instance.
"""

from __future__ import annotations

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
