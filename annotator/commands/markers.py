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
from typing import TYPE_CHECKING

from annotator.commands import finish, number, whole
from annotator.errors import UserError
from annotator.parts import PART_NAMES

if TYPE_CHECKING:
    from annotator.parts.workflow import DictionarySummary, MarkSummary


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
    from annotator.parts.workflow import MarkSettings, mark_part, write_custom_dictionary

    if args.write_dictionary:
        if args.part is not None:
            raise UserError("--write-dictionary writes a dictionary only: give no PART or OUT")
        summary: MarkSummary | DictionarySummary = write_custom_dictionary(
            args.write_dictionary,
            count=args.count,
            bits=args.bits,
            min_bits=args.min_distance,
            seed=args.seed,
        )
    elif args.part is None or args.out is None:
        raise UserError("give PART and OUT (or --write-dictionary FILE)")
    else:
        settings = MarkSettings(
            size_mm=args.size,
            dictionary=args.dictionary,
            instances=args.instances,
            first_id=args.first_id,
            max_sites=args.max_sites,
            flatness_mm=args.flatness,
            symmetry=args.symmetry,
            dpi=args.dpi,
            seed=args.seed,
        )
        summary = mark_part(args.part, args.out, settings, overwrite=args.overwrite)
    return finish(summary, as_json=args.json)
