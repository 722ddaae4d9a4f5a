"""Ground truth and results in the formats users have.

Ground truth (``read_ground_truth`` detects which):

- **our datasets** (FORMAT.md): ``scenes/<id>/gt.json``, or ``annotation.json`` when a scene has
  no gt.json; occlusion from the per-instance ``occlusion.rate`` (or ``occlusion_rate``);
- **BOP**: ``<split>/<scene>/scene_gt.json`` + ``scene_gt_info.json`` (occlusion =
  1 - visib_fract), ``models/models_info.json`` (symmetries) and ``models/obj_XXXXXX.ply``;
  scenes are keyed ``<scene_id>/<im_id>`` and objects ``obj_XXXXXX``;
- **Siléane** (the paper's format), one object folder: ``mesh.ply``, ``gt/<scene>.json`` lists of
  ``{R, t (metres), occlusion_rate}``; its symmetry from ``symmetry.yaml`` (written by our export)
  or ``--symmetry``.

Results: a BOP CSV (``scene_id,im_id,obj_id,score,R,t,time``, R row-major, t in mm; for our
datasets ``scene_id`` is the scene folder's number and ``im_id`` 0, ``obj_id`` the object's
position in dataset.yaml, from 1, or its name), or a folder of ``<scene>.json`` files, each a
list of ``{"object", "R", "t", "score"}`` (R 9 floats or 3x3, t mm).
Instances without a known occlusion rate are treated as of interest.
"""

from __future__ import annotations

import csv
import json
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from annotator.dataset import load_dataset, read_poses
from annotator.dataset.model import Symmetry
from annotator.errors import UserError
from annotator.geometry.mesh import load_mesh
from annotator.geometry.transforms import is_rotation, matrix_to_rotvec
from annotator.symmetry import PoseSpace


@dataclass
class PoseSet:
    """Poses of one object in one scene."""

    R: list[np.ndarray] = field(default_factory=list)
    t: list[np.ndarray] = field(default_factory=list)
    values: list[float] = field(default_factory=list)  # occlusion (GT) or score (results)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = len(self.R)
        return (
            np.asarray(self.R, float).reshape(n, 3, 3),
            np.asarray(self.t, float).reshape(n, 3),
            np.asarray(self.values, float).reshape(n),
        )


Table = dict[tuple[str, str], PoseSet]  # (scene key, object) -> poses


@dataclass
class GroundTruth:
    spaces: dict[str, PoseSpace]
    poses: Table
    scenes: list[str]
    kind: str
    object_ids: dict[int, str] = field(default_factory=dict)


def _occ(extra: dict) -> float:
    occ = extra.get("occlusion")
    if isinstance(occ, dict) and occ.get("rate") is not None:
        return float(occ["rate"])
    if extra.get("occlusion_rate") is not None:
        return float(extra["occlusion_rate"])
    return float("nan")


def read_ground_truth(path: str | Path, *, symmetry: str | None = None) -> GroundTruth:
    path = Path(path)
    if (path / "dataset.yaml").exists():
        return _read_ours(path)
    if (path / "models" / "models_info.json").exists():
        return _read_bop(path)
    if (path / "gt").is_dir():
        return _read_sileane(path, symmetry)
    raise UserError(
        "not a dataset: no dataset.yaml (ours), models/models_info.json (BOP) or gt/ (Siléane)",
        path=path,
    )


def _read_ours(root: Path) -> GroundTruth:
    ds = load_dataset(root)
    spaces = {n: PoseSpace.from_moments(o.mesh.moments, o.symmetry) for n, o in ds.objects.items()}
    table: Table = defaultdict(PoseSet)
    scenes = []
    for sc in ds.scenes():
        src = sc.gt_path if sc.gt_path.exists() else sc.annotation_path
        if not src.exists():
            continue
        scenes.append(sc.id)
        for p in read_poses(src):
            ps = table[(sc.id, p.object)]
            ps.R.append(p.R)
            ps.t.append(p.t)
            ps.values.append(_occ(p.extra))
    ids = {k + 1: n for k, n in enumerate(ds.objects)}
    return GroundTruth(spaces, dict(table), scenes, "ours", ids)


