"""A part made ready for marking: its object folder (``object.yaml`` with the marker sites
and the instances' ids, the mesh, true-scale sheets to print, a textured OBJ per instance),
as ``annotator markers PART OUT`` writes it."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import trimesh

from annotator.dataset.model import Instance, MarkerSites
from annotator.dataset.write import write_object_yaml
from annotator.io.atomic import atomic_folder
from annotator.io.output_folder import write_manifest
from annotator.markers.layout import MarkerLayout
from annotator.markers.sheets import SheetMarker, render_pages, write_sheets
from annotator.markers.textured import write_textured_obj
from annotator.parts import Part


@dataclass(frozen=True)
class MarkedPart:
    """A part with its marker sites, the physical copies (each with its own marker ids), the
    printed marker side (mm) and the dictionary the markers come from."""

    part: Part
    layout: MarkerLayout
    instances: list[Instance]
    size_mm: float
    dictionary: str


def write_object_files(
    folder: Path,
    part: Part,
    sites: MarkerSites,
    instances: Sequence[Instance],
    *,
    material: str | None = None,
) -> None:
    """The part's mesh (``model.ply``) and ``object.yaml`` (its symmetry, marker sites and
    instances, and ``material`` when given) in ``folder``: what a dataset needs of an
    object."""
    trimesh.Trimesh(part.mesh.vertices, part.mesh.faces, process=False).export(folder / "model.ply")
    write_object_yaml(
        folder,
        mesh_file="model.ply",
        symmetry=part.symmetry,
        markers=sites,
        instances=instances,
        **({} if material is None else {"material": material}),
    )


def write_marked_part(out: Path, marked: MarkedPart, *, dpi: int) -> None:
    """Write the object folder ``out`` at once (nothing of it if anything fails), the sheets
    at ``dpi``."""
    part = marked.part
    with atomic_folder(out) as tmp:
        write_manifest(tmp, command="markers")
        write_object_files(tmp, part, marked.layout.sites, marked.instances)
        _write_sheets(tmp / "sheets", marked, dpi=dpi)
        _write_textured(tmp / "textured", marked)


def _write_sheets(folder: Path, marked: MarkedPart, *, dpi: int) -> None:
    """The pages to print, each marker labelled with its id, instance and site."""
    labels = [
        SheetMarker(m, f"{m} {marked.part.name}/{inst.name} s{k}")
        for inst in marked.instances
        for k, m in enumerate(inst.marker_ids)
    ]
    folder.mkdir()
    write_sheets(
        folder,
        render_pages(marked.dictionary, labels, size_mm=marked.size_mm, dpi=dpi),
        dpi=dpi,
    )


def _write_textured(folder: Path, marked: MarkedPart) -> None:
    """One textured OBJ per instance; the first one is named after the part alone."""
    name, instances = marked.part.name, marked.instances
    folder.mkdir()
    for inst in instances:
        stem = name if len(instances) == 1 or inst is instances[0] else f"{name}_{inst.name}"
        write_textured_obj(
            folder,
            stem,
            marked.part.mesh,
            marked.layout.corners,
            inst.marker_ids,
            marked.dictionary,
        )
