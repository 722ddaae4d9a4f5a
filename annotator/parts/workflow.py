"""``annotator markers``' work as library functions: a part marked and its object folder
written (:func:`mark_part`), or a custom dictionary written and read back
(:func:`write_custom_dictionary`); each returns a summary whose ``to_json()`` is the
command's ``--json``."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, cast

from annotator.dataset.model import Instance, Symmetry
from annotator.errors import UserError
from annotator.geometry.mesh import load_mesh
from annotator.io.output_folder import check_output_folder
from annotator.markers.dictionary import (
    custom_dictionary,
    dictionary,
    dictionary_size,
    min_distance,
    resolve_dictionary,
    write_dictionary,
)
from annotator.markers.layout import assign_ids, place_markers
from annotator.parts import PART_NAMES, Part, build_part
from annotator.parts.marking import MarkedPart, write_marked_part
from annotator.symmetry.classes import SYMMETRY_CLASSES, SymmetryKind

__all__ = [
    "DictionarySummary",
    "MarkSettings",
    "MarkSummary",
    "mark_part",
    "write_custom_dictionary",
]


@dataclass(frozen=True)
class MarkSettings:
    """How a part is marked (``annotator markers``' options of the same names).

    Attributes:
        size_mm: The printed marker side (None: the part's own, 10 mm for a mesh file).
        dictionary: An OpenCV predefined dictionary or a dictionary file.
        instances: Physical copies, each with its own ids.
        first_id: The first marker id.
        max_sites: At most this many sites (None: as many as fit).
        flatness_mm: The largest gap between a printed square and the surface.
        symmetry: The symmetry class of a mesh file's part.
        dpi: The sheets' resolution.
        seed: The layout's random seed.

    >>> MarkSettings(size_mm=12.0, instances=4).instances
    4
    """

    size_mm: float | None = None
    dictionary: str = "DICT_4X4_1000"
    instances: int = 1
    first_id: int = 0
    max_sites: int | None = None
    flatness_mm: float = 0.35
    symmetry: str | None = None
    dpi: int = 300
    seed: int = 0


@dataclass(frozen=True)
class MarkSummary:
    """What :func:`mark_part` wrote.

    >>> s = MarkSummary("bracket", sites=12, min_facing=3, size_mm=10.0, instances=4,
    ...                 ids=(0, 47), out="bracket")
    >>> s.counts()
    {'sites': 12, 'min_facing': 3, 'instances': 4}
    >>> s.to_json()["ids"]
    [0, 47]
    """

    part: str
    sites: int
    min_facing: int
    size_mm: float
    instances: int
    ids: tuple[int, int]
    out: str

    def counts(self) -> dict[str, int]:
        return {"sites": self.sites, "min_facing": self.min_facing, "instances": self.instances}

    def warnings(self) -> list[str]:
        return []

    def written_paths(self) -> list[Path]:
        return [Path(self.out)]

    def exit_status(self) -> int:
        return 0

    def to_json(self) -> dict[str, Any]:
        """The summary as plain JSON values (``annotator markers --json``)."""
        doc = asdict(self)
        doc["ids"] = list(self.ids)
        return doc

    def text(self) -> str:
        return (
            f"markers: {self.sites} sites of {self.size_mm:g} mm on {self.part}; from any "
            f"direction at least {self.min_facing} face the viewer (within 60 degrees); "
            f"{self.instances} instances, ids {self.ids[0]}..{self.ids[1]}; written to "
            f"{self.out} (object.yaml, sheets/, textured/)"
        )


def mark_part(
    part: str | Path,
    out: str | Path,
    settings: MarkSettings | None = None,
    *,
    overwrite: bool = False,
) -> MarkSummary:
    """Place marker sites on ``part`` (a built-in part's name or a mesh file, mm) and write
    its object folder ``out``: object.yaml (sites, instances with disjoint ids), the mesh,
    true-scale sheets to print and a textured OBJ per instance.

    >>> import tempfile
    >>> from pathlib import Path
    >>> out = Path(tempfile.mkdtemp()) / "brick"
    >>> s = mark_part("brick", out, MarkSettings(instances=2, dpi=50))
    >>> s.instances, (out / "object.yaml").is_file()
    (2, True)

    Raises:
        UserError: an unknown part, OUT not writable (exists, or holds the mesh), no flat
            patch for the markers, more ids than the dictionary holds.
    """
    s = settings or MarkSettings()
    if s.instances < 1 or s.first_id < 0 or not 50 <= s.dpi <= 2400 or not s.flatness_mm > 0:
        raise UserError(
            "--instances >= 1, --first-id >= 0, --dpi in 50..2400 and --flatness > 0 are required"
        )
    if s.size_mm is not None and not s.size_mm > 0:
        raise UserError(f"--size must be positive, got {s.size_mm}")
    name = resolve_dictionary(s.dictionary, Path.cwd())
    out = Path(out)
    chosen = _part(str(part), out, s, overwrite)
    marked = _mark(chosen, s, name, dictionary_size(name))
    write_marked_part(out, marked, dpi=s.dpi)
    layout = marked.layout
    first, last = marked.instances[0].marker_ids[0], marked.instances[-1].marker_ids[-1]
    return MarkSummary(
        chosen.name, len(layout.corners), layout.min_facing, marked.size_mm, s.instances,
        (first, last), str(out),
    )  # fmt: skip


def _part(part: str, out: Path, s: MarkSettings, overwrite: bool) -> Part:
    """A built-in part, or a mesh file (which OUT must not hold) with its symmetry; OUT
    checked before the part is built or read."""
    if part in PART_NAMES:
        check_output_folder(out, command="markers", overwrite=overwrite)
        return build_part(part)
    path = Path(part)
    if path.suffix == "" and not path.exists():
        build_part(part)  # a mistyped part name: UserError listing the known ones
    check_output_folder(out, command="markers", overwrite=overwrite, protect=[path])
    kind = s.symmetry or "none"
    if kind not in SYMMETRY_CLASSES:
        raise UserError(f"--symmetry must be one of {', '.join(SYMMETRY_CLASSES)}, not {kind!r}")
    mesh = load_mesh(path)
    return Part(path.stem, mesh, Symmetry(cast(SymmetryKind, kind)), marker_size=10.0)


def _mark(part: Part, s: MarkSettings, name: str, n_dict: int) -> MarkedPart:
    """The sites on the part and the instances' ids, which must fit in the dictionary."""
    size = s.size_mm or part.marker_size
    layout = place_markers(
        part.mesh, size=size, max_sites=s.max_sites, flatness_tol=s.flatness_mm, seed=s.seed
    )
    if len(layout.corners) == 0:
        raise UserError(
            f"no flat patch of the part fits a {size:g} mm marker: try a smaller --size or a "
            "larger --flatness"
        )
    ids = assign_ids(len(layout.corners), s.instances, start=s.first_id)
    if ids[-1][-1] >= n_dict:
        raise UserError(
            f"{s.instances} instances x {len(layout.corners)} sites need ids up to "
            f"{ids[-1][-1]}, but {name} has {n_dict}: use fewer instances, --max-sites or a "
            "larger dictionary"
        )
    instances = [Instance(f"{k + 1:02d}", tuple(i)) for k, i in enumerate(ids)]
    return MarkedPart(part, layout, instances, size, name)


@dataclass(frozen=True)
class DictionarySummary:
    """What :func:`write_custom_dictionary` wrote, as read back.

    >>> s = DictionarySummary("mine.yml", markers=20, bits=6, min_distance=14,
    ...                       max_correction_bits=6)
    >>> s.counts()
    {'markers': 20, 'bits': 6, 'min_distance': 14}
    >>> [str(p) for p in s.written_paths()]
    ['mine.yml']
    """

    dictionary: str
    markers: int
    bits: int
    min_distance: int
    max_correction_bits: int

    def counts(self) -> dict[str, int]:
        return {"markers": self.markers, "bits": self.bits, "min_distance": self.min_distance}

    def warnings(self) -> list[str]:
        return []

    def written_paths(self) -> list[Path]:
        return [Path(self.dictionary)]

    def exit_status(self) -> int:
        return 0

    def to_json(self) -> dict[str, Any]:
        """The summary as plain JSON values (``annotator markers --write-dictionary --json``)."""
        return asdict(self)

    def text(self) -> str:
        return (
            f"markers: wrote {self.dictionary}: {self.markers} markers of {self.bits}x"
            f"{self.bits} bits, any two at least {self.min_distance} bits apart (up to "
            f"{self.max_correction_bits} wrong bits corrected); name it as the dictionary in "
            "dataset.yaml, board.yaml or --dictionary"
        )


def write_custom_dictionary(
    path: str | Path, *, count: int = 100, bits: int = 6, min_bits: int = 8, seed: int = 0
) -> DictionarySummary:
    """A dictionary of ``count`` markers of ``bits`` x ``bits`` bits, any two at least
    ``min_bits`` apart in any of their turns, written to ``path`` (OpenCV's format) and
    checked by reading it back.

    >>> import tempfile
    >>> from pathlib import Path
    >>> s = write_custom_dictionary(Path(tempfile.mkdtemp()) / "d.yml", count=10, bits=4, min_bits=4)
    >>> s.markers, s.bits, s.min_distance >= 4
    (10, 4, True)
    """
    path = Path(path)
    write_dictionary(path, custom_dictionary(count, bits, min_bits=min_bits, seed=seed))
    back = dictionary(str(path.resolve()))
    return DictionarySummary(
        str(path),
        int(back.bytesList.shape[0]),
        int(back.markerSize),
        min_distance(back),
        int(back.maxCorrectionBits),
    )
