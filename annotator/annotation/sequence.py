"""Annotating a sequence (one moving rig, FORMAT.md sequences): every frame's rig pose and every
instance's pose from the markers, in three steps.

1. :func:`read_frame`: the markers of every camera of one frame (and the measured depth at
   the centre of each marker the depth camera sees); frames are read independently, in any
   order, by any number of workers.
2. :func:`solve_sequence`: each frame's instances posed on their own (the fixed rig's robust
   consensus, :func:`~annotator.annotation.consensus.pose_instance`); a first frame fixes the
   scene frame; the other frames are placed one at a time, the one that sees most of what is
   already placed first, each from the hypothesis most of those markers agree with; every
   instance is then started from the frame whose pose of it most markers of all frames agree
   with; one bundle adjustment (:mod:`annotator.pnp.bundle`) refines everything over every
   corner and depth; observations that still disagree are left out and the solve repeated.
   A frame nothing connects to the rest keeps ``scene_T_rig: null`` and says why; an instance
   whose markers agree with its pose in some frames and not in others is flagged ``moved``.
   Each corner weighs as its noise says (its marker's motion streak,
   :mod:`~annotator.annotation.frame_quality`; its frame's residuals,
   :mod:`~annotator.annotation.sequence_noise`); with depth, the depth gives the scale
   (:mod:`~annotator.annotation.depth_scale`); a frame that places several parts
   differently from the rest is refused or flagged (:mod:`~annotator.annotation.consistency`).
3. :func:`frame_visibility`: occlusion rates and depth agreement of every instance as each
   frame sees it (the fixed rig's :func:`~annotator.annotation.visibility.add_visibility`).

:func:`annotate_sequence` runs the three on one scene in this process; ``annotator annotate``
runs them as batches over frames and scenes (:mod:`annotator.annotation.batch`).
"""

from __future__ import annotations

import functools
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from annotator.annotation.consensus import pose_instance
from annotator.annotation.consistency import frame_agreement
from annotator.annotation.depth_scale import depth_scale
from annotator.annotation.frame_quality import Streak, frame_streak
from annotator.annotation.scene import CONTRADICTED, _image_quality, _sort_markers
from annotator.annotation.sequence_noise import (
    CORNER_SIGMA_PX,
    MOTION_BLUR_PX,
    FrameBlur,
    corner_sigma,
    frame_sigma,
    frame_site_covariance,
    glue_spread,
    marker_depths,
    median_by,
    site_sigma,
    surface_centres,
)
from annotator.annotation.settings import AnnotateSettings
from annotator.annotation.visibility import MIN_DEPTH_PIXELS
from annotator.dataset import Dataset, Scene
from annotator.dataset.figures import (
    ImageQuality,
    MarkerUse,
    Occlusion,
    Reprojection,
    SceneWarning,
)
from annotator.dataset.flags import Flag, FrameFlag, WarningKind, sort_flags
from annotator.dataset.frames import poses_in_frame
from annotator.dataset.model import Frame
from annotator.dataset.records import (
    FramePose,
    InstanceAnnotation,
    SceneAnnotation,
)
from annotator.detection import MarkerDetector
from annotator.detection.aruco import Detection, ImageReading
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import SurfaceMoments
from annotator.geometry.transforms import invert, make_transform
from annotator.io.images import to_gray8
from annotator.markers.texture import marker_bits
from annotator.occlusion import scene_visibility
from annotator.pnp import (
    Observation,
    iter_candidate_poses,
    refine_pose,
    reprojection_errors,
)
from annotator.pnp.bundle import BundleObservations, BundleResult, bundle_adjust
from annotator.pnp.uncertainty import relative_rms_uncertainty, site_covariance

__all__ = [
    "FrameReading",
    "SequenceSolution",
    "annotate_sequence",
    "frame_annotations",
    "frame_visibility",
    "read_frame",
    "sequence_annotation",
    "solve_sequence",
]

#: A frame whose corners reproject worse than this (RMS, px) after the solve is flagged.
HIGH_REPROJECTION_PX = 1.5

#: A frame posed on fewer marker observations than this is flagged ``few_markers``.
FEW_MARKERS = 3

#: An instance whose markers disagree with its pose in at least this share of the frames
#: that see it (and in two frames or more) moved during the sequence.
MOVED_SHARE = 0.2

#: A frame whose pose is more uncertain than this (1-sigma, mm or degrees) is not posed:
#: a guess is not written.
FRAME_MAX_UNCERTAINTY_MM = 2.0
FRAME_MAX_UNCERTAINTY_DEG = 0.5

#: Each frame's occlusion rates from every this-many-th pixel at most (a sequence has many
#: frames; ``annotator occlusion`` gives every frame's exact rates).
FRAME_VISIBILITY_STEP = 4

#: Rounds of bundle adjustment, each leaving out what the previous one found disagreeing.
SOLVE_ROUNDS = 3
#: Rounds of taking the scale from the measured depth (:mod:`.depth_scale`) and adjusting
#: again.
SCALE_ROUNDS = 3
#: How well the scene's scale is known (1-sigma, relative) when no depth measures it: the
#: markers' printed size alone, read by corners a tenth of a pixel off on 30 px markers.
SCALE_SIGMA = 0.003
#: ... and when the depth measures it: never better than the depth map's own scale (its
#: calibration, the surface under a marker's centre read on a few pixels).
DEPTH_SCALE_SIGMA = 0.0003


