"""The paper's own dataset format (the "Siléane dataset", Brégier et al. 2017): its ground
truth, results, and the authors' pose-space file ``poseutils.json``; the export to it is
:mod:`annotator.export.sileane`.

One folder per object (the format holds one object per dataset); lengths in **metres**::

    OUT/<object>/mesh.ply                 the part, in its *canonical frame* (below), metres
    OUT/<object>/poseutils.json           the pose space, as the authors' evaluation code reads it
    OUT/<object>/camera_params.txt        fu, fv, cu, cv, clip_start, clip_end (m), location (m),
                                          rotation (quaternion w x y z, camera to world)
    OUT/<object>/depth/<scene>.PNG        uint16, (z - clip_start) / (clip_end - clip_start) * 65535,
                                          z in metres; 65535 where nothing was measured
    OUT/<object>/rgb/<scene>.PNG          the reference camera's image
    OUT/<object>/gt/<scene>.json          [{"R": 3x3, "t": [x, y, z], "occlusion_rate",
                                          "segmentation_id", "instance"}]
    OUT/<object>/segmentation/<scene>.PNG  uint8, segmentation_id per pixel (visible part), 255 = none
    OUT/<object>/mask_markers/<scene>.PNG  with --remove-markers: uint8, 255 where a marker of
                                          any part was filled in rgb/, 0 elsewhere

**Canonical frame.** The authors' code measures the translation part of the distance on the
pose's ``t`` itself and the rotation part about the model axes, which is the paper's
distance only when the model's origin is its surface centroid (and, for revolution parts, z
is the axis). So the export expresses each part in that frame: ``x' = B^T (x - c)`` for the
mesh, ``R' = R B``, ``t' = t + R c`` for the poses (``c`` the surface centroid, ``B`` the
identity, or a rotation taking z to the revolution axis), and ``poseutils.json`` holds the
square root of the surface second moments ``Lambda`` and the symmetry group ``G`` in that
frame (``RevolutionPoseUtils`` with ``lambda`` for revolution classes; a spherical part is a
revolution part with ``lambda = 0``). Distances computed by the authors' code on the export
are then exactly the paper's.

The reference camera only, undistorted to a pinhole camera with the same K; its frame is the
world frame (location 0, rotation identity).

Ground truth: ``gt/<scene>.json`` with ``poseutils.json`` (the authors' files: its
``distance_threshold`` is the default match threshold), or ``mesh.ply`` (millimetres) with our
``symmetry.yaml`` (exports of earlier versions) or ``--symmetry`` (a mesh less than 2 units
in radius is taken to be in metres). Results: a folder of
``<scene>.json`` lists ``{R, t, score}`` in metres, like the ground truth.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from annotator.errors import UserError
from annotator.formats.base import (
    GroundTruth,
    PoseResults,
    PoseSet,
    Table,
    checked_entries,
    read_json_lists,
)
from annotator.geometry import MM_PER_M
from annotator.io.documents import read_json, read_yaml
from annotator.symmetry.classes import SymmetryKind
from annotator.symmetry.space import PoseSpace

NAME = "sileane"
NO_SEGMENT = 255
M = MM_PER_M  # the paper's files are in metres


def detect(path: Path) -> bool:
    return (path / "gt").is_dir()


# ----------------------------------------------------------------------- poseutils.json


def poseutils_to_json(space: PoseSpace, *, threshold_mm: float) -> dict[str, Any]:
    """The authors' ``poseutils.json`` for a part expressed in its canonical frame (metres)."""
    common = {
        "Rref2i": np.eye(3).tolist(),
        "tref2i": [[0.0], [0.0], [0.0]],
        "distance_threshold": threshold_mm / M,
    }
    if space.kind in ("none", "finite"):
        return {
            "type": "AffinePoseUtils",
            "Lambda": (space.L / M).tolist(),
            "G": space.group.tolist(),
            **common,
        }
    return {
        "type": "RevolutionPoseUtils",
        "lambda": 0.0 if space.kind == "spherical" else space.lam / M,
        "rotoreflection_symmetry": space.kind == "revolution_flip",
        **common,
    }


