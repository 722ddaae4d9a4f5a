"""Pose files: ``gt.json`` and ``annotation.json`` (FORMAT.md).

Both hold ``{"instances": [{"object", "instance", "cam_R_m2c", "cam_t_m2c", ...}], ...}``.
Fields beyond the pose are kept, untouched, in :attr:`InstancePose.extra` (and top-level
fields in the ``extra`` dict returned by :func:`read_pose_file`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from annotator.errors import UserError
from annotator.geometry.transforms import is_rotation, make_transform
from annotator.io.atomic import write_json
from annotator.io.documents import finite_number, read_json


@dataclass
class InstancePose:
    """The pose of one instance in the reference camera: ``x_cam = R @ x_model + t`` (mm).

    >>> from annotator.dataset import read_poses
    >>> p = read_poses("sample_scenes/scenes/000000/gt.json")[0]
    >>> p.key, p.T.shape
    ('brick/01', (4, 4))
    """

    object: str
    instance: str
    R: np.ndarray
    t: np.ndarray
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def key(self) -> str:
        """``object/instance``, the key used in review.json."""
        return f"{self.object}/{self.instance}"

    @property
    def T(self) -> np.ndarray:  # noqa: N802 - matrix name
        """4x4 ``cam_T_model`` in the reference camera."""
        return make_transform(self.R, self.t)

    def to_json(self) -> dict[str, Any]:
        out = {
            "object": self.object,
            "instance": self.instance,
            "cam_R_m2c": [float(x) for x in np.asarray(self.R).reshape(9)],
            "cam_t_m2c": [float(x) for x in np.asarray(self.t).reshape(3)],
        }
        out.update(self.extra)
        return out


#: Numeric fields of an instance that readers use, with their bounds: ``None`` or a finite
#: number within them, else the file is refused naming the field.
_NUMBERS: tuple[tuple[str, float | None, float | None], ...] = (
    ("occlusion.rate", 0.0, 1.0),
    ("occlusion_rate", 0.0, 1.0),
    ("uncertainty_mm", 0.0, None),
    ("reprojection_px.rms", 0.0, None),
    ("reprojection_px.max", 0.0, None),
    ("depth.agreement", 0.0, 1.0),
    ("depth.median_abs_mm", 0.0, None),
)


def read_pose_file(path: str | Path) -> tuple[list[InstancePose], dict[str, Any]]:
    """Read gt.json / annotation.json: the poses and the other top-level fields.

    Raises:
        UserError: naming the file, the entry and the field, if it is not valid JSON, a pose
            is malformed or not finite, a figure is not a finite number within its bounds,
            or an instance is listed twice.
    """
    path = Path(path)
    doc = read_json(path)
    if not isinstance(doc, dict) or not isinstance(doc.get("instances"), list):
        raise UserError("expected an object with an 'instances' list", path=path)
    poses = []
    seen: set[str] = set()
    for i, rec in enumerate(doc["instances"]):
        try:
            R = np.asarray(rec["cam_R_m2c"], dtype=np.float64).reshape(3, 3)
            t = np.asarray(rec["cam_t_m2c"], dtype=np.float64).reshape(3)
            obj, inst = rec["object"], rec["instance"]
            if not isinstance(obj, (str, int)) or not isinstance(inst, (str, int)):
                raise TypeError
            obj, inst = str(obj), str(inst)
        except (KeyError, TypeError, ValueError):
            raise UserError(
                f"instances[{i}] needs object, instance, cam_R_m2c (9) and cam_t_m2c (3)", path=path
            ) from None
        where = f"instances[{i}] ({obj}/{inst})"
        for name, value in (("cam_R_m2c", R), ("cam_t_m2c", t)):
            if not np.all(np.isfinite(value)):
                raise UserError(f"{where}: {name} has a NaN or infinite value", path=path)
        if not is_rotation(R, tol=1e-3):
            raise UserError(f"{where}: cam_R_m2c is not a rotation", path=path)
        if f"{obj}/{inst}" in seen:
            raise UserError(f"{where}: the instance is listed twice", path=path)
        seen.add(f"{obj}/{inst}")
        for field_name, low, high in _NUMBERS:
            value = _dotted(rec, field_name)
            if value is not None:
                finite_number(value, f"{where}: {field_name}", path, low=low, high=high)
        _check_lists(rec, where, path)
        extra = {
            k: v
            for k, v in rec.items()
            if k not in ("object", "instance", "cam_R_m2c", "cam_t_m2c")
        }
        poses.append(InstancePose(obj, inst, R, t, extra))
    rest = {k: v for k, v in doc.items() if k != "instances"}
    return poses, rest


def _check_lists(rec: dict[str, Any], where: str, path: Path) -> None:
    """``flags``: a list of strings; ``markers``: ``{camera: {use: [ids]}}``; ``views`` a
    count; the mappings a reader walks (``occlusion``, ``depth``, ``reprojection_px``)."""
    flags = rec.get("flags")
    if flags is not None and (
        not isinstance(flags, list) or not all(isinstance(f, str) for f in flags)
    ):
        raise UserError(f"{where}: flags must be a list of strings", path=path)
    markers = rec.get("markers")
    if markers is not None and not (
        isinstance(markers, dict)
        and all(
            isinstance(uses, dict)
            and all(
                isinstance(ids, list)
                and all(isinstance(i, int) and not isinstance(i, bool) for i in ids)
                for ids in uses.values()
            )
            for uses in markers.values()
        )
    ):
        raise UserError(f"{where}: markers must map camera -> {{used: [ids], ...}}", path=path)
    views = rec.get("views")
    if views is not None:
        finite_number(views, f"{where}: views", path, low=0)
    for name in ("occlusion", "depth", "reprojection_px"):
        if rec.get(name) is not None and not isinstance(rec[name], dict):
            raise UserError(f"{where}: {name} must be a mapping or null", path=path)


def _dotted(rec: dict[str, Any], name: str) -> Any:
    """``rec["a"]["b"]`` for ``"a.b"``; None where a level is missing or not a mapping."""
    node: Any = rec
    for part in name.split("."):
        if not isinstance(node, dict):
            return None
        node = node.get(part)
    return node


def read_poses(path: str | Path) -> list[InstancePose]:
    """Read only the poses of gt.json / annotation.json."""
    return read_pose_file(path)[0]


def write_poses(path: str | Path, poses: list[InstancePose], **top_level: Any) -> None:
    """Write a pose file atomically; ``top_level`` adds fields beside ``instances``."""
    doc: dict[str, Any] = {"instances": [p.to_json() for p in poses]}
    doc.update(top_level)
    write_json(path, doc)
