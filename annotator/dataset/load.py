"""Reading ``dataset.yaml`` and ``objects/*/object.yaml`` (FORMAT.md), collecting problems.

:func:`read_dataset` parses as much as it can and returns every problem it found, each
naming its file; ``annotator check`` reports them all. :func:`load_dataset` is what commands
use: it raises a one-line :class:`~annotator.errors.UserError` if anything is wrong.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset.materials import parse_material
from annotator.dataset.model import (
    FLIP_HORIZONTAL,
    FORMAT_VERSION,
    SCENES_DIR,
    Dataset,
    DepthSpec,
    Instance,
    MarkerSites,
    ObjectModel,
    Rig,
    Symmetry,
)
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import is_rotation
from annotator.io.atomic import finish_interrupted
from annotator.io.documents import read_yaml
from annotator.symmetry.classes import symmetry_from_yaml


@dataclass(frozen=True)
class Problem:
    """One problem in a dataset: the file it is in and what is wrong.

    >>> from pathlib import Path
    >>> print(Problem(Path("ds/dataset.yaml"), "no rig section"))
    ds/dataset.yaml: no rig section
    """

    path: Path
    message: str
    warning: bool = False  # worth a look, but the dataset is usable as it is

    def __str__(self) -> str:
        return f"{self.path}: {'warning: ' if self.warning else ''}{self.message}"


def load_dataset(root: str | Path) -> Dataset:
    """Read a dataset; raise a one-line UserError on the first problem (see ``annotator check``).

    >>> ds = load_dataset("sample_scenes")
    >>> [c.name for c in ds.rig.cameras], [s.id for s in ds.scenes()]
    (['left', 'right'], ['000000', '000001', '000002', '000003'])
    """
    dataset, problems = read_dataset(root)
    if problems:
        more = (
            f" (and {len(problems) - 1} more problems: run `annotator check {root}`)"
            if len(problems) > 1
            else ""
        )
        raise UserError(problems[0].message + more, path=problems[0].path)
    assert dataset is not None
    return dataset


def as_dataset(ds: Dataset | str | Path, *, name: str = "ds") -> Dataset:
    """``ds`` itself, or the dataset at that folder (:func:`load_dataset`): what the API's
    functions take; a TypeError naming ``name`` for anything else."""
    if isinstance(ds, Dataset):
        return ds
    if isinstance(ds, (str, Path)):
        return load_dataset(ds)
    raise TypeError(
        f"{name} must be a Dataset (annotator.load_dataset) or a dataset folder, not "
        f"{type(ds).__name__}"
    )


def require_meshes(ds: Dataset) -> None:
    """Load every object's mesh now; a missing, unreadable or empty mesh is a dataset error
    (one UserError naming the file) before any scene is worked on, not one per scene."""
    for obj in ds.objects.values():
        obj.mesh  # noqa: B018  (cached property: loads and checks the file)


_LOADED: dict[Path, tuple[tuple[int, ...], Dataset]] = {}


def cached_dataset(root: str | Path) -> Dataset:
    """:func:`load_dataset`, loaded once per process while its description is unchanged
    (dataset.yaml, the objects folder, every object.yaml and mesh): batch workers reuse one
    load, with its meshes and marker table, for every scene."""
    key = Path(root).resolve()
    hit = _LOADED.get(key)
    if hit is not None and hit[0] == _stamp(hit[1]):
        return hit[1]
    dataset = load_dataset(root)
    _LOADED[key] = (_stamp(dataset), dataset)
    return dataset


def _stamp(ds: Dataset) -> tuple[int, ...]:
    files = [ds.root / "dataset.yaml", ds.root / "objects"]
    for obj in ds.objects.values():
        files += [obj.folder / "object.yaml", obj.mesh_path]
    return tuple(p.stat().st_mtime_ns if p.exists() else -1 for p in files)


def read_dataset(root: str | Path) -> tuple[Dataset | None, list[Problem]]:
    """Parse a dataset folder, returning it (None if unusable) and every problem found."""
    root = Path(root)
    problems: list[Problem] = []
    yaml_path = root / "dataset.yaml"
    if not root.is_dir():
        return None, [Problem(root, "dataset folder does not exist")]
    try:  # object.yaml files a killed `annotator sites` was writing together: finished first
        finish_interrupted(root)
    except UserError as exc:
        return None, [Problem(exc.path or root, exc.message)]
    doc = _read_yaml(yaml_path, problems)
    if doc is None:
        return None, problems
    p = _Parser(yaml_path, problems)
    if doc.get("format", FORMAT_VERSION) != FORMAT_VERSION:
        p.problem(f"unsupported format {doc.get('format')!r} (this tool reads format 1)")
    dictionary = _parse_dictionary(
        p, str(p.get(doc, "markers", dict, {}).get("dictionary", "DICT_4X4_1000")), root
    )
    rig = _parse_rig(p, p.get(doc, "rig", dict, None))
    objects: dict[str, ObjectModel] = {}
    names = p.get(doc, "objects", list, [])
    for name in names:
        obj = _parse_object(root, str(name), problems)
        if obj is not None:
            objects[obj.name] = obj
    _check_marker_ids(objects, problems)
    _check_sites(objects, _dictionary_size(dictionary), dictionary, problems)
    scenes = root / SCENES_DIR
    if (scenes.exists() or scenes.is_symlink()) and not scenes.is_dir():
        problems.append(Problem(scenes, "is not a folder (scenes/<scene_id>/ hold the scenes)"))
    if rig is None:
        return None, problems
    ds = Dataset(
        root=root,
        name=str(doc.get("name", root.name)),
        dictionary=dictionary,
        rig=rig,
        objects=objects,
        raw=doc,
    )
    return ds, problems


class _Parser:
    """Field access that records problems against one file instead of raising."""

    def __init__(self, path: Path, problems: list[Problem]) -> None:
        self.path = path
        self.problems = problems

    def problem(self, message: str) -> None:
        self.problems.append(Problem(self.path, message))

    def get(self, d: Any, key: str, typ: type, default: Any) -> Any:
        if not isinstance(d, dict) or key not in d:
            if default is None:
                self.problem(f"missing field '{key}'")
            return default
        value = d[key]
        if not isinstance(value, typ):
            self.problem(f"field '{key}' must be a {typ.__name__}, got {type(value).__name__}")
            return default
        return value

    def floats(self, value: Any, n: int | tuple[int, ...], what: str) -> np.ndarray | None:
        if value is None:
            self.problem(f"{what} is missing")
            return None
        try:
            if not _all_numbers(value):  # numpy would read "12.5" and True as numbers
                raise TypeError
            arr = np.asarray(value, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            self.problem(f"{what} must be a list of numbers (a number is written without quotes)")
            return None
        allowed = (n,) if isinstance(n, int) else n
        if arr.size not in allowed or not np.all(np.isfinite(arr)):
            want = " or ".join(str(a) for a in allowed)
            self.problem(f"{what} must have {want} finite numbers, got {arr.size}")
            return None
        return arr


def _all_numbers(value: Any) -> bool:
    """Whether ``value`` is a number or (nested) lists of numbers; not text, not booleans."""
    if isinstance(value, (list, tuple)):
        return all(_all_numbers(v) for v in value)
    if isinstance(value, np.ndarray):
        return value.dtype.kind in "iuf"
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_)
    )


#: How far a marker site may be from a square of the markers' printed side (relative).
SIZE_TOLERANCE = 0.02


def site_shape_problem(corners: np.ndarray, size: float) -> str | None:
    """Why a site's four corners (4x3, mm) are not a square of side ``size``, or None."""
    sides = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
    diag = np.linalg.norm(corners[2] - corners[0]), np.linalg.norm(corners[3] - corners[1])
    if np.any(np.abs(sides - size) > SIZE_TOLERANCE * size) or abs(diag[0] - diag[1]) > (
        SIZE_TOLERANCE * size
    ):
        return f"is not a square of side {size:g} mm (sides {np.round(sides, 2).tolist()})"
    return None


