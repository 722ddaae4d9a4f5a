"""TP/FP/FN, precision, recall, AP, AP_n, mean scene AP and F1: the definitions of the
authors' published evaluation code (Brégier et al. 2017, ``evaluation_tools.py``), which gives
the paper's numbers. Every one of them is tested in tests/test_evaluation.py.

Per scene and object: ``T`` the true poses, ``P`` the results, ``d`` the pose distance (mm),
``thr`` the match threshold.

- **To find**: the true poses with occlusion rate ``<= max_occlusion`` (inclusive; an
  unknown rate, NaN, counts as to find).
- **Kept results** at a score threshold ``s``: those with score ``>= s`` (ties enter
  together); with "at most n results", the n best-scored of those (ties broken by file order).
- ``n_T(p)``: the true pose nearest to result ``p`` among *all* true poses of the scene, to
  find or not; fixed once for the scene. ``n_P(t)``: the kept result nearest to ``t``.
- A kept result ``p`` **matches** when ``d(p, n_T(p)) <= thr`` (inclusive). It is a **TP**
  when it matches, ``n_P(n_T(p)) = p``, and ``n_T(p)`` is to find; an **FP** when it does not
  match or is not ``n_P(n_T(p))`` (a duplicate); otherwise (a match to a true pose not to
  find) neither.
- **FN**: a true pose ``t`` to find whose nearest kept result does not match it back
  (``n_T(n_P(t)) != t`` or too far), or every ``t`` to find when nothing is kept.
- precision = TP / (TP + FP), 1 when that is 0; recall = TP / (TP + FN), 1 when that is 0
  (nothing to find); recall with at most n results = TP / min(n, TP + FN), 1 when that is 0.

Curves and scores:

- A scene's curve: one (precision, recall) point per threshold ``+inf`` (nothing kept), then
  every distinct score of its results, descending.
- The **mean curve** walks the thresholds ``+inf`` and then every distinct score of any scene,
  descending (the authors' "highest next score of any scene"); at each, every scene gives its
  point for the results it keeps there, and precision and recall are averaged over **all**
  scenes (scenes with nothing to find included).
- **AP** = sum of ``p_i (r_i - r_(i-1))`` along the mean curve, ``r_0 = 0``, no interpolation;
  **AP_n** the same with at most n results per scene and recall with at most n results;
  **mean scene AP** (the authors' MAP) applies that formula to each scene's own curve and
  averages; **F1** is the best ``2pr / (p + r)`` over the points of the mean curve.

Everything is computed per scene with prefix arrays: for results sorted by decreasing score,
the nearest kept result of every true pose for every prefix comes from one running minimum,
so a scene costs O(|P| |T|) operations and memory instead of one nearest-neighbour search
per threshold. The mean curve adds each scene's steps where they happen, so it is linear in
the number of results too.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class SceneCurve:
    """One scene's classification for every number of kept results.

    Attributes:
        scores: (|P|,) result scores, sorted decreasing.
        tp, fp, fn: (|P|+1,) counts when the first k results (by decreasing score) are kept.
        to_find: Number of true poses to find.
    """

    scores: np.ndarray
    tp: np.ndarray
    fp: np.ndarray
    fn: np.ndarray
    to_find: int

    def kept(self, threshold: np.ndarray | float) -> np.ndarray:
        """Number of results with score >= ``threshold`` (elementwise)."""
        return np.searchsorted(-self.scores, -np.asarray(threshold, float), side="right")

    def points(
        self, kept: np.ndarray, max_results: int | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Precision and recall when ``kept`` results are (each entry a count)."""
        k = np.asarray(kept, int)
        if max_results is not None:
            k = np.minimum(k, max_results)
        return _precision_recall(self.tp[k], self.fp[k], self.fn[k], max_results)

    def thresholds(self) -> np.ndarray:
        """``+inf`` then every distinct score, descending: the scene's own curve."""
        return self.steps[0]

    @cached_property
    def steps(self) -> tuple[np.ndarray, np.ndarray]:
        """The scene's own thresholds and the number of results kept at each (computed once:
        every mean curve over the scene needs them)."""
        own = _thresholds(self.scores)
        return own, self.kept(own)


