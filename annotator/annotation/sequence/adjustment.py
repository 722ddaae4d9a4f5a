"""The adjustment rounds: one bundle adjustment over every placed frame and instance
(:func:`bundle`), observations that disagree left out, instances that moved during the
sequence found (:func:`moved`) and disowned ones started again, and the scale taken from the
measured depth."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

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
    cams = ds.rig.cameras
    keys = sorted(placed.models)
    live = [f for f, T in enumerate(placed.frames) if T is not None]
    obs, ids = _gathered(seen, live, keys)
    # Each marker's own streak where it was measured (a turning camera smears one side of
    # the image more than the other), else its image's.
    streak = np.array(
        [readings[live[f]].streak_px(c, m) for f, c, m in zip(obs.frame, obs.camera, ids)]
    )
    sigma = corner_sigma(streak)
    p = _Problem(
        cams,
        obs,
        frames=np.stack([T for T in placed.frames if T is not None]),
        models=np.stack([placed.models[k] for k in keys]),
        keep=np.zeros(len(ids), bool),
        sigma=sigma,
        fixed_frame=live.index(placed.reference),
        depth_camera=depth_cam,
    )
    p.keep = p.residuals() < s.inlier_px * sigma / NOISE.corner_px
    _leave_out_outliers(p, seen, live, keys, s)
    scale_sigma = _scale_by_depth(ds, p, keys, s, out)
    # Each frame's corner noise as its own residuals show it (never below what its streak
    # gives): a frame noisier than the rest is not trusted as much as the rest.
    p.sigma = frame_sigma(p.obs, p.residuals(), p.keep, p.sigma)
    # The last solve on what is kept, from where the rounds left the poses: its covariance.
    result = p.solve(covariance=True)
    err = p.residuals()
    limit = max(s.final_inlier_px, 4 * result.sigma_px)
    moved = _moved(cams, seen, live, p.frames, p.models, keys, p.obs, p.keep, limit, s)
    depth = marker_depths(cams, p.obs, p.frames, p.models)
    blur = FrameBlur(
        streaks[live].max(axis=1), median_by(p.obs.frame[p.keep], depth[p.keep], len(live))
    )
    site_mm = site_sigma(p.obs, err, p.keep, depth, float(cams[0].K[0, 0]), len(keys))
    solved = SolvedSequence(
        keys=keys,
        names=[r.frame for r in readings],
        live=live,
        obs=p.obs,
        ids=ids,
        keep=p.keep,
        result=result,
        err=err,
        placed=placed,
        moved=moved,
        blur=blur,
        agree_px=limit * p.sigma / NOISE.corner_px,
        site_mm=site_mm,
        scale=(depth, scale_sigma),
    )
    records(ds, solved, s, out)


def _gathered(
    seen: list[Seen], live: list[int], keys: list[tuple[str, str]]
) -> tuple[BundleObservations, np.ndarray]:
    """Every marker observation of the instances ``keys`` in the ``live`` frames (indexed
    among them), and each one's marker id."""
    index = {k: i for i, k in enumerate(keys)}
    rows: list[tuple[int, int, Observation, float]] = []
    for n, f in enumerate(live):
        for k, obs in seen[f].raw.items():
            if k in index:
                rows += [(n, index[k], o, z) for o, z in obs]
    gathered = BundleObservations(
        np.array([r[0] for r in rows], dtype=int),
        np.array([r[1] for r in rows], dtype=int),
        np.array([r[2].camera for r in rows], dtype=int),
        np.stack([r[2].model_corners for r in rows]).astype(np.float64),
        np.stack([r[2].image_corners for r in rows]).astype(np.float64),
        np.array([r[3] for r in rows], dtype=np.float64),
    )
    return gathered, np.array([r[2].marker_id for r in rows], dtype=int)


