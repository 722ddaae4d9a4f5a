"""Writing triangle meshes as PLY files that other tools read (the BOP toolkit among them).

BOP's ``load_ply`` reads binary properties of type float/double/int/uchar only, so models are
written as ASCII PLY with float vertices and normals and ``uchar int`` face lists.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from annotator.geometry.mesh import Mesh
from annotator.io.atomic import write_text


def write_ply(path: str | Path, mesh: Mesh) -> None:
    """Write ``mesh`` (mm) with area-weighted vertex normals, atomically."""
    vertices, faces = mesh.vertices, mesh.faces
    normals = np.zeros_like(vertices)
    np.add.at(
        normals,
        faces.reshape(-1),
        np.repeat(mesh.face_normals * mesh.face_areas[:, None], 3, axis=0),
    )
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    head = (
        f"ply\nformat ascii 1.0\nelement vertex {len(vertices)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    rows = [
        f"{x:.6f} {y:.6f} {z:.6f} {a:.6f} {b:.6f} {c:.6f}"
        for (x, y, z), (a, b, c) in zip(vertices, normals)
    ]
    rows += [f"3 {a} {b} {c}" for a, b, c in faces]
    write_text(path, head + "\n".join(rows) + "\n")
