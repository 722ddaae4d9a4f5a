"""Export to the BOP format (scene-wise), and our reader of it for round-trip checks.

Layout (checked against bop_toolkit_lib.inout: load_scene_camera, load_scene_gt, load_json,
load_ply, load_depth; and the multi-sensor naming of BOP's recent industrial sets)::

    OUT/models/obj_000001.ply, models_info.json
    OUT/camera_<cam>.json                       width, height, fx, fy, cx, cy, depth_scale
    OUT/test/<scene 000000>/gray_<cam>/000000.png
                           depth_<cam>/000000.png        (the depth camera only)
                           mask_<cam>/000000_000000.png, mask_visib_<cam>/...
                           scene_camera_<cam>.json, scene_gt_<cam>.json, scene_gt_info_<cam>.json

With a single exported camera the suffix is dropped (``gray/``, ``scene_gt.json``...), the
classic single-sensor layout. Each of our scenes is one BOP scene with one image (im_id 0);
BOP scene ids follow our sorted scene order, and ``scene_ids.json`` maps them back.
Poses are ``cam_R_m2c``/``cam_t_m2c`` in each camera's own frame; ``cam_R_w2c``/``cam_t_w2c``
give the camera in the rig's reference frame. Object ids follow dataset.yaml's order from 1.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from annotator.dataset import Dataset
from annotator.export.models import models_info, write_ply
from annotator.export.selection import Selected
from annotator.export.undistort import pinhole_rig, undistort_depth, undistort_image
from annotator.io.atomic import write_json
from annotator.io.images import encode_depth, write_png
from annotator.occlusion import scene_visibility


def _suffix(name: str, multi: bool) -> str:
    return f"_{name}" if multi else ""


def export_bop(
    ds: Dataset, selected: Sequence[Selected], out: Path, *, cameras: Sequence[str], progress=None
) -> None:
    obj_ids = {name: k + 1 for k, name in enumerate(ds.objects)}
    (out / "models").mkdir(parents=True)
    info = {}
    for name, oid in obj_ids.items():
        obj = ds.objects[name]
        write_ply(out / "models" / f"obj_{oid:06d}.ply", obj.mesh.vertices, obj.mesh.faces)
        info[str(oid)] = models_info(obj)
    write_json(out / "models" / "models_info.json", info)
    rig = pinhole_rig(ds.rig)
    multi = len(cameras) > 1
    depth_scale = ds.rig.depth.scale if ds.rig.depth else 1.0
    for name in cameras:
        cam = rig.camera(name)
        write_json(
            out / f"camera{_suffix(name, multi)}.json",
            {
                "width": cam.width,
                "height": cam.height,
                "fx": cam.K[0, 0],
                "fy": cam.K[1, 1],
                "cx": cam.K[0, 2],
                "cy": cam.K[1, 2],
                "depth_scale": depth_scale,
            },
        )
    ids = {}
    for bop_id, item in enumerate(selected):
        scene_dir = out / "test" / f"{bop_id:06d}"
        ids[f"{bop_id:06d}"] = item.scene.id
        depth = item.scene.read_depth(ds.rig)
        depth_u = None
        if depth is not None and ds.rig.depth is not None:
            depth_u = undistort_depth(depth, ds.rig.depth_camera)
        meshes = [ds.objects[p.object].mesh for p in item.poses]
        vis = scene_visibility(
            rig, meshes, [p.T for p in item.poses], depth=depth_u, cameras=cameras, masks=True
        )
        for ci, name in enumerate(cameras):
            sfx = _suffix(name, multi)
            cam_d = ds.rig.camera(name)
            cam = rig.camera(name)
            img = item.scene.read_image(cam_d)
            kind = "gray" if img.ndim == 2 else "rgb"
            write_png(scene_dir / f"{kind}{sfx}" / "000000.png", undistort_image(img, cam_d))
            has_depth = (
                depth_u is not None and ds.rig.depth is not None and name == ds.rig.depth.camera
            )
            if has_depth:
                write_png(
                    scene_dir / f"depth{sfx}" / "000000.png", encode_depth(depth_u, depth_scale)
                )
            gts, infos = [], []
            for k, (p, v) in enumerate(zip(item.poses, vis)):
                cv = v.cameras[ci]
                M = cam.cam_T_rig @ p.T
                gts.append(
                    {
                        "cam_R_m2c": M[:3, :3].ravel().tolist(),
                        "cam_t_m2c": M[:3, 3].tolist(),
                        "obj_id": obj_ids[p.object],
                    }
                )
                valid = int(np.sum(cv.mask_all & np.isfinite(depth_u))) if has_depth else cv.px_all
                infos.append(
                    {
                        "bbox_obj": list(cv.bbox_all) if cv.bbox_all else [-1, -1, -1, -1],
                        "bbox_visib": list(cv.bbox_visib) if cv.bbox_visib else [-1, -1, -1, -1],
                        "px_count_all": cv.px_all,
                        "px_count_valid": valid,
                        "px_count_visib": int(cv.mask_visib.sum()),
                        "visib_fract": float(cv.mask_visib.sum() / cv.px_all) if cv.px_all else 0.0,
                    }
                )
                write_png(
                    scene_dir / f"mask{sfx}" / f"000000_{k:06d}.png",
                    cv.mask_all.astype(np.uint8) * 255,
                )
                write_png(
                    scene_dir / f"mask_visib{sfx}" / f"000000_{k:06d}.png",
                    cv.mask_visib.astype(np.uint8) * 255,
                )
            cam_rec: dict[str, Any] = {
                "cam_K": cam.K.ravel().tolist(),
                "cam_R_w2c": cam.cam_T_rig[:3, :3].ravel().tolist(),
                "cam_t_w2c": cam.cam_T_rig[:3, 3].tolist(),
            }
            if has_depth:
                cam_rec["depth_scale"] = depth_scale
            write_json(scene_dir / f"scene_camera{sfx}.json", {"0": cam_rec})
            write_json(scene_dir / f"scene_gt{sfx}.json", {"0": gts})
            write_json(scene_dir / f"scene_gt_info{sfx}.json", {"0": infos})
        if progress:
            progress()
    write_json(out / "test" / "scene_ids.json", ids)


def read_bop_scene(root: Path, bop_scene: str, camera: str | None = None) -> dict[str, Any]:
    """Our reader (round-trip tests): poses, masks and visible fractions of one exported scene."""
    sfx = f"_{camera}" if camera else ""
    d = root / "test" / bop_scene
    gt = json.loads((d / f"scene_gt{sfx}.json").read_text())["0"]
    info = json.loads((d / f"scene_gt_info{sfx}.json").read_text())["0"]
    masks = [
        cv2.imread(str(d / f"mask{sfx}" / f"000000_{k:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
        for k in range(len(gt))
    ]
    visib = [
        cv2.imread(str(d / f"mask_visib{sfx}" / f"000000_{k:06d}.png"), cv2.IMREAD_GRAYSCALE) > 0
        for k in range(len(gt))
    ]
    return {
        "R": [np.array(g["cam_R_m2c"]).reshape(3, 3) for g in gt],
        "t": [np.array(g["cam_t_m2c"]) for g in gt],
        "obj_id": [g["obj_id"] for g in gt],
        "masks": masks,
        "masks_visib": visib,
        "visib_fract": [i["visib_fract"] for i in info],
    }
