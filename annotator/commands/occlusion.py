"""``annotator occlusion DATASET``: masks' pixel counts, boxes and occlusion rates per instance.

Reads annotation.json (or gt.json with ``--poses gt``) and writes ``visibility.json`` per scene
(atomically; up-to-date scenes are skipped unless ``--force``). annotate already stores the
rates in annotation.json; this command gives the full per-camera detail.
"""

from __future__ import annotations

import argparse
import fnmatch
from dataclasses import dataclass
from typing import Any

from annotator.batch import run_batch
from annotator.commands import add_workers_option, finish_batch, number
from annotator.dataset import cached_dataset, load_dataset, read_poses
from annotator.errors import UserError
from annotator.io.atomic import write_json
from annotator.occlusion import scene_visibility
from annotator.scale import add_ray_option
from annotator.scale.bundle import description_files


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset folder (FORMAT.md)")
    parser.add_argument("--poses", choices=("annotation", "gt"), default="annotation")
    parser.add_argument("--scenes", default="*", metavar="PATTERN")
    parser.add_argument("--depth-tolerance", type=number(low=0), default=5.0, help="mm (default 5)")
    add_workers_option(parser)
    add_ray_option(parser)
    parser.add_argument("--force", action="store_true")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--quiet", action="store_true")


@dataclass(frozen=True)
class VisibilityJob:
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
        src = "annotation.json" if self.poses == "annotation" else "gt.json"
        return [f"scenes/{scene_id}/{src}", f"scenes/{scene_id}/depth.png"]

    def output_files(self, scene_id: str) -> list[str]:
        """visibility.json."""
        return [f"scenes/{scene_id}/visibility.json"]

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
        out = {"depth_tolerance_mm": self.tolerance, "instances": []}
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
        write_json(scene.path / "visibility.json", out)
        return {"instances": len(poses)}


def run(args: argparse.Namespace) -> int:
    ds = load_dataset(args.dataset)
    scenes = [s for s in ds.scenes() if fnmatch.fnmatch(s.id, args.scenes)]
    if not scenes:
        raise UserError(f"no scene matches {args.scenes!r}", path=ds.root / "scenes")

    def fresh(s) -> bool:
        src = s.annotation_path if args.poses == "annotation" else s.gt_path
        v = s.path / "visibility.json"
        return v.exists() and src.exists() and v.stat().st_mtime >= src.stat().st_mtime

    todo = [s.id for s in scenes if args.force or not fresh(s)]
    report = run_batch(
        VisibilityJob(str(ds.root), args.poses, args.depth_tolerance),
        todo,
        workers=args.workers,
        desc="occlusion",
        quiet=args.quiet,
        ray_address=args.ray,
        ray_wait=args.ray_wait,
    )
    summary = {
        "done": len(report.done),
        "skipped": len(scenes) - len(todo),
        "failed": len(report.failed),
        "failures": report.failed,
    }
    return finish_batch(
        report,
        summary,
        f"occlusion: {summary['done']} scenes done, {summary['skipped']} up to date, "
        f"{summary['failed']} failed",
        as_json=args.json,
    )
