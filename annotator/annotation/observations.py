"""A scene's marker readings sorted to the instances that carry them (the dataset's marker
table): each camera's detections as PnP observations per instance, and the ids that belong
to no instance or were seen twice in one image."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

from annotator.dataset import Dataset
from annotator.detection.aruco import ImageReading
from annotator.pnp import Observation

__all__ = ["SortedMarkers", "sort_markers"]


@dataclass
class SortedMarkers:
    """What the scene's markers say: observations per instance, and the ids per camera that
    belong to no instance or were seen twice in one image."""

    per_instance: dict[tuple[str, str], list[Observation]]
    unknown: dict[str, list[int]]
    duplicates: dict[str, list[int]]


def sort_markers(ds: Dataset, readings: list[ImageReading]) -> SortedMarkers:
    """Each camera's markers sorted to the instances that carry them (by the dataset's
    marker table), the unknown ids and those seen twice in one image."""
    cams = ds.rig.cameras
    out = SortedMarkers(defaultdict(list), {}, {})
    for j, reading in enumerate(readings):
        counts: dict[int, int] = defaultdict(int)
        for d in reading.markers:
            counts[d.id] += 1
        for d in reading.markers:
            ref = ds.marker_table.get(d.id)
            if ref is None:
                if not d.soft:  # a soft reading of an unknown id is most likely a misreading
                    out.unknown.setdefault(cams[j].name, []).append(d.id)
                continue
            if counts[d.id] > 1 and d.id not in out.duplicates.get(cams[j].name, []):
                out.duplicates.setdefault(cams[j].name, []).append(d.id)
            X = ds.objects[ref.object].site_corners(ref.instance)[ref.site]
            out.per_instance[(ref.object, ref.instance)].append(
                Observation(j, d.id, X, d.corners, soft=d.soft)
            )
    return out