def _load_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError("file is missing", path=path) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"not valid JSON ({exc})", path=path) from None


def bop_symmetry(info: dict) -> Symmetry:
    """Our symmetry class from a BOP models_info.json entry."""
    cont = info.get("symmetries_continuous") or []
    disc = info.get("symmetries_discrete") or []
    if len(cont) >= 2:
        return Symmetry("spherical")
    if cont:
        axis = np.asarray(cont[0]["axis"], float)
        flip = any(np.asarray(s, float).reshape(4, 4)[:3, :3] @ axis @ axis < 0 for s in disc)
        return Symmetry(
            "revolution_flip" if flip else "revolution", axis=axis / np.linalg.norm(axis)
        )
    if disc:
        gens = []
        for s in disc:
            R = np.asarray(s, float).reshape(4, 4)[:3, :3]
            rv = matrix_to_rotvec(R)
            angle = np.linalg.norm(rv)
            if angle < 1e-6:
                continue
            gens.append((rv / angle, max(2, int(round(2 * np.pi / angle)))))
        return Symmetry("finite", tuple(gens)) if gens else Symmetry()
    return Symmetry()


def _read_bop(root: Path) -> GroundTruth:
    info = _load_json(root / "models" / "models_info.json")
    spaces, names = {}, {}
    for key, entry in info.items():
        oid = int(key)
        name = f"obj_{oid:06d}"
        names[oid] = name
        mesh = load_mesh(root / "models" / f"{name}.ply")
        spaces[name] = PoseSpace.from_moments(mesh.moments, bop_symmetry(entry))
    table: Table = defaultdict(PoseSet)
    scenes = []
    for scene_dir in sorted({p.parent for p in root.glob("*/*/scene_gt*.json")}):
        # Single-sensor scenes have scene_gt.json; multi-sensor ones scene_gt_<sensor>.json:
        # the first sensor (sorted by name) is evaluated.
        sensors = sorted(
            p.name[len("scene_gt") : -len(".json")]
            for p in scene_dir.glob("scene_gt*.json")
            if not p.name.startswith("scene_gt_info")
        )
        sfx = "" if "" in sensors else sensors[0]
        gt_path = scene_dir / f"scene_gt{sfx}.json"
        gt = _load_json(gt_path)
        gi_path = scene_dir / f"scene_gt_info{sfx}.json"
        gi = _load_json(gi_path) if gi_path.exists() else {}
        for im_id, insts in gt.items():
            key = f"{int(scene_dir.name)}/{int(im_id)}"
            scenes.append(key)
            infos = gi.get(im_id, [])
            for k, inst in enumerate(insts):
                name = names.get(int(inst["obj_id"]), f"obj_{int(inst['obj_id']):06d}")
                ps = table[(key, name)]
                ps.R.append(np.asarray(inst["cam_R_m2c"], float).reshape(3, 3))
                ps.t.append(np.asarray(inst["cam_t_m2c"], float).reshape(3))
                vf = infos[k].get("visib_fract") if k < len(infos) else None
                ps.values.append(1.0 - float(vf) if vf is not None else float("nan"))
    return GroundTruth(spaces, dict(table), scenes, "bop", names)


