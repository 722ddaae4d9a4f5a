"""Time per synthetic scene on one core (1280x1024 stereo, 20 instances), split into physics,
rendering and depth simulation; and how far today's images are from those of the renderer
that made the committed sample_scenes/ (the same scenes made again, compared pixel by pixel).

Target: <= 5 s per scene on one core at 20 parts.

    .venv/bin/python benchmarks/bench_synth.py [--scenes N]
"""

from __future__ import annotations

import os

# One core means one thread everywhere, BLAS included (set before numpy is imported).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402

from annotator.rendering.raycast import set_threads  # noqa: E402
from annotator.synthesis.generate import SynthConfig, make_scene, plan_dataset  # noqa: E402

TARGET_S = 5.0
SAMPLE = Path(__file__).resolve().parent.parent / "sample_scenes"


def speed(scenes: int) -> None:
    config = SynthConfig(parts=("bracket", "brick", "cylinder"), instances=(20, 20), seed=5)
    plan = plan_dataset(config)
    with tempfile.TemporaryDirectory() as tmp:
        # The first scene also builds per-camera ray tables (cached afterwards): time it apart.
        t0 = time.perf_counter()
        make_scene(plan, 0, Path(tmp) / "warm")
        warm = time.perf_counter() - t0
        rows = []
        for k in range(1, scenes + 1):
            c0, t0 = time.process_time(), time.perf_counter()
            poses, timing = make_scene(plan, k, Path(tmp) / f"{k}")
            rows.append(
                (
                    time.perf_counter() - t0,
                    time.process_time() - c0,
                    timing.physics,
                    timing.rendering,
                    timing.depth,
                    len(poses),
                )
            )
    wall, cpu, phys, rend, depth, n = np.mean(rows, axis=0)
    print(
        f"synthetic scenes, one core: 1280x1024 stereo, {n:.0f} parts on average, {scenes} "
        f"scenes after one warm-up ({warm:.2f} s)"
    )
    print(
        f"  per scene: {wall:.2f} s wall ({cpu:.2f} s CPU) = physics {phys:.2f} + rendering "
        f"{rend:.2f} + depth {depth:.2f} (+ occlusion rates and writing)"
    )
    print(
        f"  target {TARGET_S:.1f} s per scene: ratio {wall / TARGET_S:.2f} "
        f"({'met' if wall <= TARGET_S else 'NOT met'})"
    )


def sameness() -> None:
    """sample_scenes/ scene 0 made again from its own recorded configuration."""
    doc = yaml.safe_load((SAMPLE / "dataset.yaml").read_text())["synth"]
    config = SynthConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in doc.items()})
    plan = plan_dataset(config)
    with tempfile.TemporaryDirectory() as tmp:
        make_scene(plan, 0, Path(tmp))
        print("the committed sample_scenes/000000 made again by today's renderer:")
        for name in ("left.png", "right.png", "depth.png"):
            old = cv2.imread(str(SAMPLE / "scenes" / "000000" / name), cv2.IMREAD_UNCHANGED)
            new = cv2.imread(str(Path(tmp) / name), cv2.IMREAD_UNCHANGED)
            a, b = old.astype(float), new.astype(float)
            if name == "depth.png":
                both = (a > 0) & (b > 0)
                d = np.abs(a - b)[both] * float(doc.get("depth_scale", 0.1))
                print(
                    f"  {name}: valid in one only {np.mean((a > 0) != (b > 0)):.2%}; where both: "
                    f"{np.mean(d > 0):.2%} of pixels differ, {np.mean(d > 1.0):.2%} by more "
                    f"than 1 mm, mean {d.mean():.3f} mm"
                )
            else:
                d = np.abs(a - b)
                print(
                    f"  {name}: {np.mean(d > 0):.3%} of pixels differ, max {d.max():.0f} grey "
                    f"levels, mean {d.mean():.4f}"
                )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", type=int, default=3)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    set_threads(1)
    speed(args.scenes)
    sameness()


if __name__ == "__main__":
    main()