def poseutils_from_json(doc: Any, path: Path) -> tuple[PoseSpace, float | None]:
    """The pose space (mm) and the match threshold (mm, or None) of a ``poseutils.json``.

    The authors' representatives are ``(vec(Ri G Lambda), ti)`` with ``Ri = Rref2i R`` and
    ``ti = Rref2i t + tref2i``: the left factor and the offset change no distance, so the
    space is the one with ``Lambda`` and ``G`` about the model's own origin and axes.
    """
    if not isinstance(doc, dict) or doc.get("type") not in (
        "AffinePoseUtils",
        "RevolutionPoseUtils",
    ):
        raise UserError("expected type AffinePoseUtils or RevolutionPoseUtils", path=path)
    thr = doc.get("distance_threshold")
    threshold = float(thr) * M if isinstance(thr, (int, float)) and thr > 0 else None
    if doc["type"] == "AffinePoseUtils":
        try:
            L = np.asarray(doc["Lambda"], float).reshape(3, 3) * M
            G = np.asarray(doc.get("G", [np.eye(3).tolist()]), float).reshape(-1, 3, 3)
        except (KeyError, TypeError, ValueError):
            raise UserError("Lambda must be 3x3 and G a list of 3x3 matrices", path=path) from None
        ident = [k for k, g in enumerate(G) if np.abs(g - np.eye(3)).max() < 1e-6]
        if not ident or not np.all(np.isfinite(L)):
            raise UserError("G must contain the identity and Lambda be finite", path=path)
        G = np.concatenate([G[ident[0] : ident[0] + 1], np.delete(G, ident[0], axis=0)])
        finite: SymmetryKind = "finite" if len(G) > 1 else "none"
        space = PoseSpace(finite, np.zeros(3), np.eye(3), L, G, 0.0, float("nan"))
        return space, threshold
    lam = doc.get("lambda")
    if not isinstance(lam, (int, float)) or not lam >= 0:
        raise UserError("lambda must be a number >= 0", path=path)
    revolution: SymmetryKind = (
        "revolution_flip" if doc.get("rotoreflection_symmetry") else "revolution"
    )
    kind = revolution if lam != 0 else "spherical"
    space = PoseSpace(
        kind, np.zeros(3), np.eye(3), np.zeros((3, 3)), np.eye(3)[None], lam * M, float("nan")
    )
    return space, threshold


# -------------------------------------------------------------------------------- export


def canonical_frame(space: PoseSpace) -> np.ndarray:
    """``model_T_canonical``: the 4x4 transform from the exported frame to the model's."""
    T = np.eye(4)
    T[:3, :3] = space.B
    T[:3, 3] = space.centroid
    return T


# ------------------------------------------------------------------------- ground truth


def read_ground_truth(path: Path, *, symmetry: str | None = None) -> GroundTruth:
    name = path.resolve().name
    thresholds = {}
    if (path / "poseutils.json").is_file():
        space, thr = poseutils_from_json(
            read_json(path / "poseutils.json"), path / "poseutils.json"
        )
        if thr is not None:
            thresholds[name] = thr
    else:
        space = _space_from_mesh(path, symmetry)
    table: Table = {}
    scenes = []
    for f in sorted((path / "gt").glob("*.json")):
        doc = read_json(f)
        if not isinstance(doc, list):
            raise UserError("expected a JSON list of {R, t, occlusion_rate}", path=f)
        scenes.append(f.stem)
        ps = table.setdefault((f.stem, name), PoseSet())
        for i, inst in enumerate(doc):
            if not isinstance(inst, dict):
                raise UserError(f"entry {i}: expected an object {{R, t, occlusion_rate}}", path=f)
        R, t, _ = checked_entries(doc, f, scale=M)
        occ = [inst.get("occlusion_rate") for inst in doc]
        ps.extend(R, t, [o if isinstance(o, (int, float)) else math.nan for o in occ])
    return GroundTruth({name: space}, table, scenes, NAME, "m", {1: name}, thresholds)


def _space_from_mesh(path: Path, symmetry: str | None) -> PoseSpace:

    from annotator.geometry.mesh import Mesh, load_mesh
    from annotator.symmetry.classes import Symmetry, symmetry_from_yaml

    mesh_path = next(
        (p for p in (path / "mesh.ply", path / "mesh.obj", path / "mesh.stl") if p.exists()),
        None,
    )
    if mesh_path is None:
        raise UserError(
            "a Siléane object folder needs poseutils.json (the authors' files) or mesh.ply",
            path=path,
        )
    mesh = load_mesh(mesh_path)
    if mesh.moments.radius < 2.0:
        # A part a few units across is in metres (the format's unit); ours were in mm.
        mesh = Mesh(mesh.vertices * M, mesh.faces)
    sym = Symmetry()
    if (path / "symmetry.yaml").exists():
        try:
            sym = symmetry_from_yaml(read_yaml(path / "symmetry.yaml"))
        except ValueError as exc:
            raise UserError(str(exc).splitlines()[0], path=path / "symmetry.yaml") from None
    elif symmetry:
        try:
            sym = symmetry_from_yaml({"class": symmetry})
        except ValueError as exc:
            raise UserError(f"--symmetry: {exc}") from None
    return PoseSpace.from_moments(mesh.moments, sym)


# ------------------------------------------------------------------------------ results


def read_results(path: Path, gt: GroundTruth) -> PoseResults:
    if not path.is_dir():
        raise UserError(
            "results for a Siléane folder are a folder of <scene>.json lists", path=path
        )
    return read_json_lists(path, gt, scale=M)
