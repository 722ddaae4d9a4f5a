"""A fixed rig's synthetic dataset: :func:`synthesize_scenes`, what ``annotator synth OUT``
runs (a scene is :class:`~annotator.synthesis.generate.SceneJob`; a moving rig's sequences
are :func:`~annotator.synthesis.sequence.synthesize_sequences`)."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from annotator.dataset.model import SCENES_DIR
from annotator.io.atomic import atomic_folder
from annotator.io.output_folder import check_output_folder, write_manifest
from annotator.runner import BatchReport, run_batch
from annotator.summary import FolderBatch
from annotator.synthesis.generate import SceneJob, SynthSettings, cached_plan, write_dataset_files
from annotator.synthesis.pbr.cycles_job import bpy_python

#: The stages a scene's time is reported for (``seconds_per_scene``).
STAGES = ("physics", "rendering", "depth", "occlusion")


@dataclass
class SynthesisSummary(FolderBatch):
    """What :func:`synthesize_scenes` wrote; :meth:`to_json` is ``annotator synth --json``.

    Attributes:
        out: The dataset folder.
        report: Per-scene outcomes (done: instances and seconds per stage; failed: one line
            each, the scene's folder removed).

    >>> from pathlib import Path
    >>> from annotator.runner import BatchReport
    >>> times = {"physics": 0.4, "rendering": 0.1, "depth": 0.02, "occlusion": 0.01}
    >>> s = SynthesisSummary(Path("synth"), BatchReport({"000000": {"instances": 12, **times}}))
    >>> s.counts()
    {'scenes': 1, 'failed': 0, 'instances': 12}
    >>> s.warnings(), s.exit_status()
    ([], 0)
    """

    out: Path
    report: BatchReport

    @property
    def seconds_per_scene(self) -> dict[str, float]:
        """The mean seconds of a scene's physics, rendering, depth and occlusion rates."""
        done = self.report.done.values()
        return {k: round(sum(r[k] for r in done) / max(len(done), 1), 3) for k in STAGES}

    def counts(self) -> dict[str, int]:
        return {
            "scenes": len(self.report.done),
            "failed": len(self.report.failed),
            "instances": sum(r["instances"] for r in self.report.done.values()),
        }

    def to_json(self) -> dict[str, Any]:
        return {
            "out": str(self.out),
            **self.counts(),
            "seconds_per_scene": self.seconds_per_scene,
            "failures": dict(sorted(self.report.failed.items())),
        }

    def text(self) -> str:
        j, t = self.counts(), self.seconds_per_scene
        return (
            f"synth: {j['scenes']} scenes ({j['instances']} instances) written to {self.out}, "
            f"{j['failed']} failed; per scene: physics {t['physics']} s, rendering "
            f"{t['rendering']} s, depth {t['depth']} s, occlusion rates {t['occlusion']} s"
        )


def synthesize_scenes(
    out: str | Path,
    settings: SynthSettings,
    *,
    overwrite: bool = False,
    workers: int = 1,
    quiet: bool = True,
    ray_address: str | None = None,
    ray_wait: float | None = None,
) -> SynthesisSummary:
    """A fixed rig's dataset of ``settings.scenes`` synthetic scenes with exact ground truth
    (gt.json, occlusion rates, depth maps) in the new folder ``out``, built aside and put in
    place whole (``overwrite`` replaces an earlier synth's). Every byte depends on
    ``settings`` alone (its seed included), never on the workers; a scene that fails is
    reported and left out.

    >>> import tempfile
    >>> from pathlib import Path
    >>> from annotator import SynthSettings
    >>> out = Path(tempfile.mkdtemp()) / "synth"
    >>> settings = SynthSettings(parts=("brick",), scenes=1, instances=(2, 2), size=(160, 128))
    >>> s = synthesize_scenes(out, settings)
    >>> s.to_json()["scenes"], s.to_json()["instances"], (out / "scenes" / "000000" / "gt.json").is_file()
    (1, 2, True)

    Raises:
        UserError: ``out`` may not be written, or ``settings`` cannot be planned.
        ValueError: ``settings.frames`` asks for sequences (:func:`synthesize_sequences`).
    """
    if settings.frames:
        raise ValueError("settings.frames asks for sequences: use synthesize_sequences")
    out = Path(out)
    check_output_folder(out, command="synth", overwrite=overwrite)
    plan = cached_plan(settings)
    if settings.render == "pbr":
        bpy_python()  # a missing extra is told before any work
    with atomic_folder(out) as tmp:
        write_manifest(tmp, command="synth")
        write_dataset_files(plan, tmp)
        report = run_batch(
            SceneJob(settings, str(tmp), progress=not quiet and settings.render == "pbr"),
            [f"{k:06d}" for k in range(settings.scenes)],
            workers=workers,
            desc="synth",
            quiet=quiet,
            ray_address=ray_address,
            ray_wait=ray_wait,
        )
        for sid in report.failed:
            shutil.rmtree(tmp / SCENES_DIR / sid, ignore_errors=True)
    return SynthesisSummary(out, report)
