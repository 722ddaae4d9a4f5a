"""Putting it together: match results to ground truth per scene and object, aggregate.

Which scenes count, per object: every ground-truth scene in which the object has a true pose
or a result (a scene where it neither appears nor is reported says nothing about it), or, with
``only_scenes_with_results``, only those the results mention (as the authors' code, which
walks the results folder). A scene counted without any result is one where nothing was found.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from annotator.errors import UserError
from annotator.evaluation.metrics import SceneCurve, Summary, scene_curve, summarise
from annotator.formats.base import GroundTruth, PoseResults, PoseSet
from annotator.symmetry.space import MATCH_THRESHOLD_FRACTION
from annotator.values import number, of_type, whole


@dataclass(frozen=True)
class EvaluationSettings:
    """Evaluation settings (see :mod:`annotator.evaluation.metrics`).

    Attributes:
        max_occlusion: True poses up to this occlusion rate (inclusive) are to find.
        max_results: The n of each AP_n.
        threshold_mm: Match threshold in mm for every object.
        threshold_fraction: Match threshold as a fraction of each object's diameter. With
            neither, the dataset's own threshold where it has one (the paper's files carry
            one), else :data:`MATCH_THRESHOLD_FRACTION` of the diameter.
        only_scenes_with_results: Score only the scenes the results mention.

    >>> EvaluationSettings(threshold_mm=5.0).max_results
    (1, 3)
    >>> EvaluationSettings(threshold_mm=5.0, threshold_fraction=0.1)
    Traceback (most recent call last):
    ...
    annotator.errors.UserError: threshold_mm and threshold_fraction cannot be given together
    """

    max_occlusion: float = 0.5
    max_results: tuple[int, ...] = (1, 3)
    threshold_mm: float | None = None
    threshold_fraction: float | None = None
    only_scenes_with_results: bool = False

    def __post_init__(self) -> None:
        # What `annotator evaluate` refuses, refused here in the same words.
        set_ = object.__setattr__
        set_(self, "max_occlusion", number(self.max_occlusion, name="max_occlusion", low=0, high=1))
        of_type(
            self.max_results, (tuple, list), name="max_results", what="a tuple of whole numbers"
        )
        set_(
            self,
            "max_results",
            tuple(whole(n, name="max_results", low=1) for n in self.max_results),
        )
        for name in ("threshold_mm", "threshold_fraction"):
            value = getattr(self, name)
            if value is not None:
                set_(self, name, number(value, name=name, low=0, above=True))
        if self.threshold_mm is not None and self.threshold_fraction is not None:
            raise UserError("threshold_mm and threshold_fraction cannot be given together")


@dataclass
class EvaluationReport:
    """The scores of one evaluation (:func:`evaluate`).

    Attributes:
        per_object: AP, AP_n, mean scene AP, best F1, TP/FP/FN and the mean
            precision/recall curve, per object name.
        overall: The same over every object.
        thresholds: The match threshold used per object (mm).
        options: The options it was made with.
        unscored_scenes: Ground-truth scenes left out (``only_scenes_with_results``).

    >>> from annotator import read_ground_truth, annotations_as_results, evaluate
    >>> gt = read_ground_truth("sample_scenes")
    >>> report = evaluate(gt, annotations_as_results("sample_scenes", gt), EvaluationSettings())
    >>> round(report.overall.ap, 3), sorted(report.per_object)
    (1.0, ['bracket', 'brick', 'cylinder'])
    """

    per_object: dict[str, Summary]
    overall: Summary
    thresholds: dict[str, float]
    options: EvaluationSettings
    unscored_scenes: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        def s(x: Summary) -> dict[str, Any]:
            return {
                "AP": x.ap,
                **{f"AP_{n}": v for n, v in x.ap_n.items()},
                "mean_scene_AP": x.mean_scene_ap,
                "best_F1": x.best_f1,
                "scenes": x.scenes,
                "TP": x.tp,
                "FP": x.fp,
                "FN": x.fn,
                "mean_curve": {
                    "recall": x.recall.round(6).tolist(),
                    "precision": x.precision.round(6).tolist(),
                },
            }

        return {
            "options": {
                "max_occlusion": self.options.max_occlusion,
                "max_results": list(self.options.max_results),
                "only_scenes_with_results": self.options.only_scenes_with_results,
            },
            "thresholds_mm": self.thresholds,
            "overall": s(self.overall),
            "per_object": {k: s(v) for k, v in self.per_object.items()},
        }


def thresholds_for(gt: GroundTruth, options: EvaluationSettings) -> dict[str, float]:
    """The match threshold (mm) of each object."""
    out = {}
    for name, sp in gt.spaces.items():
        if options.threshold_mm is not None:
            out[name] = options.threshold_mm
        elif options.threshold_fraction is not None:
            out[name] = options.threshold_fraction * sp.diameter
        elif name in gt.thresholds:
            out[name] = gt.thresholds[name]
        else:
            out[name] = MATCH_THRESHOLD_FRACTION * sp.diameter
    return out


def evaluate(
    gt: GroundTruth, results: PoseResults, options: EvaluationSettings = EvaluationSettings()
) -> EvaluationReport:
    """Score ``results`` against ``gt`` (see :mod:`annotator.evaluation.metrics`).

    >>> from pathlib import Path
    >>> from annotator import annotations_as_results, read_ground_truth
    >>> gt = read_ground_truth("sample_scenes")
    >>> report = evaluate(gt, annotations_as_results(Path("sample_scenes"), gt))
    >>> round(report.overall.ap, 3), report.overall.tp, report.overall.fp
    (1.0, 35, 1)
    """
    of_type(gt, GroundTruth, name="gt", what="a GroundTruth (annotator.read_ground_truth)")
    of_type(results, PoseResults, name="results", what="PoseResults (annotator.read_results)")
    of_type(options, EvaluationSettings, name="options", what="annotator.EvaluationSettings")
    thresholds = thresholds_for(gt, options)
    scenes = [s for s in gt.scenes if s in results.scenes or not options.only_scenes_with_results]
    curves: dict[str, list[SceneCurve]] = {name: [] for name in gt.spaces}
    for scene in scenes:
        for name, space in gt.spaces.items():
            if gt.targets is not None and (scene, name) not in gt.targets:
                continue  # not a target of the dataset: neither to find nor scored
            g = gt.poses.get((scene, name))
            r = results.poses.get((scene, name))
            if g is None and r is None:
                continue
            Rg, tg, occ = (g or PoseSet()).arrays()
            Rr, tr, score = (r or PoseSet()).arrays()
            D = space.distance_matrix(Rr, tr, Rg, tg)
            curves[name].append(
                scene_curve(
                    D,
                    score,
                    occ,
                    threshold=thresholds[name],
                    max_occlusion=options.max_occlusion,
                )
            )
    n = options.max_results
    per_object = {name: summarise(c, max_results=n) for name, c in curves.items()}
    if len(per_object) == 1:
        overall = next(iter(per_object.values()))  # the same curves: the same summary
    else:
        overall = summarise([c for cs in curves.values() for c in cs], max_results=n)
    unscored = [s for s in gt.scenes if s not in scenes]
    return EvaluationReport(per_object, overall, thresholds, options, unscored)


def format_table(
    report: EvaluationReport,
    *,
    per_object: bool = True,
    others: dict[str, EvaluationReport] | None = None,
) -> str:
    """A table like the paper's table 3: one row per object (if ``per_object``) and ``all``.

    With ``others`` (label -> report, e.g. ``{"real": ..., "twin": ...}`` where ``report`` is
    the first of them), their rows follow, each labelled, for a side-by-side comparison."""
    reports = others or {"": report}
    ns = list(report.options.max_results)
    head = (
        (["data"] if others else [])
        + ["object", "AP"]
        + [f"AP_{n}" for n in ns]
        + ["scene AP", "best F1", "TP", "FP", "FN", "scenes", "threshold"]
    )
    single = len(report.per_object) == 1 and not per_object
    rows = []
    for label, rep in reports.items():
        objects = list(rep.per_object.items()) if per_object else []
        for name, s in objects + [("all", rep.overall)]:
            key = next(iter(rep.per_object)) if single and name == "all" else name
            thr = f"{rep.thresholds[key]:.2f} mm" if key in rep.thresholds else "-"
            rows.append(
                ([label] if others else [])
                + [key, f"{s.ap:.4f}"]
                + [f"{s.ap_n[n]:.4f}" for n in ns]
                + [f"{s.mean_scene_ap:.4f}", f"{s.best_f1:.4f}"]
                + [str(s.tp), str(s.fp), str(s.fn), str(s.scenes), thr]
            )
    text_cols = 2 if others else 1
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]

    def line(r: list[str]) -> str:
        return "  ".join(
            c.ljust(w) if i < text_cols else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))
        )

    return "\n".join([line(head), line(["-" * w for w in widths])] + [line(r) for r in rows])


def plot_curves(report: EvaluationReport, path: str | Path) -> None:
    """Mean precision/recall curves per object to a PNG (matplotlib, no display needed)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from annotator.io.atomic import write_bytes

    fig, ax = plt.subplots(figsize=(6, 4.5), dpi=120)
    for name, s in report.per_object.items():
        if s.scenes:
            ax.step(s.recall, s.precision, where="post", label=f"{name} (AP {s.ap:.3f})")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
    ax.set_title(
        f"mean precision/recall over scenes (max occlusion {report.options.max_occlusion:g})"
    )
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    plt.close(fig)
    write_bytes(path, buf.getvalue())


