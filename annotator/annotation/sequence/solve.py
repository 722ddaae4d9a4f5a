"""Solving a sequence: every frame's ``scene_T_rig`` and every instance's pose from the frames'
readings (:func:`solve_sequence`), and the three steps on one scene in this process
(:func:`annotate_sequence`)."""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from annotator.annotation.observations import sort_markers
from annotator.annotation.sequence.adjustment import bundle
from annotator.annotation.sequence.annotation import sequence_annotation
from annotator.annotation.sequence.placing import place
from annotator.annotation.sequence.reading import (
    FrameReading,
    Seen,
    depth_lookup,
    read_frame_sampled,
)
from annotator.annotation.sequence.solution import SequenceSolution
from annotator.annotation.sequence.visibility import frame_visibility, visibility_step
from annotator.annotation.settings import AnnotateSettings
from annotator.dataset import Dataset, Scene
from annotator.dataset.figures import (
    SceneWarning,
)
from annotator.dataset.flags import FrameFlag, WarningKind
from annotator.dataset.records import (
    FramePose,
    SceneAnnotation,
)
from annotator.detection import MarkerDetector
from annotator.errors import UserError


def solve_sequence(
    ds: Dataset, readings: list[FrameReading], *, settings: AnnotateSettings = AnnotateSettings()
) -> SequenceSolution:
    """Every frame's ``scene_T_rig`` and every instance's pose from the frames' readings (in
    frame order): see the module's docstring."""
    cams = ds.rig.cameras
    depth_cam = None if ds.rig.depth is None else [c.name for c in cams].index(ds.rig.depth.camera)
    names = [r.frame for r in readings]
    frames_seen: list[Seen] = []
    unknown: dict[str, set[int]] = defaultdict(set)
    duplicates: dict[str, set[int]] = defaultdict(set)
    for reading in readings:
        markers = sort_markers(ds, reading.readings)
        for cam, ids in markers.unknown.items():
            unknown[cam].update(ids)
        for cam, ids in markers.duplicates.items():
            duplicates[cam].update(ids)
        depth_of = depth_lookup(reading, depth_cam)
        seen = Seen({})
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
    placed = place(ds, frames_seen, settings)
    if placed is None:
        for name in names:
            out.frames[name] = FramePose(name, None, flags=[FrameFlag.NO_KNOWN_MARKERS])
        out.warnings.append(
            SceneWarning(WarningKind.NO_MARKERS, "no marker of a known instance in any frame")
        )
        return out
    streaks = np.array([[r.streak_px(j) for j in range(len(cams))] for r in readings])
    bundle(
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
    step = visibility_step(settings)
    read = [read_frame_sampled(ds, f, detector, step=step) for f in frames]
    readings = [r for r, _ in read]
    solution = solve_sequence(ds, readings, settings=settings)
    seen = {}
    for f, (_, depth) in zip(frames, read):
        T = solution.frames[f.name].scene_T_rig
        if T is not None:
            seen[f.name] = frame_visibility(
                ds, f, solution.instances, T, settings=settings, depth_samples=depth
            )
    return sequence_annotation(solution, readings, seen, settings=settings)
