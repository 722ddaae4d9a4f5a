"""models_info.json's symmetries and the paper's symmetry classes, both ways, and the
continuous ones as bop_toolkit discretises them for MSSD and MSPD."""

from __future__ import annotations

import math

import numpy as np
import pytest

import annotator
from annotator.evaluation.bop19 import mssd
from annotator.formats.bop_images import MAX_SYM_DISC_STEP, BopObject
from annotator.geometry.transforms import axis_angle
from annotator.symmetry.classes import Symmetry, group_of

Z = np.array([0.0, 0.0, 1.0])
X = np.array([1.0, 0.0, 0.0])
CENTROID = np.array([3.0, -2.0, 5.0])

CLASSES = [
    Symmetry(),
    Symmetry("finite", ((Z, 2),)),
    Symmetry("finite", ((Z, 6),)),
    Symmetry("finite", ((Z, 4), (X, 2))),
    Symmetry("revolution", axis=Z),
    Symmetry("revolution_flip", axis=X),
    Symmetry("spherical"),
]
#: Transforms bop_toolkit's get_symmetry_transformations makes of each class's entry
#: (``max_sym_disc_step`` 0.01: 315 turns per continuous axis).
BOP_COUNTS = [1, 2, 6, 8, 315, 630, 945]


@pytest.mark.parametrize(("sym", "count"), list(zip(CLASSES, BOP_COUNTS)), ids=str)
def test_both_ways(sym: Symmetry, count: int) -> None:
    entry = annotator.symmetry_to_bop(sym, CENTROID)
    back = annotator.symmetry_from_bop(entry)
    assert back.kind == sym.kind
    if sym.kind == "finite":
        G, H = group_of(sym), group_of(back)
        assert len(G) == len(H)
        for g in G:
            assert min(np.abs(g - h).max() for h in H) < 1e-9
    if sym.kind.startswith("revolution"):
        assert back.axis is not None and abs(abs(float(back.axis @ sym.axis)) - 1) < 1e-12
    R, t = annotator.bop_symmetries(sym, CENTROID)
    assert len(R) == count
    # every transform turns about the centroid, which it leaves in place
    assert np.allclose(R @ CENTROID + t, CENTROID)
    assert np.allclose(R[0], np.eye(3)) and np.allclose(t[0], 0)


def test_discretisation_step_as_bop_toolkit() -> None:
    """ceil(pi / step) turns: a point half a diameter from the axis moves at most ``step``
    diameters from one to the next, so the sampled MSSD of a turn about a revolution axis is
    at most that much above the paper's (0)."""
    R, t = annotator.bop_symmetries(Symmetry("revolution", axis=Z), CENTROID)
    assert len(R) == math.ceil(math.pi / MAX_SYM_DISC_STEP)
    diameter = 100.0
    far = CENTROID + np.array([diameter / 2, 0.0, 0.0])
    moved = R @ far + t
    steps = np.linalg.norm(np.diff(np.vstack([moved, moved[:1]]), axis=0), axis=1)
    assert steps.max() <= MAX_SYM_DISC_STEP * diameter
    ring = np.array([[math.cos(a), math.sin(a), 0.0] for a in np.linspace(0, 6, 40)]) * 50
    obj = BopObject(ring + CENTROID, diameter, R, t)
    pose_t = np.array([0.0, 0.0, 600.0])
    for angle in np.linspace(0.1, 6.2, 9):
        Rg = axis_angle(Z, float(angle))
        tg = pose_t + CENTROID - Rg @ CENTROID  # the same part, turned about its axis
        err = mssd(np.eye(3), pose_t, Rg, tg, obj) / diameter
        assert err <= MAX_SYM_DISC_STEP / 2 + 1e-9
