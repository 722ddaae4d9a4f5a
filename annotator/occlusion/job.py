"""``annotator occlusion`` over a dataset: the per-scene job, which writes ``visibility.json``
(masks' pixel counts, boxes and occlusion rates per instance and camera)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from annotator.dataset import Dataset, InstancePose, Scene, cached_dataset
from annotator.dataset.frames import scene_shots
from annotator.dataset.model import FRAMES_DIR, Capture
from annotator.dataset.poses import read_pose_file
from annotator.dataset.records import frames_from_json
from annotator.errors import UserError
from annotator.io.atomic import write_json
from annotator.occlusion import scene_visibility
from annotator.runner.files import description_files

#: What the job writes in each scene folder.
VISIBILITY_FILE = "visibility.json"


@dataclass(frozen=True)
class VisibilityJob:
    """The per-scene job (picklable, for worker processes and Ray tasks): the dataset folder,
    which poses (``annotation`` or ``gt``) and the depth test's tolerance in mm."""

    root: str
    poses: str
    tolerance: float

    def prepare(self) -> None:
        """Import open3d, load the dataset and tabulate the rays once, before forking."""
        ds = cached_dataset(self.root)
        for cam in ds.rig.cameras:
            cam.pixel_rays()

    # What a scene's work reads and writes, relative to ``root`` (for --ray).

    def shared_files(self) -> list[str]:
        """The dataset description (dataset.yaml, objects, background depth)."""
        return description_files(cached_dataset(self.root))

    def scene_files(self, scene_id: str) -> list[str]:
        """The poses (annotation.json or gt.json) and the depth map (every frame's, and the
        frame folders' images, which tell which frames there are, for a sequence)."""
        scene = Scene.relative(scene_id)
        src = scene.annotation_path if self.poses == "annotation" else scene.gt_path
        files = [src.as_posix(), scene.depth_path.as_posix()]
        ds = cached_dataset(self.root)
        if ds.rig.moving:
            for frame in ds.scene(scene_id).frames():
                rel = scene.path / FRAMES_DIR / frame.name
                files += [(rel / "depth.png").as_posix()]
                files += [(rel / f"{c.name}.png").as_posix() for c in ds.rig.cameras[:1]]
        return files

    def output_files(self, scene_id: str) -> list[str]:
        """visibility.json."""
        return [(Scene.relative(scene_id).path / VISIBILITY_FILE).as_posix()]

    def __call__(self, scene_id: str) -> dict[str, Any]:
        ds = cached_dataset(self.root)
        scene = ds.scene(scene_id)
        src = scene.annotation_path if self.poses == "annotation" else scene.gt_path
        if not src.exists():
            raise UserError(f"no {src.name}", path=scene.path)
        poses, top = read_pose_file(src)
        out: dict[str, Any] = {"poses": self.poses, "depth_tolerance_mm": self.tolerance}
        if not ds.rig.moving:
            out["instances"] = self._instances(ds, scene, poses)
        else:  # a sequence: every posed frame as its rig saw the scene (FORMAT.md)
            shots = scene_shots(ds, scene, frames_from_json(top.get("frames"), src))
            out["frames"] = {
                s.frame: {"instances": self._instances(ds, s.capture, s.poses(poses))}
                for s in shots
            }
        write_json(scene.path / VISIBILITY_FILE, out)
        return {"instances": len(poses)}

    def _instances(self, ds: Dataset, capture: Capture, poses: list[InstancePose]) -> list[dict]:
        """Per instance: its occlusion rate and, per camera, pixel counts, boxes and rates."""
        vis = scene_visibility(
            ds.rig,
            [ds.objects[p.object].mesh for p in poses],
            [p.T for p in poses],
            depth=capture.read_depth(ds.rig),
            depth_tolerance=self.tolerance,
        )
        out = []
        for p, v in zip(poses, vis):
            cams = {}
            for c in v.cameras:
                cams[c.camera] = {
                    "px_all": c.px_all,
                    "px_visib": c.px_visib,
                    "px_visib_depth": c.px_visib_depth,
                    "bbox_all": c.bbox_all,
                    "bbox_visib": c.bbox_visib,
                    "occlusion": round(c.occlusion, 5),
                    "occlusion_depth": None
                    if c.occlusion_depth is None
                    else round(c.occlusion_depth, 5),
                }
            out.append(
                {
                    "object": p.object,
                    "instance": p.instance,
                    "occlusion": round(v.occlusion, 5),
                    "cameras": cams,
                }
            )
        return out


def is_fresh(ds: Dataset, scene: Scene, poses: str, tolerance: float) -> bool:
    """True if the scene's visibility.json was made from the same ``poses`` (annotation or
    gt) with the same depth ``tolerance``, after they and the depth maps last changed."""
    out = scene.path / VISIBILITY_FILE
    src = scene.annotation_path if poses == "annotation" else scene.gt_path
    try:
        doc = json.loads(out.read_text(encoding="utf-8"))
        made = out.stat().st_mtime
        shots = scene.frames() if ds.rig.moving else [scene]
        depths = [shot.depth_path for shot in shots if shot.depth_path.exists()]
        newer = all(p.stat().st_mtime <= made for p in [src, *depths])
    except (OSError, ValueError):
        return False
    return (
        isinstance(doc, dict)
        and doc.get("poses", "annotation") == poses
        and doc.get("depth_tolerance_mm") == tolerance
        and newer
    )