@dataclass
class _Problem:
    """What the rounds of the adjustment work on: the observations, the poses reached so
    far (scene_T_rig of each live frame, scene_T_model of each instance), which observations
    are kept, and each one's corner noise (px)."""

    cams: Sequence[Camera]
    obs: BundleObservations
    frames: np.ndarray
    models: np.ndarray
    keep: np.ndarray
    sigma: np.ndarray
    fixed_frame: int
    depth_camera: int | None

    def solve(self, *, covariance: bool = False) -> BundleResult:
        """One bundle adjustment of what is kept, from the poses so far, which it moves."""
        result = bundle_adjust(
            self.cams,
            self.obs.subset(self.keep),
            self.frames,
            self.models,
            fixed_frame=self.fixed_frame,
            depth_camera=self.depth_camera,
            covariance=covariance,
            corner_sigma_px=NOISE.corner_px,
            obs_sigma_px=self.sigma[self.keep],
        )
        self.frames, self.models = result.scene_T_rig, result.scene_T_model
        return result

    def residuals(self) -> np.ndarray:
        return _residuals(self.cams, self.obs, self.frames, self.models)

    def agreeing(self, limit: float) -> np.ndarray:
        """The observations within ``limit`` (in units of each corner's own noise), each
        left out with the rest of its frame's view of its instance where those disagree: a
        part that moved disagrees as a whole."""
        err = self.residuals() * NOISE.corner_px / self.sigma
        bad_edge = _edge_rms(self.obs, err) > limit
        return (err < 2 * limit) & ~bad_edge[self.obs.frame, self.obs.instance]


def _leave_out_outliers(
    p: _Problem, seen: list[Seen], live: list[int], keys: list[tuple[str, str]], s: AnnotateSettings
) -> None:
    """Solve and leave out what disagrees until nothing more does (at most
    ``solve_rounds``); after the first solve, the instances the adjusted frames disown are
    started again from those frames."""
    for round_ in range(s.sequence.solve_rounds):
        result = p.solve()
        limit = max(s.final_inlier_px, 4 * result.sigma_px)
        keep = p.agreeing(limit)
        if round_ == 0:
            p.models = _restart_disowned(
                p.cams, seen, live, p.frames, p.models, keys, p.obs, keep, s
            )
            keep = p.agreeing(limit)
        if np.array_equal(keep, p.keep):
            break
        p.keep = keep


def _scale_by_depth(
    ds: Dataset,
    p: _Problem,
    keys: list[tuple[str, str]],
    s: AnnotateSettings,
    out: SequenceSolution,
) -> float:
    """The markers put at the depth measured, when the depth disagrees with the corners'
    scale: sites and translations scaled together (a similarity, which leaves the images as
    they are) and solved again, the factor kept in ``out.site_scale``. The scale's sigma."""
    scale_sigma = s.sequence.scale_sigma
    if p.depth_camera is None:
        return scale_sigma
    under = surface_centres(ds, keys, p.obs)
    for _ in range(s.sequence.scale_rounds):
        z = marker_depths(p.cams, p.obs, p.frames, p.models, under * out.site_scale)
        use = p.keep & (p.obs.camera == p.depth_camera)
        found = depth_scale(z[use], p.obs.depth_mm[use])
        if found is None:
            break
        scale_sigma = max(found.sigma, s.sequence.depth_scale_sigma)
        # Within what the depth map itself is sure of, the corners' scale stands; once the
        # depth disagrees, it is followed to the end.
        if abs(found.factor - 1) < (2 * scale_sigma if out.site_scale == 1 else 1e-5):
            break
        p.obs = replace(p.obs, model_corners=p.obs.model_corners * found.factor)
        p.frames, p.models = p.frames.copy(), p.models.copy()
        p.frames[:, :3, 3] *= found.factor
        p.models[:, :3, 3] *= found.factor
        out.site_scale *= found.factor
        p.solve()
    return scale_sigma


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
    if n < 2:
        return None
    # Per split k (1 .. n-1), the frames before it that agree and those after it that do
    # not (the first way round), and the other way round: counted at once.
    agreeing = np.cumsum(np.asarray(agree, int))
    before = agreeing[:-1]  # agreeing among the first k
    after = agreeing[-1] - before  # agreeing among the rest
    k = np.arange(1, n)
    scores = np.stack([before + (n - k - after), (k - before) + after], axis=1)
    # The best split, the first of equals in the order (k, then agreeing before) tried.
    flat = int(np.argmax(scores.ravel()))
    split, before_agrees = int(k[flat // 2]), flat % 2 == 0
    if scores.ravel()[flat] < 0.9 * n:
        return None
    side = order[split:] if before_agrees else order[:split]
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