@dataclass
class FrameReading:
    """What one frame's cameras read: per camera its :class:`ImageReading` (markers only:
    the unread candidates are dropped), the measured depth (mm, NaN: none) at the centre of
    each marker of the depth camera, in the order of its markers, and image quality."""

    frame: str
    readings: list[ImageReading]
    marker_depth: np.ndarray
    quality: dict[str, ImageQuality]
    #: Per camera, the motion streak its markers show (None: none told).
    streaks: list[Streak | None] = field(default_factory=list)

    def streak_px(self, camera: int, marker: int | None = None) -> float:
        """The streak's length (px) in camera ``camera`` (at ``marker`` when it was measured
        there), 0 when not measured."""
        s = self.streaks[camera] if camera < len(self.streaks) else None
        if s is None:
            return 0.0
        return s.per_marker.get(marker, s.length_px) if marker is not None else s.length_px


def read_frame(ds: Dataset, frame: Frame, detector: MarkerDetector) -> FrameReading:
    """Read the markers of every camera of ``frame`` (UserError for a missing or mis-sized
    image, naming the file), and the motion streak of each camera's image."""
    grays = [to_gray8(frame.read_image(cam)) for cam in ds.rig.cameras]
    readings = [detector.read(g) for g in grays]
    quality = _image_quality(ds, readings, grays)
    streaks = []
    for cam, r, g in zip(ds.rig.cameras, readings, grays):
        streak = frame_streak(g, [(d.id, d.corners, _grid(ds.dictionary, d.id)) for d in r.markers])
        streaks.append(streak)
        if streak is not None:
            quality[cam.name].extra["motion_blur_px"] = streak.length_px
            quality[cam.name].extra["motion_blur_deg"] = streak.angle_deg
    kept = [
        ImageReading(
            r.markers, np.zeros((0, 4, 2)), np.zeros((0, 1, 1), bool), np.zeros(0), r.blur_px
        )
        for r in readings
    ]
    depth = frame.read_depth(ds.rig)
    marker_depth = np.zeros(0)
    if depth is not None and ds.rig.depth is not None:
        j = [c.name for c in ds.rig.cameras].index(ds.rig.depth.camera)
        marker_depth = np.array([_depth_at(depth, d) for d in readings[j].markers])
    return FrameReading(frame.name, kept, marker_depth, quality, streaks)


@functools.cache
def _grid(dictionary_name: str, marker_id: int) -> np.ndarray:
    """A marker's cells as printed (border included), cached: every frame reads the same."""
    return marker_bits(dictionary_name, marker_id)


def _depth_at(depth: np.ndarray, d: Detection) -> float:
    """The median measured depth (mm) in the 5x5 pixels round a marker's centre (NaN: none)."""
    u, v = np.round(d.corners.mean(axis=0)).astype(int)
    h, w = depth.shape
    patch = depth[max(v - 2, 0) : min(v + 3, h), max(u - 2, 0) : min(u + 3, w)]
    good = patch[np.isfinite(patch)]
    return float(np.median(good)) if good.size >= 5 else float("nan")


@dataclass
class _Edge:
    """One instance as one frame saw it: its pose in that frame's rig (the fixed rig's
    consensus) and the observations that consensus used."""

    rig_T_model: np.ndarray
    obs: list[Observation]


@dataclass
class _Seen:
    """One frame: every observation of each instance (with the measured depth at each
    marker, NaN where none), and each instance as the frame's own consensus poses it
    (:meth:`edge`, worked out when first asked: most frames are placed by tracking)."""

    raw: dict[tuple[str, str], list[tuple[Observation, float]]]
    _edges: dict[tuple[str, str], _Edge | None] = field(default_factory=dict)

    def edge(self, ds: Dataset, key: tuple[str, str], s: AnnotateSettings) -> _Edge | None:
        """The instance posed from this frame alone (None: its markers do not pose it)."""
        if key not in self._edges:
            cams = ds.rig.cameras
            obs = [o for o, _ in self.raw[key]]
            r = pose_instance(ds, key[0], key[1], obs, s)
            edge = None
            if r is not None:
                used = {(c.name, i) for c in cams for i in r.markers.get(c.name, MarkerUse()).used}
                kept = [o for o in obs if (cams[o.camera].name, o.marker_id) in used]
                edge = _Edge(r.T, kept)
            self._edges[key] = edge
        return self._edges[key]

    def edges(self, ds: Dataset, s: AnnotateSettings) -> dict[tuple[str, str], _Edge]:
        """Every instance the frame poses on its own."""
        found = {k: self.edge(ds, k, s) for k in sorted(self.raw)}
        return {k: e for k, e in found.items() if e is not None}