def per_instance_errors(root: Path) -> list[dict[str, Any]]:
    """For each annotated instance with a true pose: the pose error (mm, the paper's distance),
    the estimated uncertainty, the diameter and the flags. In a sequence the error is the
    median over the frames both files pose of the error as each frame's rig sees the part
    (what an export of that frame holds), whatever the scene frame's own error."""
    from annotator.dataset import load_dataset
    from annotator.dataset.poses import read_pose_file
    from annotator.dataset.records import InstanceAnnotation, SceneAnnotation, frames_from_json
    from annotator.geometry.transforms import invert
    from annotator.symmetry import PoseSpace

    ds = load_dataset(root)
    spaces = {n: PoseSpace.from_moments(o.mesh.moments, o.symmetry) for n, o in ds.objects.items()}
    out = []
    for sc in ds.scenes():
        if not (sc.annotation_path.exists() and sc.gt_path.exists()):
            continue
        true_poses, top = read_pose_file(sc.gt_path)
        gt = {p.key: InstanceAnnotation.from_pose(p) for p in true_poses}
        ann = SceneAnnotation.read(sc.annotation_path)
        pairs: list[tuple[np.ndarray, np.ndarray]] | None = None  # a fixed rig: as they are
        if ds.rig.moving:
            truth = frames_from_json(top.get("frames"), sc.gt_path)
            found = ann.frames
            pairs = []
            for name, f in sorted(found.items()):
                mine, true = f.scene_T_rig, truth[name].scene_T_rig if name in truth else None
                if mine is not None and true is not None:
                    pairs.append((invert(mine), invert(true)))
        for i in ann.instances:
            g = gt.get(i.key)
            if g is None or pairs == []:
                continue
            sp = spaces[i.object]
            A = i.T[None] if pairs is None else np.stack([a @ i.T for a, _ in pairs])
            B = g.T[None] if pairs is None else np.stack([b @ g.T for _, b in pairs])
            errs = sp.distance(A[:, :3, :3], A[:, :3, 3], B[:, :3, :3], B[:, :3, 3])
            out.append(
                {
                    "scene": sc.id,
                    "instance": i.key,
                    "error_mm": float(np.median(errs)),
                    "uncertainty_mm": i.uncertainty_mm,
                    "diameter_mm": sp.diameter,
                    "occlusion": g.occlusion_rate,
                    "flags": i.flags,
                }
            )
    return out