def _check_sites(
    objects: dict[str, ObjectModel], n_dict: int | None, dictionary: str, problems: list[Problem]
) -> None:
    """Every site (the layout's and the instances' own) is a square of the printed side,
    and every marker id lies in the dictionary: what every command relies on."""
    for obj in objects.values():
        path = obj.folder / "object.yaml"
        for inst in obj.instances:
            bad = [i for i in inst.marker_ids if n_dict is not None and i >= n_dict]
            if bad:
                problems.append(
                    Problem(
                        path,
                        f"instance {inst.name!r}: marker ids {bad} are outside {dictionary} "
                        f"(0..{n_dict - 1 if n_dict else 0})",
                    )
                )
        if obj.markers is None:
            continue
        sites = [(f"markers.sites[{k}]", c) for k, c in enumerate(obj.markers.corners)]
        for inst in obj.instances:
            if inst.sites is not None:
                sites += [
                    (f"instance {inst.name!r}: sites[{k}]", c) for k, c in enumerate(inst.sites)
                ]
        for where, c in sites:
            why = site_shape_problem(c, obj.markers.size)
            if why is not None:
                problems.append(Problem(path, f"{where} {why}"))


def _read_yaml(path: Path, problems: list[Problem]) -> dict[str, Any] | None:
    if not path.is_file():
        problems.append(Problem(path, "file is missing"))
        return None
    try:
        doc = read_yaml(path)
    except UserError as exc:
        problems.append(Problem(path, exc.message))
        return None
    if not isinstance(doc, dict):
        problems.append(Problem(path, "must be a YAML mapping"))
        return None
    return doc


