"""Real against twin: the depth a real sensor measured against the depth simulated on the
scene's twin (the same rig, the annotated poses).

Per scene: the fraction of pixels with a depth value in each; on the parts (the pixels where
an annotated instance is the nearest rendered surface), the differences between real and
twin depth where both have one (median and 95th percentile of the absolute difference, and
their histogram); per instance, the fraction of its pixels whose real depth differs from the
twin's by more than ``tolerance_mm`` (1.5 mm, a few times the simulated sensor's noise). An
instance whose fraction exceeds ``max_disagreement`` (0.3) *disagrees*: its pose, or the
calibration, is off (a pose moved by 2 mm along the view already shows).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset import Dataset, InstancePose


@dataclass(frozen=True)
class InstanceComparison:
    key: str
    pixels: int
    disagreement: float  # fraction of pixels beyond the tolerance
    median_abs_mm: float | None

    def disagrees(self, limit: float) -> bool:
        return self.pixels > 0 and self.disagreement > limit


@dataclass
class SceneComparison:
    scene: str
    valid_real: float
    valid_twin: float
    part_diffs: np.ndarray  # real - twin (mm) on part pixels where both are valid
    instances: list[InstanceComparison] = field(default_factory=list)

    def to_json(self, limit: float) -> dict[str, Any]:
        d = np.abs(self.part_diffs)
        return {
            "scene": self.scene,
            "valid_real": round(self.valid_real, 4),
            "valid_twin": round(self.valid_twin, 4),
            "part_pixels": int(len(d)),
            "median_abs_mm": round(float(np.median(d)), 3) if len(d) else None,
            "p95_abs_mm": round(float(np.percentile(d, 95)), 3) if len(d) else None,
            "instances": [
                {
                    "instance": i.key,
                    "pixels": i.pixels,
                    "disagreement": round(i.disagreement, 4),
                    "median_abs_mm": None if i.median_abs_mm is None else round(i.median_abs_mm, 3),
                    "disagrees": i.disagrees(limit),
                }
                for i in self.instances
            ],
        }


def compare_scene(
    ds: Dataset,
    scene_id: str,
    real: np.ndarray,
    twin: np.ndarray,
    poses: list[InstancePose],
    *,
    tolerance_mm: float = 1.5,
    step: int = 2,
) -> tuple[SceneComparison, np.ndarray]:
    """Compare depth maps (mm, NaN = none) of a scene and its twin; also returns the index of
    the nearest instance at every ``step``-th pixel (-1 where none), for pictures."""
    from annotator.annotation.visibility import render_poses

    renders = render_poses(ds, poses, step=step)
    cam = ds.rig.depth_camera
    assert cam is not None, "comparing depth maps needs a rig with depth"
    front = renders[cam.name][1] if renders else np.full(real[::step, ::step].shape, -1)
    r, t = real[::step, ::step], twin[::step, ::step]
    both = np.isfinite(r) & np.isfinite(t)
    diff = np.where(both, r - t, np.nan)
    comp = SceneComparison(
        scene_id,
        float(np.isfinite(real).mean()),
        float(np.isfinite(twin).mean()),
        diff[both & (front >= 0)],
    )
    for k, p in enumerate(poses):
        mine = (front == k) & both
        d = np.abs(diff[mine])
        comp.instances.append(
            InstanceComparison(
                p.key,
                int(mine.sum()) * step * step,
                float(np.mean(d > tolerance_mm)) if len(d) else 0.0,
                float(np.median(d)) if len(d) else None,
            )
        )
    return comp, front


def overlay(
    image: np.ndarray, front: np.ndarray, comp: SceneComparison, limit: float, step: int
) -> np.ndarray:
    """The real image with each instance tinted green (agrees) or red (disagrees)."""
    import cv2

    from annotator.io.images import to_gray8

    gray = cv2.cvtColor(to_gray8(image), cv2.COLOR_GRAY2BGR).astype(np.float32)
    tint = np.zeros_like(gray)
    full = np.repeat(np.repeat(front, step, axis=0), step, axis=1)[: gray.shape[0], : gray.shape[1]]
    for k, inst in enumerate(comp.instances):
        colour = (40, 40, 255) if inst.disagrees(limit) else (60, 200, 60)
        tint[full == k] = colour
    mask = full >= 0
    gray[mask] = 0.55 * gray[mask] + 0.45 * tint[mask]
    return gray.astype(np.uint8)


def histogram_png(diffs: np.ndarray, path: Path) -> None:
    """Histogram of real - twin depth on the parts, to a PNG."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from annotator.io.atomic import write_bytes

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=110)
    ax.hist(np.clip(diffs, -10, 10), bins=200, range=(-10, 10), color="#4a7")
    ax.set_xlabel("real - twin depth on the parts (mm, clipped to +-10)")
    ax.set_ylabel("pixels")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    plt.close(fig)
    write_bytes(path, buf.getvalue())
