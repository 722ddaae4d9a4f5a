"""BOP's pose scores (BOP Challenge 2019 onwards): VSD, MSSD, MSPD and their average recall.

The definitions are bop_toolkit's (``scripts/eval_bop19_pose.py`` with ``eval_calc_errors.py``,
``eval_calc_scores.py``, ``pose_error.py``, ``pose_matching.py`` and ``score.py``), written
again on arrays, on the records :mod:`annotator.formats.bop_images` reads from a dataset and
a result file.

- **Targets.** Per (image, object), the targets file gives ``inst_count``. The estimates
  scored are the ``inst_count`` of that object with the highest scores (bop_toolkit's
  ``n_top = -1``); the true poses to find are the ``inst_count`` of that object most visible
  in the image (``visib_gt_min = -1``). Ties keep the file's order.
- **Errors** of an estimate against each true pose of its object in the image:

  - MSSD: the largest distance between the model points in the two poses, least over the
    object's symmetries, divided by the diameter; infinite when the two centres are a
    diameter or more apart.
  - MSPD: the same in pixels after projection, scaled to an image 640 pixels wide.
  - VSD: the share of the union of the two visible surfaces where they are not within
    ``tau`` (divided by the diameter) of each other, one value per ``tau``; visibility from
    the depth image with tolerance ``delta`` (15 mm, 5 for ITODD; pixels without depth count
    as visible); 1 when the two bounding spheres' projections do not meet.

- **Matching.** Per (image, object), estimates in decreasing score each take the valid, not
  yet taken true pose of least error, strictly below the threshold.
- **Recall** is the matched true poses over all true poses to find in the dataset, per
  threshold (and ``tau`` for VSD); a metric's AR is the mean over its settings
  (:data:`CORRECT_TH`, :data:`MSPD_TH_PX`, :data:`VSD_TAUS`), and AR the mean of the three.

Symmetries are bop_toolkit's too: every listed discrete element as written (not snapped),
continuous ones sampled so that consecutive samples are at most
:data:`MAX_SYM_DISC_STEP` x pi apart, combined with each discrete one. Poses are used as
written, not projected to the nearest rotation, as bop_toolkit does.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from annotator.evaluation.largest_gap import (
    AffineGaps,
    ProjectedGaps,
    clusters_of,
    largest_squared,
)
from annotator.formats.bop_images import VSD_DELTA_MM, BopEstimates, BopImage, BopObject
from annotator.geometry.mesh import Mesh

#: Thresholds of correctness of VSD and MSSD (a fraction), as ``np.arange(0.05, 0.51, 0.05)``
#: in bop_toolkit: the same floats, so that ties fall the same way.
CORRECT_TH = np.arange(0.05, 0.51, 0.05)
#: MSSD's thresholds in mm of BOP 2025's ``bop25_mAP_mm`` (``range(2, 21, 2)`` in
#: bop_toolkit): :mod:`.bop24` scores them, :func:`error_tables` needs the largest.
MSSD_MM_TH = np.arange(2, 21, 2).astype(float)
#: Thresholds of MSPD, in pixels of an image 640 pixels wide.
MSPD_TH_PX = np.arange(5, 51, 5)
#: VSD's misalignment tolerances (a fraction of the diameter).
VSD_TAUS = np.arange(0.05, 0.51, 0.05)
#: MSPD is scaled to an image of this width.
MSPD_REFERENCE_WIDTH_PX = 640.0

METRICS = ("vsd", "mssd", "mspd")


@dataclass
class Bop19Scores:
    """BOP's average recalls, overall and per object id (None where nothing is to be found,
    or, for VSD and AR, without depth images).

    Attributes:
        ar: Mean of the three metrics' ARs.
        metrics: ``"vsd" | "mssd" | "mspd"`` -> AR.
        per_object: object id -> ``{"AR", "vsd", "mssd", "mspd"}``.
        recalls: metric -> recall per setting (thresholds, and taus for VSD, in
            bop_toolkit's order: tau outer, threshold inner).
        targets: True poses to find; ``estimates``: estimates scored.
    """

    ar: float | None
    metrics: dict[str, float | None]
    per_object: dict[int, dict[str, float | None]]
    recalls: dict[str, list[float]]
    targets: int
    estimates: int
    notes: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """The ``"bop19"`` block of ``evaluate --json``."""
        return {
            "AR": self.ar,
            "AR_VSD": self.metrics["vsd"],
            "AR_MSSD": self.metrics["mssd"],
            "AR_MSPD": self.metrics["mspd"],
            "targets": self.targets,
            "estimates": self.estimates,
            "per_object": {
                str(oid): {
                    "AR": v["AR"],
                    "AR_VSD": v["vsd"],
                    "AR_MSSD": v["mssd"],
                    "AR_MSPD": v["mspd"],
                }
                for oid, v in sorted(self.per_object.items())
            },
            "notes": self.notes,
        }


# ---------------------------------------------------------------------------------- errors


def mssd(
    R_e: np.ndarray,
    t_e: np.ndarray,
    R_g: np.ndarray,
    t_g: np.ndarray,
    obj: BopObject,
    *,
    cutoff: float = math.inf,
) -> float:
    """Maximum symmetry-aware surface distance in mm (not divided by the diameter); infinite
    when it is ``cutoff`` or more (an error no threshold of interest accepts).

    The true pose is combined with each symmetry as bop_toolkit combines them
    (``R_g S``, ``R_g t_s + t_g``), as written: a rotation that is not quite orthonormal,
    as BOP's own files have, moves the points as bop_toolkit moves them.

    >>> obj = BopObject(np.eye(3), 1.0, np.eye(3)[None], np.zeros((1, 3)))
    >>> mssd(np.eye(3), np.array([0, 0, 2.0]), np.eye(3), np.zeros(3), obj)
    2.0
    """
    A, b = _symmetric_pose(obj, R_g, t_g)
    gaps = AffineGaps(A - R_e, b - t_e)
    return math.sqrt(_min_max(gaps, obj, cutoff * cutoff))


def mspd(
    R_e: np.ndarray,
    t_e: np.ndarray,
    R_g: np.ndarray,
    t_g: np.ndarray,
    K: np.ndarray,
    obj: BopObject,
    *,
    cutoff: float = math.inf,
) -> float:
    """Maximum symmetry-aware projection distance in pixels (not rescaled); infinite when it
    is ``cutoff`` or more."""
    A, b = _symmetric_pose(obj, R_g, t_g)
    gaps = ProjectedGaps(K @ A, b @ K.T, K @ R_e, K @ t_e)
    return math.sqrt(_min_max(gaps, obj, cutoff * cutoff))


def _symmetric_pose(
    obj: BopObject, R_g: np.ndarray, t_g: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(S, 3, 3), (S, 3): the true pose combined with each symmetry, as bop_toolkit's
    ``R_gt.dot(sym['R'])`` and ``R_gt.dot(sym['t']) + t_gt``."""
    return R_g @ obj.sym_R, obj.sym_t @ R_g.T + t_g


#: Errors past every threshold by this factor are not computed exactly (they match nothing).
_MARGIN = 1.01
#: Points the first pass of :func:`_min_max` looks at.
_SAMPLE_POINTS = 64


@functools.lru_cache(maxsize=256)
def sample_points(N: int) -> np.ndarray:
    """The points of :func:`_min_max`'s first pass, of ``N`` (shared: not to be changed)."""
    return np.linspace(0, N - 1, _SAMPLE_POINTS).astype(int)


def _min_max(gaps: AffineGaps | ProjectedGaps, obj: BopObject, cutoff: float) -> float:
    """min over the symmetries (the rows of ``gaps``) of the largest squared gap over the
    object's points, exactly; infinite when it is ``cutoff`` or more.

    The largest over a sample of points (:func:`sample_points`) is a lower bound for each
    symmetry; symmetries are taken in increasing bound, and one whose bound is not below the
    best exact value so far cannot be the least. Each is computed over the points that can
    hold its largest gap (:func:`largest_squared`)."""
    N = len(obj.points)
    everything = slice(None)
    if N <= 2 * _SAMPLE_POINTS:
        best = float(gaps.squared(everything, obj.points).max(axis=1).min())
        return best if best < cutoff else math.inf
    bound = gaps.squared(everything, obj.points[sample_points(N)]).max(axis=1)
    clusters = clusters_of(obj.points)
    best = math.inf
    for s in np.argsort(bound, kind="stable"):
        floor = float(bound[s])
        if floor >= min(best, cutoff):
            break
        best = min(best, largest_squared(gaps, int(s), clusters, found=floor, stop=best))
    return best if best < cutoff else math.inf


def error_tables(
    image: BopImage, est: BopEstimates, mine: np.ndarray, gts: np.ndarray, obj: BopObject
) -> tuple[np.ndarray, np.ndarray]:
    """(E, G) MSSD in mm and MSPD in pixels (not rescaled) of the estimates ``mine`` against
    the true poses ``gts`` of one object in one image, as :func:`mssd` and :func:`mspd`
    (MSSD infinite when the centres are a diameter or more apart). Errors past every
    threshold of BOP's scores (VSD's and MSSD's fractions, MSSD's millimetres, MSPD's
    pixels) by :data:`_MARGIN` are infinite: no threshold can tell them apart.

    Each pair is computed once per process: BOP 2019's and 2024's scores of one result
    file pair mostly the same estimates with the same true poses, and the second takes the
    first's errors (the same numbers, by the pair's poses, camera and object)."""
    E, G = len(mine), len(gts)
    mm = np.full((E, G), np.inf)
    px = np.full((E, G), np.inf)
    if not E or not G:
        return mm, px
    memo = _pair_memo(obj)
    camera = image.K.tobytes() + str(image.width).encode()
    keys_e = [est.R[e].tobytes() + est.t[e].tobytes() for e in mine]
    keys_g = [camera + image.R[g].tobytes() + image.t[g].tobytes() for g in gts]
    todo = []
    for i, ke in enumerate(keys_e):
        for j, kg in enumerate(keys_g):
            got = memo.get(ke + kg)
            if got is None:
                todo.append(i)
                break
            mm[i, j], px[i, j] = got
    if todo:
        rows = np.asarray(todo)
        mm[rows], px[rows] = _error_tables(image, est, mine[rows], gts, obj)
        if len(memo) > 1_000_000:
            memo.clear()
        for i in todo:
            for j, kg in enumerate(keys_g):
                memo[keys_e[i] + kg] = (float(mm[i, j]), float(px[i, j]))
    return mm, px


def pair_errors() -> dict[tuple[int, bytes, float], dict[bytes, tuple[float, float]]]:
    """The pairs' errors computed so far in this process, per object (as
    :func:`merge_pair_errors` takes them from another process)."""
    return {key: memo for key, (_, memo) in _PAIRS.items()}


def merge_pair_errors(
    objects: dict[int, BopObject],
    found: dict[tuple[int, bytes, float], dict[bytes, tuple[float, float]]],
) -> None:
    """Adds pairs' errors computed by another process (:func:`pair_errors` there, the
    same objects read before it started) to this process's."""
    for obj in objects.values():
        got = found.get(_memo_key(obj))
        if got:
            _pair_memo(obj).update(got)


def _memo_key(obj: BopObject) -> tuple[int, bytes, float]:
    return (id(obj.points), obj.sym_R.tobytes() + obj.sym_t.tobytes(), obj.diameter)


def _pair_memo(obj: BopObject) -> dict[bytes, tuple[float, float]]:
    """The pairs' errors computed so far for an object: by its points (one array per mesh
    file and process, :func:`annotator.geometry.mesh.load_mesh`), symmetries and diameter."""
    key = _memo_key(obj)
    got = _PAIRS.get(key)
    if got is None or got[0] is not obj.points:
        if len(_PAIRS) > 256:
            _PAIRS.clear()
        got = _PAIRS[key] = (obj.points, {})
    return got[1]


_PAIRS: dict[tuple[int, bytes, float], tuple[np.ndarray, dict[bytes, tuple[float, float]]]] = {}


def _error_tables(
    image: BopImage, est: BopEstimates, mine: np.ndarray, gts: np.ndarray, obj: BopObject
) -> tuple[np.ndarray, np.ndarray]:
    E, G = len(mine), len(gts)
    mm = np.full((E, G), np.inf)
    px = np.full((E, G), np.inf)
    scale = MSPD_REFERENCE_WIDTH_PX / image.width
    mm_cut = _MARGIN * max(float(CORRECT_TH[-1]) * obj.diameter, float(MSSD_MM_TH[-1]))
    px_cut = _MARGIN * float(MSPD_TH_PX[-1]) / scale
    K = image.K
    near = np.linalg.norm(est.t[mine][:, None] - image.t[gts][None], axis=2) < obj.diameter
    for j, g in enumerate(gts):
        A, b = _symmetric_pose(obj, image.R[g], image.t[g])
        M, m = K @ A, b @ K.T
        for i, e in enumerate(mine):
            R_e, t_e = est.R[e], est.t[e]
            if near[i, j]:
                got = _min_max(AffineGaps(A - R_e, b - t_e), obj, mm_cut * mm_cut)
                mm[i, j] = math.sqrt(got)
            got = _min_max(ProjectedGaps(M, m, K @ R_e, K @ t_e), obj, px_cut * px_cut)
            px[i, j] = math.sqrt(got)
    return mm, px


def spheres_projections_overlap(radius: float, p1: np.ndarray, p2: np.ndarray) -> bool:
    """bop_toolkit's approximate test that two spheres' projections meet."""
    if p1[2] == 0 or p2[2] == 0:
        return False
    dist = float(np.linalg.norm((p1 / p1[2])[:2] - (p2 / p2[2])[:2]))
    return dist < radius * (1.0 / p1[2] + 1.0 / p2[2])


#: Renders a mesh's z-depth (mm, 0 where it is not seen) over a pixel rectangle
#: ``(x0, y0, x1, y1)`` of an image: ``render(mesh, cam_T_model, K, width, height)`` returns
#: the rectangle and the depth over it, or None when the mesh is out of view.
DepthRenderer = Callable[
    [Mesh, np.ndarray, np.ndarray, int, int],
    "tuple[tuple[int, int, int, int], np.ndarray] | None",
]


def vsd(
    depth_test: np.ndarray,
    K: np.ndarray,
    rendered_e: tuple[tuple[int, int, int, int], np.ndarray] | None,
    rendered_g: tuple[tuple[int, int, int, int], np.ndarray] | None,
    *,
    delta: float,
    taus: Sequence[float] | np.ndarray,
    diameter: float,
) -> list[float]:
    """Visible surface discrepancy per ``tau`` ("step" cost, normalised by the diameter),
    from the depth image (mm, 0: none) and the model's depth rendered in the estimated and
    the true pose (each a rectangle and its depth, see :data:`DepthRenderer`)."""
    boxes = [r[0] for r in (rendered_e, rendered_g) if r is not None]
    if not boxes:
        return [1.0] * len(taus)
    x0, y0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
    x1, y1 = max(b[2] for b in boxes), max(b[3] for b in boxes)

    def crop(r: tuple[tuple[int, int, int, int], np.ndarray] | None) -> np.ndarray:
        out = np.zeros((y1 - y0, x1 - x0), np.float32)
        if r is not None:
            (a, b, c, d), depth = r
            out[b - y0 : d - y0, a - x0 : c - x0] = depth
        return out

    full_x, full_y = _pixel_factors(K, depth_test.shape)
    pre_x, pre_y = full_x[y0:y1, x0:x1], full_y[y0:y1, x0:x1]

    def distance(depth: np.ndarray) -> np.ndarray:
        return np.sqrt((pre_x * depth) ** 2 + (pre_y * depth) ** 2 + depth.astype(np.float64) ** 2)

    dist_test = distance(depth_test[y0:y1, x0:x1])
    dist_e, dist_g = distance(crop(rendered_e)), distance(crop(rendered_g))
    test32 = dist_test.astype(np.float32)

    def visible(d_model: np.ndarray) -> np.ndarray:
        diff = d_model.astype(np.float32) - test32
        return ((diff <= delta) | (dist_test == 0)) & (d_model > 0)

    visib_g = visible(dist_g)
    visib_e = visible(dist_e) | (visib_g & (dist_e > 0))
    inter = visib_g & visib_e
    union_count = int((visib_g | visib_e).sum())
    if union_count == 0:
        return [1.0] * len(taus)
    comp_count = union_count - int(inter.sum())
    dists = np.abs(dist_g[inter] - dist_e[inter]) / diameter
    return [(float(np.sum(dists >= tau)) + comp_count) / float(union_count) for tau in taus]


def _pixel_factors(K: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) ``(x - c_x) / f_x`` and ``(y - c_y) / f_y`` of every pixel, once per camera and
    image size (each pair's VSD slices its rectangle: the same numbers, without a grid and
    two divisions per pair)."""
    key = (K.tobytes(), tuple(shape))
    got = _FACTORS.get(key)
    if got is None:
        xs, ys = np.meshgrid(np.arange(shape[1]), np.arange(shape[0]))
        got = ((xs - K[0, 2]) / np.float64(K[0, 0]), (ys - K[1, 2]) / np.float64(K[1, 1]))
        if len(_FACTORS) > 8:
            _FACTORS.clear()
        _FACTORS[key] = got
    return got


_FACTORS: dict[tuple[bytes, tuple[int, ...]], tuple[np.ndarray, np.ndarray]] = {}


# -------------------------------------------------------------------------------- matching


def greedy_match(errors: np.ndarray, valid: np.ndarray, threshold: float) -> np.ndarray:
    """bop_toolkit's greedy matching (``pose_matching.match_poses``): ``errors`` (E, G) with
    estimates already in decreasing score; each takes the valid free true pose of least error
    strictly below ``threshold`` (on equal errors the first). Returns (E,) the true pose each
    took, -1 for none.

    >>> greedy_match(np.array([[0.1, 0.2], [0.1, 0.2]]), np.ones(2, bool), 0.25)
    array([0, 1])
    """
    return greedy_matches(errors, valid, np.array([threshold], float))[0]


def greedy_matches(errors: np.ndarray, valid: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """:func:`greedy_match` at every threshold at once: ``errors`` (E, G), or (T, E, G) with
    one table per threshold, and ``thresholds`` (T,). Returns (T, E). The estimates take
    their turns in order, each turn settled for every threshold in one step."""
    thresholds = np.asarray(thresholds, float)
    T, (E, G) = len(thresholds), errors.shape[-2:]
    tables = np.broadcast_to(errors, (T, E, G))
    taken = np.repeat(~np.asarray(valid, bool)[None], T, axis=0)
    out = np.full((T, E), -1)
    settings = np.arange(T)
    for i in range(E):
        row = tables[:, i]
        ok = (row < thresholds[:, None]) & ~taken
        # the first of the least errors among those it may take, as bop_toolkit's loop
        g = np.where(ok, row, np.inf).argmin(axis=1)
        hit = ok[settings, g]
        taken[settings[hit], g[hit]] = True
        out[hit, i] = g[hit]
    return out


def matched_count(errors: np.ndarray, valid: np.ndarray, threshold: float) -> int:
    """True poses matched by :func:`greedy_match`."""
    return int(np.sum(greedy_match(errors, valid, threshold) >= 0))


@dataclass
class _Group:
    """One (image, object) target: the error tables of its scored estimates."""

    obj_id: int
    valid: np.ndarray  # (G,) among the image's true poses of this object
    errors: dict[str, np.ndarray]  # metric -> (E, G) or (E, G, taus) for VSD


def _valid(visib: np.ndarray, count: int) -> np.ndarray:
    """The ``count`` most visible (stable on ties), as bop_toolkit's ``visib_gt_min = -1``."""
    order = np.argsort(-visib, kind="stable")
    mask = np.zeros(len(visib), bool)
    mask[order[:count]] = True
    return mask


def _image_groups(
    image: BopImage,
    estimates: BopEstimates | None,
    objects: dict[int, BopObject],
    *,
    depth: np.ndarray | None,
    render: DepthRenderer | None,
    delta: float,
) -> list[_Group]:
    groups = []
    rendered: dict[tuple[int, str, int], Any] = {}
    for oid, count in image.targets.items():
        gts = np.flatnonzero(image.obj_ids == oid)
        obj = objects[oid]
        valid = _valid(image.visib[gts], count)
        if estimates is None:
            ests = np.zeros(0, int)
        else:
            mine = np.flatnonzero(estimates.obj_ids == oid)
            ests = mine[np.argsort(-estimates.scores[mine], kind="stable")][:count]
        E, G = len(ests), len(gts)
        errs = {m: np.full((E, G), np.inf) for m in ("mssd", "mspd")}
        if depth is not None:
            errs["vsd"] = np.ones((E, G, len(VSD_TAUS)))
        scale = MSPD_REFERENCE_WIDTH_PX / image.width
        if E and G:
            mm, px = error_tables(image, estimates, ests, gts, obj)  # type: ignore[arg-type]
            errs["mssd"], errs["mspd"] = mm / obj.diameter, scale * px
        if depth is None or render is None or obj.mesh is None:
            groups.append(_Group(oid, valid, errs))
            continue
        for i, e in enumerate(ests):
            R_e, t_e = estimates.R[e], estimates.t[e]  # type: ignore[union-attr]
            for j, g in enumerate(gts):
                R_g, t_g = image.R[g], image.t[g]
                if not spheres_projections_overlap(0.5 * obj.diameter, t_e, t_g):
                    continue
                ren_e = _rendered(rendered, ("e", e), render, obj.mesh, R_e, t_e, image)
                ren_g = _rendered(rendered, ("g", int(g)), render, obj.mesh, R_g, t_g, image)
                errs["vsd"][i, j] = vsd(
                    depth,
                    image.K,
                    ren_e,
                    ren_g,
                    delta=delta,
                    taus=VSD_TAUS,
                    diameter=obj.diameter,
                )
        groups.append(_Group(oid, valid, errs))
    return groups


def _rendered(
    cache: dict[Any, Any],
    key: tuple[str, int],
    render: DepthRenderer,
    mesh: Mesh,
    R: np.ndarray,
    t: np.ndarray,
    image: BopImage,
) -> Any:
    if key not in cache:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        cache[key] = render(mesh, T, image.K, image.width, image.height)
    return cache[key]


def bop19_scores(
    images: Sequence[BopImage],
    estimates: dict[tuple[int, int], BopEstimates],
    objects: dict[int, BopObject],
    *,
    render: DepthRenderer | None = None,
    delta: float = VSD_DELTA_MM,
    progress: Callable[[], None] | None = None,
    processes: int = 1,
    prepare: Callable[[], None] | None = None,
) -> Bop19Scores:
    """BOP's ARs of ``estimates`` ((scene_id, im_id) -> estimates) on ``images``.

    VSD is computed when every image has a depth image and ``render`` is given; otherwise
    it and AR are None. ``processes``: how many processes share the images
    (:func:`annotator.evaluation.forked.in_processes`) when there are at least
    :data:`PARALLEL_MIN_ESTIMATES` estimates; the numbers do not depend on it. Before they
    do, ``prepare()`` is called and the objects' point clusters are made here, once for
    every process (the renderer's own structures, say, which each would build again).
    """
    with_vsd = render is not None and all(im.depth is not None for im in images)
    metrics = [m for m in METRICS if m != "vsd" or with_vsd]

    def tally(share: Sequence[BopImage], progress: Callable[[], Any] | None) -> _Tally:
        out = _Tally({m: {} for m in metrics})
        for image in share:
            depth = image.depth() if with_vsd and image.depth is not None else None
            groups = _image_groups(
                image,
                estimates.get((image.scene_id, image.im_id)),
                objects,
                depth=depth,
                render=render,
                delta=delta,
            )
            out.add(groups)
            if progress:
                progress()
        out.pairs = pair_errors()
        return out

    many = sum(len(e.scores) for e in estimates.values()) >= PARALLEL_MIN_ESTIMATES
    if processes > 1 and many:
        from annotator.evaluation.forked import in_processes

        for obj in objects.values():
            clusters_of(obj.points)
        if prepare is not None:
            prepare()
        tallies = in_processes(tally, images, processes, progress)
    else:
        tallies = [tally(images, progress)]
    total = _Tally({m: {} for m in metrics})
    for got in tallies:
        total.merge(got)
        merge_pair_errors(objects, got.pairs)
    return _summary(total.tps, total.tars, objects, metrics, total.scored, with_vsd)


#: Estimates from which :func:`bop19_scores` shares the images between processes (below,
#: forking costs more than it saves).
PARALLEL_MIN_ESTIMATES = 400

#: Per metric, its thresholds.
_SETTINGS = {"mssd": CORRECT_TH, "mspd": MSPD_TH_PX, "vsd": CORRECT_TH}


@dataclass
class _Tally:
    """Matched counts of some images: per metric and object, per setting; true poses to
    find per object; estimates scored; and the pairs' errors computed on the way (for BOP
    2024's scores next, in the process that merges this)."""

    tps: dict[str, dict[int, np.ndarray]]
    tars: dict[int, int] = field(default_factory=dict)
    scored: int = 0
    pairs: dict[Any, dict[bytes, tuple[float, float]]] = field(default_factory=dict)

    def add(self, groups: list[_Group]) -> None:
        for grp in groups:
            self.tars[grp.obj_id] = self.tars.get(grp.obj_id, 0) + int(grp.valid.sum())
            self.scored += len(grp.errors["mssd"])
            for m, per_object in self.tps.items():
                got = _matches(grp.errors[m], grp.valid, _SETTINGS[m], vsd=m == "vsd")
                if grp.obj_id in per_object:
                    per_object[grp.obj_id] = per_object[grp.obj_id] + got
                else:
                    per_object[grp.obj_id] = got.astype(np.int64)

    def merge(self, other: _Tally) -> None:
        for oid, n in other.tars.items():
            self.tars[oid] = self.tars.get(oid, 0) + n
        self.scored += other.scored
        for m, per_object in other.tps.items():
            mine = self.tps[m]
            for oid, counts in per_object.items():
                mine[oid] = mine[oid] + counts if oid in mine else counts.copy()


def _matches(
    errors: np.ndarray, valid: np.ndarray, thresholds: np.ndarray, *, vsd: bool
) -> np.ndarray:
    """Matched counts per setting (for VSD: per tau, then per threshold)."""
    if errors.shape[0] == 0 or not valid.any():
        return np.zeros(len(thresholds) * (errors.shape[2] if vsd else 1), np.int64)
    if vsd:
        # settings in bop_toolkit's order: tau outer, threshold inner
        n_taus = errors.shape[2]
        tables = np.repeat(np.moveaxis(errors, 2, 0), len(thresholds), axis=0)
        return (greedy_matches(tables, valid, np.tile(thresholds, n_taus)) >= 0).sum(axis=1)
    return (greedy_matches(errors, valid, thresholds) >= 0).sum(axis=1)


def _summary(
    tps: dict[str, dict[int, np.ndarray]],
    tars: dict[int, int],
    objects: dict[int, BopObject],
    metrics: list[str],
    scored: int,
    with_vsd: bool,
) -> Bop19Scores:
    total = sum(tars.values())
    ars: dict[str, float | None] = {m: None for m in METRICS}
    recalls: dict[str, list[float]] = {}
    for m in metrics:
        hits = sum(tps[m].values(), np.zeros(1, np.int64))
        if total:
            rec = hits / float(total)
            recalls[m] = rec.tolist()
            ars[m] = float(np.mean(rec))
    per_object: dict[int, dict[str, float | None]] = {}
    for oid in sorted(objects):
        row: dict[str, float | None] = {m: None for m in METRICS}
        n = tars.get(oid, 0)
        if n:
            for m in metrics:
                row[m] = float(np.mean(tps[m].get(oid, 0) / float(n)))
        row["AR"] = _mean3(row)
        per_object[oid] = row
    notes = [] if with_vsd else ["VSD not computed (no depth images): AR_VSD and AR are null"]
    return Bop19Scores(_mean3(ars), ars, per_object, recalls, total, scored, notes)


def _mean3(values: dict[str, float | None]) -> float | None:
    got = [values[m] for m in METRICS]
    return None if any(v is None for v in got) else float(np.mean(got))  # type: ignore[arg-type]