@dataclass
class SequenceSolution:
    """The solved sequence: instance poses in the scene frame, every frame's pose and
    figures, and the instances' records (markers, reprojection, uncertainty, flags)."""

    reference: str | None
    instances: list[InstanceAnnotation]
    frames: dict[str, FramePose]
    warnings: list[SceneWarning] = field(default_factory=list)
    unknown_markers: dict[str, list[int]] = field(default_factory=dict)
    duplicates: dict[str, list[int]] = field(default_factory=dict)
    #: Per posed frame, how many of each instance's marker observations the solve kept.
    markers_used: dict[str, dict[str, int]] = field(default_factory=dict)
    #: The scale the measured depth gave the sites (1: not measured, or no depth).
    site_scale: float = 1.0


def solve_sequence(
    ds: Dataset, readings: list[FrameReading], *, settings: AnnotateSettings = AnnotateSettings()
) -> SequenceSolution:
    """Every frame's ``scene_T_rig`` and every instance's pose from the frames' readings (in
    frame order): see the module's docstring."""
    cams = ds.rig.cameras
    depth_cam = None if ds.rig.depth is None else [c.name for c in cams].index(ds.rig.depth.camera)
    names = [r.frame for r in readings]
    frames_seen: list[_Seen] = []
    unknown: dict[str, set[int]] = defaultdict(set)
    duplicates: dict[str, set[int]] = defaultdict(set)
    for reading in readings:
        markers = _sort_markers(ds, reading.readings)
        for cam, ids in markers.unknown.items():
            unknown[cam].update(ids)
        for cam, ids in markers.duplicates.items():
            duplicates[cam].update(ids)
        depth_of = _depth_lookup(reading, depth_cam)
        seen = _Seen({})
        for key, obs in sorted(markers.per_instance.items()):
            seen.raw[key] = [(o, depth_of.get((o.camera, o.marker_id), np.nan)) for o in obs]
        frames_seen.append(seen)
    out = SequenceSolution(
        None,
        [],
        {},
        unknown_markers={c: sorted(v) for c, v in sorted(unknown.items())},
        duplicates={c: sorted(v) for c, v in sorted(duplicates.items())},
    )
    placed = _place(ds, frames_seen, settings)
    if placed is None:
        for name in names:
            out.frames[name] = FramePose(name, None, flags=[FrameFlag.NO_KNOWN_MARKERS])
        out.warnings.append(
            SceneWarning(WarningKind.NO_MARKERS, "no marker of a known instance in any frame")
        )
        return out
    streaks = np.array([[r.streak_px(j) for j in range(len(cams))] for r in readings])
    _bundle(
        ds,
        frames_seen,
        placed,
        depth_cam,
        settings,
        out,
        readings,
        streaks.reshape(len(names), -1),
    )
    return out


def _depth_lookup(reading: FrameReading, depth_cam: int | None) -> dict[tuple[int, int], float]:
    if depth_cam is None or reading.marker_depth.size == 0:
        return {}
    markers = reading.readings[depth_cam].markers
    return {(depth_cam, d.id): float(z) for d, z in zip(markers, reading.marker_depth)}


@dataclass
class _Placed:
    """The initial graph: the reference frame, every frame's ``scene_T_rig`` (None: not
    placed, with the reason) and every instance's ``scene_T_model``."""

    reference: int
    frames: list[np.ndarray | None]
    reasons: list[str | None]
    models: dict[tuple[str, str], np.ndarray]


def _place(ds: Dataset, seen: list[_Seen], s: AnnotateSettings) -> _Placed | None:
    """Place the frames one at a time, then start every instance from all the frames."""
    cams = ds.rig.cameras
    first = next((f for f, e in enumerate(seen) if e.edges(ds, s)), None)
    if first is None:
        return None
    frames: list[np.ndarray | None] = [None] * len(seen)
    frames[first] = np.eye(4)
    models = {k: e.rig_T_model for k, e in seen[first].edges(ds, s).items()}
    while True:
        # Next: the frame that sees most of what is placed.
        best, best_count = None, 0
        for f, here in enumerate(seen):
            if frames[f] is None:
                count = sum(len(obs) for k, obs in here.raw.items() if k in models)
                if count > best_count:
                    best, best_count = f, count
        if best is None:
            break
        T = _place_frame(ds, seen[best], models, s)
        if T is None:  # nothing here agrees with what is placed: not placeable from it
            frames[best] = np.full((4, 4), np.nan)
            continue
        frames[best] = T
        for k in seen[best].raw:
            if k not in models and (e := seen[best].edge(ds, k, s)) is not None:
                models[k] = T @ e.rig_T_model
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
        start = _instance_start(cams, seen, frames, key, s)
        if start is None:
            del models[key]
        else:
            models[key] = start
    return _Placed(first, frames, reasons, models)


#: A frame is placed from the markers of all its placed instances at once when this share
#: of them agree with that pose; else from the poses its instances have in it.
JOINT_SHARE = 0.6


