"""The PPF baseline: from a scene's depth map to scored pose hypotheses per part.

Steps, per scene and part (lengths as fractions of the part's diameter ``D``, the diameter
of the enclosing sphere centred on the surface centroid, as the evaluation's threshold):

1. the scene's oriented points, setting removed, one per ``sampling`` D
   (:mod:`~annotator.estimation.cloud`), and the model trained at the same spacing
   (:mod:`~annotator.estimation.model`, cached per part);
2. one pose vote per reference point (:mod:`~annotator.estimation.voting`);
3. **mode finding**: mean shift over the votes (:func:`~annotator.symmetry.find_modes`,
   flat kernel of radius ``bandwidth`` D). Without ``symmetric``, in SE(3): the pose space
   of the part *as if it had no symmetry* (the paper's distance with the identity group, a
   metric of SE(3)). With ``symmetric``, in the pose space of the part's own symmetry
   group, where votes for poses equal up to a symmetry are votes for the same pose;
4. **duplicates**: :func:`~annotator.symmetry.filter_duplicates` at ``duplicate_radius`` D
   in the same space (in SE(3) it only removes modes merged by the bandwidth already; with
   the symmetry it removes the hypotheses equal up to a symmetry); the ``max_hypotheses``
   heaviest are kept, scored by their summed votes;
5. with ``post_process`` (the paper's PP): the ``keep`` best are refined by point-to-plane
   ICP (:mod:`~annotator.estimation.icp`), re-scored by their agreement with the measured
   depth, the part rendered at the pose (:mod:`~annotator.estimation.scoring`), and
   filtered for duplicates again (refined hypotheses of one instance converge together).
   ICP comes before the score so that the score judges the pose that is reported.

Running the steps 3-5 of several variants on the same votes (:func:`estimate_scene` with
several settings) gives each exactly what it alone would give: they differ only from step 3.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from annotator.dataset.model import Dataset, ObjectModel, Symmetry
from annotator.errors import UserError
from annotator.estimation.cloud import OrientedCloud, scene_cloud
from annotator.estimation.icp import refine_icp
from annotator.estimation.model import train_model
from annotator.estimation.scoring import depth_consistency
from annotator.estimation.voting import Votes, vote
from annotator.geometry.camera import Camera
from annotator.symmetry import PoseSpace, filter_duplicates, find_modes


@dataclass(frozen=True)
class PPFSettings:
    """One variant of the estimator (see the module docstring); fractions of the diameter.

    Attributes:
        symmetric: Mode finding and duplicate removal in the part's own pose space.
        post_process: Keep the ``keep`` best, ICP, re-score by depth, filter duplicates.
        sampling: Model and scene point spacing (Drost et al.: 0.05; 0.06 here: the votes
            to count, most of the time, are a third of 0.05's on the gear).
        angle_bins: Angle cells per turn (30: 12 degrees, Drost et al.'s).
        reference_step: Every n-th scene point is a reference (Drost et al.: 5).
        bandwidth: Mean-shift kernel radius.
        duplicate_radius: Hypotheses closer than this are one (the evaluation's match
            threshold: a second one would be a false positive).
        max_hypotheses: Hypotheses reported per part and scene at most.
        keep: Hypotheses post-processed (the paper's 20).
    """

    symmetric: bool = False
    post_process: bool = False
    sampling: float = 0.06
    angle_bins: int = 30
    reference_step: int = 5
    bandwidth: float = 0.1
    duplicate_radius: float = 0.1
    max_hypotheses: int = 30
    keep: int = 20

    @property
    def label(self) -> str:
        """``PPF``, ``PPF sym``, ``PPF PP``, ``PPF sym PP``: the paper's names."""
        return "PPF" + (" sym" if self.symmetric else "") + (" PP" if self.post_process else "")

    def voting(self) -> tuple:
        """What the votes depend on: variants equal in it share their votes."""
        return (self.sampling, self.angle_bins, self.reference_step)


@dataclass(frozen=True)
class Hypothesis:
    """A scored pose of a part: ``pose`` maps model to the reference camera (4x4, mm)."""

    object: str
    pose: np.ndarray
    score: float


@dataclass
class SceneEstimate:
    """One variant's hypotheses for one scene, best first per part, and the seconds it took
    (the shared steps, cloud and votes, counted in every variant that uses them)."""

    hypotheses: list[Hypothesis]
    seconds: float


def pose_space(obj: ObjectModel, *, symmetric: bool) -> PoseSpace:
    """The part's pose space with its symmetry, or with none (SE(3))."""
    sym = obj.symmetry if symmetric else Symmetry("none")
    return PoseSpace.from_moments(obj.mesh.moments, sym)


def train_all(ds: Dataset, settings: Sequence[PPFSettings]) -> None:
    """Train (and cache in this process) every part of the dataset for these variants."""
    for obj in ds.objects.values():
        D = obj.mesh.moments.diameter
        for s in {v.voting() for v in settings}:
            train_model(obj.mesh, distance_step=s[0] * D, angle_bins=s[1])


def estimate_scene(
    ds: Dataset, scene_id: str, variants: Sequence[PPFSettings]
) -> list[SceneEstimate]:
    """Every variant's hypotheses for one scene of ``ds`` (from its depth map), in order.

    Raises:
        UserError: the scene has no depth map (naming it), or it is unreadable.
    """
    scene = ds.scene(scene_id)
    camera = ds.rig.depth_camera
    depth = scene.read_depth(ds.rig)
    if camera is None or depth is None:
        raise UserError("no depth map (the estimator works on depth)", path=scene.depth_path)
    rig_T_cam = camera.rig_T_cam
    out = [SceneEstimate([], 0.0) for _ in variants]
    for obj in ds.objects.values():
        D = obj.mesh.moments.diameter
        for voting in {v.voting() for v in variants}:
            t0 = time.perf_counter()
            step = voting[0] * D
            model = train_model(obj.mesh, distance_step=step, angle_bins=voting[1])
            cloud, _ = scene_cloud(camera, depth, ds.background_depth, step)
            votes = vote(model, cloud, reference_step=voting[2])
            shared = time.perf_counter() - t0
            fine: tuple[OrientedCloud, object] | None = None
            for k, v in enumerate(variants):
                if v.voting() != voting:
                    continue
                t1 = time.perf_counter()
                if v.post_process and fine is None:
                    fine = _icp_cloud(camera, depth, ds.background_depth, step)
                poses, scores = hypotheses(obj, votes, v, camera=camera, depth=depth, fine=fine)
                out[k].hypotheses += [
                    Hypothesis(obj.name, rig_T_cam @ P, float(s)) for P, s in zip(poses, scores)
                ]
                out[k].seconds += shared + time.perf_counter() - t1
    return out


def _icp_cloud(
    camera: Camera, depth: np.ndarray, background: np.ndarray | None, step: float
) -> tuple[OrientedCloud, object]:
    """The scene at half the voting spacing, for ICP, and its KD-tree."""
    from scipy.spatial import cKDTree

    cloud, _ = scene_cloud(camera, depth, background, 0.5 * step)
    return cloud, cKDTree(cloud.points)


def hypotheses(
    obj: ObjectModel,
    votes: Votes,
    settings: PPFSettings,
    *,
    camera: Camera,
    depth: np.ndarray,
    fine: tuple[OrientedCloud, object] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Steps 3-5 of the module docstring: hypotheses (K, 4, 4) in the depth camera's frame
    and their scores (K,), best first. ``fine``: the scene's points for ICP and their
    ``cKDTree`` (needed with ``post_process``)."""
    D = obj.mesh.moments.diameter
    space = pose_space(obj, symmetric=settings.symmetric)
    modes = find_modes(votes.poses, votes.weights, space, settings.bandwidth * D)
    kept = filter_duplicates(modes.poses, modes.weights, space, settings.duplicate_radius * D)
    kept = kept[: settings.max_hypotheses]
    poses, scores = modes.poses[kept], modes.weights[kept]
    if not settings.post_process or len(poses) == 0:
        return poses, scores
    if fine is None:
        raise ValueError("post-processing needs the ICP cloud (fine)")
    cloud, tree = fine
    model = train_model(
        obj.mesh, distance_step=settings.sampling * D, angle_bins=settings.angle_bins
    )
    poses = poses[: settings.keep]
    refined = np.stack(
        [
            refine_icp(
                P,
                model.points,
                model.normals,
                cloud,
                tree,
                start_gate=0.1 * D,
                end_gate=0.5 * settings.sampling * D,
            )
            for P in poses
        ]
    )
    scores = np.array([depth_consistency(camera, depth, obj.mesh, P) for P in refined])
    kept = filter_duplicates(refined, scores, space, settings.duplicate_radius * D)
    return refined[kept], scores[kept]


def variants(
    *, symmetric: Sequence[bool], post_process: Sequence[bool], **common
) -> list[PPFSettings]:
    """Every combination of ``symmetric`` and ``post_process`` values, with ``common``
    settings (the benchmark's four: ``variants(symmetric=(False, True), post_process=(False,
    True))``)."""
    base = PPFSettings(**common)
    return [replace(base, symmetric=s, post_process=p) for p in post_process for s in symmetric]
