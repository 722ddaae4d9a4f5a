"""How far a sequence's annotation is from its exact truth (rendered sequences), as a user of
each frame sees it: shared by tests/test_sequences.py and benchmarks/bench_sequences.py.

- Frames: the solved rig path is first moved onto the true one by the rigid motion that fits
  best (the chordal mean of the frames' turns, then the mean shift): the scene frame is the
  first frame's camera, whose own error would otherwise be counted in every other frame.
  Then each frame's rig position (mm) and turn (degrees) error.
- Instances: the median over the frames both files pose of the paper's distance (symmetry
  aware) between the pose each frame's rig sees in the annotation and in the truth, in % of
  the diameter: what a BOP export of that frame holds, whatever the gauge.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from annotator.dataset import load_dataset
from annotator.dataset.frames import poses_in_frame, read_frames
from annotator.dataset.poses import read_pose_file
from annotator.dataset.records import SceneAnnotation
from annotator.geometry.transforms import make_transform
from annotator.symmetry import PoseSpace


@dataclass
class SequenceErrors:
    """Per frame and per instance errors of every sequence of a dataset.

    Attributes:
        position_mm, turn_deg: Each posed frame's rig error after the best rigid fit.
        frame_flagged: Whether each posed frame has a flag, same order.
        frame_uncertainty_mm, frame_uncertainty_deg: Its stated 1-sigma, same order.
        frames, frames_posed: Frames in all, and posed by the annotation.
        error_pct: Each posed instance's median error (% of D) over the frames.
        uncertainty_pct: Its estimated uncertainty (% of D), same order.
        flagged: Whether it has a flag, same order.
        visible: Instances of the truth half visible (occlusion <= 0.5) in some frame.
        posed_visible: Of those, how many the annotation poses.
        extra: Poses of instances the truth does not have in the scene.
    """

    position_mm: list[float] = field(default_factory=list)
    turn_deg: list[float] = field(default_factory=list)
    frame_flagged: list[bool] = field(default_factory=list)
    frame_uncertainty_mm: list[float] = field(default_factory=list)
    frame_uncertainty_deg: list[float] = field(default_factory=list)
    frames: int = 0
    frames_posed: int = 0
    error_pct: list[float] = field(default_factory=list)
    uncertainty_pct: list[float] = field(default_factory=list)
    flagged: list[bool] = field(default_factory=list)
    visible: int = 0
    posed_visible: int = 0
    extra: int = 0

    @property
    def gross_unflagged(self) -> int:
        """Poses more than 5 % of D off without a flag, and poses of absent parts without."""
        return sum(e > 5 and not f for e, f in zip(self.error_pct, self.flagged))

    @property
    def silent_frames(self) -> int:
        """Posed frames more than 2 mm or 0.5 degrees off without a flag."""
        off = zip(self.position_mm, self.turn_deg, self.frame_flagged)
        return sum((p > 2 or t > 0.5) and not f for p, t, f in off)

    @property
    def frames_within_3x(self) -> float:
        """Share of the posed frames (the scene frame's own apart: its uncertainty is 0 by
        definition) whose position and turn errors are both within 3x their uncertainty."""
        rows = [
            (p <= 3 * u and t <= 3 * v)
            for p, t, u, v in zip(
                self.position_mm,
                self.turn_deg,
                self.frame_uncertainty_mm,
                self.frame_uncertainty_deg,
            )
            if u > 0
        ]
        return float(np.mean(rows)) if rows else float("nan")


def best_fit(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The rigid motion ``S`` that best maps poses ``A`` (n, 4, 4) onto ``B``: rotation the
    chordal mean of ``B_i A_i^T``, translation the mean of ``b_i - R a_i``."""
    M = np.einsum("nij,nkj->ik", B[:, :3, :3], A[:, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return make_transform(R, np.mean(B[:, :3, 3] - A[:, :3, 3] @ R.T, axis=0))


def sequence_errors(root: str | Path) -> SequenceErrors:
    """Compare every sequence's annotation.json with its gt.json (see the module)."""
    ds = load_dataset(root)
    out = SequenceErrors()
    for scene in ds.scenes():
        if not (scene.annotation_path.exists() and scene.gt_path.exists()):
            continue
        truth = read_frames(scene.gt_path)
        found = read_frames(scene.annotation_path)
        out.frames += len(truth)
        names = [n for n, f in sorted(found.items()) if f.scene_T_rig is not None and n in truth]
        out.frames_posed += len(names)
        if not names:
            continue
        A = np.stack([found[n].scene_T_rig for n in names])  # type: ignore[misc]
        B = np.stack([truth[n].scene_T_rig for n in names])  # type: ignore[misc]
        moved = best_fit(A, B) @ A
        out.position_mm += np.linalg.norm(moved[:, :3, 3] - B[:, :3, 3], axis=1).tolist()
        rel = np.einsum("nji,njk->nik", moved[:, :3, :3], B[:, :3, :3])
        cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
        out.turn_deg += np.degrees(np.arccos(cos)).tolist()
        for n in names:
            frame = found[n]
            out.frame_flagged.append(bool(frame.flags))
            out.frame_uncertainty_mm.append(float(frame.uncertainty_mm or 0.0))
            out.frame_uncertainty_deg.append(float(frame.uncertainty_deg or 0.0))
        true_poses, top = read_pose_file(scene.gt_path)
        gt = {p.key: p for p in true_poses}
        half = {
            key
            for entry in (top.get("frames") or {}).values()
            for key, seen in (entry.get("instances") or {}).items()
            if min(seen.get("occlusion", {1: 1.0}).values()) <= 0.5
        }
        out.visible += len(half)
        ann = SceneAnnotation.read(scene.annotation_path)
        out.posed_visible += len(half & {i.key for i in ann.instances})
        for inst in ann.instances:
            if inst.key not in gt:
                out.extra += 1
                out.error_pct.append(100.0)
                out.uncertainty_pct.append(float("nan"))
                out.flagged.append(bool(inst.flags))
                continue
            obj = ds.objects[inst.object]
            space = PoseSpace.from_moments(obj.mesh.moments, obj.symmetry)
            per = []
            for n in names:
                x = poses_in_frame([inst.pose], found[n].scene_T_rig)[0]  # type: ignore[arg-type]
                y = poses_in_frame([gt[inst.key]], truth[n].scene_T_rig)[0]  # type: ignore[arg-type]
                d = space.distance(x.R[None], x.t[None], y.R[None], y.t[None])[0]
                per.append(100 * float(d) / space.diameter)
            out.error_pct.append(float(np.median(per)))
            unc = inst.uncertainty_mm
            out.uncertainty_pct.append(
                float("nan") if unc is None else 100 * float(unc) / space.diameter
            )
            out.flagged.append(bool(inst.flags))
    return out
