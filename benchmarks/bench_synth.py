"""Time per synthetic scene (1280x1024 stereo, 20 instances), split into physics, rendering
and depth simulation, on one core. Target: under 5 s per scene.

    .venv/bin/python benchmarks/bench_synth.py [--scenes N]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from annotator.synthesis.generate import SynthConfig, make_scene, plan_dataset

TARGET_S = 5.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", type=int, default=3)
    args = ap.parse_args()
    config = SynthConfig(parts=("bracket", "cylinder"), instances=(20, 20), size=(1280, 1024))
    plan = plan_dataset(config)
    with tempfile.TemporaryDirectory() as tmp:
        # The first scene also builds per-camera ray tables (cached afterwards): time it apart.
        t0 = time.perf_counter()
        make_scene(plan, 0, Path(tmp) / "warm")
        warm = time.perf_counter() - t0
        rows = []
        for k in range(1, args.scenes + 1):
            t0 = time.perf_counter()
            _, timing = make_scene(plan, k, Path(tmp) / f"{k}")
            rows.append((time.perf_counter() - t0, timing.physics, timing.rendering, timing.depth))
    total, phys, rend, depth = np.mean(rows, axis=0)
    print(
        f"synthetic scenes: 1280x1024 stereo, 20 instances, {args.scenes} scenes after one warm-up ({warm:.2f} s)"
    )
    print(
        f"  per scene: {total:.2f} s = physics {phys:.2f} + rendering {rend:.2f} + depth {depth:.2f} (+ writing)"
    )
    print(
        f"  target {TARGET_S:.1f} s per scene: ratio {total / TARGET_S:.2f} ({'met' if total <= TARGET_S else 'NOT met'})"
    )


if __name__ == "__main__":
    main()
