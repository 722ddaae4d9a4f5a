"""Which scenes a command works on: those whose id matches a ``--scenes`` pattern.

Every stage that takes a pattern (annotate, occlusion, estimate, sites, the physics check,
the reviews' selection for export and twins) chooses its scenes here, so that a pattern
means the same everywhere: shell-style (:mod:`fnmatch`), matched against the whole scene id,
``*`` for every scene.

>>> from annotator.dataset import load_dataset
>>> ds = load_dataset("sample_scenes")
>>> [s.id for s in matching_scenes(ds, "00000[12]")]
['000001', '000002']
>>> matching_scenes(ds, "nothing*")
Traceback (most recent call last):
    ...
annotator.errors.UserError: sample_scenes/scenes: no scene matches 'nothing*'
"""

from __future__ import annotations

import fnmatch

from annotator.dataset.model import SCENES_DIR, Dataset, Scene
from annotator.errors import UserError

#: The pattern that matches every scene.
EVERY_SCENE = "*"


def matches(scene_id: str, pattern: str) -> bool:
    """Whether the scene id ``scene_id`` matches ``pattern`` (fnmatch).

    >>> matches("000012", "0000*"), matches("000012", "*3")
    (True, False)
    """
    return fnmatch.fnmatch(scene_id, pattern)


def matching_scenes(
    ds: Dataset, pattern: str = EVERY_SCENE, *, required: bool = True
) -> list[Scene]:
    """The scenes of ``ds`` whose id matches ``pattern``, in the dataset's order.

    Raises:
        UserError: no scene matches (unless ``required`` is False: then an empty list).
    """
    chosen = [s for s in ds.scenes() if matches(s.id, pattern)]
    if required and not chosen:
        raise UserError(f"no scene matches {pattern!r}", path=ds.root / SCENES_DIR)
    return chosen