def _place_frame(
    ds: Dataset,
    here: _Seen,
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
    if best_n < JOINT_SHARE * len(obs):
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


#: At most this many candidate poses are scored when an instance is started from all frames.
MAX_CANDIDATES = 120
#: At most this many frames' observations start an instance.
START_FRAMES = 24


def _virtual_rig(
    cams: Sequence[Camera], seen: list[_Seen], frames: list[np.ndarray | None], key: tuple[str, str]
) -> tuple[list[Camera], list[Observation]]:
    """The placed frames' cameras that saw ``key`` as cameras of one rig in the scene frame,
    and the instance's observations renumbered to them: at most :data:`START_FRAMES` frames,
    those that read most of its markers, spread over the sequence (a start needs agreement,
    not every frame: the bundle adjustment takes them all)."""
    virtual: list[Camera] = []
    obs: list[Observation] = []
    placed = [f for f, here in enumerate(seen) if frames[f] is not None and key in here.raw]
    if len(placed) > START_FRAMES:
        ranked = sorted(placed, key=lambda f: (-len(seen[f].raw[key]), f))
        placed = sorted(ranked[: START_FRAMES // 2])
        rest = [f for f in sorted(set(ranked) - set(placed))]
        step = max(len(rest) // (START_FRAMES - len(placed)), 1)
        placed = sorted(placed + rest[::step][: START_FRAMES - len(placed)])
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


def _instance_start(
    cams: Sequence[Camera],
    seen: list[_Seen],
    frames: list[np.ndarray | None],
    key: tuple[str, str],
    s: AnnotateSettings,
) -> np.ndarray | None:
    """An instance's pose from all the frames at once: the frames' cameras as one rig in the
    scene frame, the fixed rig's consensus over them (every camera's candidates scored by
    how many of the instance's markers in every frame agree, the best refined on them); a
    lone marker's mirror-image pose, or a marker misread in a few frames, loses."""
    virtual, obs = _virtual_rig(cams, seen, frames, key)
    if not obs:
        return None
    best, best_n = None, 0
    for n_tried, H in enumerate(iter_candidate_poses(virtual, obs)):
        n = int(np.sum(reprojection_errors(virtual, obs, H) < s.inlier_px))
        if n > best_n:
            best, best_n = H, n
        if n_tried >= MAX_CANDIDATES or best_n >= 0.9 * len(obs):
            break
    if best is None:
        return None
    if all(o.soft for o, e in zip(obs, reprojection_errors(virtual, obs, best)) if e < s.inlier_px):
        if best_n < 2:  # one blurred reading alone is not evidence enough
            return None
    inliers = [o for o, e in zip(obs, reprojection_errors(virtual, obs, best)) if e < s.inlier_px]
    return refine_pose(virtual, inliers, best).T


def _bundle(
    ds: Dataset,
    seen: list[_Seen],
    placed: _Placed,
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
    keep = err < s.inlier_px * sigma / CORNER_SIGMA_PX

    def solve(covariance: bool) -> BundleResult:
        return bundle_adjust(
            cams,
            all_obs.subset(keep),
            frames0,
            models0,
            fixed_frame=fidx[placed.reference],
            depth_camera=depth_cam,
            covariance=covariance,
            corner_sigma_px=CORNER_SIGMA_PX,
            obs_sigma_px=sigma[keep],
        )

    def kept(err: np.ndarray, limit: float) -> np.ndarray:
        # An observation is left out with the rest of its frame's view of its instance: a
        # part that moved disagrees as a whole. Limits in units of each corner's own noise.
        err = err * CORNER_SIGMA_PX / sigma
        bad_edge = _edge_rms(all_obs, err) > limit
        return (err < 2 * limit) & ~bad_edge[all_obs.frame, all_obs.instance]

    for round_ in range(SOLVE_ROUNDS):
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
    scale_sigma = SCALE_SIGMA
    if depth_cam is not None:
        under = surface_centres(ds, keys, all_obs)
        for _ in range(SCALE_ROUNDS):
            z = marker_depths(cams, all_obs, frames0, models0, under * out.site_scale)
            use = keep & (all_obs.camera == depth_cam)
            found = depth_scale(z[use], all_obs.depth_mm[use])
            if found is None:
                break
            scale_sigma = max(found.sigma, DEPTH_SCALE_SIGMA)
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
    moved = _moved(cams, seen, live, frames0, keys, all_obs, keep, limit, s)
    depth = marker_depths(cams, all_obs, frames0, models0)
    blur = FrameBlur(
        streaks[live].max(axis=1), median_by(all_obs.frame[keep], depth[keep], len(live))
    )
    site_mm = site_sigma(all_obs, err, keep, depth, float(cams[0].K[0, 0]), len(keys))
    agree_px = limit * sigma / CORNER_SIGMA_PX
    _records(
        ds,
        keys,
        live,
        all_obs,
        ids,
        keep,
        result,
        err,
        placed,
        s,
        out,
        names,
        moved,
        blur,
        agree_px,
        site_mm,
        (depth, scale_sigma),
    )


def _moved(
    cams: Sequence[Camera],
    seen: list[_Seen],
    live: list[int],
    frames: np.ndarray,
    keys: list[tuple[str, str]],
    obs: BundleObservations,
    keep: np.ndarray,
    limit: float,
    s: AnnotateSettings,
) -> set[int]:
    """The instances that moved: the frames that disagree with the pose (at least two, and
    :data:`MOVED_SHARE` of those that see it) agree with another pose among themselves. A
    few blurred frames disagree too, but not on one other pose."""
    out: set[int] = set()
    for i, key in enumerate(keys):
        mine = obs.instance == i
        order = sorted(set(obs.frame[mine].tolist()))
        agreeing = set(obs.frame[mine & keep].tolist())
        bad = _moved_run(order, [f in agreeing for f in order])
        if bad is None:
            continue
        placed: list[np.ndarray | None] = [None] * len(seen)
        for n in bad:
            placed[live[n]] = frames[n]
        other = _instance_start(cams, seen, placed, key, s)
        if other is None:
            continue
        explained = [
            n for n in bad if _frame_agrees(cams, seen[live[n]].raw[key], frames[n], other, limit)
        ]
        if len(explained) >= max(2, 0.8 * len(bad)):
            out.add(i)
    return out


def _moved_run(order: list[int], agree: list[bool]) -> list[int] | None:
    """The frames after (or before) a moment of the sequence that disagree with the pose,
    when that split explains at least nine frames in ten and leaves at least two frames
    (and :data:`MOVED_SHARE` of them) on the disagreeing side; None otherwise. Blurred
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
    if len(side) < 2 or len(side) < MOVED_SHARE * n:
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
    seen: list[_Seen],
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
            start = _instance_start(cams, seen, placed, key, s)
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


def _uncertainty(
    moments: SurfaceMoments,
    result: BundleResult,
    instance: int,
    frames: np.ndarray,
    sites: np.ndarray,
    site_mm: float = 0.0,
) -> float:
    """An instance's uncertainty as the frames that see it do (what a frame's export holds):
    the median over them of the RMS surface displacement of its pose relative to the frame's,
    from the joint covariance (a part's pose and the frames' are known together), plus what
    its markers' own errors on the part give (:func:`~annotator.pnp.uncertainty.site_covariance`: the same in every
    frame, so more frames do not average them out); infinite where a direction nothing fixes
    is involved. ``sites``: the corners (model frame) of the markers it was posed on, each
    off by ``site_mm`` on the part (at least :data:`SITE_SIGMA_MM`)."""
    T = result.scene_T_model[instance]
    on_part = site_covariance(T[:3, :3], sites, max(site_mm, SITE_SIGMA_MM))
    values = []
    for f in frames.tolist():
        cov = result.joint_covariance(instance, f)
        cov[:6, :6] += on_part
        if not np.isfinite(cov).all():
            values.append(np.inf)
            continue
        values.append(relative_rms_uncertainty(moments, T, result.scene_T_rig[f], cov))
    return float(np.median(values)) if values else float("inf")


#: How well each corner of a marker is known on its part (mm, 1-sigma, each on its own):
#: printing, gluing flat, the corner fit's bias. It does not average out over frames.
SITE_SIGMA_MM = 0.15


#: When at least this share of a sequence's parts (seen in two frames or more) reproject
#: worse than ``high_residual_px``, their markers are not where the layout says: the user
#: is told that ``annotator sites`` measures them.
GLUED_SHARE = 0.3


def _rejected_markers(
    obs: BundleObservations, ids: np.ndarray, mine: np.ndarray, keep: np.ndarray
) -> bool:
    """True if a marker of the instance was read in two frames or more and never kept."""
    used = set(ids[mine & keep].tolist())
    frames: dict[int, set[int]] = defaultdict(set)
    for k in np.flatnonzero(mine & ~keep):
        if int(ids[k]) not in used:
            frames[int(ids[k])].add(int(obs.frame[k]))
    return any(len(f) >= 2 for f in frames.values())


def _records(
    ds: Dataset,
    keys: list[tuple[str, str]],
    live: list[int],
    obs: BundleObservations,
    ids: np.ndarray,
    keep: np.ndarray,
    result,
    err: np.ndarray,
    placed: _Placed,
    s: AnnotateSettings,
    out: SequenceSolution,
    names: list[str],
    moved: set[int],
    blur: FrameBlur,
    agree_px: np.ndarray,
    site_mm: np.ndarray,
    scale: tuple[np.ndarray, float],
) -> None:
    """annotation.json's records from the solve: per instance and per frame."""
    cams = ds.rig.cameras
    out.reference = names[placed.reference]
    seen = np.zeros((len(live), len(keys)), dtype=bool)
    seen[obs.frame, obs.instance] = True
    agree = np.zeros_like(seen)
    agree[obs.frame[keep], obs.instance[keep]] = True
    glued = np.array([glue_spread(ds.objects[o], inst) for o, inst in keys])
    for i, (obj, inst) in enumerate(keys):
        mine = obs.instance == i
        used = mine & keep
        if not used.any():
            continue
        T = result.scene_T_model[i]
        model = ds.objects[obj]
        _, first = np.unique(ids[used], return_index=True)
        corners = obs.model_corners[np.flatnonzero(used)[first]].reshape(-1, 3)
        unc = _uncertainty(
            model.mesh.moments,
            result,
            i,
            np.unique(obs.frame[used]),
            corners,
            max(site_mm[i], glued[i]),
        )
        # The scene's scale, as well as it is known, moves the part along its line of sight.
        unc = float(np.hypot(unc, scale[1] * float(np.median(scale[0][used]))))
        markers: dict[str, MarkerUse] = {}
        per_cam: dict[str, float] = {}
        for j, cam in enumerate(cams):
            u = used & (obs.camera == j)
            r = mine & ~keep & (obs.camera == j)
            if u.any() or r.any():
                good = {int(x) for x in ids[u]}
                markers[cam.name] = MarkerUse(sorted(good), sorted({int(x) for x in ids[r]} - good))
            if u.any():
                per_cam[cam.name] = round(float(np.sqrt(np.mean(err[u] ** 2))), 4)
        rms = float(np.sqrt(np.mean(err[used] ** 2)))
        flags: list[Flag | str] = []
        if i in moved:
            flags.append(Flag.MOVED)
        if rms > s.high_residual_px:
            flags.append(Flag.HIGH_RESIDUAL)
        # A marker left out in a blurred frame is noise; one that two frames or more read
        # and none agrees with is not (glued elsewhere, or another copy's).
        if _rejected_markers(obs, ids, mine, keep):
            flags.append(Flag.REJECTED_MARKERS)
        if not unc < s.high_uncertainty_fraction * model.mesh.moments.diameter:
            flags.append(Flag.HIGH_UNCERTAINTY)
        if int(agree[:, i].sum()) == 1 and len(per_cam) == 1:
            flags.append(Flag.SINGLE_VIEW)
        out.instances.append(
            InstanceAnnotation(
                obj,
                inst,
                T[:3, :3].copy(),
                T[:3, 3].copy(),
                uncertainty_mm=round(unc, 4) if np.isfinite(unc) else None,
                reprojection=Reprojection(round(rms, 4), round(float(err[used].max()), 4), per_cam),
                markers=markers,
                views=len(per_cam),
                flags=sort_flags(flags),
                frames_seen=int(agree[:, i].sum()),
            )
        )
    several = [r for r in out.instances if (r.frames_seen or 0) >= 2]
    off = [r for r in several if Flag.HIGH_RESIDUAL in r.flags]
    if several and len(off) >= GLUED_SHARE * len(several):
        out.warnings.append(SceneWarning(WarningKind.NOTE, _sites_hint(len(off), len(several))))
    if any(Flag.MOVED in r.flags for r in out.instances):
        which = [r.key for r in out.instances if Flag.MOVED in r.flags]
        out.warnings.append(
            SceneWarning(
                WarningKind.NOTE,
                f"parts moved during the sequence: {', '.join(which)} (their markers disagree "
                "with their pose in part of the frames; the pose is the one most frames agree with)",
            )
        )
    by_live = {f: n for n, f in enumerate(live)}
    sites_off = np.maximum(np.maximum(site_mm, SITE_SIGMA_MM), glued)
    agreement = frame_agreement(obs.frame, obs.instance, ids, err < agree_px, len(live))
    for f, name in enumerate(names):
        if f not in by_live:
            reason = placed.reasons[f]
            why_not = None
            if reason == FrameFlag.OUTLIER:
                why_not = "its markers agree with no placed instance's pose"
            out.frames[name] = FramePose(
                name, None, flags=[] if reason is None else [reason], reason=why_not
            )
            continue
        n = by_live[f]
        mine = (obs.frame == n) & keep
        T = result.scene_T_rig[n]
        cov = result.frame_covariance[n]
        flags_f: list[str] = []
        if not mine.any():
            out.frames[name] = FramePose(
                name,
                None,
                flags=[FrameFlag.OUTLIER],
                reason="none of its markers agree with the solve",
            )
            continue
        blur_mm, blur_deg = blur.uncertainty(n, float(cams[0].K[0, 0]))
        scale_mm = scale[1] * float(np.linalg.norm(T[:3, 3]))  # its distance to the origin
        if f == placed.reference:  # the scene frame: its pose is the gauge, exact
            blur_mm = blur_deg = 0.0
        else:  # the sites it was posed on are off on their parts the same in every frame
            cov = cov + frame_site_covariance(obs, mine, result, T, sites_off)
        unc_mm = float(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0) + blur_mm**2 + scale_mm**2))
        unc_deg = float(
            np.sqrt(np.degrees(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))) ** 2 + blur_deg**2)
        )
        why = None
        a = agreement[n]
        others = ", ".join("/".join(keys[i]) for i in a.disagreeing)
        if a.refused:
            why = (
                f"its markers place {len(a.disagreeing)} parts ({others}) differently from the "
                f"rest of the sequence and only {len(a.agreeing)} as it does: another "
                "arrangement, or parts moved"
            )
        elif len(set(ids[mine].tolist())) < 2:
            # One square's two mirror poses fit it about equally well: not evidence enough.
            why = f"it is posed on one marker only ({int(mine.sum())} observations)"
        elif not (unc_mm <= FRAME_MAX_UNCERTAINTY_MM and unc_deg <= FRAME_MAX_UNCERTAINTY_DEG):
            why = (
                f"its {int(mine.sum())} marker observations leave its pose uncertain "
                f"(1-sigma {unc_mm:.3g} mm, {unc_deg:.3g} degrees)"
            )
        if why is not None:
            out.frames[name] = FramePose(name, None, flags=[FrameFlag.OUTLIER], reason=why)
            continue
        rms_f = float(np.sqrt(np.mean(err[mine] ** 2)))
        reasons: list[str] = []
        if rms_f > HIGH_REPROJECTION_PX:
            flags_f.append(FrameFlag.HIGH_REPROJECTION)
        if int(mine.sum()) < FEW_MARKERS:
            flags_f.append(FrameFlag.FEW_MARKERS)
        if blur.streak_px[n] >= MOTION_BLUR_PX:
            flags_f.append(FrameFlag.MOTION_BLUR)
            reasons.append(
                f"motion blur: its markers are smeared {blur.streak_px[n]:.3g} px, and which "
                "instant of the exposure its pose stands for is not known"
            )
        if a.inconsistent:
            flags_f.append(FrameFlag.INCONSISTENT)
            reasons.append(
                f"its markers place {len(a.disagreeing)} parts ({others}) differently from the "
                "rest of the sequence: parts moved, or another arrangement"
            )
        if a.single_part and len(keys) > 1:
            flags_f.append(FrameFlag.SINGLE_PART)
            reasons.append(
                f"posed on the markers of one part only ({'/'.join(keys[a.agreeing[0]])}): "
                "nothing in it checks that part against the rest"
            )
        counts = np.bincount(obs.instance[mine], minlength=len(keys))
        out.markers_used[name] = {"/".join(keys[i]): int(c) for i, c in enumerate(counts) if c}
        out.frames[name] = FramePose(
            name,
            T,
            reprojection_px=round(rms_f, 4),
            markers_used=int(mine.sum()),
            uncertainty_mm=round(unc_mm, 4),
            uncertainty_deg=round(unc_deg, 4),
            instances={},
            flags=flags_f,
            reason="; ".join(reasons) if reasons else None,
        )
    changed = [
        n
        for n, f in zip(names, (out.frames[n] for n in names))
        if f.has(FrameFlag.INCONSISTENT) or "differently from the rest" in (f.reason or "")
    ]
    if changed:
        parts = sorted(
            {
                "/".join(keys[i])
                for f in live
                if names[f] in changed
                for i in agreement[by_live[f]].disagreeing
            }
        )
        out.warnings.append(
            SceneWarning(
                WarningKind.NOTE,
                f"frames {', '.join(changed)} place parts ({', '.join(parts)}) differently from "
                "the rest of the sequence: parts moved, or frames of another arrangement (each "
                "frame's reason says which)",
            )
        )


