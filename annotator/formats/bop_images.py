"""A BOP test split image by image, as BOP's own evaluation reads it, for
:mod:`annotator.evaluation.bop19`.

What is read, as bop_toolkit's ``eval_calc_errors.py`` reads it:

- ``models_info.json`` (diameters, symmetries) and the model points: the vertices of
  ``models_eval/obj_XXXXXX.ply`` (``models/`` when the dataset has no ``models_eval/``, said in
  a note); VSD renders the same meshes.
- ``test_targets_bop19.json``; without one, targets are made as bop_toolkit's
  ``enumerate_test_targets.py`` makes them (instances at least 10 % visible), said in a note.
  For 6D detection (BOP 2024 on, ``task="detection"``), ``test_targets_bop24.json``'s images
  (every image without one), in its order, each with every true pose of the image, as
  bop_toolkit's ``inout.get_im_targets`` in detection mode.
- Per scene of the split (``test`` if there is one): ``scene_gt``, ``scene_gt_info``
  (``visib_fract``), ``scene_camera`` (``cam_K``, ``depth_scale``) and ``depth/``, of the
  sensor :func:`annotator.formats.bop.evaluated_sensor` picks.
- The image width from ``camera[_<sensor>].json`` (MSPD is rescaled by it).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from annotator.errors import UserError
from annotator.formats.base import GroundTruth, checked_poses
from annotator.formats.bop import (
    MULTIVIEW_TARGETS,
    evaluated_sensor,
    multiview_target_images,
    non_empty,
    read_csv_rows,
    target_ids,
)
from annotator.geometry.mesh import Mesh, load_mesh
from annotator.io.documents import read_json
from annotator.io.images import read_image
from annotator.symmetry.classes import Symmetry, symmetry_to_bop

#: Continuous symmetries: the farthest point moves at most this fraction of the diameter
#: between samples (bop_toolkit's ``max_sym_disc_step``).
MAX_SYM_DISC_STEP = 0.01
#: VSD's visibility tolerance in mm, and ITODD's own.
VSD_DELTA_MM = 15.0
VSD_DELTA_ITODD_MM = 5.0

#: Visible fraction of the instances a derived targets list keeps (bop_toolkit's
#: ``enumerate_test_targets.py``).
TARGETS_MIN_VISIB = 0.1


@dataclass(frozen=True)
class BopObject:
    """An object as BOP's evaluation sees it.

    Attributes:
        points: (N, 3) model points in mm (the vertices of its ``models_eval`` PLY).
        diameter: ``models_info.json``'s diameter, mm.
        sym_R: (S, 3, 3) symmetry rotations, the identity first (:func:`symmetry_transformations`).
        sym_t: (S, 3) their translations, mm.
        mesh: The mesh VSD renders (None: VSD cannot be computed for it).
    """

    points: np.ndarray
    diameter: float
    sym_R: np.ndarray
    sym_t: np.ndarray
    mesh: Mesh | None = None


@dataclass
class BopImage:
    """One test image: its camera, its true poses and what is to be found in it.

    Attributes:
        scene_id, im_id: BOP's ids.
        K: 3x3 intrinsics; ``width`` and ``height`` in pixels.
        obj_ids: (G,) object id of each true pose, in scene_gt.json's order.
        R, t: (G, 3, 3) and (G, 3) true poses (model to camera, mm).
        visib: (G,) visible fractions (scene_gt_info.json).
        targets: object id -> instances to find (the targets file's ``inst_count``).
        depth: Reads the depth image in mm (0: no measurement), or None without one.
    """

    scene_id: int
    im_id: int
    K: np.ndarray
    width: int
    height: int
    obj_ids: np.ndarray
    R: np.ndarray
    t: np.ndarray
    visib: np.ndarray
    targets: dict[int, int]
    depth: Callable[[], np.ndarray] | None = None


@dataclass
class BopEstimates:
    """Pose estimates of one image, in the result file's order: (E,) object ids and scores,
    (E, 3, 3) rotations and (E, 3) translations in mm."""

    obj_ids: np.ndarray
    scores: np.ndarray
    R: np.ndarray
    t: np.ndarray


# ------------------------------------------------------------------------------ symmetries


def symmetry_transformations(
    info: dict[str, Any], max_disc_step: float = MAX_SYM_DISC_STEP
) -> tuple[np.ndarray, np.ndarray]:
    """The symmetry transforms ``x -> R x + t`` of a models_info.json entry, as bop_toolkit's
    ``misc.get_symmetry_transformations``: the identity and each discrete element as written,
    each combined with ``ceil(pi / max_disc_step)`` turns about every continuous axis (about
    its offset). Returns (S, 3, 3) and (S, 3)."""
    disc_R, disc_t = [np.eye(3)], [np.zeros(3)]
    for sym in info.get("symmetries_discrete") or []:
        M = np.asarray(sym, float).reshape(4, 4)
        disc_R.append(M[:3, :3])
        disc_t.append(M[:3, 3])
    cont_R: list[np.ndarray] = []
    cont_t: list[np.ndarray] = []
    for sym in info.get("symmetries_continuous") or []:
        axis = np.asarray(sym["axis"], float)
        axis = axis / math.sqrt(float(np.dot(axis, axis)))
        offset = np.asarray(sym["offset"], float).reshape(3)
        steps = int(np.ceil(np.pi / max_disc_step))
        step = 2.0 * np.pi / steps
        for i in range(steps):
            R = _axis_rotation(i * step, axis)
            cont_R.append(R)
            cont_t.append(-R.dot(offset) + offset)
    if not cont_R:
        return np.array(disc_R), np.array(disc_t)
    Rs, ts = [], []
    for Rd, td in zip(disc_R, disc_t):
        for Rc, tc in zip(cont_R, cont_t):
            Rs.append(Rc.dot(Rd))
            ts.append(Rc.dot(td) + tc)
    return np.array(Rs), np.array(ts)


def bop_symmetries(
    sym: Symmetry, centroid: np.ndarray, max_disc_step: float = MAX_SYM_DISC_STEP
) -> tuple[np.ndarray, np.ndarray]:
    """One of the paper's symmetry classes as BOP's evaluation samples it: its models_info.json
    entry (:func:`annotator.symmetry.classes.symmetry_to_bop`, axes through ``centroid``)
    made into transforms by :func:`symmetry_transformations`, each continuous axis in
    ``ceil(pi / max_disc_step)`` turns, so that a point at half the diameter from the axis
    moves at most ``max_disc_step`` diameters between two. (S, 3, 3) and (S, 3).

    >>> from annotator.symmetry.classes import Symmetry
    >>> R, t = bop_symmetries(Symmetry("revolution", axis=np.array([0.0, 0.0, 1.0])), np.zeros(3))
    >>> R.shape, t.shape  # ceil(pi / 0.01) turns
    ((315, 3, 3), (315, 3))
    """
    return symmetry_transformations(symmetry_to_bop(sym, centroid), max_disc_step)


def _axis_rotation(angle: float, unit_axis: np.ndarray) -> np.ndarray:
    """Rodrigues' rotation, term by term as bop_toolkit's ``transform.rotation_matrix``."""
    sina, cosa = math.sin(angle), math.cos(angle)
    R = np.diag([cosa, cosa, cosa])
    R += np.outer(unit_axis, unit_axis) * (1.0 - cosa)
    d = unit_axis * sina
    R += np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    return R


# ----------------------------------------------------------------------------- reading


@dataclass
class BopSplit:
    """Everything BOP's evaluation needs of a dataset and a result file."""

    images: list[BopImage]
    objects: dict[int, BopObject]
    estimates: dict[tuple[int, int], BopEstimates]
    delta: float
    notes: list[str] = field(default_factory=list)
    times: dict[tuple[int, int], float] | None = None  # image -> seconds; None: not given


def read_bop_split(
    path: Path, results: Path, gt: GroundTruth, *, task: str = "localization"
) -> BopSplit:
    """The dataset at ``path`` and the result CSV ``results`` (already readable as ``gt``'s
    results), for :func:`annotator.evaluation.bop19.bop19_scores` (``task="localization"``)
    or :func:`annotator.evaluation.bop24.bop24_scores` (``task="detection"``)."""
    notes: list[str] = []
    objects = _objects(path, notes)
    split = _split_folder(path, notes)
    if task == "detection":
        targets = _detection_targets(path)
        if targets is None:
            notes.append("no test_targets_bop24.json: every image of the split is scored")
    else:
        targets = _targets(path)
        if targets is None:
            notes.append(
                "no test_targets_bop19.json: targets are the instances at least "
                f"{TARGETS_MIN_VISIB:g} visible, as bop_toolkit's enumerate_test_targets.py"
            )
    images = _images(split, objects, targets, every_pose=task == "detection")
    if task == "detection":
        images = _in_targets_order(images, targets)
    delta = VSD_DELTA_ITODD_MM if path.resolve().name.startswith("itodd") else VSD_DELTA_MM
    estimates, times = _estimates(results, gt)
    return BopSplit(images, objects, estimates, delta, notes, times)


#: Wanted objects of an image that are every true pose of it (6D detection).
EVERY_POSE: dict[int, int] = {}


def _targets_list(file: Path, entries: str) -> tuple[Path, list[Any]] | None:
    """A targets file's list of ``entries`` (None without the file)."""
    if not file.is_file():
        return None
    return file, non_empty(read_json(file), file, entries)


def _detection_targets(path: Path) -> dict[tuple[int, int], dict[int, int]] | None:
    """The images test_targets_bop24.json (else the evaluated sensor's of the multi-view
    targets, :data:`~annotator.formats.bop.MULTIVIEW_TARGETS`) lists, in its order (bop_toolkit's targets_org:
    scenes in the order they first appear, then images), each mapped to
    :data:`EVERY_POSE`."""
    found = _targets_list(path / "test_targets_bop24.json", "{scene_id, im_id}")
    if found is None:
        images = multiview_target_images(path)
        if images is None:
            return None
        found = path / MULTIVIEW_TARGETS, [{"scene_id": s, "im_id": im} for s, im in images]
    file, doc = found
    by_scene: dict[int, dict[int, dict[int, int]]] = {}
    for i, e in enumerate(doc):
        scene_id, im_id = target_ids(e, ("scene_id", "im_id"), i, file)
        by_scene.setdefault(scene_id, {})[im_id] = EVERY_POSE
    return {(s, im): w for s, ims in by_scene.items() for im, w in ims.items()}


def _in_targets_order(
    images: list[BopImage], targets: dict[tuple[int, int], dict[int, int]] | None
) -> list[BopImage]:
    if targets is None:
        return images
    rank = {key: k for k, key in enumerate(targets)}
    return sorted(images, key=lambda im: rank[(im.scene_id, im.im_id)])


def _objects(path: Path, notes: list[str]) -> dict[int, BopObject]:
    info_path = path / "models" / "models_info.json"
    info = read_json(info_path)
    if not isinstance(info, dict):
        raise UserError("expected an object {obj_id: {...}}", path=info_path)
    folder = path / "models_eval"
    if not folder.is_dir():
        folder = path / "models"
        notes.append("no models_eval/: BOP's scores use the points of models/")
    objects = {}
    for key, entry in info.items():
        oid = int(key)
        mesh = load_mesh(folder / f"obj_{oid:06d}.ply")
        try:
            diameter = float(entry["diameter"])
            sym_R, sym_t = symmetry_transformations(entry)
        except (KeyError, TypeError, ValueError) as exc:
            raise UserError(f"object {key}: malformed entry ({exc})", path=info_path) from None
        if not (math.isfinite(diameter) and diameter > 0):
            # BOP's thresholds are fractions of it: any other value changes every score.
            raise UserError(
                f"object {key}: diameter must be a positive number of mm, got {entry['diameter']}",
                path=info_path,
            )
        objects[oid] = BopObject(mesh.vertices, diameter, sym_R, sym_t, mesh)
    return objects


def _split_folder(path: Path, notes: list[str]) -> Path:
    splits = sorted({p.parent.parent for p in path.glob("*/*/scene_gt*.json")})
    if not splits:
        raise UserError("no <split>/<scene>/scene_gt.json", path=path)
    for s in splits:
        if s.name == "test":
            return s
    if len(splits) > 1:
        notes.append(f"BOP's scores are on split {splits[0].name}/ (there is no test/)")
    return splits[0]


def _targets(path: Path) -> dict[tuple[int, int], dict[int, int]] | None:
    found = _targets_list(path / "test_targets_bop19.json", "{scene_id, im_id, obj_id, inst_count}")
    if found is None:
        return None
    file, doc = found
    out: dict[tuple[int, int], dict[int, int]] = {}
    for i, e in enumerate(doc):
        scene_id, im_id, obj_id, count = target_ids(
            e, ("scene_id", "im_id", "obj_id", "inst_count"), i, file
        )
        out.setdefault((scene_id, im_id), {})[obj_id] = count
    return out


def _images(
    split: Path,
    objects: dict[int, BopObject],
    targets: dict[tuple[int, int], dict[int, int]] | None,
    *,
    every_pose: bool = False,
) -> list[BopImage]:
    images: list[BopImage] = []
    scenes = {int(d.name): d for d in split.iterdir() if d.is_dir() and d.name.isdigit()}
    wanted = sorted({s for s, _ in targets}) if targets is not None else sorted(scenes)
    for scene_id in wanted:
        if scene_id not in scenes:
            raise UserError(f"the targets name scene {scene_id}, which is not in {split}")
        images += _scene_images(scene_id, scenes[scene_id], objects, targets, every_pose)
    return images


def _scene_images(
    scene_id: int,
    folder: Path,
    objects: dict[int, BopObject],
    targets: dict[tuple[int, int], dict[int, int]] | None,
    every_pose: bool,
) -> list[BopImage]:
    sfx = evaluated_sensor(folder)
    gt_path = folder / f"scene_gt{sfx}.json"
    info_path = folder / f"scene_gt_info{sfx}.json"
    cams_path = folder / f"scene_camera{sfx}.json"
    gt, info, cams = _mapping(gt_path), _mapping(info_path), _mapping(cams_path)
    width, height = _image_size(folder, sfx)
    out = []
    for im_key in sorted(gt, key=int):
        im_id = int(im_key)
        insts = gt[im_key] or []
        if not isinstance(insts, list):
            raise UserError(f"image {im_key}: expected a list of poses", path=gt_path)
        obj_ids = np.array([int(g.get("obj_id", -1)) for g in insts], int)
        visib = _visible_fractions(info.get(im_key) or [], len(insts), im_key, info_path)
        if targets is None:
            wanted = _counts(obj_ids if every_pose else obj_ids[visib >= TARGETS_MIN_VISIB])
        elif (scene_id, im_id) in targets:
            wanted = targets[(scene_id, im_id)]
            if wanted is EVERY_POSE:
                wanted = _counts(obj_ids)
        else:
            continue
        unknown = [o for o in wanted if o not in objects]
        if unknown:
            raise UserError(f"image {im_key}: object {unknown[0]} is not in models_info.json")
        R, t = _poses_as_written(insts, im_key, gt_path)
        cam = cams.get(im_key) or {}
        K = _camera_matrix(cam, im_key, cams_path)
        depth = _depth_reader(folder, sfx, im_id, cam)
        out.append(BopImage(scene_id, im_id, K, width, height, obj_ids, R, t, visib, wanted, depth))
    return out


def _counts(obj_ids: np.ndarray) -> dict[int, int]:
    """Poses per object id, in the order the ids first appear."""
    out: dict[int, int] = {}
    for oid in obj_ids.tolist():
        out[oid] = out.get(oid, 0) + 1
    return out


def _visible_fractions(infos: Any, n: int, im_key: str, path: Path) -> np.ndarray:
    """The ``visib_fract`` of each of an image's ``n`` poses."""
    try:
        return np.array([float(infos[k]["visib_fract"]) for k in range(n)])
    except (IndexError, KeyError, TypeError, ValueError):
        raise UserError(f"image {im_key}: every pose needs a visib_fract", path=path) from None


def _poses_as_written(insts: list[Any], im_key: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """An image's poses, checked (finite, near-rotations), with R as written: bop_toolkit
    scores a rotation that is not quite orthonormal as it is, and so does this."""
    if not insts:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))

    def where(k: int) -> str:
        return f"image {im_key}, entry {k}"

    _, t, _ = checked_poses(
        [g.get("cam_R_m2c") for g in insts], [g.get("cam_t_m2c") for g in insts], where, path
    )
    return np.asarray([g["cam_R_m2c"] for g in insts], float).reshape(-1, 3, 3), t


