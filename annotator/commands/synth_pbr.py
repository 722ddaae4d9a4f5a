"""``synth --render pbr``'s options: Cycles' images (the ``pbr`` extra), the materials
of the parts, the lights, the lens and the sensor."""

from __future__ import annotations

import argparse

from annotator.commands import number_pair, whole
from annotator.dataset.materials import PRESETS
from annotator.errors import UserError
from annotator.synthesis.generate import RENDERS
from annotator.synthesis.pbr.cycles_job import Quality
from annotator.synthesis.pbr.render import DEPTH_MODELS, PbrSettings
from annotator.synthesis.pbr.sensor import SensorSettings


def add_pbr_options(parser: argparse.ArgumentParser) -> None:
    """``--render pbr``: Cycles' images (the ``pbr`` extra) and what they are made of."""
    group = parser.add_argument_group("--render pbr", "physically based images (Cycles)")
    group.add_argument(
        "--render",
        choices=RENDERS,
        default="lambert",
        help="lambert: the quick ray-cast render (default); pbr: Cycles, with materials, area "
        "lights, depth of field, sensor noise and a structured-light depth map (needs "
        "`pip install 'bin-annotator[pbr]'`, see README)",
    )
    group.add_argument(
        "--material",
        action="append",
        default=[],
        metavar="PART=PRESET",
        help=f"a part's material, written to its object.yaml ({', '.join(sorted(PRESETS))}; "
        "default painted_plastic); repeat for each part",
    )
    q = Quality()
    group.add_argument(
        "--samples",
        type=whole(low=1, high=4096),
        default=q.samples,
        help=f"Cycles samples per pixel (default {q.samples}, denoised)",
    )
    group.add_argument("--no-denoise", action="store_true", help="no OpenImageDenoise pass")
    group.add_argument(
        "--lights",
        type=int,
        choices=(0, 1, 2),
        default=2,
        help="area lights above the bin (default 2; the environment lights too)",
    )
    group.add_argument(
        "--dof",
        type=number_pair("MM,F", "520,2.8"),
        default=None,
        metavar="MM,F",
        help="depth of field: focus distance (mm) and f-number (default: none, a pinhole)",
    )
    group.add_argument(
        "--exposure",
        type=float,
        default=0.0,
        metavar="STOPS",
        help="stops above the automatic exposure (default 0)",
    )
    group.add_argument(
        "--no-sensor-noise", action="store_true", help="no shot and read noise (an ideal sensor)"
    )
    group.add_argument(
        "--depth-model",
        choices=DEPTH_MODELS,
        default="structured_light",
        help="--render pbr's depth.png: a structured-light sensor (default) or the default "
        "render's active stereo",
    )
    group.add_argument(
        "--device",
        choices=("auto", "cpu", "gpu"),
        default="auto",
        help="Cycles' device: auto (a GPU when Cycles finds one, default), cpu or gpu",
    )


def pbr_settings(args: argparse.Namespace) -> PbrSettings:
    """The ``--render pbr`` options' settings (UserError naming a malformed option)."""
    materials = []
    for item in args.material:
        part, eq, preset = item.partition("=")
        if not eq or not part.strip() or not preset.strip():
            raise UserError(f"--material must be PART=PRESET, got {item!r}")
        materials.append((part.strip(), preset.strip()))
    return PbrSettings(
        quality=Quality(samples=args.samples, denoise=not args.no_denoise),
        materials=tuple(materials),
        lights=args.lights,
        dof=args.dof,
        sensor=SensorSettings(exposure=args.exposure, noise=not args.no_sensor_noise),
        depth_model=args.depth_model,
        device=args.device,
    )