def outside(root: Path, path: Path) -> bool:
    """True if ``path`` leads out of the folder ``root`` (an absolute path elsewhere, ``..``,
    or a symbolic link on the way whose target is elsewhere)."""
    real_root = os.path.realpath(root)
    real = os.path.realpath(path)
    return os.path.commonpath([real_root, real]) != real_root


def _parse_dictionary(p: _Parser, name: str, root: Path) -> str:
    """The markers' dictionary: a predefined name, or a dictionary file (relative to the
    dataset folder) made absolute so that every reader opens the same file."""
    from annotator.markers.dictionary import dictionary, resolve_dictionary

    resolved = resolve_dictionary(name, root)
    try:
        dictionary(resolved)
    except UserError as exc:
        where = f" ({exc.path})" if exc.path is not None else ""
        p.problem(f"markers.dictionary: {exc.message}{where}")
    return resolved


def _dictionary_size(resolved: str) -> int | None:
    """How many markers the dictionary has (None if it is unusable: reported already)."""
    from annotator.markers.dictionary import dictionary_size

    try:
        return dictionary_size(resolved)
    except UserError:
        return None


@dataclass(frozen=True)
class _RigCameras:
    """The rig's cameras that parsed, the mirrored ones, and the names of those with a
    problem (each reported once: a depth section naming one adds no knock-on line)."""

    cameras: list[Camera]
    flipped: set[str]
    broken: list[str]


def _parse_rig(p: _Parser, rig: dict[str, Any] | None) -> Rig | None:
    if rig is None:
        return None
    cams_doc = p.get(rig, "cameras", list, None)
    if not cams_doc:
        if cams_doc is not None:
            p.problem("rig.cameras is empty")
        return None
    parsed = _parse_cameras(p, cams_doc)
    depth = None
    if "depth" in rig and rig["depth"] is not None:
        depth = _parse_depth(p, rig["depth"], parsed)
    moving = rig.get("moving", False)
    if not isinstance(moving, bool):
        p.problem(
            f"rig.moving must be true (a moving rig: scenes are sequences) or false, got {moving!r}"
        )
        moving = False
    if not parsed.cameras:
        return None
    return Rig(
        cameras=tuple(parsed.cameras),
        depth=depth,
        flipped=frozenset(parsed.flipped),
        moving=moving,
    )


def _parse_cameras(p: _Parser, cams_doc: list[Any]) -> _RigCameras:
    """``rig.cameras``: each entry's fields, the first one the reference frame, unique
    names, an optional horizontal flip."""
    out = _RigCameras([], set(), [])
    for i, c in enumerate(cams_doc):
        where = f"rig.cameras[{i}]"
        if not isinstance(c, dict):
            p.problem(f"{where} must be a mapping")
            continue
        name = str(c.get("name", ""))
        if not name:
            p.problem(f"{where}.name is missing")
            continue
        camera = _parse_camera(p, c, name, where)
        if camera is None:
            out.broken.append(name)
            continue
        if i == 0 and not np.allclose(camera.rig_T_cam, np.eye(4), atol=1e-9):
            p.problem(
                f"{where}.rig_T_cam must be the identity: the first camera is the reference frame"
            )
        if any(cam.name == name for cam in out.cameras):
            p.problem(f"{where}: duplicate camera name {name!r}")
            continue
        flip = c.get("flip")
        if flip not in (None, "none", FLIP_HORIZONTAL):
            p.problem(
                f"{where}.flip must be {FLIP_HORIZONTAL!r} (a mirrored camera) or absent, got "
                f"{flip!r}"
            )
        elif flip == FLIP_HORIZONTAL:
            out.flipped.add(name)
        out.cameras.append(camera)
    return out