def _precision_recall(
    tp: np.ndarray, fp: np.ndarray, fn: np.ndarray, max_results: int | None
) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall from counts (see the module docstring)."""
    precision = np.where(tp + fp > 0, tp / np.maximum(tp + fp, 1), 1.0)
    denom = tp + fn if max_results is None else np.minimum(max_results, tp + fn)
    recall = np.where(denom > 0, tp / np.maximum(denom, 1), 1.0)
    return precision, recall


def _thresholds(scores: np.ndarray) -> np.ndarray:
    """``+inf`` then the distinct values of ``scores``, descending. (np.unique would do, but
    it imports numpy.ma, a tenth of evaluate's start-up.)"""
    s = np.sort(np.asarray(scores, float))[::-1]
    distinct = np.ones(len(s), bool)
    distinct[1:] = s[1:] != s[:-1]
    return np.concatenate([[np.inf], s[distinct]])


def scene_curve(
    distances: np.ndarray,
    scores: np.ndarray,
    occlusion: np.ndarray,
    *,
    threshold: float,
    max_occlusion: float,
) -> SceneCurve:
    """Classify a scene's results for every number of kept results.

    Args:
        distances: (|P|, |T|) pose distances between results and true poses (mm).
        scores: (|P|,) result scores (finite).
        occlusion: (|T|,) occlusion rates of the true poses (NaN: unknown, to find).
        threshold: The match threshold (mm), inclusive.
        max_occlusion: True poses up to this occlusion rate (inclusive) are to find.
    """
    D = np.asarray(distances, float)
    n_p, n_t = D.shape
    occ = np.asarray(occlusion, float)
    to_find = ~(occ > max_occlusion)
    n_find = int(to_find.sum())
    # Python's sort, which the reference uses, is stable: equal scores stay in file order.
    order = np.argsort(-np.asarray(scores, float), kind="stable")
    sorted_scores = np.asarray(scores, float)[order]
    tp = np.zeros(n_p + 1, int)
    fp = np.zeros(n_p + 1, int)
    fn = np.full(n_p + 1, n_find)
    if n_p == 0:
        return SceneCurve(sorted_scores, tp, fp, fn, n_find)
    if n_t == 0:
        fp[1:] = np.arange(1, n_p + 1)
        return SceneCurve(sorted_scores, tp, fp, fn, n_find)
    D = D[order]
    nearest_t = D.argmin(axis=1)  # n_T(p)
    matched = D[np.arange(n_p), nearest_t] <= threshold
    # nearest[k - 1, t]: index of n_P(t) among the first k results. A later result takes over
    # only if strictly nearer (the first of equally near ones stays, as argmin does).
    running = np.minimum.accumulate(D, axis=0)
    better = np.zeros_like(D, dtype=bool)
    better[0] = True
    better[1:] = D[1:] < running[:-1]
    del running
    index_type = np.int32 if n_p < 2**31 else np.int64
    rows = np.arange(n_p, dtype=index_type)[:, None]
    nearest = np.maximum.accumulate(np.where(better, rows, 0), axis=0)
    del better
    # back[k - 1, t]: n_P(t) matches t back (t is its nearest true pose, within the
    # threshold). Such t and the results that are n_P(n_T(p)) and match are one to one, so
    # counting over the true poses gives TP and the good results without any |P| x |P| table.
    back = (nearest_t[nearest] == np.arange(n_t)[None, :]) & matched[nearest]
    del nearest
    good = back.sum(axis=1)
    tp[1:] = back[:, to_find].sum(axis=1)
    fp[1:] = np.arange(1, n_p + 1) - good
    fn[1:] = n_find - tp[1:]
    return SceneCurve(sorted_scores, tp, fp, fn, n_find)


def average_precision(precision: np.ndarray, recall: np.ndarray) -> float:
    """``sum p_i (r_i - r_(i-1))`` with ``r_0 = 0``, no interpolation."""
    r = np.asarray(recall, float)
    return float(np.sum(np.asarray(precision, float) * np.diff(r, prepend=0.0)))


@dataclass(frozen=True)
class Summary:
    """Scores over a set of scenes (see the module docstring).

    Attributes:
        ap: AP of the mean curve.
        ap_n: AP with at most n results per scene, per n.
        mean_scene_ap: Mean of the scenes' own APs (the authors' MAP).
        best_f1: Best F1 along the mean curve.
        precision, recall: The mean curve, one point per threshold.
        scenes: Number of scenes averaged.
        tp, fp, fn: Totals with every result kept.
    """

    ap: float
    ap_n: dict[int, float]
    mean_scene_ap: float
    best_f1: float
    precision: np.ndarray
    recall: np.ndarray
    scenes: int
    tp: int
    fp: int
    fn: int


def mean_curve(
    curves: Sequence[SceneCurve], max_results: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The mean precision and recall at ``+inf`` and every distinct score of any scene."""
    return _Steps.of(curves).mean_curve(max_results)


@dataclass(frozen=True)
class _Steps:
    """Every scene's own steps end to end, so that a mean curve is a few array operations
    whatever the number of scenes.

    Attributes:
        tp, fp, fn: Every scene's counts, concatenated.
        base: Per step, where its scene's counts start in ``tp``.
        kept: Per step, the number of results its scene keeps there.
        at: Per step, its index among the thresholds of all scenes.
        first: Per step, True where a scene's steps start.
        starts: Where each scene's steps start.
        count: Number of thresholds of all scenes (``+inf`` included).
        scenes: Number of scenes.
    """

    tp: np.ndarray
    fp: np.ndarray
    fn: np.ndarray
    base: np.ndarray
    kept: np.ndarray
    at: np.ndarray
    first: np.ndarray
    starts: np.ndarray
    count: int
    scenes: int

    @classmethod
    def of(cls, curves: Sequence[SceneCurve]) -> _Steps:
        thresholds = _thresholds(np.concatenate([c.scores for c in curves] or [np.zeros(0)]))
        sizes = np.array([len(c.tp) for c in curves], int)
        steps = np.array([len(c.steps[0]) for c in curves], int)
        starts = np.cumsum(steps) - steps
        first = np.zeros(int(steps.sum()), bool)
        first[starts[steps > 0]] = True
        own = np.concatenate([c.steps[0] for c in curves] or [np.zeros(0)])
        kept = np.concatenate([c.steps[1] for c in curves] or [np.zeros(0, int)])
        offsets = np.cumsum(sizes) - sizes

        def counts(name: str) -> np.ndarray:
            return np.concatenate([getattr(c, name) for c in curves] or [np.zeros(0, int)])

        return cls(
            tp=counts("tp"),
            fp=counts("fp"),
            fn=counts("fn"),
            base=np.repeat(offsets, steps),
            kept=kept.astype(int),
            # A scene's point changes only at its own thresholds (a subset of all of them).
            at=np.searchsorted(-thresholds, -own),
            first=first,
            starts=starts,
            count=len(thresholds),
            scenes=len(curves),
        )

    def points(self, max_results: int | None) -> tuple[np.ndarray, np.ndarray]:
        """Every step's precision and recall."""
        k = self.kept if max_results is None else np.minimum(self.kept, max_results)
        k = self.base + k
        return _precision_recall(self.tp[k], self.fp[k], self.fn[k], max_results)

    def within(self, x: np.ndarray) -> np.ndarray:
        """``x`` minus its previous step in the same scene (0 before a scene's first)."""
        d = np.empty_like(x)
        d[0:1] = x[0:1]
        d[1:] = x[1:] - x[:-1]
        d[self.first] = x[self.first]
        return d

    def mean_curve(self, max_results: int | None) -> tuple[np.ndarray, np.ndarray]:
        """See :func:`mean_curve`: each scene's steps are added where they happen and
        summed up, instead of evaluating every scene at every threshold."""
        if not self.scenes:
            return np.ones(1), np.ones(1)
        p, r = self.points(max_results)
        precision = np.bincount(self.at, weights=self.within(p), minlength=self.count)
        recall = np.bincount(self.at, weights=self.within(r), minlength=self.count)
        return np.cumsum(precision) / self.scenes, np.cumsum(recall) / self.scenes

    def scene_aps(self) -> np.ndarray:
        """Each scene's AP along its own curve (:func:`average_precision`)."""
        if not self.scenes:
            return np.zeros(0)
        p, r = self.points(None)
        return np.add.reduceat(p * self.within(r), self.starts)


def summarise(curves: Sequence[SceneCurve], *, max_results: Sequence[int] = ()) -> Summary:
    """AP, AP_n, mean scene AP and best F1 over ``curves`` (see the module docstring)."""
    steps = _Steps.of(curves)
    precision, recall = steps.mean_curve(None)
    ap_n = {int(n): average_precision(*steps.mean_curve(int(n))) for n in max_results}
    scene_aps = steps.scene_aps()
    f1 = np.where(
        precision + recall > 0, 2 * precision * recall / np.maximum(precision + recall, 1e-300), 0
    )
    return Summary(
        ap=average_precision(precision, recall),
        ap_n=ap_n,
        # No scene (an object neither in the ground truth nor in the results): nothing to
        # find and nothing found, which the authors' conventions score 1, as the mean curve.
        mean_scene_ap=float(np.mean(scene_aps)) if len(scene_aps) else 1.0,
        best_f1=float(f1.max()),
        precision=precision,
        recall=recall,
        scenes=len(curves),
        tp=int(sum(c.tp[-1] for c in curves)),
        fp=int(sum(c.fp[-1] for c in curves)),
        fn=int(sum(c.fn[-1] for c in curves)),
    )
