"""Object models for export: BOP's models_info.json fields and a PLY the BOP toolkit reads.

BOP's ``load_ply`` reads binary properties of type float/double/int/uchar only, so models are
written as ASCII PLY with float vertices and normals and ``uchar int`` face lists.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull

from annotator.dataset.model import ObjectModel
from annotator.geometry.transforms import axis_angle
from annotator.io.atomic import write_text
from annotator.symmetry import finite_group


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    from annotator.geometry.mesh import Mesh

    mesh = Mesh(vertices, faces)
    normals = np.zeros_like(vertices)
    np.add.at(
        normals,
        faces.reshape(-1),
        np.repeat(mesh.face_normals * mesh.face_areas[:, None], 3, axis=0),
    )
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    head = (
        f"ply\nformat ascii 1.0\nelement vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"property float nx\nproperty float ny\nproperty float nz\nelement face {len(faces)}\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    rows = [
        f"{x:.6f} {y:.6f} {z:.6f} {a:.6f} {b:.6f} {c:.6f}"
        for (x, y, z), (a, b, c) in zip(vertices, normals)
    ]
    rows += [f"3 {a} {b} {c}" for a, b, c in faces]
    write_text(path, head + "\n".join(rows) + "\n")


def models_info(obj: ObjectModel) -> dict[str, Any]:
    """diameter (largest vertex distance), min/size, and the symmetries in BOP's terms.

    BOP symmetries are transforms of the model frame: ``x -> R x + t``; ours are rotations about
    the surface centroid ``c``, so ``t = c - R c``. Revolution gives ``symmetries_continuous``
    (axis through ``c``, offset ``c``); revolution_flip adds the half turn about an axis
    perpendicular to it; a spherical part (which BOP cannot express) gets three continuous axes.
    """
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
    c = obj.mesh.moments.centroid
    sym = obj.symmetry

    def T(R: np.ndarray) -> list[float]:
        M = np.eye(4)
        M[:3, :3] = R
        M[:3, 3] = c - R @ c
        return [float(x) for x in M.ravel()]

    if sym.kind == "finite":
        info["symmetries_discrete"] = [T(G) for G in finite_group(sym.generators)[1:]]
    elif sym.kind in ("revolution", "revolution_flip"):
        axis = sym.axis / np.linalg.norm(sym.axis)
        info["symmetries_continuous"] = [{"axis": axis.tolist(), "offset": c.tolist()}]
        if sym.kind == "revolution_flip":
            perp = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
            info["symmetries_discrete"] = [T(axis_angle(perp, np.pi))]
    elif sym.kind == "spherical":
        info["symmetries_continuous"] = [
            {"axis": a, "offset": c.tolist()} for a in ([1, 0, 0], [0, 1, 0], [0, 0, 1])
        ]
    return info