def _sites_hint(off: int, parts: int) -> str:
    """The one line that says the markers are not where the layout puts them."""
    return (
        f"the markers of {off} of {parts} parts sit off their layout in every frame (glued by "
        "hand?): their spread is in the uncertainties; `annotator sites` measures where they "
        "are, and annotating again then tightens the poses"
    )


def frame_visibility(
    ds: Dataset,
    frame: Frame,
    instances: list[InstanceAnnotation],
    scene_T_rig: np.ndarray,
    *,
    settings: AnnotateSettings = AnnotateSettings(),
) -> dict[str, dict]:
    """What ``frame`` sees of the posed instances (scene frame): per instance whose silhouette
    falls in one of its cameras, ``{"occlusion": {camera: rate}, "depth_agreement": a}``."""
    if not instances:
        return {}
    local = poses_in_frame(instances, scene_T_rig)
    depth = frame.read_depth(ds.rig)
    vis = scene_visibility(
        ds.rig,
        [ds.objects[r.object].mesh for r in local],
        [r.T for r in local],
        depth=depth,
        agreement_tolerance=settings.depth_tolerance_mm,
        step=max(settings.visibility_step, FRAME_VISIBILITY_STEP),
    )
    out: dict[str, dict] = {}
    depth_cam = None if ds.rig.depth is None else ds.rig.depth.camera
    for r, v in zip(instances, vis):
        if not any(c.px_all > 0 for c in v.cameras):
            continue
        entry: dict = {"occlusion": {c.camera: round(c.occlusion, 4) for c in v.cameras}}
        cv = next((c for c in v.cameras if c.camera == depth_cam), None)
        if (
            depth is not None
            and cv is not None
            and cv.depth_agreement is not None
            and cv.depth_pixels >= MIN_DEPTH_PIXELS
        ):
            entry["depth_agreement"] = round(cv.depth_agreement, 4)
        out[r.key] = entry
    return out


