"""``annotator occlusion`` over a dataset: the per-scene job, which writes ``visibility.json``
(masks' pixel counts, boxes and occlusion rates per instance and camera)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from annotator.dataset import Scene, cached_dataset, read_poses
from annotator.errors import UserError
from annotator.io.atomic import write_json
from annotator.occlusion import scene_visibility
from annotator.runner.bundle import description_files

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
        """The poses (annotation.json or gt.json) and the depth map."""
        scene = Scene.relative(scene_id)
        src = scene.annotation_path if self.poses == "annotation" else scene.gt_path
        return [src.as_posix(), scene.depth_path.as_posix()]

    def output_files(self, scene_id: str) -> list[str]:
        """visibility.json."""
        return [(Scene.relative(scene_id).path / VISIBILITY_FILE).as_posix()]

    def __call__(self, scene_id: str) -> dict[str, Any]:
        ds = cached_dataset(self.root)
        scene = ds.scene(scene_id)
        src = scene.annotation_path if self.poses == "annotation" else scene.gt_path
        if not src.exists():
            raise UserError(f"no {src.name}", path=scene.path)
        poses = read_poses(src)
        vis = scene_visibility(
            ds.rig,
            [ds.objects[p.object].mesh for p in poses],
            [p.T for p in poses],
            depth=scene.read_depth(ds.rig),
            depth_tolerance=self.tolerance,
        )
        out: dict[str, Any] = {"depth_tolerance_mm": self.tolerance, "instances": []}
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
            out["instances"].append(
                {
                    "object": p.object,
                    "instance": p.instance,
                    "occlusion": round(v.occlusion, 5),
                    "cameras": cams,
                }
            )
        write_json(scene.path / VISIBILITY_FILE, out)
        return {"instances": len(poses)}
