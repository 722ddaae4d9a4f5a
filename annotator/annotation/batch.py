"""``annotate`` over a whole dataset: which scenes need work, and the per-scene job."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from annotator.annotation.scene import Settings, annotate_scene
from annotator.dataset import Dataset, Scene, cached_dataset
from annotator.dataset.poses import write_poses
from annotator.dataset.review import now_iso
from annotator.detection import MarkerDetector
from annotator.errors import UserError


def inputs_of(ds: Dataset, scene: Scene) -> list[Path]:
    """Files an annotation depends on: the images, the depth map and the dataset's YAML."""
    files = [scene.image_path(c) for c in ds.rig.cameras]
    if scene.depth_path.exists():
        files.append(scene.depth_path)
    files.append(ds.root / "dataset.yaml")
    files += [o.folder / "object.yaml" for o in ds.objects.values()]
    return files


def is_up_to_date(ds: Dataset, scene: Scene) -> bool:
    """True if annotation.json exists and is newer than every input."""
    if not scene.annotation_path.exists():
        return False
    mtime = scene.annotation_path.stat().st_mtime
    return all(p.exists() and p.stat().st_mtime <= mtime for p in inputs_of(ds, scene))


@dataclass(frozen=True)
class AnnotateJob:
    """The per-scene job (picklable, for worker processes: each loads the dataset once)."""

    root: str
    settings: Settings = Settings()

    def prepare(self) -> None:
        """Do once what every scene needs (see :mod:`annotator.batch`): import open3d, load
        the dataset, meshes and marker table, tabulate every camera's pixel rays."""
        import annotator.occlusion  # noqa: F401  (imports open3d: seconds)

        ds, _ = _context(self.root)
        ds.marker_table  # noqa: B018  (cached property)
        for obj in ds.objects.values():
            obj.mesh.moments  # noqa: B018
        for cam in ds.rig.cameras:
            cam.pixel_rays(self.settings.visibility_step)

    def __call__(self, scene_id: str) -> dict[str, Any]:
        ds, detector = _context(self.root)
        scene = ds.scene(scene_id)
        poses, top = annotate_scene(ds, scene, detector, settings=self.settings)
        if not poses and top["warnings"]:
            raise UserError("no marker of any known instance detected", path=scene.path)
        write_poses(scene.annotation_path, poses, format=1, created_at=now_iso(), errors=[], **top)
        return {
            "instances": len(poses),
            "flagged": sum(1 for p in poses if p.extra.get("flags")),
        }


def _context(root: str) -> tuple[Dataset, MarkerDetector]:
    ds = cached_dataset(root)
    return ds, _detector(ds.dictionary)


@functools.cache
def _detector(dictionary: str) -> MarkerDetector:
    return MarkerDetector(dictionary)
