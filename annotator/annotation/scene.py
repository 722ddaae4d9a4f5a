"""Annotating one scene: detection in every camera, consensus per instance
(:mod:`~annotator.annotation.consensus`), marker recovery (:mod:`~annotator.annotation.recovery`),
poses on few markers refined against the depth (:mod:`~annotator.annotation.refine`),
visibility and trust (:mod:`~annotator.annotation.visibility`), and the scene's completeness
(:mod:`~annotator.annotation.unexplained`, :mod:`~annotator.annotation.completeness`).

Blurred markers (see :mod:`annotator.detection.deblur`) are held to the support of others: a
pose on *soft* readings alone needs two of them that agree, and is kept only if the measured
depth confirms it (or, without depth, two different markers do): blur can misread a marker
the same way in both cameras. Its markers are then listed as unconfirmed; a part really there
shows as unexplained depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from annotator.annotation.completeness import image_quality, quality_warnings
from annotator.annotation.consensus import flag_overlaps, pose_instance
from annotator.annotation.misreads import forgive_misreadings
from annotator.annotation.observations import sort_markers
from annotator.annotation.recovery import recover_markers
from annotator.annotation.refine import refine_few_marker_poses
from annotator.annotation.settings import AnnotateSettings
from annotator.annotation.unexplained import unexplained_depth
from annotator.annotation.visibility import Renders, add_visibility
from annotator.dataset import Dataset, Scene
from annotator.dataset.figures import SceneWarning
from annotator.dataset.flags import Flag, WarningKind
from annotator.dataset.frames import scene_shots
from annotator.dataset.model import UNEXPLAINED_MASK
from annotator.dataset.records import InstanceAnnotation, SceneAnnotation
from annotator.detection import MarkerDetector
from annotator.io.images import to_gray8
from annotator.occlusion import CastMemo
from annotator.physics.scene import record_physics
from annotator.values import of_type

__all__ = ["UNEXPLAINED_MASK", "AnnotateSettings", "SceneResult", "annotate_scene"]

#: Below this depth agreement a pose on one marker id is contradicted by the depth.
CONTRADICTED = 0.3


@dataclass
class SceneResult:
    """What annotating a scene gives: the annotation.json record and the unexplained-depth
    mask (uint8, 255 = unexplained, on the depth camera's grid), or None without depth.

    :func:`annotate_scene`'s example makes one; this one holds an annotation.json as written:

    >>> from annotator.dataset.records import SceneAnnotation
    >>> ann = SceneAnnotation.read("sample_scenes/scenes/000003/annotation.json")
    >>> result = SceneResult(ann, None)
    >>> len(result.annotation.instances), result.unexplained is None
    (10, True)
    """

    annotation: SceneAnnotation
    unexplained: np.ndarray | None


def annotate_scene(
    ds: Dataset,
    scene: Scene,
    detector: MarkerDetector,
    *,
    settings: AnnotateSettings = AnnotateSettings(),
) -> SceneResult:
    """Pose every instance with detected markers, and check the scene's completeness.

    >>> from annotator import MarkerDetector, load_dataset
    >>> ds = load_dataset("sample_scenes")
    >>> result = annotate_scene(ds, ds.scene("000000"), MarkerDetector(ds.dictionary))
    >>> len(result.annotation.instances), result.annotation.instances[0].key
    (8, 'bracket/01')
    """
    of_type(ds, Dataset, name="ds", what="a Dataset (annotator.load_dataset)")
    of_type(scene, Scene, name="scene", what="a Scene of the dataset (ds.scene(id))")
    of_type(detector, MarkerDetector, name="detector", what="an annotator.MarkerDetector")
    of_type(settings, AnnotateSettings, name="settings", what="annotator.AnnotateSettings")
    grays = [to_gray8(scene.read_image(cam)) for cam in ds.rig.cameras]
    readings = [detector.read(g) for g in grays]
    markers = sort_markers(ds, readings)
    instances = []
    for (obj, inst), obs in sorted(markers.per_instance.items()):
        r = pose_instance(ds, obj, inst, obs, settings)
        if r is not None and recover_markers(
            ds, obj, inst, r.T, obs, readings, grays, detector, within_px=settings.final_inlier_px
        ):
            r = pose_instance(ds, obj, inst, obs, settings) or r
        if r is not None:
            instances.append(r)
    flag_overlaps(ds, instances)
    forgive_misreadings(ds.rig.cameras, instances, markers.per_instance)
    depth = scene.read_depth(ds.rig)
    renders: Renders = {}
    memo: CastMemo = {}  # the parts that the steps below leave where they are: cast once
    add_visibility(ds, instances, depth, settings, renders, memo)
    doubtful = [r for r in instances if not _supported(r, depth is not None)]
    unconfirmed: dict[str, list[int]] = {}
    if doubtful:
        instances = [r for r in instances if not any(r is d for d in doubtful)]
        for r in doubtful:
            for cam_name, m in r.markers.items():
                unconfirmed.setdefault(cam_name, []).extend(m.used)
        renders = {}
        add_visibility(ds, instances, depth, settings, renders, memo)
    if refine_few_marker_poses(ds, instances, markers.per_instance, depth, settings, memo):
        renders = {}
        add_visibility(ds, instances, depth, settings, renders, memo)
    record_physics(ds, scene_shots(ds, scene)[0], instances, depth)
    quality = image_quality(ds, readings, grays)
    warnings = quality_warnings(quality, settings.completeness)
    if not any(r.markers for r in readings):
        warnings.insert(0, SceneWarning(WarningKind.NO_MARKERS, "no marker detected in any camera"))
    mask = None
    if depth is not None and ds.rig.depth is not None:
        found, mask = unexplained_depth(
            ds,
            depth,
            renders,
            disagreeing=[k for k, r in enumerate(instances) if _owns_its_region(r)],
            unread=readings[[c.name for c in ds.rig.cameras].index(ds.rig.depth.camera)].unread,
            settings=settings,
        )
        if found is not None:
            warnings.append(found)
    annotation = SceneAnnotation(
        instances=instances,
        warnings=warnings,
        image_quality=quality,
        unknown_markers=markers.unknown,
        unconfirmed_markers={c: sorted(set(v)) for c, v in unconfirmed.items()},
        duplicates=markers.duplicates,
        unexplained_mask=UNEXPLAINED_MASK if mask is not None and mask.any() else None,
    )
    return SceneResult(annotation, mask)


def _supported(r: InstanceAnnotation, with_depth: bool) -> bool:
    """False for a pose on blurred readings only that the depth does not confirm."""
    if not all(set(m.used) <= set(m.recovered) for m in r.markers.values()):
        return True
    if with_depth and r.depth is not None:
        return Flag.DEPTH_DISAGREEMENT not in r.flags
    return len(r.marker_ids()) >= 2


def _owns_its_region(r: InstanceAnnotation) -> bool:
    """A pose flagged ``depth_disagreement`` that still explains its part: on several
    markers, or not contradicted outright. (A single marker id whose pose the depth
    contradicts may be a misread or stray marker: the region stays reported.)"""
    if Flag.DEPTH_DISAGREEMENT not in r.flags:
        return False
    agreement = r.depth_agreement
    return len(r.marker_ids()) > 1 or agreement is None or agreement >= CONTRADICTED
