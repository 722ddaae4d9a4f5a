"""The frames of a sequence (FORMAT.md, sequences): each frame's ``scene_T_rig``, and the
instance poses as one frame's rig sees them.

A sequence's pose files hold every instance once, in the *scene frame* (the reference
camera of the first frame), and under ``frames`` where the rig was for each frame. Whatever
works on one shot of a fixed rig (occlusion, export, evaluation, the review page) works on a
frame by taking the poses through :func:`poses_in_frame`.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TypeVar

import numpy as np

from annotator.dataset.flags import FrameFlag
from annotator.dataset.model import FRAMES_DIR, Capture, Dataset, DepthSpec, Rig, Scene
from annotator.dataset.poses import InstancePose, read_pose_file
from annotator.dataset.records import FramePose, InstanceAnnotation, frames_from_json
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert

__all__ = [
    "FramesScene",
    "Shot",
    "frames_left_out",
    "frames_line",
    "poses_in_frame",
    "read_frames",
    "frames_view",
    "scene_shots",
    "shown_frames",
]


#: A pose record: a file's (InstancePose) or annotate's (InstanceAnnotation).
P = TypeVar("P", InstancePose, InstanceAnnotation)


def poses_in_frame(poses: Sequence[P], scene_T_rig: np.ndarray) -> list[P]:
    """The instance poses (scene frame) as that frame's reference camera sees them:
    ``inverse(scene_T_rig) @ scene_T_model``, each record's other fields kept.

    >>> import numpy as np
    >>> p = InstancePose("part", "01", np.eye(3), np.array([0.0, 0.0, 500.0]))
    >>> T = np.eye(4); T[2, 3] = 100.0  # the rig moved 100 mm forward
    >>> poses_in_frame([p], T)[0].t.tolist()
    [0.0, 0.0, 400.0]
    """
    rig_T_scene = invert(np.asarray(scene_T_rig, dtype=np.float64))
    out = []
    for p in poses:
        T = rig_T_scene @ p.T
        out.append(replace(p, R=T[:3, :3].copy(), t=T[:3, 3].copy()))
    return out


@dataclass(frozen=True)
class Shot:
    """One shot of a scene's rig with its images and where the scene is in its rig: the
    scene itself for a fixed rig (``frame`` None, ``rig_T_scene`` the identity), or one
    posed frame of a sequence. What works on one shot (occlusion, export, the review page)
    takes the poses through :meth:`poses`."""

    scene: Scene
    capture: Capture
    frame: str | None
    rig_T_scene: np.ndarray

    @property
    def id(self) -> str:
        """``<scene>`` or ``<scene>/<frame>``: how messages name the shot."""
        return self.scene.id if self.frame is None else f"{self.scene.id}/{self.frame}"

    def poses(self, scene_poses: list[InstancePose]) -> list[InstancePose]:
        """The scene's poses as this shot's rig sees them."""
        if self.frame is None:
            return scene_poses
        return poses_in_frame(scene_poses, invert(self.rig_T_scene))


def read_frames(path: str | Path) -> dict[str, FramePose]:
    """The ``frames`` mapping of a pose file (gt.json, annotation.json); UserError naming
    the file if it is malformed."""
    _, top = read_pose_file(path)
    return frames_from_json(top.get("frames"), Path(path))


def scene_shots(
    ds: Dataset,
    scene: Scene,
    frames: Mapping[str, FramePose] | None = None,
    *,
    rejected: Collection[str] = (),
) -> list[Shot]:
    """The scene's shots: the scene itself for a fixed rig; for a moving rig every frame
    folder that ``frames`` (the pose file's mapping) poses, that is not ``rejected`` and
    that annotate did not flag ``inconsistent`` (the scene's poses are not that frame's).

    Raises:
        UserError: a moving rig's scene whose pose file has no ``frames``, or names a frame
            folder that is not there.
    """
    if not ds.rig.moving:
        return [Shot(scene, scene, None, np.eye(4))]
    frames = frames or {}
    if not frames:
        raise UserError(
            "a moving rig's pose file needs 'frames' (each frame's scene_T_rig)", path=scene.path
        )
    folders = {f.name: f for f in scene.frames()}
    missing = sorted(set(frames) - set(folders))
    if missing:
        raise UserError(f"frames {', '.join(missing[:3])} have no frame folder", path=scene.path)
    out = []
    for name in sorted(frames):
        T = frames[name].scene_T_rig
        if T is None or name in rejected or frames[name].has(FrameFlag.INCONSISTENT):
            continue
        out.append(Shot(scene, folders[name], name, invert(T)))
    return out


def frames_left_out(
    frames: Mapping[str, FramePose], rejected: Collection[str] = ()
) -> dict[str, str]:
    """A sequence's frames that none of its exports or evaluations take, and why: not posed
    (its flags and reason, as annotate wrote them), posed but flagged ``inconsistent`` (its
    markers place parts elsewhere: the scene's poses are not its truth), or ``rejected`` by
    a reviewer.

    >>> frames = {"000000": FramePose("000000", np.eye(4)),
    ...           "000001": FramePose("000001", None, flags=["outlier"], reason="far")}
    >>> frames_left_out(frames, rejected=["000000"])
    {'000000': 'rejected by a reviewer', '000001': 'not posed: outlier (far)'}
    """
    out = {}
    for name in sorted(frames):
        f = frames[name]
        if f.scene_T_rig is None:
            flags = ", ".join(str(x) for x in f.flags or []) or "no pose"
            reason = f.reason
            out[name] = f"not posed: {flags}" + (f" ({reason})" if reason else "")
        elif f.has(FrameFlag.INCONSISTENT):
            reason = f.reason
            out[name] = "flagged inconsistent" + (f" ({reason})" if reason else "")
        elif name in rejected:
            out[name] = "rejected by a reviewer"
    return out


def frames_line(left: Mapping[str, str], total: int | None = None) -> str:
    """One line naming the frames :func:`frames_left_out` gives, grouped by why (the
    flags; each frame's own figures are in the files and ``--json``).

    >>> frames_line({"000001": "not posed: outlier (its 3 marker ...)",
    ...              "000002": "not posed: outlier (it is posed on one marker only)"}, 6)
    '2 of 6 frames left out: 000001, 000002 not posed: outlier'
    """
    by_why: dict[str, list[str]] = {}
    for name, why in sorted(left.items()):
        by_why.setdefault(why.split(" (")[0], []).append(name)
    parts = []
    for why, names in by_why.items():
        shown = ", ".join(names[:5]) + (f" (+{len(names) - 5} more)" if len(names) > 5 else "")
        parts.append(f"{shown} {why}")
    of = f" of {total}" if total is not None else ""
    noun = "frame" if (total if total is not None else len(left)) == 1 else "frames"
    return f"{len(left)}{of} {noun} left out: " + "; ".join(parts)


#: How many of a sequence's frames a review page shows side by side.
SHOWN_FRAMES = 3


def shown_frames(
    frames: Mapping[str, FramePose], *, count: int = SHOWN_FRAMES, offset: int = 0
) -> list[str]:
    """``count`` posed frames of a sequence spread evenly over it, the first ``offset``
    frames on (a page steps through every posed frame by raising ``offset``)."""
    posed = sorted(name for name, f in frames.items() if f.scene_T_rig is not None)
    if not posed:
        return []
    n = min(count, len(posed))
    stride = len(posed) / n
    return [posed[(int(k * stride) + offset) % len(posed)] for k in range(n)]


def view_camera_name(frame: str, camera: str) -> str:
    """The name a frame's camera has in a :func:`frames_view`: ``<frame>:<camera>``."""
    return f"{frame}:{camera}"


@dataclass(frozen=True)
class FramesScene(Scene):
    """A sequence's scene as a :func:`frames_view` sees it: camera ``<frame>:<camera>``'s
    image is that frame's, the depth map ``depth_frame``'s; its annotation and review files
    are the scene's own."""

    depth_frame: str | None = None

    def image_path(self, camera: Camera | str) -> Path:
        name = camera if isinstance(camera, str) else camera.name
        frame, _, cam = name.partition(":")
        return self.path / FRAMES_DIR / frame / f"{cam}.png"

    @property
    def depth_path(self) -> Path:
        if self.depth_frame is None:
            return self.path / FRAMES_DIR / ".none" / "depth.png"
        return self.path / FRAMES_DIR / self.depth_frame / "depth.png"


def frames_view(
    ds: Dataset, scene: Scene, frames: Mapping[str, FramePose], shown: Sequence[str]
) -> tuple[Dataset, FramesScene]:
    """Some frames of a sequence as one fixed rig in the scene frame: every shown frame's
    cameras (``<frame>:<camera>``, placed by the frame's ``scene_T_rig``), the first shown
    frame's depth camera the depth camera. What works on a fixed rig's scene (the review
    page's overlays and repairs) then works on poses in the scene frame, and a repair made
    there shows in every frame.

    Raises:
        ValueError: a shown frame that ``frames`` does not pose.
    """
    cams: list[Camera] = []
    for name in shown:
        T = frames[name].scene_T_rig if name in frames else None
        if T is None:
            raise ValueError(f"frame {name!r} has no pose")
        for c in ds.rig.cameras:
            cams.append(replace(c, name=view_camera_name(name, c.name), rig_T_cam=T @ c.rig_T_cam))
    depth = None
    if ds.rig.depth is not None and shown:
        depth = DepthSpec(view_camera_name(shown[0], ds.rig.depth.camera), ds.rig.depth.scale)
    flipped = frozenset(view_camera_name(f, c) for f in shown for c in ds.rig.flipped)
    rig = Rig(tuple(cams), depth, flipped)
    view = replace(ds, rig=rig)
    return view, FramesScene(scene.id, scene.path, flipped, shown[0] if shown else None)
