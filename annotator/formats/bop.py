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
classic single-sensor layout, unless ``export --sensors`` asks for BOP's multi-sensor layout
(then also ``OUT/sensors.json``: ``{"sensors": [...], "eval_sensor": <first camera>}``, the
sensor the targets files are for). BOP's own industrial datasets (IPD, XYZ-IBD, ITODD-MV) are
read in that layout too: ``rgb_<sensor>/`` or ``gray_<sensor>/``, ``depth_<sensor>/``,
``scene_*_<sensor>.json``, ``camera_<sensor>.json``. Each of our scenes is one BOP scene with one image (im_id 0), in
sorted order. Poses are ``cam_R_m2c``/``cam_t_m2c`` (mm) in each camera's own frame;
``cam_R_w2c``/``cam_t_w2c`` give the camera in the rig's reference frame. Object ids follow
dataset.yaml's order from 1. Symmetries: :func:`annotator.symmetry.classes.symmetry_to_bop`.

Ground truth: ``<split>/<scene>/scene_gt[_<sensor>].json`` and ``scene_gt_info`` (occlusion =
1 - visib_fract), ``models/models_info.json`` and ``models/obj_XXXXXX.ply``; scenes are keyed
``<scene_id>/<im_id>`` and objects ``obj_XXXXXX``; a multi-sensor dataset is evaluated on the
sensor :func:`evaluated_sensor` picks (BOP's own for IPD, XYZ-IBD and ITODD-MV).

Results: BOP's CSV ``scene_id,im_id,obj_id,score,R,t,time`` (R row-major, t in mm).
"""

from __future__ import annotations

import csv
import io
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from annotator.errors import UserError
from annotator.formats.base import (
    GroundTruth,
    PoseResults,
    PoseSet,
    Table,
    checked_pose,
    checked_poses,
    checked_score,
    projected_note,
)
from annotator.geometry.transforms import is_rotation
from annotator.io.documents import read_json

if TYPE_CHECKING:
    pass

NAME = "bop"


def detect(path: Path) -> bool:
    return (path / "models" / "models_info.json").is_file()


# ------------------------------------------------------------------------- ground truth


def read_ground_truth(path: Path, *, symmetry: str | None = None) -> GroundTruth:
    notes: list[str] = []
    spaces, names = _read_models(path, notes)
    table: Table = {}
    scenes: list[str] = []
    counts = [0, 0]  # poses whose R had to be projected onto a rotation, poses
    for scene_dir in sorted({p.parent for p in path.glob("*/*/scene_gt*.json")}):
        scenes += _read_scene_gt(scene_dir, names, table, counts)
    notes += projected_note(counts[0], counts[1], "the ground truth")
    targets = read_targets(path, names)
    if targets is not None:
        source, pairs = targets
        images = {scene for scene, _ in pairs}
        scenes = [s for s in scenes if s in images]
        notes.append(
            f"targets from {source}: {len(images)} images, {len(pairs)} (image, object) pairs "
            "to score; the dataset's other poses and any results for them are not scored"
        )
        return GroundTruth(spaces, table, scenes, NAME, "mm", names, notes=notes, targets=pairs)
    return GroundTruth(spaces, table, scenes, NAME, "mm", names, notes=notes)


def _read_models(path: Path, notes: list[str]) -> tuple[dict[str, Any], dict[int, str]]:
    """Each object's pose space (from its mesh and models_info.json's symmetries) and name;
    symmetries snapped or off the centre are said in ``notes``."""
    from annotator.geometry.mesh import load_mesh
    from annotator.symmetry import PoseSpace
    from annotator.symmetry.classes import symmetry_from_bop

    info_path = path / "models" / "models_info.json"
    info = read_json(info_path)
    if not isinstance(info, dict):
        raise UserError("expected an object {obj_id: {...}}", path=info_path)
    spaces, names = {}, {}
    for key, entry in info.items():
        oid = int(key)
        name = f"obj_{oid:06d}"
        names[oid] = name
        snapped: list[str] = []
        try:
            sym = symmetry_from_bop(entry, snapped=snapped)
        except ValueError as exc:
            raise UserError(f"object {key}: {exc}", path=info_path) from None
        notes += [f"{info_path}: object {key}: {line}" for line in snapped]
        mesh = load_mesh(path / "models" / f"{name}.ply")
        spaces[name] = PoseSpace.from_moments(mesh.moments, sym)
        notes += [
            f"{info_path}: object {key}: {line}"
            for line in off_centre(entry, mesh.moments.centroid, float(spaces[name].diameter))
        ]
    return spaces, names


def _read_scene_gt(
    scene_dir: Path, names: dict[int, str], table: Table, counts: list[int]
) -> list[str]:
    """Add a scene folder's poses to ``table`` (``counts``: poses projected, poses); returns
    its images' keys."""
    sfx = evaluated_sensor(scene_dir)
    gt_path = scene_dir / f"scene_gt{sfx}.json"
    gt = read_json(gt_path)
    gi_path = scene_dir / f"scene_gt_info{sfx}.json"
    gi = read_json(gi_path) if gi_path.exists() else {}
    keys = []
    for im_id, insts in gt.items():
        key = f"{int(scene_dir.name)}/{int(im_id)}"
        keys.append(key)
        infos = gi.get(im_id, [])
        for k, inst in enumerate(insts):
            oid = _object_id(inst.get("obj_id"))
            name = None if oid is None else names.get(oid)
            if name is None:
                raise UserError(
                    f"image {im_id}, entry {k}: object {inst.get('obj_id')!r} is not in "
                    "models/models_info.json",
                    path=gt_path,
                )
            vf = infos[k].get("visib_fract") if k < len(infos) else None
            R, t = checked_pose(
                inst.get("cam_R_m2c"), inst.get("cam_t_m2c"), f"image {im_id}, entry {k}", gt_path
            )
            counts[1] += 1
            counts[0] += not is_rotation(
                np.asarray(inst["cam_R_m2c"], float).reshape(3, 3), tol=1e-3
            )
            table.setdefault((key, name), PoseSet()).add(
                R, t, 1.0 - float(vf) if vf is not None else float("nan")
            )
    return keys


