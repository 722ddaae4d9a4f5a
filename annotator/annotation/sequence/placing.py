"""Placing a sequence's frames and instances before the adjustment: a first frame fixes the
scene frame, the other frames are placed one at a time from the instances they share with
what is placed, and every instance is started from all the frames at once (:func:`place`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from annotator.annotation.sequence.reading import Seen
from annotator.annotation.settings import AnnotateSettings
from annotator.dataset import Dataset
from annotator.dataset.flags import FrameFlag
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert, make_transform
from annotator.pnp import (
    Observation,
    iter_candidate_poses,
    refine_pose,
    reprojection_errors,
)


@dataclass
class Placed:
    """The initial graph: the reference frame, every frame's ``scene_T_rig`` (None: not
    placed, with the reason) and every instance's ``scene_T_model``."""

    reference: int
    frames: list[np.ndarray | None]
    reasons: list[str | None]
    models: dict[tuple[str, str], np.ndarray]


def place(ds: Dataset, seen: list[Seen], s: AnnotateSettings) -> Placed | None:
    """Place the frames one at a time, then start every instance from all the frames."""
    cams = ds.rig.cameras
    first = next((f for f, e in enumerate(seen) if e.edges(ds, s)), None)
    if first is None:
        return None
    frames: list[np.ndarray | None] = [None] * len(seen)
    frames[first] = np.eye(4)
    models = {k: e.rig_T_model for k, e in seen[first].edges(ds, s).items()}
    # Per frame, its observations of what is placed, kept up to date as instances are
    # placed (counting them again for every frame at every step took as long as placing).
    sees: dict[tuple[str, str], list[int]] = {}
    for f, here in enumerate(seen):
        for k in here.raw:
            sees.setdefault(k, []).append(f)
    counts = np.zeros(len(seen), int)
    _count_placed(counts, seen, sees, models)
    while True:
        # Next: the frame that sees most of what is placed (the first of equals).
        open_counts = np.where([T is None for T in frames], counts, 0)
        best = int(np.argmax(open_counts))
        if open_counts[best] <= 0:
            break
        T = _place_frame(ds, seen[best], models, s)
        if T is None:  # nothing here agrees with what is placed: not placeable from it
            frames[best] = np.full((4, 4), np.nan)
            continue
        frames[best] = T
        new = {}
        for k in seen[best].raw:
            if k not in models and (e := seen[best].edge(ds, k, s)) is not None:
                new[k] = models[k] = T @ e.rig_T_model
        _count_placed(counts, seen, sees, new)
    reasons: list[str | None] = []
    for f, T in enumerate(frames):
        if T is None:
            reasons.append(FrameFlag.NO_KNOWN_MARKERS if not seen[f].raw else FrameFlag.UNCONNECTED)
            frames[f] = None
        elif np.isnan(T).any():
            reasons.append(FrameFlag.OUTLIER)
            frames[f] = None
        else:
            reasons.append(None)
    for key in list(models):
        start = instance_start(cams, seen, frames, key, s)
        if start is None:
            del models[key]
        else:
            models[key] = start
    return Placed(first, frames, reasons, models)


def _count_placed(
    counts: np.ndarray,
    seen: list[Seen],
    sees: dict[tuple[str, str], list[int]],
    placed: dict[tuple[str, str], np.ndarray],
) -> None:
    """Add to each frame's count its observations of the newly ``placed`` instances
    (``sees``: the frames that observe each instance)."""
    for k in placed:
        for f in sees.get(k, []):
            counts[f] += len(seen[f].raw[k])


def _place_frame(
    ds: Dataset,
    here: Seen,
    models: dict[tuple[str, str], np.ndarray],
    s: AnnotateSettings,
) -> np.ndarray | None:
    """``scene_T_rig`` of a frame from the placed instances it sees: every placed marker's
    corners are points of the scene frame, so each camera's RANSAC PnP over all of them is a
    hypothesis; when those do not hold, each placed instance's pose in the frame is one. The
    one most markers agree with is refined on them."""
    cams = ds.rig.cameras
    obs: list[Observation] = []
    for k, raw in here.raw.items():
        if k in models:
            obs += _in_scene([o for o, _ in raw], models[k])
    hyps = _joint_hypotheses(cams, obs, s)
    best, best_n = _best_hypothesis(cams, obs, hyps, s)
    if best_n < s.sequence.joint_share * len(obs):
        hyps = []
        for k in here.raw:
            if k in models and (e := here.edge(ds, k, s)) is not None:
                hyps.append(e.rig_T_model @ invert(models[k]))
        more, more_n = _best_hypothesis(cams, obs, hyps, s)
        if more_n > best_n:
            best, best_n = more, more_n
    if best is None:
        return None
    inliers = [o for o, e in zip(obs, reprojection_errors(cams, obs, best)) if e < s.inlier_px]
    est = refine_pose(cams, inliers, best)
    return invert(est.T)