def sequence_annotation(
    solution: SequenceSolution,
    readings: list[FrameReading],
    seen: dict[str, dict[str, dict]],
    *,
    settings: AnnotateSettings = AnnotateSettings(),
) -> SceneAnnotation:
    """annotation.json of a sequence from its solve and, per posed frame, what
    :func:`frame_visibility` found: each frame's ``instances`` (with how many of the
    instance's markers it used), each instance's least occluded view and median depth
    agreement (``depth_disagreement`` below the settings' minimum)."""
    frames = {name: replace(f) for name, f in solution.frames.items()}
    best: dict[str, tuple[float, dict[str, float]]] = {}
    agreements: dict[str, list[float]] = defaultdict(list)
    for name, found in seen.items():
        per = {}
        for key, v in sorted(found.items()):
            per[key] = {
                "markers_used": solution.markers_used.get(name, {}).get(key, 0),
                "occlusion": v["occlusion"],
            }
            rate = min(v["occlusion"].values())
            if key not in best or rate < best[key][0]:
                best[key] = (rate, v["occlusion"])
            if "depth_agreement" in v:
                agreements[key].append(v["depth_agreement"])
        frames[name].instances = per
    instances = []
    unconfirmed: dict[str, set[int]] = defaultdict(set)
    for r in solution.instances:
        if _contradicted_lone(r, agreements.get(r.key), settings) or _phantom(r, seen):
            for cam, m in r.markers.items():
                unconfirmed[cam].update(m.used)
            continue
        if r.key in best:
            rate, per_cam = best[r.key]
            r.occlusion = Occlusion(round(rate, 4), per_cam)
        flags = [f for f in r.flags if f != Flag.DEPTH_DISAGREEMENT]
        if agreements.get(r.key):
            a = float(np.median(agreements[r.key]))
            r.depth_agreement_median = round(a, 4)
            if a < settings.depth_min_agreement:
                flags.append(Flag.DEPTH_DISAGREEMENT)
        r.flags = sort_flags(flags)
        instances.append(r)
    kept = {r.key for r in instances}
    for f in frames.values():  # a pose left out is in no frame either
        if f.instances is not None:
            f.instances = {k: v for k, v in f.instances.items() if k in kept}
    for reading in readings:
        frames[reading.frame].image_quality = dict(reading.quality)
    return SceneAnnotation(
        instances=instances,
        warnings=list(solution.warnings),
        unknown_markers=solution.unknown_markers,
        unconfirmed_markers={c: sorted(v) for c, v in sorted(unconfirmed.items())},
        duplicates=solution.duplicates,
        scene_frame=solution.reference,
        frames=frames,
        depth_scale=round(solution.site_scale, 6) if solution.site_scale != 1 else None,
    )


