"""The paper's pose distance (section 4.1, table 2), exact for every class of proper symmetry,
and its use inside pose estimators (section 4.2).

A pose of a part is mapped to a small set of points (its *representatives*) in R^12 (no or
finite symmetry), R^6 (revolution, with or without flip) or R^3 (spherical), such that the
distance between two poses, the RMS displacement of the surface points minimised over the
symmetry group, is the Euclidean distance from any representative of one to the nearest
representative of the other. Neighbourhood queries are therefore KD-tree queries:
:func:`filter_duplicates` (early duplicate removal) and :func:`find_modes` (mean shift over
pose votes) use them.
"""

from annotator.symmetry.duplicates import filter_duplicates
from annotator.symmetry.group import finite_group
from annotator.symmetry.modes import Modes, find_modes
from annotator.symmetry.space import PoseSpace

__all__ = ["Modes", "PoseSpace", "filter_duplicates", "find_modes", "finite_group"]
