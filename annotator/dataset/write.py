"""Writing the YAML side of the dataset contract: ``dataset.yaml`` and ``object.yaml``.

Used by ``annotator synth`` and ``annotator markers``; written atomically, readable back with
:func:`annotator.dataset.load_dataset`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from annotator.dataset.model import FLIP_HORIZONTAL, FORMAT_VERSION, Instance, MarkerSites, Rig
from annotator.io.atomic import write_text
from annotator.symmetry.classes import Symmetry, symmetry_to_yaml


def _floats(a: np.ndarray, ndigits: int = 9) -> list[float]:
    return [round(float(x), ndigits) for x in np.asarray(a, dtype=float).reshape(-1)]


def rig_to_yaml(rig: Rig) -> dict[str, Any]:
    """The ``rig`` mapping of dataset.yaml."""
    cams = [
        {
            "name": c.name,
            "size": [int(c.width), int(c.height)],
            "K": _floats(c.K),
            "dist": _floats(c.dist),
            "rig_T_cam": _floats(c.rig_T_cam),
            **({"flip": FLIP_HORIZONTAL} if c.name in rig.flipped else {}),
        }
        for c in rig.cameras
    ]
    out: dict[str, Any] = {"cameras": cams}
    if rig.moving:
        out["moving"] = True
    if rig.depth is not None:
        out["depth"] = {"camera": rig.depth.camera, "scale": float(rig.depth.scale)}
        if rig.depth.background is not None:
            out["depth"]["background"] = rig.depth.background
    return out


def write_dataset_yaml(
    root: str | Path, *, name: str, dictionary: str, rig: Rig, objects: Sequence[str], **extra: Any
) -> None:
    """Write ``<root>/dataset.yaml`` (format 1); ``extra`` adds free top-level fields."""
    doc: dict[str, Any] = {
        "format": FORMAT_VERSION,
        "name": name,
        "markers": {"dictionary": dictionary},
        "rig": rig_to_yaml(rig),
        "objects": list(objects),
    }
    doc.update(extra)
    write_text(Path(root) / "dataset.yaml", yaml.safe_dump(doc, sort_keys=False, width=120))


def instance_to_yaml(instance: Instance) -> dict[str, Any]:
    """An ``instances`` entry of object.yaml (with its measured ``sites`` if it has them)."""
    out: dict[str, Any] = {
        "name": instance.name,
        "marker_ids": [int(m) for m in instance.marker_ids],
    }
    if instance.sites is not None:
        out["sites"] = sites_to_yaml(instance.sites)
    if instance.site_scenes is not None:
        out["site_scenes"] = [int(n) for n in instance.site_scenes]
    return out


def sites_to_yaml(corners: np.ndarray) -> list[list[list[float]]]:
    """Marker sites (S, 4, 3) as object.yaml lists (mm, micrometre resolution)."""
    return [[_floats(c, 6) for c in site] for site in np.asarray(corners, float)]


def write_object_yaml(
    folder: str | Path,
    *,
    mesh_file: str,
    symmetry: Symmetry,
    markers: MarkerSites | None,
    instances: Sequence[Instance],
    **extra: Any,
) -> None:
    """Write ``<folder>/object.yaml``; the mesh file itself is written by the caller."""
    doc: dict[str, Any] = {"mesh": mesh_file, "symmetry": symmetry_to_yaml(symmetry)}
    if markers is not None:
        doc["markers"] = {
            "size": float(markers.size),
            "sites": sites_to_yaml(markers.corners),
        }
    doc["instances"] = [instance_to_yaml(i) for i in instances]
    doc.update(extra)
    write_text(
        Path(folder) / "object.yaml",
        yaml.safe_dump(doc, sort_keys=False, width=120, default_flow_style=None),
    )
