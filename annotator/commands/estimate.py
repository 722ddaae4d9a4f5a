"""``annotator estimate DATASET OUT --method ppf``: a baseline pose estimator's results.

Poses of every part in every scene from its depth map alone, written to OUT as one BOP
results CSV that ``annotator evaluate DATASET --results OUT`` scores, and beside it (OUT ending
``.json``) as BOP's COCO results for 2D detection and segmentation, which ``annotator evaluate
BOP_EXPORT --coco-results`` scores. The method is a native
point pair feature estimator (Drost et al. 2010) whose vote clustering is mean shift in SE(3),
or, with ``--symmetric``, in the pose space of the part's symmetry (Brégier et al. 2017,
section 4.2); see :mod:`annotator.estimation`. This module only reads options and prints.
"""

from __future__ import annotations

import argparse
import fnmatch
from pathlib import Path
from typing import TYPE_CHECKING

from annotator.commands import add_ray_option, add_workers_option, finish_batch, whole
from annotator.dataset import load_dataset, require_meshes
from annotator.dataset.model import SCENES_DIR
from annotator.errors import UserError
from annotator.io.output_folder import check_output_files
from annotator.runner import run_batch

if TYPE_CHECKING:
    from annotator.dataset import Dataset
    from annotator.estimation.results import ResultRow


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dataset", help="dataset folder (FORMAT.md) with depth maps")
    parser.add_argument(
        "out",
        help="results file to write (BOP CSV); its COCO results (2D boxes and masks) go "
        "beside it, the same name ending .json",
    )
    parser.add_argument(
        "--method",
        choices=("ppf",),
        default="ppf",
        help="ppf: point pair features, Drost et al. 2010 (the only method so far)",
    )
    parser.add_argument(
        "--symmetric",
        action="store_true",
        help="mean shift and duplicate removal by the part's symmetry-aware distance instead "
        "of in SE(3) (the paper's 'PPF sym')",
    )
    parser.add_argument(
        "--post-process",
        action="store_true",
        help="keep the 20 best hypotheses, refine them by ICP, re-score them by agreement with "
        "the measured depth and filter duplicates (the paper's 'PP')",
    )
    parser.add_argument(
        "--scenes", default="*", metavar="PATTERN", help="only scenes whose id matches (fnmatch)"
    )
    parser.add_argument(
        "--max-hypotheses",
        type=whole(low=1),
        default=30,
        metavar="N",
        help="results per part and scene at most (default 30)",
    )
    add_workers_option(parser)
    add_ray_option(parser)
    parser.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from annotator.estimation.estimator import PPFSettings
    from annotator.estimation.job import EstimateJob
    from annotator.estimation.results import coco_path, write_results

    out = Path(args.out)
    if out.is_dir():
        raise UserError("is a folder; give a file name for the results CSV", path=out)
    if not out.parent.is_dir():
        raise UserError("the folder to write the results in does not exist", path=out)
    check_output_files([("OUT", out), ("OUT's COCO", coco_path(out))], datasets=[args.dataset])
    ds = load_dataset(args.dataset)
    if ds.rig.depth is None:
        raise UserError(
            "the rig has no depth camera (rig.depth): the estimator works on depth maps",
            path=ds.root / "dataset.yaml",
        )
    if ds.rig.moving:
        raise UserError(
            "the rig is a moving one (rig.moving): the baseline estimator works on a fixed "
            "rig's scenes, one shot each, not on sequences",
            path=ds.root / "dataset.yaml",
        )
    scenes = [s for s in ds.scenes() if fnmatch.fnmatch(s.id, args.scenes)]
    if not scenes:
        raise UserError(f"no scene matches {args.scenes!r}", path=ds.root / SCENES_DIR)
    require_meshes(ds)
    ds.background_depth  # noqa: B018  (an unreadable background is a dataset error: now)
    settings = PPFSettings(
        symmetric=args.symmetric,
        post_process=args.post_process,
        max_hypotheses=args.max_hypotheses,
    )
    report = run_batch(
        EstimateJob(str(ds.root), (settings,)),
        [s.id for s in scenes],
        workers=args.workers,
        desc=f"estimate ({settings.label})",
        quiet=args.quiet,
        ray_address=args.ray,
        ray_wait=args.ray_wait,
    )
    rows = [row for sid in sorted(report.done) for row in report.done[sid]["rows"][0]]
    write_results(out, rows)
    _write_coco(ds, rows, coco_path(out))
    seconds = [report.done[sid]["seconds"][0] for sid in report.done]
    summary = {
        "method": settings.label,
        "out": str(out),
        "coco": str(coco_path(out)),
        "scenes": len(scenes),
        "done": len(report.done),
        "failed": len(report.failed),
        "results": len(rows),
        "seconds_per_scene": round(sum(seconds) / max(len(seconds), 1), 3),
        "failures": dict(sorted(report.failed.items())),
    }
    return finish_batch(
        report,
        summary,
        f"estimate ({settings.label}): {summary['results']} results for {len(report.done)} "
        f"scenes written to {out}, {len(report.failed)} failed; "
        f"{summary['seconds_per_scene']} s per scene (one worker)",
        as_json=args.json,
    )


def _write_coco(ds: Dataset, rows: list[ResultRow], path: Path) -> None:
    """The hypotheses as COCO results, in the reference camera without distortion."""
    from annotator.estimation.results import coco_results
    from annotator.export.undistort import pinhole_rig
    from annotator.io.atomic import write_json

    cam = pinhole_rig(ds.rig).cameras[0]
    meshes = [ds.objects[name].mesh for name in ds.objects]
    write_json(path, coco_results(rows, meshes, cam.K, cam.width, cam.height))