def _object_id(value: Any) -> int | None:
    """A scene_gt entry's obj_id as an int (None if it is not a whole number)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        return None
    try:
        number = float(value)
    except ValueError:
        return None
    return int(number) if number.is_integer() else None


#: A listed symmetry whose axis misses the surface centroid by more than this fraction of the
#: diameter is said in the header (the paper's distance takes every axis through the centroid,
#: where a rigid part's symmetry axes must pass).
OFF_CENTRE_FRACTION = 0.01


def off_centre(entry: dict[str, Any], centroid: np.ndarray, diameter: float) -> list[str]:
    """Header lines for the symmetries of a models_info.json entry whose axis (continuous:
    through ``offset``; discrete: the points ``R x + t`` leaves in place) passes farther than
    :data:`OFF_CENTRE_FRACTION` of the diameter from the surface centroid."""
    lines = []
    for k, c in enumerate(entry.get("symmetries_continuous") or []):
        axis = np.asarray(c.get("axis"), float)
        axis = axis / np.linalg.norm(axis)
        d = np.asarray(c.get("offset", [0, 0, 0]), float) - centroid
        miss = float(np.linalg.norm(d - (d @ axis) * axis))
        if miss > OFF_CENTRE_FRACTION * diameter:
            lines.append(
                f"symmetries_continuous[{k}]: its axis (through offset) passes {miss:.2f} mm "
                "from the surface centroid; taken through the centroid"
            )
    for k, m in enumerate(entry.get("symmetries_discrete") or []):
        M = np.asarray(m, float).reshape(4, 4)
        miss = float(np.linalg.norm(M[:3, :3] @ centroid + M[:3, 3] - centroid))
        if miss > OFF_CENTRE_FRACTION * diameter:
            lines.append(
                f"symmetries_discrete[{k}] moves the surface centroid by {miss:.2f} mm; taken "
                "as the same rotation about the centroid"
            )
    return lines


#: The sensor BOP evaluates its industrial multi-sensor datasets on (bop_toolkit's
#: ``dataset_params.py``: ``eval_sensor``), by the dataset folder's name.
EVAL_SENSORS = {"ipd": "photoneo", "xyzibd": "xyz", "itoddmv": "3dlong"}


def evaluated_sensor(scene_dir: Path) -> str:
    """The file suffix of the sensor a scene is evaluated on: ``""`` for the classic
    single-sensor layout; else BOP's own choice for its industrial datasets
    (:data:`EVAL_SENSORS`, by the dataset folder's name), the ``eval_sensor`` of the
    dataset's ``sensors.json`` (written by ``export --sensors``), or the first sensor by name
    (``_<sensor>``)."""
    sensors = sorted(
        p.name[len("scene_gt") : -len(".json")]
        for p in scene_dir.glob("scene_gt*.json")
        if not p.name.startswith(("scene_gt_info", "scene_gt_coco"))
    )
    if "" in sensors or not sensors:
        return ""
    root = scene_dir.resolve().parent.parent
    chosen = EVAL_SENSORS.get(root.name)
    listed = root / "sensors.json"
    if chosen is None and listed.is_file():
        doc = read_json(listed)
        chosen = doc.get("eval_sensor") if isinstance(doc, dict) else None
        if not isinstance(chosen, str) or f"_{chosen}" not in sensors:
            have = ", ".join(s.lstrip("_") for s in sensors)
            raise UserError(
                f"eval_sensor must name a sensor the scenes have ({have}), got {chosen!r}",
                path=listed,
            )
    if isinstance(chosen, str) and f"_{chosen}" in sensors:
        return f"_{chosen}"
    return sensors[0]


#: BOP's lists of what is to be found, in the order they are looked for at the dataset's
#: root: the localisation task's (``{scene_id, im_id, obj_id, inst_count}``), the
#: detection task's (``{scene_id, im_id}``: every object of the image) and, last, the 2025
#: multi-view one's (:data:`MULTIVIEW_TARGETS`).
TARGET_FILES = ("test_targets_bop19.json", "test_targets_bop24.json")

#: BOP 2025's multi-view targets of its multi-sensor datasets: one entry per moment,
#: ``{"scene_id": s, "im_id": [[sensor, im_id], ...]}``, the images every sensor took then
#: (what a multi-view method is given together; the evaluated sensor's image is scored).
MULTIVIEW_TARGETS = "test_targets_multiview_bop25.json"


def read_multiview_targets(path: Path) -> list[tuple[int, dict[str, int]]] | None:
    """The entries of a dataset's :data:`MULTIVIEW_TARGETS`, each ``(scene_id, {sensor:
    im_id})`` in the file's order; None without the file.

    Raises:
        UserError: naming the file and the entry, for an entry not of BOP's layout.
    """
    file = path / MULTIVIEW_TARGETS
    if not file.is_file():
        return None
    doc = non_empty(read_json(file), file, '{"scene_id", "im_id": [[sensor, im_id], ...]}')
    out = []
    for i, entry in enumerate(doc):
        try:
            (scene_id,) = target_ids(entry, ("scene_id",), i, file)
            views = {
                str(sensor): target_ids({"im_id": im}, ("im_id",), i, file)[0]
                for sensor, im in entry["im_id"]
            }
            out.append((scene_id, views))
        except (KeyError, TypeError, ValueError):
            raise UserError(
                f"entry {i}: needs an integer scene_id and im_id as [[sensor, im_id], ...]",
                path=file,
            ) from None
        if not views:
            raise UserError(f"entry {i}: im_id lists no sensor's image", path=file)
    return out


def multiview_images(
    targets: list[tuple[int, dict[str, int]]], sensor: str
) -> list[tuple[int, int]]:
    """``(scene_id, im_id)`` of the images of ``sensor`` (its file suffix without the ``_``;
    ``""`` or a sensor an entry lacks: the entry's first) the multi-view targets list.

    >>> multiview_images([(0, {"photoneo": 3, "cam1": 3}), (0, {"cam1": 4})], "photoneo")
    [(0, 3), (0, 4)]
    """
    return [(s, views.get(sensor, next(iter(views.values())))) for s, views in targets]


def multiview_target_images(path: Path) -> list[tuple[int, int]] | None:
    """``(scene_id, im_id)`` of the images a BOP dataset's multi-view targets score: each
    moment's image of the sensor evaluated (:func:`evaluated_sensor`), in the file's order;
    None without the file."""
    targets = read_multiview_targets(path)
    if targets is None:
        return None
    scene_dirs = sorted((path / "test").glob("*/")) if (path / "test").is_dir() else []
    sensor = evaluated_sensor(scene_dirs[0]).lstrip("_") if scene_dirs else ""
    return multiview_images(targets, sensor)


def target_ids(entry: Any, keys: tuple[str, ...], i: int, file: Path) -> tuple[int, ...]:
    """The integers ``keys`` of a targets file's entry ``i``, each a whole number of 0 or
    more (not a string, a fraction or a boolean), or a one-line UserError naming the entry.

    >>> target_ids({"scene_id": 1, "im_id": 4}, ("scene_id", "im_id"), 0, Path("t.json"))
    (1, 4)
    """
    values = []
    for key in keys:
        v = entry.get(key) if isinstance(entry, dict) else None
        if type(v) is not int or v < 0:
            raise UserError(
                f"entry {i}: {key} must be a whole number of 0 or more, got {v!r}", path=file
            )
        values.append(v)
    return tuple(values)


def non_empty(doc: Any, file: Path, entries: str) -> list[Any]:
    """A targets file's list, refused in one line when it is not a list or lists nothing
    (an empty targets file would score nothing, and say 0)."""
    if not isinstance(doc, list):
        raise UserError(f"expected a list of {entries}", path=file)
    if not doc:
        raise UserError("lists no target: nothing would be scored", path=file)
    return doc


def read_targets(path: Path, names: dict[int, str]) -> tuple[str, set[tuple[str, str]]] | None:
    """The (scene key, object name) pairs a BOP dataset's targets file lists, with the
    file's name; None without one. Object ids it names that the models do not have are a
    one-line error."""
    for name in TARGET_FILES:
        file = path / name
        if not file.is_file():
            continue
        doc = non_empty(read_json(file), file, "{scene_id, im_id[, obj_id, inst_count]}")
        pairs: set[tuple[str, str]] = set()
        for i, entry in enumerate(doc):
            scene_id, im_id = target_ids(entry, ("scene_id", "im_id"), i, file)
            key = f"{scene_id}/{im_id}"
            oid = (
                None if entry.get("obj_id") is None else target_ids(entry, ("obj_id",), i, file)[0]
            )
            if oid is None:
                pairs |= {(key, n) for n in names.values()}
            elif oid in names:
                pairs.add((key, names[oid]))
            else:
                raise UserError(f"entry {i}: object {oid} is not in models_info.json", path=file)
        return name, pairs
    images = multiview_target_images(path)
    if images is None:
        return None
    return MULTIVIEW_TARGETS, {(f"{s}/{im}", n) for s, im in images for n in names.values()}


# ------------------------------------------------------------------------------ results


def read_results(path: Path, gt: GroundTruth) -> PoseResults:
    if path.is_dir():
        raise UserError("BOP results are a CSV file, not a folder", path=path)
    return read_csv_results(path, gt, scene_key=lambda sid, im: f"{int(sid)}/{im}")


#: BOP's result columns, in their order when the file has no header.
CSV_COLUMNS = ("scene_id", "im_id", "obj_id", "score", "R", "t", "time")


def read_csv_results(
    path: Path, gt: GroundTruth, *, scene_key: Callable[[str, int], str]
) -> PoseResults:
    """BOP's CSV: one result per line, ``scene_id,im_id,obj_id,score,R,t,time``; the
    header line is optional and may put the columns in any order (``time`` may be left
    out); a UTF-8 byte-order mark is allowed; ``obj_id`` is a number (or, for our datasets,
    a name).

    A file of numbers only is parsed in one go by numpy, so that a million lines take
    seconds; any other file, or one that numpy cannot take, is read cell by cell, which
    names the first bad line as :func:`checked_pose` and :func:`checked_score` do.
    """
    rows, numbers, objects, R, t, projected = read_csv_rows(path, gt)
    keys: dict[tuple[str, int], str] = {}
    groups: dict[tuple[str, str], list[int]] = {}
    known = set(gt.scenes)
    unknown: list[str] = []
    for i, (sid, im, obj) in enumerate(zip(rows.scene_ids, rows.im_ids.tolist(), objects)):
        key = keys.get((sid, im))
        if key is None:
            try:
                key = keys[(sid, im)] = scene_key(sid, im)
            except ValueError:
                raise UserError(
                    f"line {numbers[i]}: malformed scene_id {sid!r}", path=path
                ) from None
            if key not in known and key not in unknown:
                unknown.append(key)
        if key in known:
            groups.setdefault((key, obj), []).append(i)
    table: Table = {g: PoseSet.of(R[i], t[i], rows.scores[i]) for g, i in groups.items()}
    notes = projected_note(projected, len(R), path.name)
    negative = int((rows.scores < 0).sum())
    if negative:
        notes.append(
            f"{negative} results of {path.name} have a negative score (ranked as written: "
            "BOP sets no range, but a detector's confidence rarely goes below 0)"
        )
    return PoseResults(table, unknown, notes=notes)


def read_csv_rows(
    path: Path, gt: GroundTruth
) -> tuple[CsvRows, list[int], list[str], np.ndarray, np.ndarray, int]:
    """A results CSV's rows as written, checked: the rows, their line numbers, object names,
    rotations (near-rotations projected), translations and how many were projected (see
    :func:`read_csv_results`)."""
    if not path.is_file():
        raise UserError("results file or folder is missing", path=path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read ({exc})", path=path) from None
    lines = text.splitlines()
    numbers = [n for n, line in enumerate(lines, 1) if line.strip()]
    index = dict(zip(CSV_COLUMNS[:6], range(6)))
    header: list[str] | None = None
    if numbers:
        first = next(csv.reader([lines[numbers[0] - 1]]))
        if any(c.strip().lower() == "scene_id" for c in first):
            header = [c.strip() for c in first]
            index = _header(header, path)
            numbers = numbers[1:]
    rows = _numeric_rows(lines, numbers, header)
    try:
        if rows is None:
            rows = _cell_rows(lines, numbers, index, path)
        objects, R, t, projected = _checked(rows, numbers, gt, path)
    except UserError:
        if rows is None or rows.score_cells is not None:
            raise
        # Read in one go, a line's numbers may have shifted from R into t: cell by cell, the
        # line is named with what is really wrong with it.
        rows = _cell_rows(lines, numbers, index, path)
        objects, R, t, projected = _checked(rows, numbers, gt, path)
    return rows, numbers, objects, R, t, projected


def _checked(
    rows: CsvRows, numbers: list[int], gt: GroundTruth, path: Path
) -> tuple[list[str], np.ndarray, np.ndarray, int]:
    """The rows' object names and poses, checked (the first bad line is named), and how
    many rotations were projected."""
    objects = _object_names(rows.objects, numbers, gt, path)
    bad = np.flatnonzero(~np.isfinite(rows.scores))
    if bad.size and rows.score_cells is not None:
        checked_score(rows.score_cells[bad[0]], f"line {numbers[bad[0]]}", path)
    if rows.times is not None:
        with np.errstate(invalid="ignore"):
            bad = np.flatnonzero(~np.isfinite(rows.times) | ((rows.times < 0) & (rows.times != -1)))
        if bad.size:
            raise UserError(
                f"line {numbers[bad[0]]}: time is {rows.times[bad[0]]:g}; it must be seconds "
                "(or -1 when unknown, as BOP writes it)",
                path=path,
            )
    R, t, projected = checked_poses(rows.R, rows.t, lambda i: f"line {numbers[i]}", path)
    return objects, R, t, projected


@dataclass
class CsvRows:
    """The columns of a results CSV, one entry per data line."""

    scene_ids: Sequence[str]
    im_ids: np.ndarray
    objects: Sequence[str]
    scores: np.ndarray
    R: Any  # (N, 9) numbers, or one list per line (its length checked with the pose)
    t: Any
    score_cells: Sequence[str] | None = None  # as written, to name a bad one
    times: np.ndarray | None = None  # the time column (s), None without one


#: How many numbers each column holds.
_WIDTHS = {"R": 9, "t": 3}


def _numeric_rows(lines: list[str], numbers: list[int], header: list[str] | None) -> CsvRows | None:
    """The rows of a file made of numbers only, parsed by numpy; None if it is not one (the
    cell-by-cell reader then reads it and names what is wrong)."""
    names = header or list(CSV_COLUMNS)
    if any(n not in CSV_COLUMNS for n in names) or not numbers:
        return None
    offsets, width = {}, 0
    for name in names:
        offsets[name] = width
        width += _WIDTHS.get(name, 1)
    body = "\n".join(lines[n - 1] for n in numbers).replace(",", " ")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            table = np.loadtxt(io.StringIO(body), dtype=np.float64, ndmin=2)
    except (ValueError, Warning):
        return None
    # Every line must also have its commas where the header says (R and t of 9 and 3 numbers).
    if table.shape != (len(numbers), width) or any(
        lines[n - 1].count(",") != len(names) - 1 for n in numbers
    ):
        return None

    def col(name: str, k: int = 1) -> np.ndarray:
        return table[:, offsets[name] : offsets[name] + k]

    ids = np.concatenate([col("scene_id"), col("im_id"), col("obj_id")], axis=1)
    if not np.all(np.isfinite(ids) & (ids == np.round(ids)) & (ids >= 0)):
        return None
    if not np.all(np.isfinite(col("score"))):
        return None  # named with the cell's own text
    ids = ids.astype(np.int64)
    return CsvRows(
        scene_ids=_as_text(ids[:, 0]),
        im_ids=ids[:, 1],
        objects=_as_text(ids[:, 2]),
        scores=col("score")[:, 0].copy(),
        R=col("R", 9),
        t=col("t", 3),
        times=col("time")[:, 0].copy() if "time" in names else None,
    )


def _as_text(values: np.ndarray) -> Sequence[str]:
    """Integers as their decimal text (each distinct value converted once)."""
    unique, inverse = np.unique(values, return_inverse=True)
    return np.array([str(v) for v in unique], dtype=object)[inverse.reshape(-1)].tolist()


def _cell_rows(lines: list[str], numbers: list[int], index: dict[str, int], path: Path) -> CsvRows:
    """The rows read cell by cell; the first bad line is named."""
    table = list(csv.reader(lines[n - 1] for n in numbers))
    width = max(index[c] for c in CSV_COLUMNS[:6]) + 1
    for n, row in zip(numbers, table):
        if len(row) < width:
            raise UserError(f"line {n}: expected {','.join(CSV_COLUMNS)}", path=path)

    def column(name: str) -> list[str]:
        i = index[name]
        return [row[i].strip() for row in table]

    scores = column("score")
    times = None
    at = index.get("time", width)
    if all(len(row) > at for row in table):
        try:
            times = np.array([float(row[at]) for row in table])
        except ValueError:
            times = None  # not needed to score: BOP then reports no time
    return CsvRows(
        scene_ids=column("scene_id"),
        im_ids=_parsed(column("im_id"), numbers, path, int, "malformed number"),
        objects=column("obj_id"),
        scores=_parsed(scores, numbers, path, float, None),
        R=_vectors(column("R"), numbers, path),
        t=_vectors(column("t"), numbers, path),
        score_cells=scores,
        times=times,
    )


def _header(names: list[str], path: Path) -> dict[str, int]:
    """Column name -> position, from a header line in any order."""
    missing = [c for c in CSV_COLUMNS[:6] if c not in names]
    if missing:
        raise UserError(
            f"line 1: the header lacks {', '.join(missing)} (columns: {','.join(CSV_COLUMNS)})",
            path=path,
        )
    return {c: names.index(c) for c in CSV_COLUMNS if c in names}


def _parsed(
    cells: list[str], numbers: list[int], path: Path, kind: type, message: str | None
) -> np.ndarray:
    """``cells`` as an int or float array; the first cell that is not one is named (with
    ``message``, or as :func:`checked_score` names a score)."""
    try:
        return np.array([kind(c) for c in cells], dtype=np.int64 if kind is int else np.float64)
    except (ValueError, OverflowError):
        for n, c in zip(numbers, cells):
            try:
                kind(c)
            except (ValueError, OverflowError):
                if message is None:
                    checked_score(c, f"line {n}", path)
                raise UserError(f"line {n}: {message}", path=path) from None
        raise


def _vectors(cells: list[str], numbers: list[int], path: Path) -> list[list[float]]:
    """Space-separated numbers per cell (their count is checked with the pose)."""
    try:
        return [[float(v) for v in c.split()] for c in cells]
    except ValueError:
        for n, c in zip(numbers, cells):
            try:
                [float(v) for v in c.split()]
            except ValueError:
                raise UserError(f"line {n}: malformed number", path=path) from None
        raise


def _object_names(
    cells: Sequence[str], numbers: list[int], gt: GroundTruth, path: Path
) -> list[str]:
    """Object names for ``obj_id`` cells (numbers through ``gt.object_ids``, or names)."""
    names: dict[str, str] = {}
    out = []
    for n, cell in zip(numbers, cells):
        name = names.get(cell)
        if name is None:
            name = cell
            if cell.isdigit():
                name = gt.object_ids.get(int(cell), f"obj_{int(cell):06d}")
            if name not in gt.spaces:
                raise UserError(f"line {n}: result for unknown object {cell!r}", path=path)
            names[cell] = name
        out.append(name)
    return out
