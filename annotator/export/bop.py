"""Writing accepted scenes of one of our datasets as a BOP dataset (the layout is in
:mod:`annotator.formats.bop`), with what BOP's own tools expect beside the scenes:

- ``models/`` and ``models_eval/`` (the same meshes: MSSD's largest distance over a triangle
  is at one of its corners, so the vertices are the points BOP's scores need);
- with ``sensors``, ``test_targets_multiview_bop25.json`` (BOP 2025's multi-view targets: per
  shot, the image of every sensor);
- ``test_targets_bop19.json`` (per image and object, the instances at least 10 % visible, as
  bop_toolkit's ``enumerate_test_targets.py``) and ``test_targets_bop24.json`` (every image);
- ``scene_gt_coco[_<cam>].json`` per scene: COCO annotations with RLE masks of the visible
  part (pycocotools), amodal boxes and ``ignore`` for instances less than 10 % visible, as
  bop_toolkit's ``calc_gt_coco.py``.

With ``remove_markers`` (``export --remove-markers``) the intensity images are written with
the markers filled in (:mod:`annotator.export.removal`), and beside each one its
``mask_markers[_<cam>]/000000.png`` (uint8, 255 where a marker was filled, 0 elsewhere); the
COCO file then has a ``marker`` category of its own (id: the largest object id + 1), one
annotation per visible marker with its ``marker_id``, ``obj_id``, ``gt_index`` (the
instance's place in scene_gt.json) and projected ``corners``. Depth is left as measured.

``layout`` ``imagewise`` and ``webdataset`` then turn ``test/`` into bop_toolkit's
``bop_imagewise`` files (``test_imagewise/KEY.gray.tiff``, ``KEY.depth.png``,
``KEY.camera.json``, ``KEY.gt.json``, ``KEY.gt_info.json``, ``KEY.mask.json``,
``KEY.mask_visib.json``, ``KEY.mask_markers.png`` with ``remove_markers``, with KEY ``<scene>_<image>``; a rig's cameras are images 0, 1, ...
of their scene), or into the tar shards of ``bop_webdataset`` (``test_webdataset/
shard-000000.tar``... and ``key_to_shard.json``), as MegaPose's training sets are stored.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import webdataset as wds
from pycocotools import mask as coco_mask
from scipy.spatial import ConvexHull

from annotator.dataset import Dataset
from annotator.dataset.frames import Shot
from annotator.errors import UserError
from annotator.export.inputs import SceneInputs, read_scene_inputs
from annotator.export.markers import MarkerRegion
from annotator.export.options import LAYOUTS, Layout
from annotator.export.removal import remove_scene_markers
from annotator.export.selection import Selected
from annotator.export.undistort import pinhole_rig
from annotator.formats.bop import MULTIVIEW_TARGETS
from annotator.io.atomic import write_bytes, write_json
from annotator.io.images import encode_depth, read_image, write_png
from annotator.io.ply import write_ply
from annotator.occlusion import scene_visibility
from annotator.physics.labels import PickLabel, pick_labels
from annotator.physics.scene import bodies_of, shot_support
from annotator.symmetry.classes import symmetry_to_bop

#: Instances at least this visible are targets (BOP's test_targets_bop19.json rule), and
#: the others are ``ignore`` in COCO.
TARGET_MIN_VISIB = 0.1
#: Images per tar shard of the webdataset layout (bop_toolkit's default ``maxcount``).
SHARD_IMAGES = 1000


def models_info(obj: Any) -> dict[str, Any]:
    """A models_info.json entry: diameter (largest vertex distance), min/size, symmetries."""
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


def export_bop(
    ds: Dataset,
    selected: Sequence[Selected],
    out: Path,
    *,
    cameras: Sequence[str],
    progress: Callable[[], None] | None = None,
    layout: Layout = "scenewise",
    remove_markers: bool = False,
    fill: str = "surface",
    markers_filled: Callable[[int, int], None] | None = None,
    sensors: bool = False,
) -> dict[str, str]:
    """Write ``selected`` scenes into the empty folder ``out``; returns the scenes left out
    because an input was unreadable (scene id -> one-line reason). ``remove_markers``: the
    images with their markers filled in by ``fill`` (:mod:`annotator.export.fill`), and
    ``mask_markers``; ``markers_filled`` is told how many markers each scene's images had
    filled in, and how many of them were found beyond where the poses put them. ``sensors``: every camera is a BOP sensor named after it, as in BOP's
    industrial datasets, even when only one is exported (:data:`SENSORS_FILE` names the one
    the targets are for); otherwise a single camera is written in the classic layout."""
    if layout not in LAYOUTS:
        raise UserError(f"unknown layout {layout!r} (expected one of {', '.join(LAYOUTS)})")
    obj_ids = _write_models(ds, out)
    rig = pinhole_rig(ds.rig)
    multi = sensors or len(cameras) > 1
    depth_scale = ds.rig.depth.scale if ds.rig.depth else 1.0
    for name in cameras:
        cam = rig.camera(name)
        write_json(
            out / f"camera{suffix(name, multi)}.json",
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
    ids: dict[str, str] = {}
    failed: dict[str, str] = {}
    targets: list[dict[str, int]] = []
    images: list[dict[str, int]] = []
    for item in selected:
        try:  # every shot read before anything of the scene is written
            shots = [
                (_image_id(item, shot), shot, read_scene_inputs(ds, shot.capture, cameras))
                for shot in item.shots
            ]
        except UserError as exc:
            failed[item.scene.id] = str(exc)
        else:
            bop_id = len(ids)
            ids[f"{bop_id:06d}"] = item.scene.id
            scene = _SceneWriter(ds, rig, cameras, obj_ids, out / "test" / f"{bop_id:06d}")
            scene.multi = multi
            scene.remove_markers, scene.fill = remove_markers, fill
            scene.markers_filled = markers_filled
            targets += scene.write(item, shots, bop_id)
            images += [{"scene_id": bop_id, "im_id": im_id} for im_id, _, _ in shots]
        if progress:
            progress()
    write_json(out / "test" / "scene_ids.json", ids)
    write_json(out / "test_targets_bop19.json", targets)
    write_json(out / "test_targets_bop24.json", images)
    if sensors:
        write_json(out / SENSORS_FILE, {"sensors": list(cameras), "eval_sensor": cameras[0]})
        # every sensor took every shot: one moment, one image id
        moments = [{**i, "im_id": [[c, i["im_id"]] for c in cameras]} for i in images]
        write_json(out / MULTIVIEW_TARGETS, moments)
    if layout != "scenewise":
        _imagewise(out / "test", out / "test_imagewise", cameras, multi)
        if layout == "webdataset":
            _webdataset(out / "test_imagewise", out / "test_webdataset")
            shutil.rmtree(out / "test_imagewise")
        shutil.move(out / "test" / "scene_ids.json", out / "scene_ids.json")
        shutil.rmtree(out / "test")
    return failed


#: With ``sensors``: the exported sensors and the one the targets files are for (BOP keeps
#: this in bop_toolkit's ``dataset_params.py``; readers here look for it first).
SENSORS_FILE = "sensors.json"


def suffix(name: str, multi: bool) -> str:
    """A camera's file suffix: ``_<name>`` when several cameras are exported."""
    return f"_{name}" if multi else ""


