"""Built-in parts: procedural meshes covering every proper-symmetry class of the paper.

==========  ================  ===========================================
name        symmetry class    group
==========  ================  ===========================================
bracket     none              identity only
brick       finite            half turn about z (order 2)
gear        finite            turns of 2 pi / 8 about z (order 8)
cup         revolution        all turns about z
cylinder    revolution_flip   all turns about z, and the half turn about x
ball        spherical         SO(3)
==========  ================  ===========================================

Meshes are in millimetres with the surface centroid at the origin, so the symmetry axes
written in object.yaml pass through it (FORMAT.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from annotator.dataset.model import Symmetry
from annotator.errors import UserError
from annotator.geometry.mesh import Mesh
from annotator.parts import shapes

Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Part:
    """A built-in part: its mesh, its proper symmetry group and a suitable marker size (mm)."""

    name: str
    mesh: Mesh
    symmetry: Symmetry
    marker_size: float


_REGISTRY: dict[str, tuple[Callable[[], Mesh], Symmetry, float]] = {
    "bracket": (shapes.bracket, Symmetry("none"), 10.0),
    "brick": (shapes.brick, Symmetry("finite", ((Z, 2),)), 10.0),
    "gear": (shapes.gear, Symmetry("finite", ((Z, 8),)), 9.0),
    "cup": (shapes.cup, Symmetry("revolution", axis=Z), 8.0),
    "cylinder": (shapes.cylinder, Symmetry("revolution_flip", axis=Z), 8.0),
    "ball": (shapes.ball, Symmetry("spherical"), 6.0),
}

#: Names of the built-in parts.
PART_NAMES: tuple[str, ...] = tuple(_REGISTRY)


def build_part(name: str) -> Part:
    """Build the built-in part called ``name``.

    Raises:
        UserError: if ``name`` is not one of :data:`PART_NAMES`.
    """
    if name not in _REGISTRY:
        raise UserError(f"unknown part {name!r} (built-in parts: {', '.join(PART_NAMES)})")
    builder, symmetry, marker_size = _REGISTRY[name]
    return Part(name=name, mesh=builder(), symmetry=symmetry, marker_size=marker_size)
