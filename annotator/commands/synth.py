"""``annotator synth OUT``: synthetic bin-picking scenes with exact ground truth."""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path
from typing import Any

from annotator.commands import add_ray_option, add_workers_option, finish_batch, number, whole
from annotator.dataset.model import SCENES_DIR
from annotator.errors import UserError
from annotator.io.atomic import atomic_folder
from annotator.io.output_folder import check_output_folder, write_manifest
from annotator.parts import PART_NAMES, build_part
from annotator.runner import run_batch
from annotator.synthesis.generate import (
    GLUED_SITES,
    SceneJob,
    SynthConfig,
    _plan,
    write_dataset_files,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # The order of the calls is the order of the usage line, which argparse errors print.
    parser.add_argument(
        "out", help="output dataset folder (new or empty; an earlier synth's with --overwrite)"
    )
    _add_scene_options(parser)
    add_workers_option(parser)
    add_ray_option(parser)
    _add_rendering_options(parser)
    _add_calibration_options(parser)
    _add_twin_options(parser)
    _add_output_options(parser)


def _add_scene_options(parser: argparse.ArgumentParser) -> None:
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


def _add_rendering_options(parser: argparse.ArgumentParser) -> None:
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
        type=_glue,
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
        default=SynthConfig.supersample,
        metavar="N",
        help="sub-pixel rays per side on marker edges (default "
        f"{SynthConfig.supersample}; 1 is quick, for tests)",
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


def _add_calibration_options(parser: argparse.ArgumentParser) -> None:
    """``--calibration``: board shots instead of scenes, and how the board is seen."""
    calib = parser.add_argument_group("--calibration", "the board shots")
    calib.add_argument(
        "--calibration",
        action="store_true",
        help="instead of scenes, render a ChArUco board in --scenes random poses (use 30) seen "
        "by the rig, into OUT/<camera>/<shot>.png with board.yaml and truth.yaml "
        "(for `annotator calibrate`)",
    )
    calib.add_argument(
        "--board-kind",
        choices=("charuco", "chessboard"),
        default="charuco",
        help="a 7x5 ChArUco board (default) or a 9x6 plain chessboard, 30 mm squares",
    )
    calib.add_argument(
        "--board-dictionary",
        metavar="NAME|FILE",
        help="the ChArUco board's dictionary: a predefined name or a dictionary file, copied "
        "beside board.yaml (default DICT_4X4_50)",
    )
    calib.add_argument("--inverted", action="store_true", help="the board printed colour-inverted")
    calib.add_argument(
        "--mirror",
        metavar="CAMERA",
        action="append",
        default=[],
        help="store this camera's images mirrored (a webcam in selfie mode); repeatable",
    )
    calib.add_argument(
        "--centre",
        type=number(low=0.1, high=1.0),
        default=1.0,
        metavar="F",
        help="keep the board within the central fraction F of every image (default 1: anywhere)",
    )
    calib.add_argument(
        "--distance",
        metavar="MIN-MAX",
        default="520-760",
        help="range of the board centre's depth in the first camera, mm (default 520-760)",
    )
    calib.add_argument(
        "--video",
        action="store_true",
        help="one video per camera (OUT/<camera>.mkv, lossless) with timestamps files, "
        "instead of image folders",
    )


def _add_twin_options(parser: argparse.ArgumentParser) -> None:
    """``--twin``: the synthetic twins of an annotated dataset instead of new scenes."""
    group = parser.add_argument_group("--twin", "synthetic twins of annotated scenes")
    group.add_argument(
        "--twin",
        metavar="DATASET",
        help="instead of new scenes, the synthetic twin of every accepted scene of DATASET: its "
        "rig, its annotated poses, its background, the same sensor simulation (paper section 5)",
    )
    group.add_argument(
        "--include-pending",
        action="store_true",
        help="--twin: also the annotated scenes not reviewed yet",
    )
    group.add_argument(
        "--drop-rejected-instances",
        action="store_true",
        help="--twin: twin accepted scenes with rejected instances, without them",
    )


def _add_output_options(parser: argparse.ArgumentParser) -> None:
    """Where the output goes and what is printed."""
    group = parser.add_argument_group("output")
    group.add_argument(
        "--overwrite", action="store_true", help="replace OUT if an earlier synth wrote it"
    )
    group.add_argument("--json", action="store_true", help="print the summary as JSON")
    group.add_argument("--quiet", action="store_true", help="no progress bar")


def _glue(text: str) -> tuple[float, float]:
    """``MM,DEG`` for --glue: two finite numbers, at least 0."""
    parts = text.split(",")
    finite = number(low=0)
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"must be MM,DEG (e.g. 0.7,2), not {text!r}")
    return finite(parts[0]), finite(parts[1])


def _config(args: argparse.Namespace) -> SynthConfig:
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
    return SynthConfig(
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
    )


