"""The review of a dataset's annotations: each scene's decisions and repairs, read from and
written to its review.json, shared by every page of every server on the dataset.

- :mod:`annotator.review.scenes`: what the review knows of one scene (:class:`SceneInfo`)
  and the errors a decision may meet.
- :mod:`annotator.review.state`: :class:`ReviewState`, which reads and writes them.

The browser pages that make the decisions are the :mod:`viewer`'s; the records of
review.json are :mod:`annotator.dataset.review`'s.
"""

from __future__ import annotations

from annotator.review.scenes import (
    FILTERS,
    Conflict,
    SaveError,
    SceneInfo,
    Staged,
    changed_since,
    frames_digest,
    same_edit,
    view_key,
)
from annotator.review.state import ReviewState

__all__ = [
    "FILTERS",
    "Conflict",
    "ReviewState",
    "SaveError",
    "SceneInfo",
    "Staged",
    "changed_since",
    "frames_digest",
    "same_edit",
    "view_key",
]
