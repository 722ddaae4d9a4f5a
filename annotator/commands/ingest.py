"""``annotator ingest DATASET SOURCE --scene ID``: a recorded sequence into a moving rig's
dataset (:func:`annotator.ingest.scene.ingest_recording`)."""

from __future__ import annotations

import argparse

from annotator.commands import finish, number, whole
from annotator.ingest.selection import BLUR_THRESHOLD
from annotator.ingest.sources import PAIR_TOLERANCE_S

#: The argument naming the dataset this command writes into (its writer lock is held).
WRITES = "dataset"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "dataset",
        help="dataset folder whose dataset.yaml says rig.moving: true (or a new one, with "
        "--rig-from-source)",
    )
    parser.add_argument(
        "source",
        help="a recorder's file: a ROS 1 bag (RealSense Viewer's .bag too), a ROS 2 bag "
        "(folder, .mcap, .db3), an Azure Kinect .mkv, a Record3D .r3d; a video file (.mp4 "
        ".avi .mkv .mov .webm); or a folder of colour images, with depth images beside them "
        "or in a depth/ folder (RealSense, ROS image_saver and bag export names)",
    )
    parser.add_argument(
        "--scene", required=True, metavar="ID", help="the scene to write: scenes/ID/"
    )
    parser.add_argument(
        "--camera",
        metavar="NAME",
        help="the rig camera the images are of (a rig of one camera; with "
        "--rig-from-source, the name of the new rig's camera, default cam)",
    )
    parser.add_argument(
        "--stream",
        metavar="NAME",
        help="in a folder of several colour streams (left0000.png, right0000.png), the one "
        "to take (default: the one named like the camera)",
    )
    parser.add_argument(
        "--every",
        type=whole(low=1),
        default=1,
        metavar="N",
        help="take every N-th frame of the source (default 1: all)",
    )
    parser.add_argument(
        "--blur-threshold",
        type=number(low=0),
        default=BLUR_THRESHOLD,
        metavar="F",
        help="drop a frame whose sharpness (variance of the Laplacian) is below F times the "
        f"running median of its neighbours' (default {BLUR_THRESHOLD:g}; 0 keeps every frame)",
    )
    _add_depth_options(parser)
    _add_recorder_options(parser)
    parser.add_argument(
        "--overwrite", action="store_true", help="replace the scene if ingest wrote it"
    )
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_depth_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("depth", "the depth frames and how they pair with colour")
    group.add_argument("--no-depth", action="store_true", help="leave the depth images out")
    group.add_argument(
        "--depth-scale",
        type=number(low=0, above=True),
        default=None,
        metavar="MM",
        help="millimetres per unit of the source's 16-bit depth (default: what a recorder's "
        "file says; 1 for an image folder, as RealSense writes them); depth.png is written at "
        "the rig's rig.depth.scale",
    )
    group.add_argument(
        "--tolerance-ms",
        type=number(low=0),
        default=PAIR_TOLERANCE_S * 1000,
        metavar="MS",
        help="how far apart in time a colour frame and its depth partner may be (a folder's "
        f"images whose names do not share a number, a recording's frames; default "
        f"{PAIR_TOLERANCE_S * 1000:g})",
    )
    group.add_argument(
        "--fps",
        type=number(low=0, above=True),
        help="the frame rate of a folder whose names are frame indices (frame0000.jpg): "
        "gives the frames their times",
    )


def _add_recorder_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("recorders' files", "bags, and a rig from the file")
    group.add_argument(
        "--color-topic",
        metavar="TOPIC",
        help="a bag's colour image topic (Image or CompressedImage), when several could be",
    )
    group.add_argument(
        "--depth-topic",
        metavar="TOPIC",
        help="a bag's depth image topic (16UC1, mono16 or 32FC1), when several could be",
    )
    group.add_argument(
        "--rig-from-source",
        action="store_true",
        help="when DATASET does not exist, create it with dataset.yaml holding a moving rig "
        "of the file's colour camera (K, distortion, size) and depth, the --dictionary and no "
        "objects yet; an existing rig is checked against the file's intrinsics (1 %%) anyway",
    )
    group.add_argument(
        "--dictionary",
        default="DICT_4X4_1000",
        metavar="NAME",
        help="the ArUco dictionary of a dataset created by --rig-from-source (default "
        "DICT_4X4_1000)",
    )


def run(args: argparse.Namespace) -> int:
    from annotator.ingest.scene import IngestSettings, ingest_recording

    settings = IngestSettings(
        camera=args.camera,
        stream=args.stream,
        every=args.every,
        blur_threshold=args.blur_threshold,
        depth=not args.no_depth,
        depth_scale=args.depth_scale,
        tolerance_s=args.tolerance_ms / 1000.0,
        fps=args.fps,
        color_topic=args.color_topic,
        depth_topic=args.depth_topic,
        rig_from_source=args.rig_from_source,
        dictionary=args.dictionary,
        overwrite=args.overwrite,
    )
    summary = ingest_recording(args.dataset, args.source, args.scene, settings, quiet=args.quiet)
    return finish(summary, as_json=args.json)