def _write_models(ds: Dataset, out: Path) -> dict[str, int]:
    """models/ and models_eval/ with models_info.json; object name -> BOP id."""
    obj_ids = {name: k + 1 for k, name in enumerate(ds.objects)}
    info = {str(oid): models_info(ds.objects[name]) for name, oid in obj_ids.items()}
    for folder in ("models", "models_eval"):
        for name, oid in obj_ids.items():
            write_ply(out / folder / f"obj_{oid:06d}.ply", ds.objects[name].mesh)
        write_json(out / folder / "models_info.json", info)
    return obj_ids


class _SceneWriter:
    """One of our scenes as one BOP scene: an image per exported camera, with its poses,
    masks, visibility and COCO annotations."""

    def __init__(
        self,
        ds: Dataset,
        rig: Any,
        cameras: Sequence[str],
        obj_ids: dict[str, int],
        folder: Path,
    ) -> None:
        self.ds, self.rig, self.cameras, self.obj_ids, self.folder = (
            ds,
            rig,
            cameras,
            obj_ids,
            folder,
        )
        self.depth_scale = ds.rig.depth.scale if ds.rig.depth else 1.0
        self.remove_markers = False
        self.fill = "surface"
        self.markers_filled: Callable[[int, int], None] | None = None
        self.multi = len(cameras) > 1

    def write(
        self, item: Selected, shots: list[tuple[int, Shot, SceneInputs]], bop_id: int
    ) -> list[dict[str, int]]:
        """Write the scene, one BOP image per shot (a fixed rig's scene is image 0, a
        sequence's frame ``k`` image ``k``); returns its entries of test_targets_bop19.json
        (for the first camera: BOP's targets name one image per shot here)."""
        files = {c: _CameraFiles() for c in self.cameras}
        targets: list[dict[str, int]] = []
        picks = self._pick_labels(item, shots)
        for im_id, shot, inputs in shots:
            poses = shot.poses(item.poses)
            markers, vis, images = self._shot(item, shot, poses, inputs)
            for ci, name in enumerate(self.cameras):
                visib = self._write_camera(
                    ci,
                    name,
                    im_id,
                    shot,
                    poses,
                    images[name],
                    inputs.depth,
                    vis,
                    markers[name],
                    files[name],
                    picks,
                )
                if ci == 0:
                    ids = [self.obj_ids[p.object] for p in poses]
                    targets += _targets(bop_id, im_id, ids, visib)
        for name, f in files.items():
            sfx = suffix(name, self.multi)
            write_json(self.folder / f"scene_camera{sfx}.json", f.camera)
            write_json(self.folder / f"scene_gt{sfx}.json", f.gt)
            write_json(self.folder / f"scene_gt_info{sfx}.json", f.gt_info)
            write_json(self.folder / f"scene_gt_coco{sfx}.json", f.coco)
            write_json(self.folder / f"scene_pick{sfx}.json", f.pick)
        return targets

    def _pick_labels(
        self, item: Selected, shots: list[tuple[int, Shot, SceneInputs]]
    ) -> list[PickLabel]:
        """Each instance's pick-ready label, in the scene's frame (the same in every shot:
        the support from the first shot's depth)."""
        bodies = bodies_of(self.ds, item.poses)
        _, shot, inputs = shots[0]
        return pick_labels(bodies, shot_support(self.ds, shot, bodies, inputs.depth))

    def _shot(
        self, item: Selected, shot: Shot, poses: list[Any], inputs: SceneInputs
    ) -> tuple[dict[str, list[MarkerRegion] | None], Any, dict[str, np.ndarray]]:
        """One shot's markers (with ``remove_markers``), visibility and images to write."""
        depth = inputs.depth
        images = inputs.images
        markers: dict[str, list[MarkerRegion] | None] = {c: None for c in self.cameras}
        if self.remove_markers:
            removed = remove_scene_markers(
                self.ds,
                self.rig,
                item.scene,
                poses,
                images,
                cameras=self.cameras,
                depth=depth,
                fill=self.fill,
                frame=shot.frame,
            )
            vis, images = removed.visibility, removed.images
            if self.markers_filled:
                self.markers_filled(removed.filled, sum(removed.found_beyond.values()))
            im = _image_name(shot, item)
            for name, m in removed.markers.items():
                mask = m.mask.astype(np.uint8) * 255
                write_png(
                    self.folder / f"mask_markers{suffix(name, self.multi)}" / f"{im}.png", mask
                )
                markers[name] = m.regions
        else:
            meshes = [self.ds.objects[p.object].mesh for p in poses]
            vis = scene_visibility(
                self.rig,
                meshes,
                [p.T for p in poses],
                depth=depth,
                cameras=self.cameras,
                masks=True,
            )
        return markers, vis, images

    def _write_camera(
        self,
        ci: int,
        name: str,
        im_id: int,
        shot: Shot,
        poses: list[Any],
        img: np.ndarray,
        depth: Any,
        vis: Any,
        markers: list[MarkerRegion] | None,
        files: _CameraFiles,
        picks: list[PickLabel],
    ) -> list[float]:
        sfx = suffix(name, self.multi)
        cam = self.rig.camera(name)
        d = self.folder
        im = f"{im_id:06d}"
        kind = "gray" if img.ndim == 2 else "rgb"
        write_png(d / f"{kind}{sfx}" / f"{im}.png", img)
        has_depth = (
            depth is not None and self.ds.rig.depth is not None and name == self.ds.rig.depth.camera
        )
        if has_depth:
            write_png(d / f"depth{sfx}" / f"{im}.png", encode_depth(depth, self.depth_scale))
        gts, infos, coco, pick = self._instance_records(
            ci, cam, im, sfx, poses, vis, picks, depth if has_depth else None
        )
        files.camera[str(im_id)] = self._camera_record(cam, shot, has_depth)
        files.gt[str(im_id)] = gts
        files.gt_info[str(im_id)] = infos
        files.pick[str(im_id)] = pick
        files.add_coco(
            coco_scene(
                coco,
                f"{kind}{sfx}/{im}.png",
                cam.width,
                cam.height,
                self.obj_ids,
                markers=markers,
                marker_objects=[self.obj_ids[p.object] for p in poses],
                image_id=im_id,
            )
        )
        return [c[3] for c in coco]

    def _instance_records(
        self,
        ci: int,
        cam: Any,
        im: str,
        sfx: str,
        poses: list[Any],
        vis: Any,
        picks: list[PickLabel],
        depth: np.ndarray | None,
    ) -> tuple[list[dict], list[dict], list[tuple], list[dict]]:
        """One image's ``scene_gt``, ``scene_gt_info``, COCO and pick records, an entry per
        instance; writes the instances' masks."""
        d = self.folder
        gts, infos, coco, pick = [], [], [], []
        for k, (p, v, label) in enumerate(zip(poses, vis, picks)):
            cv = v.cameras[ci]
            M = cam.cam_T_rig @ p.T
            gts.append(
                {
                    "cam_R_m2c": M[:3, :3].ravel().tolist(),
                    "cam_t_m2c": M[:3, 3].tolist(),
                    "obj_id": self.obj_ids[p.object],
                }
            )
            visib_px = int(cv.mask_visib.sum())
            fract = float(visib_px / cv.px_all) if cv.px_all else 0.0
            infos.append(
                {
                    "bbox_obj": list(cv.bbox_all) if cv.bbox_all else [-1, -1, -1, -1],
                    "bbox_visib": list(cv.bbox_visib) if cv.bbox_visib else [-1, -1, -1, -1],
                    "px_count_all": cv.px_all,
                    "px_count_valid": (
                        int(np.sum(cv.mask_all & np.isfinite(depth)))
                        if depth is not None
                        else cv.px_all
                    ),
                    "px_count_visib": visib_px,
                    "visib_fract": fract,
                }
            )
            write_png(d / f"mask{sfx}" / f"{im}_{k:06d}.png", cv.mask_all.astype(np.uint8) * 255)
            write_png(
                d / f"mask_visib{sfx}" / f"{im}_{k:06d}.png",
                cv.mask_visib.astype(np.uint8) * 255,
            )
            coco.append((self.obj_ids[p.object], cv.mask_all, cv.mask_visib, fract))
            pick.append({"obj_id": self.obj_ids[p.object], **label.to_json(), "visib_fract": fract})
        return gts, infos, coco, pick

    def _camera_record(self, cam: Any, shot: Shot, has_depth: bool) -> dict[str, Any]:
        """One image's ``scene_camera`` record."""
        # The world of a sequence is its scene frame; a fixed rig's is its reference camera.
        w2c = cam.cam_T_rig if shot.frame is None else cam.cam_T_rig @ shot.rig_T_scene
        rec: dict[str, Any] = {
            "cam_K": cam.K.ravel().tolist(),
            "cam_R_w2c": w2c[:3, :3].ravel().tolist(),
            "cam_t_w2c": w2c[:3, 3].tolist(),
        }
        if has_depth:
            rec["depth_scale"] = self.depth_scale
        return rec


