"""A sequence's annotation.json from its solve and what each frame sees
(:func:`sequence_annotation`), and back to one fixed-rig annotation per frame
(:func:`frame_annotations`)."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import replace

import numpy as np

from annotator.annotation.scene import CONTRADICTED
from annotator.annotation.sequence.reading import FrameReading
from annotator.annotation.sequence.solution import SequenceSolution
from annotator.annotation.settings import AnnotateSettings
from annotator.dataset.figures import (
    Occlusion,
)
from annotator.dataset.flags import Flag, sort_flags
from annotator.dataset.frames import poses_in_frame
from annotator.dataset.records import (
    InstanceAnnotation,
    SceneAnnotation,
)


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
        if _contradicted_lone(r, agreements.get(r.key), settings) or _phantom(r, seen, settings):
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


def _phantom(r: InstanceAnnotation, seen: dict[str, dict[str, dict]], s: AnnotateSettings) -> bool:
    """A pose on one marker read once (one camera, one frame) that other frames see mostly
    unhidden (the settings' ``phantom_frames`` of them) without reading any of its markers."""
    if not (r.frames_seen == 1 and r.count("used") == 1):
        return False
    unread = sum(
        1
        for found in seen.values()
        if r.key in found and min(found[r.key]["occlusion"].values()) < 0.5
    )
    return unread - 1 >= s.sequence.phantom_frames


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
