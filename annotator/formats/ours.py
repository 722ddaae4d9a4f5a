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

from annotator.dataset.frames import scene_shots
from annotator.dataset.poses import read_pose_file
from annotator.dataset.records import FramePose, frames_from_json
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
    from annotator.dataset import load_dataset
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
        poses, top = read_pose_file(src)
        review = read_review(sc.review_path) if src == sc.annotation_path else None
        if src == sc.annotation_path:
            why = _rejected(review, poses)
            if why is not None:
                left_out[why] = left_out.get(why, 0) + 1
                continue
            poses = apply_edits(poses, review).poses
        for i, p in enumerate(poses):
            if p.object not in spaces:
                raise UserError(
                    f"instances[{i}]: unknown object {p.object!r} (objects: {', '.join(spaces)})",
                    path=src,
                )
        for key, shot_poses, occlusion in _shots(
            ds, sc, frames_from_json(top.get("frames"), src), poses, review
        ):
            scenes.append(key)
            for p in shot_poses:
                table.setdefault((key, p.object), PoseSet()).add(p.R, p.t, occlusion(p))
    ids = {k + 1: n for k, n in enumerate(ds.objects)}
    notes = [
        f"{n} scene(s) without gt.json left out of the ground truth: {why}"
        for why, n in sorted(left_out.items())
    ]
    return GroundTruth(spaces, table, scenes, NAME, "mm", ids, notes=notes, root=Path(path))


def _shots(ds, sc, frames: dict[str, FramePose], poses: list, review: Review | None):
    """The evaluation's scenes of one scene folder: the scene itself, or (a sequence) each
    posed frame not rejected on its own, keyed ``<scene>/<frame>``, with its poses as that
    frame's rig saw them and each instance's occlusion rate there (the reference camera's)."""
    if not ds.rig.moving:
        yield sc.id, poses, lambda p: _occlusion(p.extra)
        return
    ref = ds.rig.cameras[0].name
    rejected = review.rejected_frames if review is not None else ()
    for shot in scene_shots(ds, sc, frames, rejected=rejected):
        assert shot.frame is not None  # a sequence's shots are frames
        seen = frames[shot.frame].instances or {}

        def occlusion(p, seen=seen):
            rate = (seen.get(p.key) or {}).get("occlusion", {}).get(ref)
            return float(rate) if isinstance(rate, (int, float)) else 1.0

        yield shot.id, shot.poses(poses), occlusion


def frame_keys(root: Path) -> dict[str, list[str]]:
    """A moving rig's dataset: each scene's frame names in order (a BOP image id is a
    frame's place among them, as ``export`` numbers them); empty for a fixed rig."""
    from annotator.dataset import load_dataset

    ds = load_dataset(root)
    if not ds.rig.moving:
        return {}
    return {sc.id: [f.name for f in sc.frames()] for sc in ds.scenes()}


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
    """Results as a folder of ``<scene>.json`` lists (a sequence: ``<scene>/<frame>.json``)
    or a BOP CSV (a sequence's ``im_id``: the frame's place among its frame folders)."""
    frames = frame_keys(gt.root) if gt.root is not None else {}
    if path.is_dir():
        return read_json_lists(
            path,
            gt,
            scale=1.0,
            scene_key=lambda stem: _scene_key(stem, gt),
            nested=bool(frames),
        )
    from annotator.formats.bop import read_csv_results

    def key(sid: str, im: int) -> str:
        scene = _scene_key(sid, gt, frames)
        names = frames.get(scene)
        if names is None:
            return scene
        return f"{scene}/{names[im]}" if 0 <= im < len(names) else f"{scene}/#{im}"

    return read_csv_results(path, gt, scene_key=key)


def _scene_key(scene_id: str, gt: GroundTruth, frames: dict | None = None) -> str:
    """Our scene folder for a results id: the same name, or the same number (``12`` for
    ``000012``); a sequence's frame ``<scene>/<frame>`` likewise, part by part."""
    if "/" in scene_id:
        scene, frame = scene_id.rsplit("/", 1)
        return f"{_scene_key(scene, gt, frames)}/{frame}"
    names = list(frames) if frames else gt.scenes
    if scene_id in names:
        return scene_id
    if scene_id.isdigit():
        for s in names:
            if s.isdigit() and int(s) == int(scene_id):
                return s
    return scene_id


def annotations_as_results(root: Path, gt: GroundTruth) -> PoseResults:
    """annotation.json poses (repaired ones applied) as results, scored ``1 / (1 +
    uncertainty_mm)`` (an instance added by hand has none: score 0); a sequence's in each
    of its posed frames.

    >>> from annotator import read_ground_truth
    >>> gt = read_ground_truth("sample_scenes")
    >>> sorted(annotations_as_results(Path("sample_scenes"), gt).scenes)
    ['000000', '000001', '000002', '000003']
    """
    from annotator.dataset import load_dataset
    from annotator.dataset.records import SceneAnnotation

    ds = load_dataset(root)
    table: Table = {}
    for sc in ds.scenes():
        if not sc.annotation_path.exists():
            continue
        ann = SceneAnnotation.read(sc.annotation_path)
        review = read_review(sc.review_path)
        edited = apply_edits(ann.instances, review).poses
        score = {
            i.key: (
                1.0 / (1.0 + float(u))
                if (u := getattr(i, "uncertainty_mm", None)) is not None
                else 0.0
            )
            for i in edited
        }
        poses = [i.pose if hasattr(i, "pose") else i for i in edited]
        for key, shot_poses, _ in _shots(ds, sc, ann.frames, poses, review):
            for p in shot_poses:
                table.setdefault((key, p.object), PoseSet()).add(p.R, p.t, score[p.key])
    return PoseResults(table)