@dataclass
class _CameraFiles:
    """One camera's scene-level JSON files, filled image by image."""

    camera: dict[str, Any] = field(default_factory=dict)
    gt: dict[str, Any] = field(default_factory=dict)
    gt_info: dict[str, Any] = field(default_factory=dict)
    coco: dict[str, Any] = field(default_factory=dict)
    pick: dict[str, Any] = field(default_factory=dict)

    def add_coco(self, doc: dict[str, Any]) -> None:
        """One image's COCO document merged in (annotation ids kept unique)."""
        if not self.coco:
            self.coco = doc
            return
        first = len(self.coco["annotations"])
        for k, a in enumerate(doc["annotations"]):
            a["id"] = first + k + 1
        self.coco["images"] += doc["images"]
        self.coco["annotations"] += doc["annotations"]


def _image_id(item: Selected, shot: Shot) -> int:
    """A shot's BOP image id: 0 for a fixed rig's scene, the frame's place among the
    sequence's frame folders for a frame (a rejected frame leaves its number unused)."""
    if shot.frame is None:
        return 0
    return [f.name for f in item.scene.frames()].index(shot.frame)


def _image_name(shot: Shot, item: Selected) -> str:
    return f"{_image_id(item, shot):06d}"


def _targets(
    scene_id: int, im_id: int, obj_ids: list[int], visib: list[float]
) -> list[dict[str, int]]:
    counts: dict[int, int] = {}
    for oid, v in zip(obj_ids, visib):
        if v >= TARGET_MIN_VISIB:
            counts[oid] = counts.get(oid, 0) + 1
    return [
        {"scene_id": scene_id, "im_id": im_id, "obj_id": oid, "inst_count": n}
        for oid, n in counts.items()
    ]


