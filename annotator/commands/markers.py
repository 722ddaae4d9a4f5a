"""``annotator markers PART OUT``: place marker sites on a part; print and preview them.

PART is a built-in part name or a mesh file (mm). OUT receives ``object.yaml`` (markers and
instances with disjoint ids), the mesh, ``sheets/`` (true-scale PNG pages and a PDF) and
``textured/`` (an OBJ per instance showing its markers). ``--dictionary`` is a predefined
name or a dictionary file (:mod:`annotator.markers.dictionary`).

``annotator markers --write-dictionary FILE --count N --bits B --min-distance D`` writes a
custom dictionary instead: N markers of B x B bits, any two at least D bits apart in any of
their turns (OpenCV's format, usable wherever a dictionary is named).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from annotator.commands import number, whole
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


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "part", nargs="?", help=f"a built-in part ({', '.join(PART_NAMES)}) or a mesh file in mm"
    )
    parser.add_argument("out", nargs="?", help="output folder (an object folder of a dataset)")
    parser.add_argument(
        "--size",
        type=number(low=0, above=True),
        help="printed marker side in mm (default: the part's, or 10)",
    )
    parser.add_argument(
        "--dictionary",
        default="DICT_4X4_1000",
        help="ArUco dictionary: an OpenCV predefined name or a dictionary file (default "
        "DICT_4X4_1000)",
    )
    custom = parser.add_argument_group(
        "custom dictionary", "--write-dictionary FILE: write a dictionary instead (no PART, OUT)"
    )
    custom.add_argument("--write-dictionary", metavar="FILE", help="the dictionary file to write")
    custom.add_argument(
        "--count", type=whole(low=1), default=100, help="markers in it (default 100)"
    )
    custom.add_argument(
        "--bits", type=whole(low=3, high=8), default=6, help="bits per marker side (default 6)"
    )
    custom.add_argument(
        "--min-distance",
        type=whole(low=1),
        default=8,
        help="smallest distance between two markers, in bits, any turn (default 8)",
    )
    parser.add_argument(
        "--instances", type=whole(low=1), default=1, help="physical copies to make (default 1)"
    )
    parser.add_argument(
        "--first-id", type=whole(low=0), default=0, help="first marker id (default 0)"
    )
    parser.add_argument("--max-sites", type=whole(low=1), help="at most this many sites per part")
    parser.add_argument(
        "--flatness",
        type=number(low=0, above=True),
        default=0.35,
        help="max gap between square and surface, mm (default 0.35)",
    )
    parser.add_argument(
        "--symmetry", default=None, help="symmetry class for a mesh file (default none)"
    )
    parser.add_argument(
        "--dpi",
        type=whole(low=1, high=2400),
        default=300,
        help="resolution of the PNG sheets (default 300)",
    )
    parser.add_argument("--seed", type=whole(low=0), default=0, help="random seed (default 0)")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace OUT if an earlier `markers` wrote it"
    )
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")


def run(args: argparse.Namespace) -> int:
    if args.write_dictionary:
        return _write_dictionary(args)
    if args.part is None or args.out is None:
        raise UserError("give PART and OUT (or --write-dictionary FILE)")
    args.dictionary = resolve_dictionary(args.dictionary, Path.cwd())
    out = Path(args.out)
    if args.size is not None and args.size <= 0:
        raise UserError(f"--size must be positive, got {args.size}")
    if args.instances < 1 or args.first_id < 0 or not 50 <= args.dpi <= 2400 or args.flatness <= 0:
        raise UserError(
            "--instances >= 1, --first-id >= 0, --dpi in 50..2400 and --flatness > 0 are required"
        )
    n_dict = dictionary_size(args.dictionary)
    part = _part(args, out)
    marked = _mark(args, part, n_dict)
    write_marked_part(out, marked, dpi=args.dpi)
    _print_summary(args, marked, out)
    return 0


def _part(args: argparse.Namespace, out: Path) -> Part:
    """PART: a built-in part, or a mesh file (which OUT must not hold) with --symmetry; OUT
    checked before the part is built or read."""
    if args.part in PART_NAMES:
        check_output_folder(out, command="markers", overwrite=args.overwrite)
        return build_part(args.part)
    path = Path(args.part)
    if path.suffix == "" and not path.exists():
        build_part(args.part)  # a mistyped part name: UserError listing the known ones
    check_output_folder(out, command="markers", overwrite=args.overwrite, protect=[path])
    mesh = load_mesh(path)
    return Part(path.stem, mesh, Symmetry(args.symmetry or "none"), marker_size=10.0)


def _mark(args: argparse.Namespace, part: Part, n_dict: int) -> MarkedPart:
    """The sites on the part and the instances' ids, which must fit in the dictionary."""
    size = args.size or part.marker_size
    layout = place_markers(
        part.mesh, size=size, max_sites=args.max_sites, flatness_tol=args.flatness, seed=args.seed
    )
    if len(layout.corners) == 0:
        raise UserError(
            f"no flat patch of the part fits a {size:g} mm marker: try a smaller --size or a larger --flatness"
        )
    ids = assign_ids(len(layout.corners), args.instances, start=args.first_id)
    if ids[-1][-1] >= n_dict:
        raise UserError(
            f"{args.instances} instances x {len(layout.corners)} sites need ids up to {ids[-1][-1]}, "
            f"but {args.dictionary} has {n_dict}: use fewer instances, --max-sites or a larger dictionary"
        )
    instances = [Instance(f"{k + 1:02d}", tuple(i)) for k, i in enumerate(ids)]
    return MarkedPart(part, layout, instances, size, args.dictionary)


def _print_summary(args: argparse.Namespace, marked: MarkedPart, out: Path) -> None:
    name, size, layout = marked.part.name, marked.size_mm, marked.layout
    first, last = marked.instances[0].marker_ids[0], marked.instances[-1].marker_ids[-1]
    summary = {
        "part": name,
        "sites": len(layout.corners),
        "min_facing": layout.min_facing,
        "size_mm": size,
        "instances": args.instances,
        "ids": [first, last],
        "out": str(out),
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"markers: {summary['sites']} sites of {size:g} mm on {name}; from any direction at least "
            f"{layout.min_facing} face the viewer (within 60 degrees); {args.instances} instances, ids "
            f"{first}..{last}; written to {out} (object.yaml, sheets/, textured/)"
        )


def _write_dictionary(args: argparse.Namespace) -> int:
    """``--write-dictionary FILE``: a custom dictionary, checked by reading it back."""
    if args.part is not None:
        raise UserError("--write-dictionary writes a dictionary only: give no PART or OUT")
    path = Path(args.write_dictionary)
    d = custom_dictionary(args.count, args.bits, min_bits=args.min_distance, seed=args.seed)
    write_dictionary(path, d)
    back = dictionary(str(path.resolve()))
    reached = min_distance(back)
    summary = {
        "dictionary": str(path),
        "markers": int(back.bytesList.shape[0]),
        "bits": int(back.markerSize),
        "min_distance": reached,
        "max_correction_bits": int(back.maxCorrectionBits),
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"markers: wrote {path}: {summary['markers']} markers of {args.bits}x{args.bits} "
            f"bits, any two at least {reached} bits apart (up to "
            f"{summary['max_correction_bits']} wrong bits corrected); name it as the "
            "dictionary in dataset.yaml, board.yaml or --dictionary"
        )
    return 0
