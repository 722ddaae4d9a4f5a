"""A textured mesh showing the markers on the part (OBJ + MTL + PNG atlas).

The part keeps a plain grey material; each marker is an extra textured quad 0.05 mm above its
site (so that it is never hidden by the surface it lies on), mapped to its tile of the atlas.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from annotator.geometry.mesh import Mesh
from annotator.io.atomic import write_text
from annotator.io.images import write_png
from annotator.markers.texture import marker_image


def write_textured_obj(
    folder: Path,
    name: str,
    mesh: Mesh,
    corners: np.ndarray,
    marker_ids: Sequence[int],
    dictionary: str,
    *,
    tile: int = 120,
) -> Path:
    """Write ``<name>.obj``, ``<name>.mtl`` and ``<name>_texture.png``; return the OBJ path."""
    n = len(marker_ids)
    cols = int(np.ceil(np.sqrt(max(n, 1))))
    rows = int(np.ceil(max(n, 1) / cols))
    atlas = np.full((rows * tile, cols * tile), 255, np.uint8)
    for k, mid in enumerate(marker_ids):
        r, c = divmod(k, cols)
        atlas[r * tile : (r + 1) * tile, c * tile : (c + 1) * tile] = marker_image(
            dictionary, int(mid), tile
        )
    write_png(folder / f"{name}_texture.png", atlas)
    write_text(
        folder / f"{name}.mtl",
        f"newmtl part\nKd 0.7 0.7 0.7\n\nnewmtl markers\nKd 1 1 1\nmap_Kd {name}_texture.png\n",
    )
    lines = [f"mtllib {name}.mtl", "o part"]
    lines += [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in mesh.vertices]
    lines.append("usemtl part")
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    base = len(mesh.vertices)
    lines.append("o markers")
    lines.append("usemtl markers")
    vt = 0
    for k in range(n):
        q = corners[k]
        normal = np.cross(q[3] - q[0], q[1] - q[0])
        normal /= np.linalg.norm(normal)
        q = q + 0.05 * normal
        lines += [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in q]
        r, c = divmod(k, cols)
        # Texture v runs upwards in OBJ; image row 0 is the top of the atlas.
        u0, u1 = c / cols, (c + 1) / cols
        v0, v1 = 1 - r / rows, 1 - (r + 1) / rows
        lines += [
            f"vt {u0:.6f} {v0:.6f}",
            f"vt {u1:.6f} {v0:.6f}",
            f"vt {u1:.6f} {v1:.6f}",
            f"vt {u0:.6f} {v1:.6f}",
        ]
        v = base + 4 * k + 1
        t = vt + 1
        # TL, TR, BR, BL seen from outside: (TL, BL, BR) and (TL, BR, TR) wind outward.
        lines.append(f"f {v}/{t} {v + 3}/{t + 3} {v + 2}/{t + 2}")
        lines.append(f"f {v}/{t} {v + 2}/{t + 2} {v + 1}/{t + 1}")
        vt += 4
    path = folder / f"{name}.obj"
    write_text(path, "\n".join(lines) + "\n")
    return path