def rle(mask: np.ndarray) -> dict[str, Any]:
    """A boolean mask as COCO's compressed RLE, JSON-ready (``counts`` as text)."""
    code = coco_mask.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"counts": code["counts"].decode("ascii"), "size": [int(s) for s in code["size"]]}


def rle_of_pixels(pixels: np.ndarray, width: int, height: int) -> dict[str, Any]:
    """:func:`rle` of the mask of ``pixels`` ((N, 2) ``(row, column)``, no repeats), from
    the pixels themselves: a marker's few hundred pixels, not a full image per marker."""
    idx = np.sort(pixels[:, 1].astype(np.int64) * height + pixels[:, 0])
    # Column-major runs: zeros before the first pixel, then alternating ones and zeros.
    starts = np.flatnonzero(np.r_[True, np.diff(idx) != 1])
    ends = np.r_[starts[1:], len(idx)]
    counts: list[int] = []
    pos = 0
    for a, b in zip(starts, ends):
        first = int(idx[a])
        counts += [first - pos, int(b - a)]
        pos = first + int(b - a)
    if pos < height * width:  # (pycocotools writes no empty last run)
        counts.append(height * width - pos)
    code = coco_mask.frPyObjects({"counts": counts, "size": [height, width]}, height, width)
    return {"counts": code["counts"].decode("ascii"), "size": [int(s) for s in code["size"]]}


