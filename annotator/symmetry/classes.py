"""The proper symmetry group of a part: the :class:`Symmetry` record, its classes, and its
conversions to and from object.yaml and BOP's ``models_info.json``.

Classes (the paper's table 2), all rotations about axes through the surface centroid:

=================== ===============================================================
``none``            no symmetry
``finite``          a finite group, given by generators ``(axis, order)``: a turn of
                    ``2 pi / order`` about ``axis``
``revolution``      every rotation about ``axis``
``revolution_flip`` every rotation about ``axis``, and half turns about the axes
                    perpendicular to it
``spherical``       every rotation
=================== ===============================================================

BOP describes a symmetry as transforms of the model frame ``x -> R x + t``: continuous ones by
an axis and an offset (a point on the axis), discrete ones by *every* non-identity element of
the group as a 4x4 matrix. Ours are rotations about the surface centroid ``c``, so
``t = c - R c``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np

from annotator.geometry.lie import matrix_to_rotvec
from annotator.geometry.transforms import axis_angle
from annotator.symmetry.group import finite_group

#: The classes of proper symmetry (object.yaml ``symmetry.class``).
SymmetryKind = Literal["none", "finite", "revolution", "revolution_flip", "spherical"]
SYMMETRY_CLASSES: tuple[SymmetryKind, ...] = get_args(SymmetryKind)


@dataclass(frozen=True)
class Symmetry:
    """The proper symmetry group of a part.

    Attributes:
        kind: One of :data:`SYMMETRY_CLASSES`.
        generators: For ``finite``: (axis (3,), order) pairs of rotations about axes through
            the surface centroid.
        axis: For revolution classes: the axis direction (through the surface centroid).
    """

    kind: SymmetryKind = "none"
    generators: tuple[tuple[np.ndarray, int], ...] = ()
    axis: np.ndarray | None = None


def _floats(a: Any, ndigits: int = 9) -> list[float]:
    return [round(float(x), ndigits) for x in np.asarray(a, dtype=float).reshape(-1)]


def _unit(value: Any, what: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=float).reshape(3)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be 3 numbers") from None
    n = np.linalg.norm(v)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f"{what} must be a non-zero, finite vector")
    return v / n


# ---------------------------------------------------------------------------- object.yaml


def symmetry_to_yaml(sym: Symmetry) -> dict[str, Any]:
    """The ``symmetry`` mapping of object.yaml."""
    out: dict[str, Any] = {"class": sym.kind}
    if sym.kind == "finite":
        out["generators"] = [{"axis": _floats(a), "order": int(o)} for a, o in sym.generators]
    if sym.kind in ("revolution", "revolution_flip"):
        out["axis"] = _floats(sym.axis if sym.axis is not None else [0, 0, 1])
    return out


def symmetry_from_yaml(doc: Any) -> Symmetry:
    """Read the ``symmetry`` mapping of object.yaml. Raises ValueError saying what is wrong
    (the caller names the file)."""
    if not isinstance(doc, dict):
        raise ValueError("symmetry must be a mapping with a 'class'")
    kind = doc.get("class", "none")
    if kind not in SYMMETRY_CLASSES:
        raise ValueError(
            f"unknown symmetry class {kind!r} (expected one of {', '.join(SYMMETRY_CLASSES)})"
        )
    if kind == "finite":
        gens = []
        for i, g in enumerate(doc.get("generators") or []):
            if not isinstance(g, dict):
                raise ValueError(f"symmetry.generators[{i}] must be a mapping {{axis, order}}")
            order = g.get("order")
            if not isinstance(order, int) or isinstance(order, bool) or order < 2:
                raise ValueError(f"symmetry.generators[{i}].order must be an integer >= 2")
            gens.append((_unit(g.get("axis"), f"symmetry.generators[{i}].axis"), order))
        if not gens:
            raise ValueError("finite symmetry needs at least one generator {axis, order}")
        sym = Symmetry(kind, generators=tuple(gens))
        group_of(sym)  # generators that generate no finite group: say so here
        return sym
    if kind in ("revolution", "revolution_flip"):
        return Symmetry(kind, axis=_unit(doc.get("axis", [0, 0, 1]), "symmetry.axis"))
    return Symmetry(kind)


def group_of(sym: Symmetry) -> np.ndarray:
    """The elements of a finite symmetry group, identity first, shape (G, 3, 3) (just the
    identity for ``none``). ValueError if the generators generate no finite group."""
    if sym.kind == "none":
        return np.eye(3)[None]
    if sym.kind != "finite":
        raise ValueError(f"a {sym.kind} symmetry has no finite list of elements")
    return finite_group(sym.generators)


# ---------------------------------------------------------------------------------- BOP


def symmetry_to_bop(sym: Symmetry, centroid: np.ndarray) -> dict[str, Any]:
    """``symmetries_discrete`` / ``symmetries_continuous`` of a models_info.json entry.

    Revolution gives one continuous axis through the centroid; revolution_flip adds the
    half turn about an axis perpendicular to it; a spherical part (which BOP cannot express)
    gets three continuous axes; a finite group lists all its non-identity elements.

    >>> symmetry_to_bop(Symmetry("revolution", axis=np.array([0.0, 0.0, 1.0])), np.zeros(3))
    {'symmetries_continuous': [{'axis': [0.0, 0.0, 1.0], 'offset': [0.0, 0.0, 0.0]}]}
    """
    c = np.asarray(centroid, float)

    def T(R: np.ndarray) -> list[float]:
        M = np.eye(4)
        M[:3, :3] = R
        M[:3, 3] = c - R @ c
        return [float(x) for x in M.ravel()]

    if sym.kind == "finite":
        return {"symmetries_discrete": [T(G) for G in group_of(sym)[1:]]}
    if sym.kind in ("revolution", "revolution_flip"):
        given = sym.axis if sym.axis is not None else [0.0, 0.0, 1.0]  # as symmetry_to_yaml
        axis = np.asarray(given, float) / np.linalg.norm(given)
        out: dict[str, Any] = {
            "symmetries_continuous": [{"axis": axis.tolist(), "offset": c.tolist()}]
        }
        if sym.kind == "revolution_flip":
            perp = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
            out["symmetries_discrete"] = [T(axis_angle(perp, np.pi))]
        return out
    if sym.kind == "spherical":
        return {
            "symmetries_continuous": [
                {"axis": a, "offset": c.tolist()} for a in ([1, 0, 0], [0, 1, 0], [0, 0, 1])
            ]
        }
    return {}


#: A listed discrete symmetry within this angle (degrees) of a turn of finite order (up to
#: :data:`MAX_SNAP_ORDER`) is taken as that turn: BOP's symmetries are measured, not exact
#: (LM-O's eggbox lists 179.8 degrees, its glue 178.5).
SNAP_DEG = 2.0
MAX_SNAP_ORDER = 36
#: Turns of higher order (to 120) are taken only when they are exact to this (rad).
EXACT_RAD = 1e-4


def symmetry_from_bop(
    entry: dict[str, Any], *, tol: float = 1e-3, snapped: list[str] | None = None
) -> Symmetry:
    """Our symmetry from a models_info.json entry. Raises ValueError if it is malformed, or
    if the listed discrete elements do not form a group.

    A finite group is rebuilt from its listed elements themselves, each taken as the
    generator of its own cyclic subgroup (a turn of 135 degrees has order 8, not 3), and the
    group they generate must be exactly the listed elements plus the identity. An element
    that is not of finite order but within :data:`SNAP_DEG` of a turn that is, is taken as
    that turn about its own axis; a line saying so is added to ``snapped``.

    >>> sym = symmetry_from_bop({"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]})
    >>> sym.kind, sym.axis.tolist()
    ('revolution', [0.0, 0.0, 1.0])
    """
    cont = entry.get("symmetries_continuous") or []
    disc = entry.get("symmetries_discrete") or []
    if not isinstance(cont, list) or not isinstance(disc, list):
        raise ValueError("symmetries_continuous and symmetries_discrete must be lists")
    rotations = [_bop_rotation(s, k) for k, s in enumerate(disc)]
    axes = []
    for k, c in enumerate(cont):
        if not isinstance(c, dict):
            raise ValueError(f"symmetries_continuous[{k}] must be a mapping {{axis, offset}}")
        axes.append(_unit(c.get("axis"), f"symmetries_continuous[{k}].axis"))
    if len(axes) >= 2:
        return Symmetry("spherical")
    if axes:
        axis = axes[0]
        for k, R in enumerate(rotations):
            _check_with_axis(R, axis, k)
        flip = any(float(axis @ R @ axis) < 0 for R in rotations)
        return Symmetry("revolution_flip" if flip else "revolution", axis=axis)
    gens = _generators(rotations, snapped)
    if not gens:
        return Symmetry()
    sym = Symmetry("finite", generators=tuple(gens))
    _check_closed(sym, rotations, tol)
    return sym


def _check_with_axis(R: np.ndarray, axis: np.ndarray, k: int) -> None:
    """ValueError unless ``symmetries_discrete[k]`` can stand beside a continuous symmetry
    about ``axis``: a turn about that axis, or a half turn about an axis across it (a flip),
    each within :data:`SNAP_DEG`. Any other element and the turns about the axis generate
    every rotation, which is a sphere's symmetry, not a part's with one axis."""
    rv = matrix_to_rotvec(R)
    angle = float(np.linalg.norm(rv))
    if angle < math.radians(SNAP_DEG):
        return
    tilt = math.degrees(math.acos(min(1.0, abs(float(axis @ rv)) / angle)))
    if tilt <= SNAP_DEG:
        return
    if abs(90.0 - tilt) <= SNAP_DEG and abs(math.degrees(angle) - 180.0) <= SNAP_DEG:
        return
    raise ValueError(
        f"symmetries_discrete[{k}] (a turn of {math.degrees(angle):.1f} degrees about an axis "
        f"{tilt:.1f} degrees from the continuous axis) is neither a turn about the continuous "
        "axis nor a half turn across it"
    )


def _bop_rotation(element: Any, k: int) -> np.ndarray:
    """The rotation of ``symmetries_discrete[k]``; ValueError if it is not a proper one."""
    try:
        M = np.asarray(element, float).reshape(4, 4)
    except (TypeError, ValueError):
        raise ValueError(f"symmetries_discrete[{k}] must be 16 numbers") from None
    R = M[:3, :3]
    if not (np.all(np.isfinite(R)) and np.allclose(R @ R.T, np.eye(3), atol=1e-3)):
        raise ValueError(f"symmetries_discrete[{k}] is not a rotation")
    if np.linalg.det(R) < 0:
        raise ValueError(f"symmetries_discrete[{k}] is a reflection (improper symmetry)")
    return R


def _generators(
    rotations: list[np.ndarray], snapped: list[str] | None
) -> list[tuple[np.ndarray, int]]:
    """One (axis, order) generator per axis of the listed rotations, each rotation taken as
    the generator of its own cyclic subgroup; a rotation snapped to a turn of finite order
    is replaced in ``rotations`` by that turn, and said in ``snapped``."""
    gens: list[tuple[np.ndarray, int]] = []
    for k, R in enumerate(rotations):
        rv = matrix_to_rotvec(R)
        angle = float(np.linalg.norm(rv))
        if angle < 1e-6:
            continue  # an identity listed among the elements
        axis = rv / angle
        order, exact = _snap(angle, f"symmetries_discrete[{k}]", axis)
        if abs(exact - angle) > EXACT_RAD:
            rotations[k] = axis_angle(axis, exact)
            if snapped is not None:
                snapped.append(_snapped_line(angle, axis, order, exact))
        # Elements about one axis generate one cyclic group, of the lcm of their orders: one
        # exact generator for it keeps the closure free of rounding noise.
        for j, (a, o) in enumerate(gens):
            if abs(float(a @ axis)) > 1.0 - 1e-6:
                gens[j] = (a, math.lcm(o, order))
                break
        else:
            gens.append((axis, order))
    return gens


def _snapped_line(angle: float, axis: np.ndarray, order: int, exact: float) -> str:
    named = (
        "the half turn" if order == 2 else f"a turn of {np.degrees(exact):g} deg (order {order})"
    )
    return (
        f"symmetry {np.degrees(angle):.1f} deg about "
        f"({', '.join(f'{v:.3f}' for v in axis)}) taken as {named}"
    )


def _check_closed(sym: Symmetry, rotations: list[np.ndarray], tol: float) -> None:
    """ValueError unless the group ``sym`` generates is exactly the listed rotations plus
    the identity."""
    try:
        group = group_of(sym)
    except ValueError:
        group = np.zeros((0, 3, 3))
    listed: list[np.ndarray] = []
    for L in [np.eye(3)] + rotations:
        if not any(np.abs(L - M).max() < tol for M in listed):
            listed.append(L)
    closed = len(group) == len(listed) and all(
        any(np.abs(G - L).max() < tol for L in listed) for G in group
    )
    if not closed:
        raise ValueError(
            f"symmetries_discrete lists {len(listed) - 1} distinct rotations, which with the "
            "identity do not form a group"
        )


def _snap(angle: float, what: str, axis: np.ndarray) -> tuple[int, float]:
    """The order and angle (rad) of the turn of finite order within :data:`SNAP_DEG` (and a
    tenth of that order's spacing) of ``angle`` (orders up to :data:`MAX_SNAP_ORDER`, the
    smallest first; higher ones, to 120, only exact to :data:`EXACT_RAD`); ValueError naming
    ``what`` otherwise."""
    for n in range(2, 121):
        k = round(angle * n / (2 * np.pi))
        # Within a tenth of the spacing of the order's turns too, so that it is unambiguous.
        spacing = 2 * np.pi / n
        bound = min(np.radians(SNAP_DEG), spacing / 10) if n <= MAX_SNAP_ORDER else EXACT_RAD
        if k and math.gcd(k, n) == 1 and abs(angle - 2 * np.pi * k / n) <= bound:
            return n, 2 * np.pi * k / n
    raise ValueError(
        f"{what}: a turn of {np.degrees(angle):.2f} deg about ({', '.join(f'{v:.3f}' for v in axis)}) "
        f"is not within {SNAP_DEG:g} deg of a rotation of finite order (at most {MAX_SNAP_ORDER})"
    )