def _read_sileane(root: Path, symmetry: str | None) -> GroundTruth:
    mesh_path = next(
        (p for p in (root / "mesh.ply", root / "mesh.obj", root / "mesh.stl") if p.exists()),
        root / "mesh.ply",
    )
    mesh = load_mesh(mesh_path)
    sym = Symmetry()
    if (root / "symmetry.yaml").exists():
        doc = yaml.safe_load((root / "symmetry.yaml").read_text())
        kind = doc.get("class", "none")
        if kind == "finite":
            sym = Symmetry(
                kind,
                tuple((np.asarray(g["axis"], float), int(g["order"])) for g in doc["generators"]),
            )
        elif kind in ("revolution", "revolution_flip"):
            sym = Symmetry(kind, axis=np.asarray(doc.get("axis", [0, 0, 1]), float))
        else:
            sym = Symmetry(kind)
    elif symmetry:
        sym = Symmetry(
            symmetry, axis=np.array([0.0, 0.0, 1.0]) if "revolution" in symmetry else None
        )
    name = root.name
    table: Table = defaultdict(PoseSet)
    scenes = []
    for f in sorted((root / "gt").glob("*.json")):
        scenes.append(f.stem)
        for _k, inst in enumerate(_load_json(f)):
            ps = table[(f.stem, name)]
            ps.R.append(np.asarray(inst["R"], float).reshape(3, 3))
            ps.t.append(np.asarray(inst["t"], float).reshape(3) * 1000.0)
            ps.values.append(float(inst.get("occlusion_rate", float("nan"))))
    return GroundTruth(
        {name: PoseSpace.from_moments(mesh.moments, sym)}, dict(table), scenes, "sileane", {1: name}
    )


def _pose(R, t, where: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        Rm = np.asarray(R, float).reshape(3, 3)
        tv = np.asarray(t, float).reshape(3)
    except (TypeError, ValueError):
        raise UserError(f"{where}: R must have 9 numbers and t 3", path=path) from None
    if not is_rotation(Rm, tol=1e-3):
        raise UserError(f"{where}: R is not a rotation matrix", path=path)
    return Rm, tv


def read_results(path: str | Path, gt: GroundTruth) -> Table:
    """Results from a BOP CSV file or a folder of per-scene JSON lists (see module docstring)."""
    path = Path(path)
    table: Table = defaultdict(PoseSet)
    if path.is_dir():
        for f in sorted(path.glob("*.json")):
            doc = _load_json(f)
            if not isinstance(doc, list):
                raise UserError("expected a JSON list of {object, R, t, score}", path=f)
            for i, r in enumerate(doc):
                where = f"entry {i}"
                obj = str(r.get("object", next(iter(gt.spaces)) if len(gt.spaces) == 1 else ""))
                if obj not in gt.spaces:
                    raise UserError(f"{where}: unknown object {obj!r}", path=f)
                R, t = _pose(r.get("R"), r.get("t"), where, f)
                ps = table[(f.stem, obj)]
                ps.R.append(R)
                ps.t.append(t)
                ps.values.append(float(r.get("score", 1.0)))
        return dict(table)
    if not path.is_file():
        raise UserError("results file or folder is missing", path=path)
    with path.open(newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    start = 1 if rows and rows[0] and rows[0][0].strip() == "scene_id" else 0
    for n, row in enumerate(rows[start:], start=start + 1):
        if not row or not "".join(row).strip():
            continue
        where = f"line {n}"
        if len(row) < 6:
            raise UserError(f"{where}: expected scene_id,im_id,obj_id,score,R,t,time", path=path)
        try:
            scene_id, im_id, score = row[0].strip(), int(row[1]), float(row[3])
            R = [float(v) for v in row[4].split()]
            t = [float(v) for v in row[5].split()]
        except ValueError:
            raise UserError(f"{where}: malformed number", path=path) from None
        obj = row[2].strip()
        if obj.isdigit():
            obj = gt.object_ids.get(int(obj), f"obj_{int(obj):06d}")
        if obj not in gt.spaces:
            raise UserError(f"{where}: result for unknown object {row[2].strip()!r}", path=path)
        Rm, tv = _pose(R, t, where, path)
        key = (
            f"{int(scene_id)}/{im_id}" if gt.kind == "bop" else _our_scene_key(scene_id, gt.scenes)
        )
        ps = table[(key, obj)]
        ps.R.append(Rm)
        ps.t.append(tv)
        ps.values.append(score)
    return dict(table)


def _our_scene_key(scene_id: str, scenes: list[str]) -> str:
    if scene_id in scenes:
        return scene_id
    for s in scenes:
        if s.isdigit() and scene_id.isdigit() and int(s) == int(scene_id):
            return s
    return scene_id
