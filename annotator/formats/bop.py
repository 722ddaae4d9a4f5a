"""The BOP format (bop.felk.cvut.cz): export of accepted scenes, ground truth and CSV results.

Export layout (scene-wise; checked against bop_toolkit_lib.inout: load_scene_camera,
load_scene_gt, load_json, load_ply, load_depth, and the multi-sensor naming of BOP's recent
industrial sets)::

    OUT/models/obj_000001.ply, models_info.json
    OUT/camera_<cam>.json                       width, height, fx, fy, cx, cy, depth_scale
    OUT/test/<scene 000000>/gray_<cam>/000000.png
                           depth_<cam>/000000.png        (the depth camera only)
                           mask_<cam>/000000_000000.png, mask_visib_<cam>/...
                           scene_camera_<cam>.json, scene_gt_<cam>.json, scene_gt_info_<cam>.json
    OUT/test/scene_ids.json                     BOP scene id -> our scene id

With a single exported camera the suffix is dropped (``gray/``, ``scene_gt.json``...), the
classic single-sensor layout. Each of our scenes is one BOP scene with one image (im_id 0), in
sorted order. Poses are ``cam_R_m2c``/``cam_t_m2c`` (mm) in each camera's own frame;
``cam_R_w2c``/``cam_t_w2c`` give the camera in the rig's reference frame. Object ids follow
dataset.yaml's order from 1. Symmetries: :func:`annotator.symmetry.classes.symmetry_to_bop`.

Ground truth: ``<split>/<scene>/scene_gt[_<sensor>].json`` and ``scene_gt_info`` (occlusion =
1 - visib_fract), ``models/models_info.json`` and ``models/obj_XXXXXX.ply``; scenes are keyed
``<scene_id>/<im_id>`` and objects ``obj_XXXXXX``; a multi-sensor dataset is evaluated on its
first sensor (sorted by name).

Results: BOP's CSV ``scene_id,im_id,obj_id,score,R,t,time`` (R row-major, t in mm).
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from annotator.errors import UserError
from annotator.formats.base import (
    GroundTruth,
    PoseSet,
    Results,
    Table,
    checked_pose,
    checked_score,
    load_json,
)

NAME = "bop"


def detect(path: Path) -> bool:
    return (path / "models" / "models_info.json").is_file()


# -------------------------------------------------------------------------------- export


def models_info(obj: Any) -> dict[str, Any]:
    """A models_info.json entry: diameter (largest vertex distance), min/size, symmetries."""
    from scipy.spatial import ConvexHull

    from annotator.symmetry.classes import symmetry_to_bop

    v = obj.mesh.vertices
    hull = v[ConvexHull(v).vertices]
    d = np.sqrt(((hull[:, None] - hull[None]) ** 2).sum(-1)).max()
    lo, hi = v.min(axis=0), v.max(axis=0)
    info: dict[str, Any] = {
        "diameter": float(d),
        "min_x": float(lo[0]),
        "min_y": float(lo[1]),
        "min_z": float(lo[2]),
        "size_x": float(hi[0] - lo[0]),
        "size_y": float(hi[1] - lo[1]),
        "size_z": float(hi[2] - lo[2]),
    }
    info.update(symmetry_to_bop(obj.symmetry, obj.mesh.moments.centroid))
    return info


def export(
    ds: Any,
    selected: Sequence[Any],
    out: Path,
    *,
    cameras: Sequence[str],
    progress: Callable[[], None] | None = None,
) -> dict[str, str]:
    """Write ``selected`` scenes into the empty folder ``out``; returns the scenes left out
    because an input was unreadable (scene id -> one-line reason)."""
    from annotator.export.inputs import read_scene_inputs
    from annotator.export.undistort import pinhole_rig
    from annotator.io.atomic import write_json
    from annotator.io.images import encode_depth, write_png
    from annotator.io.ply import write_ply
    from annotator.occlusion import scene_visibility

    obj_ids = {name: k + 1 for k, name in enumerate(ds.objects)}
    info = {}
    for name, oid in obj_ids.items():
        write_ply(out / "models" / f"obj_{oid:06d}.ply", ds.objects[name].mesh)
        info[str(oid)] = models_info(ds.objects[name])
    write_json(out / "models" / "models_info.json", info)
    rig = pinhole_rig(ds.rig)
    multi = len(cameras) > 1
    depth_scale = ds.rig.depth.scale if ds.rig.depth else 1.0
    for name in cameras:
        K = rig.camera(name).K
        write_json(
            out / f"camera{_suffix(name, multi)}.json",
            {
                "width": rig.camera(name).width,
                "height": rig.camera(name).height,
                "fx": K[0, 0],
                "fy": K[1, 1],
                "cx": K[0, 2],
                "cy": K[1, 2],
                "depth_scale": depth_scale,
            },
        )
    ids: dict[str, str] = {}
    failed: dict[str, str] = {}
    for item in selected:
        try:
            inputs = read_scene_inputs(ds, item.scene, cameras)
        except UserError as exc:
            failed[item.scene.id] = str(exc)
            if progress:
                progress()
            continue
        bop_id = f"{len(ids):06d}"
        ids[bop_id] = item.scene.id
        scene_dir = out / "test" / bop_id
        depth = inputs.depth
        meshes = [ds.objects[p.object].mesh for p in item.poses]
        vis = scene_visibility(
            rig, meshes, [p.T for p in item.poses], depth=depth, cameras=cameras, masks=True
        )
        for ci, name in enumerate(cameras):
            sfx = _suffix(name, multi)
            cam = rig.camera(name)
            img = inputs.images[name]
            write_png(scene_dir / f"{'gray' if img.ndim == 2 else 'rgb'}{sfx}" / "000000.png", img)
            has_depth = depth is not None and name == ds.rig.depth.camera
            if has_depth:
                write_png(
                    scene_dir / f"depth{sfx}" / "000000.png", encode_depth(depth, depth_scale)
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
                valid = int(np.sum(cv.mask_all & np.isfinite(depth))) if has_depth else cv.px_all
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
    return failed


def _suffix(name: str, multi: bool) -> str:
    return f"_{name}" if multi else ""


# ------------------------------------------------------------------------- ground truth


def read_ground_truth(path: Path, *, symmetry: str | None = None) -> GroundTruth:
    from annotator.geometry.mesh import load_mesh
    from annotator.symmetry import PoseSpace
    from annotator.symmetry.classes import symmetry_from_bop

    info_path = path / "models" / "models_info.json"
    info = load_json(info_path)
    if not isinstance(info, dict):
        raise UserError("expected an object {obj_id: {...}}", path=info_path)
    spaces, names = {}, {}
    for key, entry in info.items():
        oid = int(key)
        name = f"obj_{oid:06d}"
        names[oid] = name
        try:
            sym = symmetry_from_bop(entry)
        except ValueError as exc:
            raise UserError(f"object {key}: {exc}", path=info_path) from None
        mesh = load_mesh(path / "models" / f"{name}.ply")
        spaces[name] = PoseSpace.from_moments(mesh.moments, sym)
    table: Table = {}
    scenes = []
    for scene_dir in sorted({p.parent for p in path.glob("*/*/scene_gt*.json")}):
        sensors = sorted(
            p.name[len("scene_gt") : -len(".json")]
            for p in scene_dir.glob("scene_gt*.json")
            if not p.name.startswith("scene_gt_info")
        )
        sfx = "" if "" in sensors else sensors[0]
        gt = load_json(scene_dir / f"scene_gt{sfx}.json")
        gi_path = scene_dir / f"scene_gt_info{sfx}.json"
        gi = load_json(gi_path) if gi_path.exists() else {}
        for im_id, insts in gt.items():
            key = f"{int(scene_dir.name)}/{int(im_id)}"
            scenes.append(key)
            infos = gi.get(im_id, [])
            for k, inst in enumerate(insts):
                name = names.get(int(inst["obj_id"]), f"obj_{int(inst['obj_id']):06d}")
                vf = infos[k].get("visib_fract") if k < len(infos) else None
                table.setdefault((key, name), PoseSet()).add(
                    np.asarray(inst["cam_R_m2c"], float).reshape(3, 3),
                    np.asarray(inst["cam_t_m2c"], float).reshape(3),
                    1.0 - float(vf) if vf is not None else float("nan"),
                )
    return GroundTruth(spaces, table, scenes, NAME, "mm", names)


# ------------------------------------------------------------------------------ results


def read_results(path: Path, gt: GroundTruth) -> Results:
    if path.is_dir():
        raise UserError("BOP results are a CSV file, not a folder", path=path)
    return read_csv_results(path, gt, scene_key=lambda sid, im: f"{int(sid)}/{im}")


def read_csv_results(
    path: Path, gt: GroundTruth, *, scene_key: Callable[[str, int], str]
) -> Results:
    """BOP's CSV: one result per line, ``scene_id,im_id,obj_id,score,R,t,time``; the
    header line is optional; ``obj_id`` is a number (or, for our datasets, a name)."""
    if not path.is_file():
        raise UserError("results file or folder is missing", path=path)
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read ({exc})", path=path) from None
    table: Table = {}
    known = set(gt.scenes)
    unknown: list[str] = []
    start = 1 if rows and rows[0] and rows[0][0].strip() == "scene_id" else 0
    for n, row in enumerate(rows[start:], start=start + 1):
        if not row or not "".join(row).strip():
            continue
        where = f"line {n}"
        if len(row) < 6:
            raise UserError(f"{where}: expected scene_id,im_id,obj_id,score,R,t,time", path=path)
        try:
            scene_id, im_id = row[0].strip(), int(row[1])
            R = [float(v) for v in row[4].split()]
            t = [float(v) for v in row[5].split()]
        except ValueError:
            raise UserError(f"{where}: malformed number", path=path) from None
        score = checked_score(row[3].strip(), where, path)
        obj = row[2].strip()
        if obj.isdigit():
            obj = gt.object_ids.get(int(obj), f"obj_{int(obj):06d}")
        if obj not in gt.spaces:
            raise UserError(f"{where}: result for unknown object {row[2].strip()!r}", path=path)
        Rm, tv = checked_pose(R, t, where, path)
        try:
            key = scene_key(scene_id, im_id)
        except ValueError:
            raise UserError(f"{where}: malformed scene_id {scene_id!r}", path=path) from None
        if key not in known:
            if key not in unknown:
                unknown.append(key)
            continue
        table.setdefault((key, obj), PoseSet()).add(Rm, tv, score)
    return Results(table, unknown)