def _joint_hypotheses(
    cams: Sequence[Camera], obs: list[Observation], s: AnnotateSettings
) -> list[np.ndarray]:
    """``rig_T_scene`` from each camera's RANSAC PnP over every observation it has (at least
    two markers)."""
    out = []
    for j, cam in enumerate(cams):
        mine = [o for o in obs if o.camera == j]
        if len(mine) < 2:
            continue
        X = np.concatenate([o.model_corners for o in mine]).astype(np.float64)
        x = np.concatenate([o.image_corners for o in mine]).astype(np.float64)
        try:
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                X,
                x,
                cam.K,
                cam.dist,
                reprojectionError=s.inlier_px,
                iterationsCount=200,
                confidence=0.999,
            )
        except cv2.error:
            continue
        if ok and inl is not None and len(inl) >= 8:
            out.append(cam.rig_T_cam @ make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel()))
    return out


def _best_hypothesis(
    cams: Sequence[Camera], obs: list[Observation], hyps: list[np.ndarray], s: AnnotateSettings
) -> tuple[np.ndarray | None, int]:
    """The hypothesis most observations agree with (within ``inlier_px``), and how many."""
    best, best_n = None, 0
    for H in hyps:
        n = int(np.sum(reprojection_errors(cams, obs, H) < s.inlier_px))
        if n > best_n:
            best, best_n = H, n
    return best, best_n


def _in_scene(obs: list[Observation], scene_T_model: np.ndarray) -> list[Observation]:
    """Observations with their corners in the scene frame."""
    R, t = scene_T_model[:3, :3], scene_T_model[:3, 3]
    return [replace(o, model_corners=o.model_corners @ R.T + t) for o in obs]


def _virtual_rig(
    cams: Sequence[Camera],
    seen: list[Seen],
    frames: list[np.ndarray | None],
    key: tuple[str, str],
    start_frames: int,
) -> tuple[list[Camera], list[Observation]]:
    """The placed frames' cameras that saw ``key`` as cameras of one rig in the scene frame,
    and the instance's observations renumbered to them: at most ``start_frames`` frames,
    those that read most of its markers, spread over the sequence (a start needs agreement,
    not every frame: the bundle adjustment takes them all)."""
    virtual: list[Camera] = []
    obs: list[Observation] = []
    placed = [f for f, here in enumerate(seen) if frames[f] is not None and key in here.raw]
    if len(placed) > start_frames:
        ranked = sorted(placed, key=lambda f: (-len(seen[f].raw[key]), f))
        placed = sorted(ranked[: start_frames // 2])
        rest = [f for f in sorted(set(ranked) - set(placed))]
        step = max(len(rest) // (start_frames - len(placed)), 1)
        placed = sorted(placed + rest[::step][: start_frames - len(placed)])
    for f in placed:
        here, T = seen[f], frames[f]
        assert T is not None
        index: dict[int, int] = {}
        for o, _ in here.raw[key]:
            if o.camera not in index:
                c = cams[o.camera]
                index[o.camera] = len(virtual)
                virtual.append(Camera(c.name, c.width, c.height, c.K, c.dist, T @ c.rig_T_cam))
            obs.append(replace(o, camera=index[o.camera]))
    return virtual, obs


def instance_start(
    cams: Sequence[Camera],
    seen: list[Seen],
    frames: list[np.ndarray | None],
    key: tuple[str, str],
    s: AnnotateSettings,
) -> np.ndarray | None:
    """An instance's pose from all the frames at once: the frames' cameras as one rig in the
    scene frame, the fixed rig's consensus over them (every camera's candidates scored by
    how many of the instance's markers in every frame agree, the best refined on them); a
    lone marker's mirror-image pose, or a marker misread in a few frames, loses."""
    virtual, obs = _virtual_rig(cams, seen, frames, key, s.sequence.start_frames)
    if not obs:
        return None
    best, best_n = None, 0
    for n_tried, H in enumerate(iter_candidate_poses(virtual, obs)):
        n = int(np.sum(reprojection_errors(virtual, obs, H) < s.inlier_px))
        if n > best_n:
            best, best_n = H, n
        if n_tried >= s.sequence.max_candidates or best_n >= 0.9 * len(obs):
            break
    if best is None:
        return None
    if all(o.soft for o, e in zip(obs, reprojection_errors(virtual, obs, best)) if e < s.inlier_px):
        if best_n < 2:  # one blurred reading alone is not evidence enough
            return None
    inliers = [o for o, e in zip(obs, reprojection_errors(virtual, obs, best)) if e < s.inlier_px]
    return refine_pose(virtual, inliers, best).T