#: ``--motion-blur``'s default: a quarter of a sequence's frames are blurred.
MOTION_BLUR = 0.25


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if args.no_markers and (args.twin or args.calibration):
        # A twin's markers are the real scene's, and board shots have no parts.
        raise UserError(
            f"--no-markers does not apply to {'--twin' if args.twin else '--calibration'}"
        )
    if args.frames and (args.twin or args.calibration):
        raise UserError(
            f"--frames does not apply to {'--twin' if args.twin else '--calibration'} "
            "(sequences are made of new scenes)"
        )
    if args.cameras != 2 and (args.twin or args.calibration):
        raise UserError(f"--cameras does not apply to {'--twin' if args.twin else '--calibration'}")
    if args.motion_blur is not None and not args.frames:
        raise UserError("--motion-blur applies to sequences only: give --frames N too")
    if args.twin:
        from annotator.commands.twin import synth_twin

        return synth_twin(args)
    config = _config(args)
    if config.frames:
        return _sequences(args, config)
    check_output_folder(out, command="synth", overwrite=args.overwrite)
    if args.calibration:
        if args.ray is not None:
            raise UserError("--ray does not apply to --calibration (board shots are quick)")
        return _calibration_captures(args, config)
    with atomic_folder(out) as tmp:
        write_manifest(tmp, command="synth")
        plan = _plan(config)
        write_dataset_files(plan, tmp)
        ids = [f"{k:06d}" for k in range(config.scenes)]
        report = run_batch(
            SceneJob(config, str(tmp)),
            ids,
            workers=args.workers,
            desc="synth",
            quiet=args.quiet,
            ray_address=args.ray,
            ray_wait=args.ray_wait,
        )
        for sid in report.failed:
            shutil.rmtree(tmp / SCENES_DIR / sid, ignore_errors=True)
    summary = {
        "out": str(out),
        "scenes": len(report.done),
        "failed": len(report.failed),
        "instances": sum(r["instances"] for r in report.done.values()),
        "seconds_per_scene": {
            k: round(sum(r[k] for r in report.done.values()) / max(len(report.done), 1), 3)
            for k in ("physics", "rendering", "depth", "occlusion")
        },
        "failures": dict(sorted(report.failed.items())),
    }
    t = summary["seconds_per_scene"]
    return finish_batch(
        report,
        summary,
        f"synth: {summary['scenes']} scenes ({summary['instances']} instances) written to {out}, "
        f"{summary['failed']} failed; per scene: physics {t['physics']} s, rendering "
        f"{t['rendering']} s, depth {t['depth']} s, occlusion rates {t['occlusion']} s",
        as_json=args.json,
    )


def _sequences(args: argparse.Namespace, config: SynthConfig) -> int:
    """``annotator synth --frames N OUT``: sequences of a moving rig
    (:func:`annotator.synthesis.sequence.synthesize_sequences`)."""
    from annotator.synthesis.sequence import synthesize_sequences

    done = synthesize_sequences(
        args.out,
        config,
        overwrite=args.overwrite,
        workers=args.workers,
        quiet=args.quiet,
        ray_address=args.ray,
        ray_wait=args.ray_wait,
    )
    return finish_batch(done.report, done.to_json(), done.line(), as_json=args.json)


def _calibration_captures(args: argparse.Namespace, config: Any) -> int:
    """``annotator synth --calibration OUT``: a board in ``--scenes`` random poses seen by the
    synthetic rig of ``--seed`` (``--size``, ``--noise``, ``--blur`` apply), written by
    :func:`annotator.synthesis.board.write_captures`."""
    from annotator.calibration.board import BoardSpec
    from annotator.markers.dictionary import resolve_dictionary
    from annotator.synthesis.board import CaptureConfig, write_captures

    if args.board_kind == "chessboard":
        board = BoardSpec(9, 6, 30.0, kind="chessboard")
    else:
        name = args.board_dictionary or BoardSpec.dictionary
        board = BoardSpec(dictionary=resolve_dictionary(name, Path.cwd()))
    try:
        lo, _, hi = args.distance.partition("-")
        distance = (float(lo), float(hi))
    except ValueError:
        raise UserError(f"--distance must be MIN-MAX in mm, got {args.distance!r}") from None
    if not 0 < distance[0] <= distance[1]:
        raise UserError(f"--distance must satisfy 0 < MIN <= MAX, got {args.distance!r}")
    cfg = CaptureConfig(
        shots=config.scenes,
        distance=distance,
        seed=config.seed,
        size=config.size,
        board=board,
        # A plain chessboard is only found whole.
        min_visible=1.0 if not board.has_markers else CaptureConfig.min_visible,
        noise=config.noise,
        blur=config.blur,
        inverted=args.inverted,
        mirrored=tuple(args.mirror),
        centre=args.centre,
    )
    out = Path(args.out)
    plan = write_captures(cfg, out, workers=args.workers, quiet=args.quiet, video=args.video)
    cameras = [c.name for c in plan.rig.cameras]
    summary = {
        "out": str(out),
        "shots": len(plan.shot_names),
        "cameras": cameras,
        "board": cfg.board.to_yaml(),
    }
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        print(
            f"synth --calibration: {len(plan.shot_names)} shots of a {cfg.board.describe()} "
            f"board seen by {', '.join(cameras)}, written to {out} (board.yaml, truth.yaml)"
        )
    return 0
