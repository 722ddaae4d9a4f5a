"""``annotator synth``'s options of the scenes and their images, and the
:class:`~annotator.synthesis.generate.SynthSettings` they give (:mod:`annotator.commands.synth`)."""

from __future__ import annotations

import argparse

from annotator.commands import number, number_pair, whole
from annotator.commands.synth_pbr import pbr_settings
from annotator.errors import UserError
from annotator.parts import PART_NAMES, build_part
from annotator.synthesis.generate import GLUED_SITES, SynthSettings


def add_scene_options(parser: argparse.ArgumentParser) -> None:
    """What the scenes hold, and the seed that makes them."""
    group = parser.add_argument_group("scenes")
    group.add_argument(
        "--parts",
        default="bracket,cylinder",
        help=f"comma-separated built-in parts ({', '.join(PART_NAMES)})",
    )
    group.add_argument(
        "--scenes", type=whole(low=1), default=10, help="number of scenes (default 10)"
    )
    group.add_argument(
        "--instances", default="8-20", metavar="MIN-MAX", help="instances per scene (default 8-20)"
    )
    group.add_argument(
        "--seed",
        type=whole(low=0),
        default=0,
        help="random seed: same seed, same dataset (default 0)",
    )
    group.add_argument(
        "--frames",
        type=whole(low=1),
        default=None,
        metavar="N",
        help="sequences: a moving rig (rig.moving: true) carried by hand over each scene's "
        "bin, N frames per scene in scenes/<id>/frames/<frame>/ (gt.json in the first "
        "frame's camera, with every frame's scene_T_rig)",
    )


def add_rendering_options(parser: argparse.ArgumentParser) -> None:
    """The images: their size, clutter, sensor noise, glued markers, depth maps."""
    group = parser.add_argument_group("rendering")
    group.add_argument(
        "--size", default="1280x1024", metavar="WxH", help="image size (default 1280x1024)"
    )
    group.add_argument(
        "--clutter",
        type=whole(low=0),
        default=0,
        help="parts without markers per scene (default 0)",
    )
    group.add_argument(
        "--noise",
        type=number(low=0),
        default=2.0,
        help="image noise sigma, grey levels (default 2)",
    )
    group.add_argument(
        "--blur", type=number(low=0), default=0.6, help="image blur sigma, px (default 0.6)"
    )
    group.add_argument(
        "--glue",
        type=number_pair("MM,DEG", "0.7,2"),
        default=(0.0, 0.0),
        metavar="MM,DEG",
        help="markers glued by hand: each marker of each instance moved in its own plane by "
        "N(0, MM) along both axes and turned by N(0, DEG) about its normal, the same in every "
        f"scene; the true sites go to OUT/{GLUED_SITES} (default 0,0: exactly on the layout)",
    )
    group.add_argument(
        "--cameras",
        type=int,
        choices=(1, 2),
        default=2,
        help="the rig's cameras: 2 (default), or 1, the reference camera alone like an RGB-D "
        "sensor's colour camera (its depth still from the simulated stereo pair)",
    )
    group.add_argument(
        "--supersample",
        type=whole(low=1, high=8),
        default=SynthSettings.supersample,
        metavar="N",
        help="sub-pixel rays per side on marker edges (default "
        f"{SynthSettings.supersample}; 1 is quick, for tests)",
    )
    group.add_argument(
        "--motion-blur",
        type=number(low=0, high=1),
        default=None,
        metavar="FRACTION",
        help="--frames: the fraction of each sequence's frames taken with a long exposure, "
        "blurred along their true image motion (default 0.25)",
    )
    group.add_argument("--no-depth", action="store_true", help="skip the active-stereo depth maps")
    group.add_argument(
        "--no-markers",
        action="store_true",
        help="render the parts bare (object.yaml still lists the markers): with the same seed "
        "and options, the same scenes as with markers, pixel for pixel away from them",
    )


def scene_settings(args: argparse.Namespace) -> SynthSettings:
    """The settings the options give (each checked, one line naming the option)."""
    parts = tuple(p.strip() for p in args.parts.split(",") if p.strip())
    if not parts:
        raise UserError("--parts is empty")
    for p in parts:
        build_part(p)  # UserError naming the known parts
    try:
        lo, _, hi = args.instances.partition("-")
        inst = (int(lo), int(hi or lo))
    except ValueError:
        raise UserError(f"--instances must be MIN-MAX, got {args.instances!r}") from None
    if inst[0] < 1 or inst[1] < inst[0]:
        raise UserError(f"--instances must satisfy 1 <= MIN <= MAX, got {args.instances!r}")
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise UserError(f"--size must be WxH, got {args.size!r}") from None
    if w < 160 or h < 120 or w > 8192 or h > 8192:
        raise UserError(f"--size {w}x{h} is out of range (160x120 to 8192x8192)")
    return SynthSettings(
        parts=parts,
        scenes=args.scenes,
        instances=inst,
        seed=args.seed,
        size=(w, h),
        clutter=args.clutter,
        noise=args.noise,
        blur=args.blur,
        depth=not args.no_depth,
        glue=args.glue,
        markers=not args.no_markers,
        supersample=args.supersample,
        cameras=args.cameras,
        frames=args.frames or 0,
        motion_blur=(MOTION_BLUR if args.motion_blur is None else args.motion_blur)
        if args.frames
        else 0.0,
        render=args.render,
        pbr=pbr_settings(args),
    )


#: ``--motion-blur``'s default: a quarter of a sequence's frames are blurred.
MOTION_BLUR = 0.25
