"""``annotator synth OUT``: synthetic bin-picking scenes with exact ground truth."""

from __future__ import annotations

import argparse

from annotator.commands import add_ray_option, add_workers_option, finish
from annotator.commands.synth_calibration import add_calibration_options, synth_calibration
from annotator.commands.synth_pbr import add_pbr_options
from annotator.commands.synth_scenes import add_rendering_options, add_scene_options, scene_settings
from annotator.errors import UserError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # The order of the calls is the order of the usage line, which argparse errors print.
    parser.add_argument(
        "out", help="output dataset folder (new or empty; an earlier synth's with --overwrite)"
    )
    add_scene_options(parser)
    add_workers_option(parser)
    add_ray_option(parser)
    add_rendering_options(parser)
    add_pbr_options(parser)
    add_calibration_options(parser)
    _add_twin_options(parser)
    _add_output_options(parser)


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


def run(args: argparse.Namespace) -> int:
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
    if args.render == "pbr" and (args.twin or args.calibration or args.frames):
        what = "--twin" if args.twin else "--calibration" if args.calibration else "--frames"
        raise UserError(f"--render pbr does not apply to {what} (fixed-rig scenes only)")
    if args.motion_blur is not None and not args.frames:
        raise UserError("--motion-blur applies to sequences only: give --frames N too")
    batch = dict(
        workers=args.workers, quiet=args.quiet, ray_address=args.ray, ray_wait=args.ray_wait
    )
    if args.twin:
        from annotator.twins.dataset import synthesize_twins
        from annotator.twins.render import TwinSettings

        done = synthesize_twins(
            args.twin,
            args.out,
            settings=TwinSettings(blur=args.blur, noise=args.noise, seed=args.seed),
            include_pending=args.include_pending,
            drop_rejected_instances=args.drop_rejected_instances,
            overwrite=args.overwrite,
            **batch,
        )
        return finish(done, as_json=args.json)
    settings = scene_settings(args)
    if settings.frames:
        from annotator.synthesis.sequence import synthesize_sequences

        made = synthesize_sequences(args.out, settings, overwrite=args.overwrite, **batch)
        return finish(made, as_json=args.json)
    if args.calibration:
        return synth_calibration(args, settings)
    from annotator.synthesis.scenes import synthesize_scenes

    scenes = synthesize_scenes(args.out, settings, overwrite=args.overwrite, **batch)
    return finish(scenes, as_json=args.json)