def _parse_camera(p: _Parser, c: dict[str, Any], name: str, where: str) -> Camera | None:
    """One camera's size, K, dist and rig_T_cam; None if any of them has a problem (every
    problem of the entry reported)."""
    size = p.floats(c.get("size"), 2, f"{where}.size")
    K = p.floats(c.get("K"), 9, f"{where}.K")
    dist = p.floats(c.get("dist", [0, 0, 0, 0, 0]), (4, 5, 8, 12, 14), f"{where}.dist")
    T = p.floats(c.get("rig_T_cam", np.eye(4).ravel().tolist()), 16, f"{where}.rig_T_cam")
    ok = size is not None and K is not None and dist is not None and T is not None
    if K is not None:
        K = K.reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[1, 0] != 0 or np.any(K[2] != [0, 0, 1]):
            p.problem(f"{where}.K is not a pinhole matrix [fx 0 cx 0 fy cy 0 0 1] with fx, fy > 0")
            ok = False
    if size is not None and (np.any(size <= 0) or np.any(size != np.round(size))):
        p.problem(f"{where}.size must be two positive integers")
        ok = False
    if T is not None:
        T = T.reshape(4, 4)
        if not is_rotation(T[:3, :3], tol=1e-5) or np.any(np.abs(T[3] - [0, 0, 0, 1]) > 1e-9):
            p.problem(
                f"{where}.rig_T_cam is not a rigid transform (rotation block not orthonormal or last row not 0 0 0 1)"
            )
            ok = False
    if not ok:
        return None
    assert size is not None and K is not None and dist is not None and T is not None  # ok
    return Camera(name=name, width=int(size[0]), height=int(size[1]), K=K, dist=dist, rig_T_cam=T)


def _parse_depth(p: _Parser, d: Any, parsed: _RigCameras) -> DepthSpec | None:
    """``rig.depth``: the camera whose pixel grid the depth maps use (default the first),
    their scale, an optional background file inside the dataset."""
    if not isinstance(d, dict):
        p.problem("rig.depth must be a mapping")
        return None
    cameras = parsed.cameras
    cam = str(d.get("camera", cameras[0].name if cameras else ""))
    scale = d.get("scale")
    if not isinstance(scale, (int, float)) or isinstance(scale, bool) or not 0 < scale < math.inf:
        p.problem("rig.depth.scale is missing or not a positive number (mm per depth unit)")
        return None
    if cam in parsed.broken:
        return None  # that camera's own problem is already reported: no knock-on line
    if cameras and cam not in [c.name for c in cameras]:
        p.problem(f"rig.depth.camera {cam!r} is not a rig camera")
        return None
    bg = d.get("background")
    if bg is not None and not isinstance(bg, str):
        p.problem("rig.depth.background must be a file name (the empty bin's depth)")
        bg = None
    elif bg is not None and outside(p.path.parent, p.path.parent / bg):
        p.problem(f"rig.depth.background {bg!r} lies outside the dataset")
        bg = None
    return DepthSpec(camera=cam, scale=float(scale), background=bg)


def _parse_object(root: Path, name: str, problems: list[Problem]) -> ObjectModel | None:
    folder = root / "objects" / name
    path = folder / "object.yaml"
    if outside(root / "objects", folder) or folder == root / "objects":
        problems.append(
            Problem(root / "dataset.yaml", f"object {name!r} is not a folder under objects/")
        )
        return None
    doc = _read_yaml(path, problems)
    if doc is None:
        return None
    p = _Parser(path, problems)
    mesh_path = _mesh_path(p, doc, root, folder)
    if mesh_path is None:
        return None
    symmetry = _parse_symmetry(p, doc.get("symmetry", {"class": "none"}))
    if doc.get("material") is not None:
        try:
            parse_material(doc["material"], path=path)
        except UserError as exc:
            # parse_material names the file itself; the problem is reported with its path.
            p.problem(exc.message.removeprefix(f"{path}: "))
    markers = None
    if "markers" in doc and doc["markers"] is not None:
        markers = _parse_markers(p, doc["markers"])
    n_sites = 0 if markers is None else markers.corners.shape[0]
    instances = _parse_instances(p, p.get(doc, "instances", list, []), n_sites)
    return ObjectModel(
        name=name,
        folder=folder,
        mesh_path=mesh_path,
        symmetry=symmetry,
        markers=markers,
        instances=tuple(instances),
        raw=doc,
    )


