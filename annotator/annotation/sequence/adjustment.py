"""The adjustment rounds: one bundle adjustment over every placed frame and instance
(:func:`bundle`), observations that disagree left out, instances that moved during the
sequence found (:func:`moved`) and disowned ones started again, and the scale taken from the
measured depth."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from annotator.annotation.depth_scale import depth_scale
from annotator.annotation.sequence.noise import (
    FrameBlur,
    corner_sigma,
    frame_sigma,
    marker_depths,
    median_by,
    site_sigma,
    surface_centres,
)
from annotator.annotation.sequence.placing import Placed, instance_start
from annotator.annotation.sequence.reading import FrameReading, Seen
from annotator.annotation.sequence.solution import SequenceSolution, SolvedSequence, records
from annotator.annotation.settings import AnnotateSettings
from annotator.dataset import Dataset
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert
from annotator.noise import NOISE
from annotator.pnp import (
    Observation,
    reprojection_errors,
)
from annotator.pnp.bundle import BundleObservations, BundleResult, bundle_adjust


def bundle(
    ds: Dataset,
    seen: list[Seen],
    placed: Placed,
    depth_cam: int | None,
    s: AnnotateSettings,
    out: SequenceSolution,
    readings: list[FrameReading],
    streaks: np.ndarray,
) -> None:
    """The bundle adjustment over every placed frame and instance, its outliers left out and
    the instances it disowns started again from the adjusted frames. ``streaks``: (frames,
    cameras) the motion streak (px) of each image (each marker's own in ``readings``): its
    corners' noise (:func:`corner_sigma`)."""
    names = [r.frame for r in readings]
    cams = ds.rig.cameras
    keys = sorted(placed.models)
    index = {k: i for i, k in enumerate(keys)}
    live = [f for f, T in enumerate(placed.frames) if T is not None]
    fidx = {f: n for n, f in enumerate(live)}
    rows: list[tuple[int, int, Observation, float]] = []
    for f in live:
        for k, obs in seen[f].raw.items():
            if k in index:
                rows += [(fidx[f], index[k], o, z) for o, z in obs]
    all_obs = BundleObservations(
        np.array([r[0] for r in rows], dtype=int),
        np.array([r[1] for r in rows], dtype=int),
        np.array([r[2].camera for r in rows], dtype=int),
        np.stack([r[2].model_corners for r in rows]).astype(np.float64),
        np.stack([r[2].image_corners for r in rows]).astype(np.float64),
        np.array([r[3] for r in rows], dtype=np.float64),
    )
    frames0 = np.stack([T for T in placed.frames if T is not None])
    models0 = np.stack([placed.models[k] for k in keys])
    err = _residuals(cams, all_obs, frames0, models0)
    # Each marker's own streak where it was measured (a turning camera smears one side of
    # the image more than the other), else its image's.
    streak = np.array([readings[live[r[0]]].streak_px(r[2].camera, r[2].marker_id) for r in rows])
    sigma = corner_sigma(streak)
    keep = err < s.inlier_px * sigma / NOISE.corner_px

    def solve(covariance: bool) -> BundleResult:
        return bundle_adjust(
            cams,
            all_obs.subset(keep),
            frames0,
            models0,
            fixed_frame=fidx[placed.reference],
            depth_camera=depth_cam,
            covariance=covariance,
            corner_sigma_px=NOISE.corner_px,
            obs_sigma_px=sigma[keep],
        )

    def kept(err: np.ndarray, limit: float) -> np.ndarray:
        # An observation is left out with the rest of its frame's view of its instance: a
        # part that moved disagrees as a whole. Limits in units of each corner's own noise.
        err = err * NOISE.corner_px / sigma
        bad_edge = _edge_rms(all_obs, err) > limit
        return (err < 2 * limit) & ~bad_edge[all_obs.frame, all_obs.instance]

    for round_ in range(s.sequence.solve_rounds):
        result = solve(covariance=False)
        frames0, models0 = result.scene_T_rig, result.scene_T_model
        limit = max(s.final_inlier_px, 4 * result.sigma_px)
        new_keep = kept(_residuals(cams, all_obs, frames0, models0), limit)
        if round_ == 0:
            models0 = _restart_disowned(
                cams, seen, live, frames0, models0, keys, all_obs, new_keep, s
            )
            new_keep = kept(_residuals(cams, all_obs, frames0, models0), limit)
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    scale_sigma = s.sequence.scale_sigma
    if depth_cam is not None:
        under = surface_centres(ds, keys, all_obs)
        for _ in range(s.sequence.scale_rounds):
            z = marker_depths(cams, all_obs, frames0, models0, under * out.site_scale)
            use = keep & (all_obs.camera == depth_cam)
            found = depth_scale(z[use], all_obs.depth_mm[use])
            if found is None:
                break
            scale_sigma = max(found.sigma, s.sequence.depth_scale_sigma)
            # Within what the depth map itself is sure of, the corners' scale stands; once
            # the depth disagrees, it is followed to the end.
            if abs(found.factor - 1) < (2 * scale_sigma if out.site_scale == 1 else 1e-5):
                break
            # A similarity: sites and translations scaled together leave the images as
            # they are, and put the markers at the depth measured.
            all_obs = replace(all_obs, model_corners=all_obs.model_corners * found.factor)
            frames0, models0 = frames0.copy(), models0.copy()
            frames0[:, :3, 3] *= found.factor
            models0[:, :3, 3] *= found.factor
            out.site_scale *= found.factor
            result = solve(covariance=False)
            frames0, models0 = result.scene_T_rig, result.scene_T_model
    # Each frame's corner noise as its own residuals show it (never below what its streak
    # gives): a frame noisier than the rest is not trusted as much as the rest.
    sigma = frame_sigma(all_obs, _residuals(cams, all_obs, frames0, models0), keep, sigma)
    # The last solve on what is kept, from where the rounds left the poses: its covariance.
    result = solve(covariance=True)
    frames0, models0 = result.scene_T_rig, result.scene_T_model
    err = _residuals(cams, all_obs, frames0, models0)
    ids = np.array([r[2].marker_id for r in rows], dtype=int)
    limit = max(s.final_inlier_px, 4 * result.sigma_px)
    moved = _moved(cams, seen, live, frames0, models0, keys, all_obs, keep, limit, s)
    depth = marker_depths(cams, all_obs, frames0, models0)
    blur = FrameBlur(
        streaks[live].max(axis=1), median_by(all_obs.frame[keep], depth[keep], len(live))
    )
    site_mm = site_sigma(all_obs, err, keep, depth, float(cams[0].K[0, 0]), len(keys))
    agree_px = limit * sigma / NOISE.corner_px
    solved = SolvedSequence(
        keys=keys,
        names=names,
        live=live,
        obs=all_obs,
        ids=ids,
        keep=keep,
        result=result,
        err=err,
        placed=placed,
        moved=moved,
        blur=blur,
        agree_px=agree_px,
        site_mm=site_mm,
        scale=(depth, scale_sigma),
    )
    records(ds, solved, s, out)


def _moved(
    cams: Sequence[Camera],
    seen: list[Seen],
    live: list[int],
    frames: np.ndarray,
    models: np.ndarray,
    keys: list[tuple[str, str]],
    obs: BundleObservations,
    keep: np.ndarray,
    limit: float,
    s: AnnotateSettings,
) -> set[int]:
    """The instances that moved: the frames that disagree with the pose (at least two, and
    the settings' ``moved_share`` of those that see it) agree with another pose among themselves,
    and most of their markers not with the pose. A few blurred frames disagree too, but not
    on one other pose; a frame whose view of a part was left out for one misread marker
    still agrees with the pose on the rest."""
    out: set[int] = set()
    for i, key in enumerate(keys):
        mine = obs.instance == i
        order = sorted(set(obs.frame[mine].tolist()))
        agreeing = set(obs.frame[mine & keep].tolist())
        bad = _moved_run(order, [f in agreeing for f in order], s.sequence.moved_share)
        if bad is None:
            continue
        placed: list[np.ndarray | None] = [None] * len(seen)
        for n in bad:
            placed[live[n]] = frames[n]
        other = instance_start(cams, seen, placed, key, s)
        if other is None:
            continue
        explained = [
            n
            for n in bad
            if _frame_agrees(cams, seen[live[n]].raw[key], frames[n], other, limit)
            and not _frame_agrees(cams, seen[live[n]].raw[key], frames[n], models[i], limit)
        ]
        if len(explained) >= max(2, 0.8 * len(bad)):
            out.add(i)
    return out


def _moved_run(order: list[int], agree: list[bool], share: float) -> list[int] | None:
    """The frames after (or before) a moment of the sequence that disagree with the pose,
    when that split explains at least nine frames in ten and leaves at least two frames
    (and ``share`` of them) on the disagreeing side; None otherwise. Blurred
    frames disagree here and there, a part that moved from a moment on."""
    n = len(order)
    best: tuple[int, list[int]] | None = None
    for k in range(1, n):
        for before_agrees in (True, False):
            score = sum(a == before_agrees for a in agree[:k]) + sum(
                a != before_agrees for a in agree[k:]
            )
            side = order[k:] if before_agrees else order[:k]
            if best is None or score > best[0]:
                best = (score, side)
    if best is None or best[0] < 0.9 * n:
        return None
    side = best[1]
    if len(side) < 2 or len(side) < share * n:
        return None
    return side


def _frame_agrees(
    cams: Sequence[Camera],
    obs: list[tuple[Observation, float]],
    scene_T_rig: np.ndarray,
    scene_T_model: np.ndarray,
    limit: float,
) -> bool:
    """True if most of a frame's observations of an instance agree with this pose."""
    err = reprojection_errors(cams, [o for o, _ in obs], invert(scene_T_rig) @ scene_T_model)
    return bool(np.mean(err < limit) > 0.5)


def _restart_disowned(
    cams: Sequence[Camera],
    seen: list[Seen],
    live: list[int],
    frames: np.ndarray,
    models: np.ndarray,
    keys: list[tuple[str, str]],
    obs: BundleObservations,
    keep: np.ndarray,
    s: AnnotateSettings,
) -> np.ndarray:
    """Instances of which the solve keeps less than half the observations started again from
    the adjusted frames (their first start came from frames placed less well)."""
    models = models.copy()
    placed: list[np.ndarray | None] = [None] * len(seen)
    for n, f in enumerate(live):
        placed[f] = frames[n]
    for i, key in enumerate(keys):
        mine = obs.instance == i
        if mine.any() and keep[mine].mean() < 0.5:
            start = instance_start(cams, seen, placed, key, s)
            if start is not None:
                models[i] = start
    return models


def _residuals(
    cams: Sequence[Camera], obs: BundleObservations, frames: np.ndarray, models: np.ndarray
) -> np.ndarray:
    """RMS corner reprojection error (px) of every observation at these poses."""
    err = np.empty(len(obs))
    M = np.einsum("nij,njk->nik", invert(frames[obs.frame]), models[obs.instance])
    for j, cam in enumerate(cams):
        sel = np.flatnonzero(obs.camera == j)
        if sel.size == 0:
            continue
        C = cam.cam_T_rig @ M[sel]
        pc = np.einsum("nij,nkj->nki", C[:, :3, :3], obs.model_corners[sel]) + C[:, None, :3, 3]
        uv = cam.project(pc)
        e = np.sqrt(np.mean(np.sum((uv - obs.image_corners[sel]) ** 2, axis=-1), axis=-1))
        err[sel] = np.where(np.isfinite(e), e, np.inf)
    return err


def _edge_rms(obs: BundleObservations, err: np.ndarray) -> np.ndarray:
    """(frames, instances) RMS over each frame's observations of each instance (0: none)."""
    shape = (int(obs.frame.max()) + 1, int(obs.instance.max()) + 1)
    sq = np.zeros(shape)
    n = np.zeros(shape)
    np.add.at(sq, (obs.frame, obs.instance), np.minimum(err, 1e6) ** 2)
    np.add.at(n, (obs.frame, obs.instance), 1)
    return np.where(n > 0, np.sqrt(sq / np.maximum(n, 1)), 0.0)
