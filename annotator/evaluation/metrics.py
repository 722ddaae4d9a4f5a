"""TP/FP/FN, precision, recall, recall with at most n results, AP and AP_n (paper section 5).

Definitions, per scene and object, with ``T`` the true poses, ``T_o`` those of interest
(occlusion rate below ``max_occlusion``), ``P`` the results, ``d`` the pose distance,
``m(p, t) = d(p, t) < threshold`` and ``n_S(q)`` the pose of ``S`` nearest to ``q``:

- ``n_T`` is taken over *all* true poses ``T``, so that a result on an instance of no interest
  that matches it (mutually) is neither a TP nor an FP, as the paper states;
- TP = {(p, t) in P x T_o : m(p, t), p = n_P(t), t = n_T(p)} (mutual nearest neighbours);
- FP = {p in P : not m(p, n_T(p)) or n_P(n_T(p)) != p} (so duplicates are FP);
- FN = {t in T_o : not m(t, n_P(t)) or n_T(n_P(t)) != t};
- precision = TP / (TP + FP), recall = TP / (TP + FN) = TP / |T_o|;
- recall with at most n results = TP / min(n, |T_o|), P being the n best-scored results.

Curves: the results are ranked by decreasing score and the sets are recomputed for every
prefix (every score threshold). A scene's interpolated precision at recall r is the best
precision at any threshold reaching recall >= r (0 if none), on a grid of 101 recall levels.
The *mean curve* averages that over the scenes having instances of interest; **AP** is the
area under the mean curve; **AP_n** is the same with every scene limited to its n best results
and recall measured as recall with at most n results; *mean scene AP* averages the per-scene
areas; *best F1* is the best ``2PR / (P + R)`` along the mean curve. A scene without instance of
interest counts only through its false positives: it adds no recall point (it is excluded from
the mean curve), which is the usual convention.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

RECALL_GRID = np.linspace(0.0, 1.0, 101)


@dataclass(frozen=True)
class SceneCounts:
    """TP/FP/FN of one scene and object for each prefix of the score-ranked results."""

    tp: np.ndarray  # (K+1,) for prefixes of 0..K results
    fp: np.ndarray
    n_interest: int

    @property
    def fn(self) -> np.ndarray:
        return self.n_interest - self.tp


def scene_counts(
    distances: np.ndarray, scores: np.ndarray, interest: np.ndarray, threshold: float
) -> SceneCounts:
    """Counts for every prefix of the results ranked by decreasing score.

    Args:
        distances: (|P|, |T|) pose distances between results and true poses.
        scores: (|P|,) result scores.
        interest: (|T|,) bool, the instances of interest.
        threshold: match threshold (same unit as distances).
    """
    n_p, n_t = distances.shape
    interest = np.asarray(interest, bool)
    tp = np.zeros(n_p + 1, int)
    fp = np.zeros(n_p + 1, int)
    if n_p == 0:
        return SceneCounts(tp, fp, int(interest.sum()))
    order = np.argsort(-np.asarray(scores, float), kind="stable")
    D = distances[order]
    if n_t == 0:
        fp[1:] = np.arange(1, n_p + 1)
        return SceneCounts(tp, fp, 0)
    nT = D.argmin(axis=1)  # n_T(p): does not depend on the prefix
    dT = D[np.arange(n_p), nT]
    for k in range(1, n_p + 1):
        nP = D[:k].argmin(axis=0)  # n_P(t) within the k best results
        mutual = nP[nT[:k]] == np.arange(k)
        matched = dT[:k] < threshold
        good = mutual & matched
        tp[k] = int(np.sum(good & interest[nT[:k]]))
        fp[k] = int(np.sum(~good))
    return SceneCounts(tp, fp, int(interest.sum()))


def precision_recall(
    c: SceneCounts, *, max_results: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Precision and recall for each non-empty prefix (recall with at most n if given)."""
    k = np.arange(1, len(c.tp))
    if max_results is not None:
        k = k[k <= max_results]
    tp, fp = c.tp[k], c.fp[k]
    precision = np.where(tp + fp > 0, tp / np.maximum(tp + fp, 1), 1.0)
    denom = c.n_interest if max_results is None else min(max_results, c.n_interest)
    recall = tp / denom if denom > 0 else np.zeros_like(precision)
    return precision, recall


def interpolated_precision(precision: np.ndarray, recall: np.ndarray) -> np.ndarray:
    """Best precision reaching each recall level of :data:`RECALL_GRID` (0 where unreached)."""
    out = np.zeros(len(RECALL_GRID))
    for i, r in enumerate(RECALL_GRID):
        ok = recall >= r - 1e-12
        out[i] = precision[ok].max() if np.any(ok) else 0.0
    return out


@dataclass(frozen=True)
class Summary:
    """Aggregated metrics over scenes."""

    ap: float
    ap_n: dict[int, float]
    mean_scene_ap: float
    best_f1: float
    mean_curve: np.ndarray  # precision over RECALL_GRID
    scenes: int
    tp: int
    fp: int
    fn: int


def _area(curve: np.ndarray) -> float:
    return (
        float(np.trapezoid(curve, RECALL_GRID))
        if hasattr(np, "trapezoid")
        else float(np.trapezoid(curve, RECALL_GRID))
    )


def summarise(counts: Sequence[SceneCounts], *, max_results: Sequence[int] = ()) -> Summary:
    """AP, AP_n, mean per-scene AP and best F1 over scenes (see the module docstring)."""
    scored = [c for c in counts if c.n_interest > 0]
    curves = [interpolated_precision(*precision_recall(c)) for c in scored]
    mean = np.mean(curves, axis=0) if curves else np.zeros(len(RECALL_GRID))
    ap_n = {}
    for n in max_results:
        cn = [interpolated_precision(*precision_recall(c, max_results=n)) for c in scored]
        ap_n[int(n)] = _area(np.mean(cn, axis=0)) if cn else 0.0
    f1 = np.where(
        mean + RECALL_GRID > 0, 2 * mean * RECALL_GRID / np.maximum(mean + RECALL_GRID, 1e-12), 0.0
    )
    return Summary(
        ap=_area(mean),
        ap_n=ap_n,
        mean_scene_ap=float(np.mean([_area(c) for c in curves])) if curves else 0.0,
        best_f1=float(f1.max()),
        mean_curve=mean,
        scenes=len(scored),
        tp=int(sum(c.tp[-1] for c in counts)),
        fp=int(sum(c.fp[-1] for c in counts)),
        fn=int(sum(c.fn[-1] for c in counts)),
    )