def _contradicted_lone(
    r: InstanceAnnotation, agreements: list[float] | None, s: AnnotateSettings
) -> bool:
    """A pose on one marker (one id, however many frames read it: a misreading can repeat)
    that the measured depth disagrees with, or on two readings that it contradicts outright:
    a misread or stray marker, not a part (its ids are listed as unconfirmed; a part really
    there shows unposed, not wrongly posed)."""
    if not agreements:
        return False
    agreement = float(np.median(agreements))
    if len(r.marker_ids()) == 1:  # one marker, however many frames read it the same way
        return agreement < s.depth_min_agreement
    return (
        (3 if r.frames_seen is None else r.frames_seen) <= 2
        and r.count("used") <= 2
        and agreement < CONTRADICTED
    )


#: A pose on one reading whose part other frames should see, this many of them, and read
#: no marker of, is a misread or stray marker.
PHANTOM_FRAMES = 3


def _phantom(r: InstanceAnnotation, seen: dict[str, dict[str, dict]]) -> bool:
    """A pose on one marker read once (one camera, one frame) that other frames see mostly
    unhidden (:data:`PHANTOM_FRAMES` of them) without reading any of its markers."""
    if not (r.frames_seen == 1 and r.count("used") == 1):
        return False
    unread = sum(
        1
        for found in seen.values()
        if r.key in found and min(found[r.key]["occlusion"].values()) < 0.5
    )
    return unread - 1 >= PHANTOM_FRAMES


