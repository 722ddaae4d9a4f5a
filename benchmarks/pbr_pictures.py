"""The pictures of README's "Photoreal scenes": one per effect of ``synth --render pbr``.

One scene (seed 21, the bracket in steel, the brick in aluminium, the reference camera
alone) is rendered four ways: by the default renderer, and by Cycles with everything on
(two area lights, depth of field at 480 mm f/1.4, shot and read noise, structured-light
depth), without the depth of field, and without the sensor noise.
Each picture puts the same crop of two of them side by side:

- ``docs/pbr_metal.png``: the default render and Cycles on the part whose markers sit
  nearest a highlight;
- ``docs/pbr_dof.png``: Cycles without and with the depth of field, on the part farthest
  from the focus distance;
- ``docs/pbr_noise.png``: Cycles without and with the sensor noise (a dark corner, 3x);
- ``docs/pbr_depth.png``: the default render's active-stereo depth and the structured-light
  depth of the whole image (holes black).

    .venv/bin/python -m benchmarks.pbr_pictures [--out docs] [--samples 16]

Prints what it rendered and the seconds per image.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from annotator.dataset import load_dataset, read_poses

EXE = str(Path(sys.executable).with_name("annotator"))
COMMON = ["--scenes", "1", "--seed", "21", "--parts", "bracket,brick", "--instances", "8-14"]
COMMON += ["--cameras", "1", "--quiet", "--overwrite"]
PBR = ["--render", "pbr", "--material", "bracket=steel", "--material", "brick=aluminium"]
PBR += ["--lights", "2"]
FOCUS = ["--dof", "480,1.4"]
VARIANTS = {
    "lambert": [],
    "pbr": PBR + FOCUS,
    "pbr_pinhole": PBR,
    "pbr_ideal_sensor": PBR + FOCUS + ["--no-sensor-noise"],
}
CROP = 200  # px, the side of each crop at full resolution


def render(root: Path, samples: int) -> dict[str, Path]:
    done = {}
    for name, extra in VARIANTS.items():
        out = root / name
        t0 = time.perf_counter()
        args = [*COMMON, *extra] + (["--samples", str(samples)] if extra else [])
        proc = subprocess.run([EXE, "synth", str(out), *args], capture_output=True, text=True)
        if proc.returncode != 0:
            sys.exit(f"annotator synth {' '.join(args)} failed:\n{proc.stderr}")
        print(f"  {name:17s} {time.perf_counter() - t0:6.1f} s (one image, whole process)")
        done[name] = out / "scenes" / "000000"
    return done


def centres(scene: Path, dataset: Path) -> dict[str, tuple[np.ndarray, float]]:
    """Each instance's image position and distance (mm) in the reference camera."""
    cam = load_dataset(dataset).rig.cameras[0]
    out = {}
    for p in read_poses(scene / "gt.json"):
        t = (cam.cam_T_rig @ p.T)[:3, 3]
        out[p.key] = (cam.project(t[None])[0], float(t[2]))
    return out


def crop(image: np.ndarray, centre: np.ndarray, scale: int = 1) -> np.ndarray:
    h, w = image.shape[:2]
    x = int(np.clip(centre[0] - CROP // 2, 0, w - CROP))
    y = int(np.clip(centre[1] - CROP // 2, 0, h - CROP))
    part = image[y : y + CROP, x : x + CROP]
    if scale > 1:
        part = cv2.resize(part, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    return part


def pair(a: np.ndarray, b: np.ndarray, labels: tuple[str, str]) -> np.ndarray:
    tiles = []
    for image, label in zip((a, b), labels):
        tile = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
        cv2.putText(tile, label, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 0), 4)
        cv2.putText(tile, label, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 1)
        tiles.append(tile)
    gap = np.full((tiles[0].shape[0], 6, 3), 255, np.uint8)
    return np.hstack([tiles[0], gap, tiles[1]])


def coloured_depth(depth: np.ndarray, lo: float, hi: float) -> np.ndarray:
    scaled = np.clip((depth.astype(np.float64) - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)
    image = cv2.applyColorMap(scaled, cv2.COLORMAP_VIRIDIS)
    image[(depth == 0) | (depth == 65535)] = 0
    return image


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("docs"))
    ap.add_argument("--samples", type=int, default=16)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        scenes = render(Path(tmp), args.samples)
        read = {k: cv2.imread(str(v / "left.png"), cv2.IMREAD_GRAYSCALE) for k, v in scenes.items()}
        where = centres(scenes["pbr"], Path(tmp) / "pbr")
        # The metal part with the brightest highlight near its centre.
        bright = max(
            where,
            key=lambda k: (
                float(crop(read["pbr"], where[k][0]).max())
                + float(np.mean(crop(read["pbr"], where[k][0]) > 250))
            ),
        )
        metal = pair(
            crop(read["lambert"], where[bright][0]),
            crop(read["pbr"], where[bright][0]),
            ("default render", "pbr: steel, aluminium"),
        )
        far = max(where, key=lambda k: abs(where[k][1] - 480.0))
        dof = pair(
            crop(read["pbr_pinhole"], where[far][0]),
            crop(read["pbr"], where[far][0]),
            ("pbr, pinhole", f"pbr, f/1.4 focused at 480 mm ({where[far][1]:.0f} mm)"),
        )
        near = min(where, key=lambda k: float(np.mean(crop(read["pbr"], where[k][0]))))
        noise = pair(
            crop(read["pbr_ideal_sensor"], where[near][0])[: CROP // 3, : CROP // 3],
            crop(read["pbr"], where[near][0])[: CROP // 3, : CROP // 3],
            ("ideal", "noise"),
        )
        noise = cv2.resize(noise, None, fx=3, fy=3, interpolation=cv2.INTER_NEAREST)
        stereo = cv2.imread(str(scenes["lambert"] / "depth.png"), cv2.IMREAD_UNCHANGED)
        light = cv2.imread(str(scenes["pbr"] / "depth.png"), cv2.IMREAD_UNCHANGED)
        seen = light[(light > 0) & (light < 65535)]
        lo, hi = np.percentile(seen, 2), np.percentile(seen, 98)
        depth = pair(
            coloured_depth(stereo, lo, hi),
            coloured_depth(light, lo, hi),
            ("active stereo (default)", "structured light (pbr)"),
        )
        depth = cv2.resize(depth, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
        args.out.mkdir(parents=True, exist_ok=True)
        for name, image in (("metal", metal), ("dof", dof), ("noise", noise), ("depth", depth)):
            path = args.out / f"pbr_{name}.png"
            cv2.imwrite(str(path), image)
            print(f"  wrote {path}")


if __name__ == "__main__":
    main()