def _camera_matrix(cam: dict[str, Any], im_key: str, path: Path) -> np.ndarray:
    try:
        K = np.asarray(cam["cam_K"], float).reshape(3, 3)
    except (KeyError, TypeError, ValueError):
        raise UserError(f"image {im_key}: cam_K must be 9 numbers", path=path) from None
    proper = np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0
    if not (proper and np.allclose(K[2], [0, 0, 1]) and K[1, 0] == 0):
        raise UserError(
            f"image {im_key}: cam_K must be a camera matrix [fx, s, cx, 0, fy, cy, 0, 0, 1] of "
            "finite numbers with fx, fy > 0",
            path=path,
        )
    return K


def _mapping(path: Path) -> dict[str, Any]:
    doc = read_json(path)
    if not isinstance(doc, dict):
        raise UserError("expected an object {im_id: ...}", path=path)
    return doc


def _image_size(folder: Path, sfx: str) -> tuple[int, int]:
    for cam_file in (
        folder.parent.parent / f"camera{sfx}.json",
        folder.parent.parent / "camera.json",
    ):
        if cam_file.is_file():
            cam = read_json(cam_file)
            try:
                return int(cam["width"]), int(cam["height"])
            except (KeyError, TypeError, ValueError):
                raise UserError("needs integer width and height", path=cam_file) from None
    for kind in ("rgb", "gray", "depth"):
        files = sorted((folder / f"{kind}{sfx}").glob("*.*"))
        if files:
            h, w = read_image(files[0]).shape[:2]
            return w, h
    raise UserError(f"no camera{sfx}.json and no image to tell the image size", path=folder)


