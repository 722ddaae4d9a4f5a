"""The synthetic twins of a dataset's accepted scenes: :func:`synthesize_twins`, what
``annotator synth --twin DATASET OUT`` runs (a scene is :class:`~annotator.twins.render.TwinJob`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from annotator.dataset import Dataset, as_dataset, require_meshes
from annotator.export.selection import select_scenes
from annotator.geometry.transforms import invert
from annotator.io.atomic import atomic_folder
from annotator.io.output_folder import check_output_folder, write_manifest
from annotator.runner import BatchReport, run_batch
from annotator.summary import FolderBatch
from annotator.twins.render import TwinJob, TwinSettings, write_twin_description


@dataclass
class TwinSummary(FolderBatch):
    """What :func:`synthesize_twins` wrote; :meth:`to_json` is ``annotator synth --twin
    --json``.

    Attributes:
        source: The dataset twinned.
        out: The twin dataset's folder.
        report: Per-scene outcomes (a twin scene each; failed: one line each).
        left_out: Why scenes were not twinned (by the reviews) -> how many.

    >>> from pathlib import Path
    >>> from annotator.runner import BatchReport
    >>> report = BatchReport({"000000": {}})
    >>> s = TwinSummary(Path("real"), Path("twin"), report, left_out={"pending": 2})
    >>> print(s.text())  # doctest: +NORMALIZE_WHITESPACE
    synth --twin: 1 twin scenes of real written to twin; left out: 2 pending; compare them:
    annotator twin-report real twin
    """

    source: Path
    out: Path
    report: BatchReport
    left_out: dict[str, int] = field(default_factory=dict)

    def counts(self) -> dict[str, int]:
        return {"twins": len(self.report.done), "failed": len(self.report.failed)}

    def to_json(self) -> dict[str, Any]:
        return {
            "out": str(self.out),
            **self.counts(),
            "left_out": self.left_out,
            "failures": dict(sorted(self.report.failed.items())),
        }

    def text(self) -> str:
        why = "; ".join(f"{n} {r}" for r, n in sorted(self.left_out.items()))
        return (
            f"synth --twin: {len(self.report.done)} twin scenes of {self.source} written to "
            f"{self.out}"
            + (f"; left out: {why}" if why else "")
            + f"; compare them: annotator twin-report {self.source} {self.out}"
        )


def synthesize_twins(
    ds: Dataset | str | Path,
    out: str | Path,
    *,
    settings: TwinSettings | None = None,
    include_pending: bool = False,
    drop_rejected_instances: bool = False,
    overwrite: bool = False,
    workers: int = 1,
    quiet: bool = True,
    ray_address: str | None = None,
    ray_wait: float | None = None,
) -> TwinSummary:
    """The synthetic twin of every accepted scene of ``ds`` (its rig, its annotated poses,
    its background, the sensor simulated as ``annotator synth`` does; of a moving rig's
    sequence, every posed frame a reviewer did not reject) in the new folder ``out``
    (``overwrite``: an earlier synth's), built aside and put in place whole.

    >>> import shutil, tempfile
    >>> from pathlib import Path
    >>> root = shutil.copytree("sample_scenes", Path(tempfile.mkdtemp()) / "ds")
    >>> for sid in ("000001", "000002", "000003"):  # one scene is enough here
    ...     shutil.rmtree(root / "scenes" / sid)
    >>> synthesize_twins(root, root.parent / "twin", include_pending=True).to_json()["twins"]
    1

    Args:
        settings: The images' blur and noise, the seed (default
            :class:`~annotator.twins.render.TwinSettings`).
        include_pending: Also the annotated scenes not reviewed yet.
        drop_rejected_instances: Twin accepted scenes with rejected instances, without them.
        workers, quiet, ray_address, ray_wait: As :func:`annotator.runner.run_batch`.

    Raises:
        UserError: a mesh is unreadable, ``out`` may not be written, or no scene is
            accepted.
    """
    ds = as_dataset(ds, name="ds")
    require_meshes(ds)
    out = Path(out)
    check_output_folder(out, command="synth", overwrite=overwrite, protect=[ds.root])
    sel = select_scenes(
        ds, include_pending=include_pending, drop_rejected_instances=drop_rejected_instances
    )
    if not sel.scenes:
        raise sel.nothing_error(ds, include_pending=include_pending, what="to make a twin of")
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
    with atomic_folder(out) as tmp:
        write_manifest(tmp, command="synth")
        write_twin_description(ds, tmp)
        job = TwinJob(str(ds.root), str(tmp), poses, settings or TwinSettings(), frames)
        report = run_batch(
            job,
            sorted(poses),
            workers=workers,
            desc="twin",
            quiet=quiet,
            ray_address=ray_address,
            ray_wait=ray_wait,
        )
    return TwinSummary(ds.root, out, report, sel.reasons())