def _mesh_path(p: _Parser, doc: dict[str, Any], root: Path, folder: Path) -> Path | None:
    """The object's mesh file, relative to its folder and inside the dataset (None: no
    object; a missing file is reported but the object stays)."""
    mesh_name = p.get(doc, "mesh", str, None)
    if mesh_name is None:
        return None
    mesh_path = folder / mesh_name
    if outside(root, mesh_path):
        p.problem(
            f"mesh {mesh_name!r} lies outside the dataset; give a path relative to the "
            "object's folder that stays inside the dataset"
        )
        return None
    if not mesh_path.is_file():
        p.problem(f"mesh file {mesh_name!r} is missing")
    return mesh_path


def _parse_markers(p: _Parser, m: Any) -> MarkerSites | None:
    """``markers``: the printed side and the sites' corners (None if either is wrong)."""
    size = m.get("size") if isinstance(m, dict) else None
    if not isinstance(size, (int, float)) or not 0 < size < math.inf:
        p.problem("markers.size must be a positive number (mm)")
    sites = m.get("sites", []) if isinstance(m, dict) else []
    corners = p.floats(
        sites, len(sites) * 12 if isinstance(sites, list) and sites else 12, "markers.sites"
    )
    if corners is not None and isinstance(size, (int, float)) and 0 < size < math.inf:
        return MarkerSites(size=float(size), corners=corners.reshape(-1, 4, 3))
    return None


def _parse_instances(p: _Parser, docs: list[Any], n_sites: int) -> list[Instance]:
    """``instances``: each with a name, its marker ids (at most one per site, none twice)
    and optionally its own measured sites; names unique."""
    instances: list[Instance] = []
    for i, inst in enumerate(docs):
        if not isinstance(inst, dict) or "name" not in inst:
            p.problem(f"instances[{i}] must have a name")
            continue
        ids = inst.get("marker_ids", [])
        if not isinstance(ids, list) or not all(isinstance(x, int) and x >= 0 for x in ids):
            p.problem(f"instances[{i}].marker_ids must be a list of non-negative integers")
            continue
        if len(ids) > n_sites:
            p.problem(f"instance {inst['name']!r} has {len(ids)} marker ids for {n_sites} sites")
        if len(set(ids)) != len(ids):
            p.problem(f"instance {inst['name']!r} repeats a marker id")
        own = None
        if inst.get("sites") is not None:
            own = p.floats(inst["sites"], max(n_sites, 1) * 12, f"instances[{i}].sites")
            if own is not None:
                own = own.reshape(-1, 4, 3)
        counts = inst.get("site_scenes")
        if counts is not None and not (
            isinstance(counts, list)
            and len(counts) == n_sites
            and all(isinstance(x, int) and x >= 0 for x in counts)
        ):
            p.problem(
                f"instances[{i}].site_scenes must be {n_sites} non-negative integers, one per site"
            )
            counts = None
        instances.append(
            Instance(
                name=str(inst["name"]),
                marker_ids=tuple(ids),
                sites=own,
                site_scenes=None if counts is None else tuple(counts),
            )
        )
    if len({i.name for i in instances}) != len(instances):
        p.problem("duplicate instance names")
    return instances


def _parse_symmetry(p: _Parser, doc: Any) -> Symmetry:
    try:
        return symmetry_from_yaml(doc)
    except ValueError as exc:
        p.problem(str(exc))
        return Symmetry()


def _check_marker_ids(objects: dict[str, ObjectModel], problems: list[Problem]) -> None:
    seen: dict[int, str] = {}
    for obj in objects.values():
        for inst in obj.instances:
            for mid in inst.marker_ids:
                here = f"{obj.name}/{inst.name}"
                if mid in seen and seen[mid] != here:
                    problems.append(
                        Problem(
                            obj.folder / "object.yaml",
                            f"marker id {mid} of {here} is also used by {seen[mid]}",
                        )
                    )
                seen.setdefault(mid, here)