def coco_scene(
    instances: list[tuple[int, np.ndarray, np.ndarray, float]],
    file_name: str,
    width: int,
    height: int,
    obj_ids: dict[str, int],
    *,
    markers: Sequence[MarkerRegion] | None = None,
    marker_objects: Sequence[int] = (),
    image_id: int = 0,
) -> dict[str, Any]:
    """A scene_gt_coco.json of one image: per instance (object id, full mask, visible mask,
    visible fraction); instances with nothing visible are left out, as bop_toolkit does.
    ``markers``: the image's markers, as annotations of a category of their own
    (:func:`marker_category`); ``marker_objects``: the object id of each instance."""
    annotations: list[dict[str, Any]] = []
    for oid, full, visib, fract in instances:
        if not visib.any() or not full.any():
            continue
        ys, xs = np.nonzero(full)
        x0, y0 = int(xs.min()), int(ys.min())
        annotations.append(
            {
                "id": len(annotations) + 1,
                "image_id": image_id,
                "category_id": oid,
                "iscrowd": 0,
                "area": int(visib.sum()),
                "bbox": [x0, y0, int(xs.max()) - x0 + 1, int(ys.max()) - y0 + 1],
                "segmentation": rle(visib),
                "width": int(width),
                "height": int(height),
                "ignore": bool(fract < TARGET_MIN_VISIB),
            }
        )
    categories = [
        {"id": oid, "name": str(oid), "supercategory": "annotator"} for oid in obj_ids.values()
    ]
    if markers is not None:
        marker_id = marker_category(obj_ids)
        categories.append({"id": marker_id, "name": "marker", "supercategory": "marker"})
        for m in markers:
            if not len(m.pixels) or m.bbox_visib is None:
                continue
            annotations.append(
                {
                    "id": len(annotations) + 1,
                    "image_id": image_id,
                    "category_id": marker_id,
                    "iscrowd": 0,
                    "area": int(len(m.pixels)),
                    "bbox": list(m.bbox_visib),
                    "segmentation": rle_of_pixels(m.pixels, width, height),
                    "width": int(width),
                    "height": int(height),
                    "ignore": False,
                    "marker_id": m.marker_id,
                    "obj_id": int(marker_objects[m.instance]),
                    "gt_index": m.instance,
                    "corners": np.round(m.corners, 3).tolist(),
                    "visib_fract": round(m.visib_fract, 4),
                }
            )
    return {
        "info": {"description": "annotator export", "url": "", "version": "0.1.0"},
        "licenses": [],
        "categories": categories,
        "images": [
            {"id": image_id, "file_name": file_name, "width": int(width), "height": int(height)}
        ],
        "annotations": annotations,
    }


