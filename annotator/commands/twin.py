"""``annotator synth --twin DATASET OUT``: the synthetic twin of every accepted scene (of a
moving rig's sequence, every posed frame a reviewer did not reject).

Called by :mod:`annotator.commands.synth`; see :mod:`annotator.twins.render`.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def synth_twin(args: argparse.Namespace) -> int:
    from annotator.commands import finish_batch
    from annotator.dataset import load_dataset, require_meshes
    from annotator.export.selection import select_scenes
    from annotator.geometry.transforms import invert
    from annotator.io.atomic import atomic_folder
    from annotator.io.output_folder import check_output_folder, write_manifest
    from annotator.runner import run_batch
    from annotator.twins.render import TwinJob, TwinSettings, write_twin_description

    ds = load_dataset(args.twin)
    require_meshes(ds)
    out = Path(args.out)
    check_output_folder(out, command="synth", overwrite=args.overwrite, protect=[ds.root])
    sel = select_scenes(
        ds,
        include_pending=args.include_pending,
        drop_rejected_instances=args.drop_rejected_instances,
    )
    if not sel.scenes:
        raise sel.nothing_error(ds, include_pending=args.include_pending, what="to make a twin of")
    poses = {
        item.scene.id: [
            (p.object, p.instance, p.R.ravel().tolist(), p.t.tolist()) for p in item.poses
        ]
        for item in sel.scenes
    }
    # A sequence's frames: those posed and not rejected on their own (the export's shots).
    frames = {
        item.scene.id: {
            shot.frame: invert(shot.rig_T_scene).ravel().tolist()
            for shot in item.shots
            if shot.frame is not None
        }
        for item in sel.scenes
        if ds.rig.moving
    }
    settings = TwinSettings(blur=args.blur, noise=args.noise, seed=args.seed)
    with atomic_folder(out) as tmp:
        write_manifest(tmp, command="synth")
        write_twin_description(ds, tmp)
        job = TwinJob(str(ds.root), str(tmp), poses, settings, frames)
        report = run_batch(
            job,
            sorted(poses),
            workers=args.workers,
            desc="twin",
            quiet=args.quiet,
            ray_address=args.ray,
            ray_wait=args.ray_wait,
        )
    summary = {
        "out": str(out),
        "twins": len(report.done),
        "failed": len(report.failed),
        "left_out": sel.reasons(),
        "failures": dict(sorted(report.failed.items())),
    }
    why = "; ".join(f"{n} {r}" for r, n in sorted(sel.reasons().items()))
    return finish_batch(
        report,
        summary,
        f"synth --twin: {len(report.done)} twin scenes of {ds.root} written to {out}"
        + (f"; left out: {why}" if why else "")
        + f"; compare them: annotator twin-report {ds.root} {out}",
        as_json=args.json,
    )