def annotate_sequence(
    ds: Dataset,
    scene: Scene,
    detector: MarkerDetector,
    *,
    settings: AnnotateSettings = AnnotateSettings(),
) -> SceneAnnotation:
    """Annotate one sequence in this process: read every frame, solve, see every frame.

    Raises:
        UserError: the scene has no frame folder, or a frame's image is missing or mis-sized.
    """
    frames = scene.frames()
    if not frames:
        raise UserError(
            "a moving rig's scene holds its images in frames/<frame>/: none found", path=scene.path
        )
    readings = [read_frame(ds, f, detector) for f in frames]
    solution = solve_sequence(ds, readings, settings=settings)
    seen = {}
    for f in frames:
        T = solution.frames[f.name].scene_T_rig
        if T is not None:
            seen[f.name] = frame_visibility(ds, f, solution.instances, T, settings=settings)
    return sequence_annotation(solution, readings, seen, settings=settings)


def frame_annotations(ann: SceneAnnotation) -> dict[str, SceneAnnotation]:
    """A sequence's annotation as one fixed-rig annotation per posed frame (keyed by the
    frame's name): the instances that frame read markers of, posed as its rig saw them, with
    their markers' use (over the sequence) and figures. What works on a fixed rig's
    annotated scene (``annotator sites``) then works on every frame of a sequence."""
    out = {}
    for name, frame in sorted(ann.frames.items()):
        if frame.scene_T_rig is None:
            continue
        read = {k for k, v in (frame.instances or {}).items() if v.get("markers_used")}
        seen = [r for r in ann.instances if r.key in read]
        out[name] = SceneAnnotation(instances=poses_in_frame(seen, frame.scene_T_rig))
    return out
