"""Our own dataset format (docs/FORMAT.md) as ground truth and results for the evaluation.

- Ground truth: ``scenes/<id>/gt.json``, or ``annotation.json`` when a scene has no gt.json
  (with the poses a reviewer repaired in review.json applied, see
  :func:`annotator.dataset.review.apply_edits`; a scene a reviewer rejected, or one with a
  rejected instance, whose true pose is then unknown, is left out and counted in the notes);
  occlusion from each instance's ``occlusion.rate`` (or ``occlusion_rate``); symmetries from
  object.yaml (see :mod:`annotator.symmetry.classes`). Millimetres.
- Results: a folder of ``<scene>.json`` lists (millimetres), a BOP CSV (see
  :mod:`annotator.formats.bop`), or, with no results given, the dataset's own annotation.json
  poses, repaired ones applied (how good is the annotation against gt.json).

The dataset itself is written by ``annotator synth`` and ``annotator markers``
(:mod:`annotator.dataset.write`); there is no export to this format.
"""

from __future__ import annotations

from pathlib import Path

from annotator.dataset.review import (
    Review,
    ReviewStatus,
    apply_edits,
    poses_fingerprint,
    read_review,
)
from annotator.errors import UserError
from annotator.formats.base import GroundTruth, PoseResults, PoseSet, Table, read_json_lists

NAME = "ours"


def detect(path: Path) -> bool:
    return (path / "dataset.yaml").is_file()


def _occlusion(extra: dict) -> float:
    occ = extra.get("occlusion")
    if isinstance(occ, dict) and occ.get("rate") is not None:
        return float(occ["rate"])
    if extra.get("occlusion_rate") is not None:
        return float(extra["occlusion_rate"])
    return float("nan")


def read_ground_truth(path: Path, *, symmetry: str | None = None) -> GroundTruth:
    from annotator.dataset import load_dataset, read_poses
    from annotator.symmetry import PoseSpace

    ds = load_dataset(path)
    spaces = {n: PoseSpace.from_moments(o.mesh.moments, o.symmetry) for n, o in ds.objects.items()}
    table: Table = {}
    scenes = []
    left_out: dict[str, int] = {}
    for sc in ds.scenes():
        src = sc.gt_path if sc.gt_path.exists() else sc.annotation_path
        if not src.exists():
            continue
        poses = read_poses(src)
        if src == sc.annotation_path:
            review = read_review(sc.review_path)
            why = _rejected(review, poses)
            if why is not None:
                left_out[why] = left_out.get(why, 0) + 1
                continue
            poses = apply_edits(poses, review).poses
        scenes.append(sc.id)
        for i, p in enumerate(poses):
            if p.object not in spaces:
                raise UserError(
                    f"instances[{i}]: unknown object {p.object!r} (objects: {', '.join(spaces)})",
                    path=src,
                )
            table.setdefault((sc.id, p.object), PoseSet()).add(p.R, p.t, _occlusion(p.extra))
    ids = {k + 1: n for k, n in enumerate(ds.objects)}
    notes = [
        f"{n} scene(s) without gt.json left out of the ground truth: {why}"
        for why, n in sorted(left_out.items())
    ]
    return GroundTruth(spaces, table, scenes, NAME, "mm", ids, notes=notes)


def _rejected(review: Review | None, poses: list) -> str | None:
    """Why a scene's annotation cannot be ground truth by its review (None: it can). A
    decision made on other poses (stale) says nothing of these: the scene counts as pending."""
    if review is None or review.is_stale(poses_fingerprint(poses)):
        return None
    if review.status == ReviewStatus.REJECTED:
        return "rejected by a reviewer"
    if any(v == ReviewStatus.REJECTED for v in review.instances.values()):
        return "an instance rejected by a reviewer (its true pose is unknown)"
    return None


def read_results(path: Path, gt: GroundTruth) -> PoseResults:
    if path.is_dir():
        return read_json_lists(path, gt, scale=1.0, scene_key=lambda stem: _scene_key(stem, gt))
    from annotator.formats.bop import read_csv_results

    return read_csv_results(path, gt, scene_key=lambda sid, im: _scene_key(sid, gt))


def _scene_key(scene_id: str, gt: GroundTruth) -> str:
    """Our scene folder for a results id: the same name, or the same number (``12`` for
    ``000012``)."""
    if scene_id in gt.scenes:
        return scene_id
    if scene_id.isdigit():
        for s in gt.scenes:
            if s.isdigit() and int(s) == int(scene_id):
                return s
    return scene_id


def annotations_as_results(root: Path, gt: GroundTruth) -> PoseResults:
    """annotation.json poses (repaired ones applied) as results, scored ``1 / (1 +
    uncertainty_mm)`` (an instance added by hand has none: score 0)."""
    from annotator.dataset import load_dataset
    from annotator.dataset.annotation import SceneAnnotation

    ds = load_dataset(root)
    table: Table = {}
    for sc in ds.scenes():
        if not sc.annotation_path.exists():
            continue
        instances = SceneAnnotation.read(sc.annotation_path).instances
        for i in apply_edits(instances, read_review(sc.review_path)).poses:
            unc = getattr(i, "uncertainty_mm", None)
            score = 1.0 / (1.0 + float(unc)) if unc is not None else 0.0
            table.setdefault((sc.id, i.object), PoseSet()).add(i.R, i.t, score)
    return PoseResults(table)