def marker_category(obj_ids: dict[str, int]) -> int:
    """The COCO category id of markers: one past the largest object id."""
    return max(obj_ids.values(), default=0) + 1


# -------------------------------------------------------------------------------- layouts


def _imagewise(scenes: Path, out: Path, cameras: Sequence[str], multi: bool) -> None:
    """bop_toolkit's bop_imagewise files from the scene-wise export: one image per (scene,
    image, camera), numbered ``image * cameras + camera`` (a fixed rig's cameras are images
    0, 1, ... of their scene)."""
    for scene in sorted(p for p in scenes.iterdir() if p.is_dir()):
        for ci, name in enumerate(cameras):
            sfx = suffix(name, multi)
            docs = {
                what: json.loads((scene / f"scene_{what}{sfx}.json").read_text())
                for what in ("camera", "gt", "gt_info", "pick")
            }
            for image in sorted(docs["camera"], key=int):
                im = f"{int(image):06d}"
                key = f"{scene.name}_{int(image) * len(cameras) + ci:06d}"
                for what, doc in docs.items():
                    write_json(out / f"{key}.{what}.json", doc[image])
                for what in ("mask", "mask_visib"):
                    files = sorted((scene / f"{what}{sfx}").glob(f"{im}_*.png"))
                    masks = {str(k): rle(read_image(f) > 0) for k, f in enumerate(files)}
                    write_json(out / f"{key}.{what}.json", masks)
                if (scene / f"rgb{sfx}").is_dir():
                    shutil.copy(scene / f"rgb{sfx}" / f"{im}.png", out / f"{key}.rgb.png")
                else:  # bop_imagewise reads grey images as TIFF only
                    gray = read_image(scene / f"gray{sfx}" / f"{im}.png")
                    # uncompressed: imageio's TIFF reader needs an extra codec package for LZW
                    ok, buf = cv2.imencode(".tiff", gray, [cv2.IMWRITE_TIFF_COMPRESSION, 1])
                    if not ok:
                        raise OSError(f"{key}: TIFF encoding failed")
                    write_bytes(out / f"{key}.gray.tiff", buf.tobytes())
                if (scene / f"depth{sfx}").is_dir():
                    shutil.copy(scene / f"depth{sfx}" / f"{im}.png", out / f"{key}.depth.png")
                if (scene / f"mask_markers{sfx}").is_dir():
                    shutil.copy(
                        scene / f"mask_markers{sfx}" / f"{im}.png", out / f"{key}.mask_markers.png"
                    )


def _webdataset(imagewise: Path, out: Path) -> None:
    """The imagewise files as tar shards (one sample per image key) and key_to_shard.json."""
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, list[Path]] = {}
    for f in sorted(imagewise.iterdir()):
        files.setdefault(f.name.split(".")[0], []).append(f)
    key_to_shard: dict[str, int] = {}
    with wds.ShardWriter(
        str(out / "shard-%06d.tar"), maxcount=SHARD_IMAGES, encoder=False, verbose=0
    ) as sink:
        for n, (key, group) in enumerate(sorted(files.items())):
            sample: dict[str, Any] = {"__key__": key}
            for f in group:
                sample[f.name[len(key) + 1 :]] = f.read_bytes()
            sink.write(sample)
            key_to_shard[key] = n // SHARD_IMAGES
    write_json(out / "key_to_shard.json", key_to_shard)
