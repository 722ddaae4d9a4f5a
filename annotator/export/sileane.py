"""Export to the paper's dataset format ("Siléane dataset"), and our reader of it.

One folder per object (the format holds one object per dataset)::

    OUT/<object>/mesh.ply
    OUT/<object>/camera_params.txt        fu, fv, cu, cv, clip_start, clip_end (m), location (m),
                                          rotation (quaternion w x y z, camera to world)
    OUT/<object>/depth/<scene>.PNG        uint16, (z - clip_start) / (clip_end - clip_start) * 65535,
                                          z in metres; 65535 where nothing was measured
    OUT/<object>/rgb/<scene>.PNG          the reference camera's image
    OUT/<object>/gt/<scene>.json          [{"R": 3x3, "t": [x, y, z] (metres), "occlusion_rate",
                                          "segmentation_id"}]
    OUT/<object>/segmentation/<scene>.PNG  uint8, segmentation_id per pixel (visible part), 255 = none
    OUT/<object>/symmetry.yaml            our symmetry class (for ``annotator evaluate``)

The reference camera only, undistorted to a pinhole camera with the same K; its frame is the
world frame (location 0, rotation identity). The layout follows the paper's published dataset
as far as its description goes; the exact key order of camera_params.txt is our reading of it.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from annotator.dataset import Dataset
from annotator.dataset.write import symmetry_to_yaml
from annotator.export.models import write_ply
from annotator.export.selection import Selected
from annotator.export.undistort import pinhole_rig, undistort_depth, undistort_image
from annotator.io.atomic import write_json, write_text
from annotator.io.images import write_png
from annotator.occlusion import scene_visibility

NO_SEGMENT = 255


def export_sileane(ds: Dataset, selected: Sequence[Selected], out: Path, *, progress=None) -> None:
    rig = pinhole_rig(ds.rig)
    ref = rig.cameras[0]
    depths = {}
    for item in selected:
        d = item.scene.read_depth(ds.rig)
        if d is not None and ds.rig.depth is not None and ds.rig.depth.camera == ref.name:
            depths[item.scene.id] = undistort_depth(d, ds.rig.depth_camera)
    finite = [d[np.isfinite(d)] for d in depths.values() if np.isfinite(d).any()]
    clip_start = (min(float(f.min()) for f in finite) - 50.0) / 1000.0 if finite else 0.1
    clip_end = (max(float(f.max()) for f in finite) + 50.0) / 1000.0 if finite else 2.0
    for name, obj in ds.objects.items():
        folder = out / name
        folder.mkdir(parents=True)
        write_ply(folder / "mesh.ply", obj.mesh.vertices, obj.mesh.faces)  # mm, as our meshes
        write_text(
            folder / "symmetry.yaml",
            yaml.safe_dump(symmetry_to_yaml(obj.symmetry), sort_keys=False),
        )
        K = ref.K
        write_text(
            folder / "camera_params.txt",
            f"fu\t{K[0, 0]:.6f}\nfv\t{K[1, 1]:.6f}\ncu\t{K[0, 2]:.6f}\ncv\t{K[1, 2]:.6f}\n"
            f"clip_start\t{clip_start:.6f}\nclip_end\t{clip_end:.6f}\n"
            "location\t0.0\t0.0\t0.0\nrotation\t1.0\t0.0\t0.0\t0.0\n",
        )
    for item in selected:
        sid = item.scene.id
        meshes = [ds.objects[p.object].mesh for p in item.poses]
        depth = depths.get(sid)
        vis = scene_visibility(
            rig, meshes, [p.T for p in item.poses], depth=depth, cameras=[ref.name], masks=True
        )
        img = undistort_image(item.scene.read_image(ds.rig.cameras[0]), ds.rig.cameras[0])
        for name in ds.objects:
            folder = out / name
            write_png(folder / "rgb" / f"{sid}.PNG", img)
            if depth is not None:
                z = depth / 1000.0
                enc = np.clip((z - clip_start) / (clip_end - clip_start), 0, 1) * 65535
                enc = np.where(np.isfinite(z), np.round(enc), 65535).astype(np.uint16)
                write_png(folder / "depth" / f"{sid}.PNG", enc)
            seg = np.full((ref.height, ref.width), NO_SEGMENT, np.uint8)
            gt = []
            for p, v in zip(item.poses, vis):
                if p.object != name:
                    continue
                seg_id = len(gt)
                seg[v.cameras[0].mask_visib] = seg_id
                gt.append(
                    {
                        "R": p.R.tolist(),
                        "t": (p.t / 1000.0).tolist(),
                        "occlusion_rate": float(v.occlusion),
                        "segmentation_id": seg_id,
                        "instance": p.instance,
                    }
                )
            write_png(folder / "segmentation" / f"{sid}.PNG", seg)
            write_json(folder / "gt" / f"{sid}.json", gt)
        if progress:
            progress()


def read_sileane_scene(folder: Path, scene: str) -> dict[str, Any]:
    """Our reader (round-trip tests): poses (mm), occlusion rates and visible masks."""
    gt = json.loads((folder / "gt" / f"{scene}.json").read_text())
    seg = cv2.imread(str(folder / "segmentation" / f"{scene}.PNG"), cv2.IMREAD_UNCHANGED)
    return {
        "R": [np.array(g["R"]) for g in gt],
        "t": [np.array(g["t"]) * 1000.0 for g in gt],
        "occlusion_rate": [g["occlusion_rate"] for g in gt],
        "masks_visib": [seg == g["segmentation_id"] for g in gt],
        "instance": [g.get("instance") for g in gt],
    }