def _depth_reader(
    folder: Path, sfx: str, im_id: int, cam: dict[str, Any]
) -> Callable[[], np.ndarray] | None:
    for ext in (".png", ".tif"):
        file = folder / f"depth{sfx}" / f"{im_id:06d}{ext}"
        if file.is_file():
            scale = np.float32(cam.get("depth_scale", 1.0))

            def read(file: Path = file, scale: np.float32 = scale) -> np.ndarray:
                return read_image(file).astype(np.float32) * scale

            return read
    return None


def _estimates(
    results: Path, gt: GroundTruth
) -> tuple[dict[tuple[int, int], BopEstimates], dict[tuple[int, int], float] | None]:
    """The result file's estimates per image, in its order, and each image's time (None when
    a line has none or a negative one, as bop_toolkit's ``check_consistent_timings``)."""
    rows, _, objects, _, t, _ = read_csv_rows(results, gt)
    R = np.asarray(rows.R, float).reshape(-1, 3, 3)  # as written: bop_toolkit does not project
    names = {name: oid for oid, name in gt.object_ids.items()}
    obj = np.array([names[n] for n in objects], int)
    scene = np.array([int(s) for s in rows.scene_ids], int)
    im = np.asarray(rows.im_ids, int)
    out: dict[tuple[int, int], BopEstimates] = {}
    times: dict[tuple[int, int], float] | None = None
    if rows.times is not None and np.all(rows.times >= 0):
        times = {}
        for s_, i_, dt in zip(scene.tolist(), im.tolist(), rows.times.tolist()):
            times.setdefault((s_, i_), dt)
    if not len(obj):
        return out, times
    keys = scene * (int(im.max()) + 1) + im
    order = np.argsort(keys, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(keys[order]) != 0])
    for a, b in zip(starts, np.r_[starts[1:], len(order)]):
        idx = order[a:b]
        out[(int(scene[idx[0]]), int(im[idx[0]]))] = BopEstimates(
            obj[idx], rows.scores[idx], R[idx], t[idx]
        )
    return out, times
