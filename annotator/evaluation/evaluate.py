"""Putting it together: match results to ground truth per scene and object, aggregate."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from annotator.evaluation.metrics import RECALL_GRID, SceneCounts, Summary, scene_counts, summarise
from annotator.evaluation.readers import GroundTruth, PoseSet, Table


@dataclass(frozen=True)
class Options:
    max_occlusion: float = 0.5
    max_results: tuple[int, ...] = (1, 3)
    threshold_mm: float | None = None  # default: threshold_fraction * diameter
    threshold_fraction: float = 0.1


@dataclass
class Report:
    per_object: dict[str, Summary]
    overall: Summary
    thresholds: dict[str, float]
    options: Options

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
                    "recall": RECALL_GRID.round(3).tolist(),
                    "precision": x.mean_curve.round(5).tolist(),
                },
            }

        return {
            "options": {
                "max_occlusion": self.options.max_occlusion,
                "max_results": list(self.options.max_results),
            },
            "thresholds_mm": self.thresholds,
            "overall": s(self.overall),
            "per_object": {k: s(v) for k, v in self.per_object.items()},
        }


def evaluate(gt: GroundTruth, results: Table, options: Options = Options()) -> Report:
    """Score ``results`` against ``gt`` (see :mod:`annotator.evaluation.metrics`)."""
    thresholds = {
        name: options.threshold_mm
        if options.threshold_mm is not None
        else options.threshold_fraction * sp.diameter
        for name, sp in gt.spaces.items()
    }
    counts: dict[str, list[SceneCounts]] = {name: [] for name in gt.spaces}
    for scene in gt.scenes:
        for name, space in gt.spaces.items():
            g = gt.poses.get((scene, name), PoseSet())
            r = results.get((scene, name), PoseSet())
            if not g.R and not r.R:
                continue
            Rg, tg, occ = g.arrays()
            Rr, tr, score = r.arrays()
            D = space.distance_matrix(Rr, tr, Rg, tg)
            interest = ~(occ >= options.max_occlusion)  # NaN (unknown) counts as of interest
            counts[name].append(scene_counts(D, score, interest, thresholds[name]))
    n = options.max_results
    per_object = {name: summarise(c, max_results=n) for name, c in counts.items()}
    overall = summarise([c for cs in counts.values() for c in cs], max_results=n)
    return Report(per_object, overall, thresholds, options)


def format_table(report: Report, *, per_object: bool = True) -> str:
    """A table like the paper's table 3: one row per object (if ``per_object``) and ``all``."""
    ns = list(report.options.max_results)
    head = (
        ["object", "AP"]
        + [f"AP_{n}" for n in ns]
        + ["scene AP", "best F1", "TP", "FP", "FN", "threshold"]
    )
    rows = []
    objects = list(report.per_object.items()) if per_object else []
    for name, s in objects + [("all", report.overall)]:
        thr = f"{report.thresholds[name]:.2f} mm" if name in report.thresholds else "-"
        rows.append(
            [name, f"{s.ap:.3f}"]
            + [f"{s.ap_n[n]:.3f}" for n in ns]
            + [f"{s.mean_scene_ap:.3f}", f"{s.best_f1:.3f}", str(s.tp), str(s.fp), str(s.fn), thr]
        )
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]

    def line(r: list[str]) -> str:
        return "  ".join(
            c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))
        )

    return "\n".join([line(head), line(["-" * w for w in widths])] + [line(r) for r in rows])


def plot_curves(report: Report, path: str | Path) -> None:
    """Mean precision/recall curves per object to a PNG (matplotlib, no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from annotator.io.atomic import write_bytes

    fig, ax = plt.subplots(figsize=(6, 4.5), dpi=120)
    for name, s in report.per_object.items():
        if s.scenes:
            ax.plot(RECALL_GRID, s.mean_curve, label=f"{name} (AP {s.ap:.3f})")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
    ax.set_title(
        f"mean precision/recall over scenes (max occlusion {report.options.max_occlusion:g})"
    )
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    plt.close(fig)
    write_bytes(path, buf.getvalue())


def annotations_as_results(root: Path, gt: GroundTruth) -> Table:
    """annotation.json poses as results (score = 1 / (1 + uncertainty_mm)): how good is the
    auto-annotation against gt.json."""
    from annotator.dataset import load_dataset, read_poses

    ds = load_dataset(root)
    table: Table = {}
    for sc in ds.scenes():
        if not sc.annotation_path.exists():
            continue
        for p in read_poses(sc.annotation_path):
            ps = table.setdefault((sc.id, p.object), PoseSet())
            ps.R.append(p.R)
            ps.t.append(p.t)
            unc = p.extra.get("uncertainty_mm")
            ps.values.append(1.0 / (1.0 + float(unc)) if unc is not None else 0.0)
    return table


def per_instance_errors(root: Path) -> list[dict[str, Any]]:
    """For each annotated instance with a true pose: the pose error (mm, the paper's distance),
    the estimated uncertainty, the diameter and the flags."""
    from annotator.dataset import load_dataset, read_poses
    from annotator.symmetry import PoseSpace

    ds = load_dataset(root)
    spaces = {n: PoseSpace.from_moments(o.mesh.moments, o.symmetry) for n, o in ds.objects.items()}
    out = []
    for sc in ds.scenes():
        if not (sc.annotation_path.exists() and sc.gt_path.exists()):
            continue
        gt = {p.key: p for p in read_poses(sc.gt_path)}
        for p in read_poses(sc.annotation_path):
            g = gt.get(p.key)
            if g is None:
                continue
            sp = spaces[p.object]
            err = float(sp.distance(p.R[None], p.t[None], g.R[None], g.t[None])[0])
            occ = g.extra.get("occlusion", {}) or {}
            out.append(
                {
                    "scene": sc.id,
                    "instance": p.key,
                    "error_mm": err,
                    "uncertainty_mm": p.extra.get("uncertainty_mm"),
                    "diameter_mm": sp.diameter,
                    "occlusion": occ.get("rate") if isinstance(occ, dict) else None,
                    "flags": p.extra.get("flags", []),
                }
            )
    return out
