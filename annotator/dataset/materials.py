"""Surface materials of the physically based render: named presets, as object.yaml names them.

An object's ``object.yaml`` may carry ``material:``, either a preset's name or a mapping with
a ``preset`` and any of ``color`` (linear RGB, 0..1, or one grey value), ``roughness`` and
``metallic`` overriding it::

    material: steel
    material: {preset: painted_plastic, color: [0.8, 0.2, 0.1], roughness: 0.5}

Without one a part is :data:`DEFAULT_MATERIAL`. The markers are always :data:`PAPER`: matte
printed paper, whatever the part is made of.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from annotator.errors import UserError


@dataclass(frozen=True)
class Material:
    """A Principled-BSDF surface: ``metallic`` 1 is a conductor (its colour is its
    reflectance, it has no diffuse part), 0 a dielectric with a diffuse ``color`` and a thin
    specular coat; ``roughness`` 0 is a mirror, 1 fully matte."""

    name: str
    color: tuple[float, float, float]
    roughness: float
    metallic: float = 0.0
    specular: float = 0.5

    @property
    def diffuse(self) -> float:
        """The diffuse (Lambertian) reflectance, grey: what scatters light back everywhere."""
        return (1.0 - self.metallic) * sum(self.color) / 3.0

    @property
    def mirror(self) -> float:
        """The specular reflectance at normal incidence, grey (a conductor's is its colour)."""
        dielectric = 0.08 * self.specular
        return self.metallic * sum(self.color) / 3.0 + (1.0 - self.metallic) * dielectric

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "color": list(self.color),
            "roughness": self.roughness,
            "metallic": self.metallic,
            "specular": self.specular,
        }


def _grey(v: float) -> tuple[float, float, float]:
    return (v, v, v)


#: The presets by name.
PRESETS: dict[str, Material] = {
    m.name: m
    for m in (
        Material("steel", (0.56, 0.57, 0.58), roughness=0.3, metallic=1.0),
        Material("polished_steel", (0.56, 0.57, 0.58), roughness=0.08, metallic=1.0),
        Material("aluminium", (0.91, 0.92, 0.92), roughness=0.35, metallic=1.0),
        Material("brass", (0.91, 0.78, 0.42), roughness=0.25, metallic=1.0),
        Material("painted_plastic", _grey(0.6), roughness=0.45),
        Material("black_plastic", _grey(0.04), roughness=0.5),
        Material("rubber", _grey(0.1), roughness=0.9, specular=0.2),
    )
}

#: A part without ``material:``.
DEFAULT_MATERIAL = "painted_plastic"

#: The markers' paper: white 0.85, the printed black 0.04 (the cells' texture scales it).
PAPER = Material("paper", _grey(1.0), roughness=0.9, specular=0.3)


def material_named(name: str, *, where: str = "") -> Material:
    """The preset ``name``.

    Raises:
        UserError: no preset has that name (the valid names listed); ``where`` says what
            named it.
    """
    if name not in PRESETS:
        at = f"{where}: " if where else ""
        raise UserError(f"{at}unknown material {name!r} (valid: {', '.join(sorted(PRESETS))})")
    return PRESETS[name]


def parse_material(doc: Any, *, path: str | Path = "object.yaml") -> Material:
    """The material an object.yaml's ``material:`` value describes (``None``: the default).

    >>> parse_material({"preset": "steel", "roughness": 0.1}).roughness
    0.1
    >>> parse_material("chrome", path="objects/bracket/object.yaml")
    Traceback (most recent call last):
    ...
    annotator.errors.UserError: objects/bracket/object.yaml: unknown material 'chrome' (valid: aluminium, black_plastic, brass, painted_plastic, polished_steel, rubber, steel)

    Raises:
        UserError: an unknown preset or a malformed value, naming ``path``.
    """
    where = str(path)
    if doc is None:
        return PRESETS[DEFAULT_MATERIAL]
    if isinstance(doc, str):
        return material_named(doc, where=where)
    if not isinstance(doc, Mapping):
        raise UserError(f"{where}: material must be a preset name or a mapping with 'preset'")
    unknown = set(doc) - {"preset", "color", "roughness", "metallic"}
    if unknown:
        raise UserError(
            f"{where}: material has unknown keys {sorted(unknown)} "
            "(preset, color, roughness, metallic)"
        )
    base = material_named(str(doc.get("preset", DEFAULT_MATERIAL)), where=where)
    changes: dict[str, Any] = {}
    for key in ("roughness", "metallic"):
        if key in doc:
            changes[key] = _unit(doc[key], f"{where}: material {key}")
    if "color" in doc:
        c = doc["color"]
        values = [c] * 3 if isinstance(c, int | float) else c
        if not isinstance(values, list) or len(values) != 3:
            raise UserError(f"{where}: material color must be one grey value or [r, g, b]")
        changes["color"] = tuple(_unit(v, f"{where}: material color") for v in values)
    return replace(base, **changes) if changes else base


def _unit(v: Any, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not 0.0 <= float(v) <= 1.0:
        raise UserError(f"{what} must be a number in [0, 1], not {v!r}")
    return float(v)
