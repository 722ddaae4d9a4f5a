"""The pictures of README's "Photoreal scenes": one per effect of ``synth --render pbr``.

One scene (seed 21, the bracket in steel, the brick in aluminium, the reference camera
alone) is rendered five ways: by the default renderer, and by Cycles with everything on
(two area lights, depth of field at 480 mm f/1.4, shot and read noise, structured-light
depth), without the depth of field, focused nearer (400 mm, so that the parts are out of
focus: at 480 mm on a 4.8 um sensor the bin's depth blurs by about a pixel at most), and
without the sensor noise.
Each picture puts the same crop of two of them side by side:

- ``docs/pbr_metal.png``: the default render and Cycles on the part whose markers sit
  nearest a highlight;
- ``docs/pbr_dof.png``: Cycles without and with the depth of field focused at 400 mm, on
  the farthest part (2x);
- ``docs/pbr_noise.png``: Cycles without and with the sensor noise, on a marker (3x);
- ``docs/pbr_depth.png``: the default render's active-stereo depth and the structured-light
  depth of the whole image (holes black).

    .venv/bin/python -m benchmarks.pbr_pictures [--out docs] [--samples 16] [--keep DIR]

Prints what it rendered and the seconds per image.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import cv2
import numpy as np

from annotator.dataset import load_dataset, read_poses
from devkit.whole_process import run_annotator

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
    "pbr_focus_400": PBR + ["--dof", "400,1.4"],
}
CROP = 200  # px, the side of each crop at full resolution


def render(root: Path, samples: int) -> dict[str, Path]:
    done = {}
    for name, extra in VARIANTS.items():
        out = root / name
        done[name] = out / "scenes" / "000000"
        if (done[name] / "left.png").exists():
            continue  # kept from an earlier run (--keep)
        args = [*COMMON, *extra] + (["--samples", str(samples)] if extra else [])
        seconds, _ = run_annotator("synth", str(out), *args)
        print(f"  {name:17s} {seconds:6.1f} s (one image, whole process)")
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
    """The square of CROP / scale px around ``centre``, magnified ``scale`` times."""
    h, w = image.shape[:2]
    side = CROP // scale
    x = int(np.clip(centre[0] - side // 2, 0, w - side))
    y = int(np.clip(centre[1] - side // 2, 0, h - side))
    part = image[y : y + side, x : x + side]
    if scale > 1:
        part = cv2.resize(part, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    return part


def pair(a: np.ndarray, b: np.ndarray, labels: tuple[str, str]) -> np.ndarray:
    tiles = []
    for image, label in zip((a, b), labels):
        tile = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
        font = cv2.FONT_HERSHEY_SIMPLEX
        cv2.putText(tile, label, (6, 16), font, 0.42, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(tile, label, (6, 16), font, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
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
    ap.add_argument("--keep", type=Path, help="render into (and reuse) this folder")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        scenes = render(args.keep or Path(tmp), args.samples)
        read = {k: cv2.imread(str(v / "left.png"), cv2.IMREAD_GRAYSCALE) for k, v in scenes.items()}
        where = centres(scenes["pbr"], scenes["pbr"].parents[1])
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
        far = max(where, key=lambda k: where[k][1])
        dof = pair(
            crop(read["pbr_pinhole"], where[far][0], 2),
            crop(read["pbr_focus_400"], where[far][0], 2),
            ("pinhole", f"f/1.4, focus 400 mm, part {where[far][1]:.0f} mm"),
        )
        noise = pair(
            crop(read["pbr_ideal_sensor"], where[bright][0], 3),
            crop(read["pbr"], where[bright][0], 3),
            ("ideal sensor", "shot and read noise"),
        )
        stereo = cv2.imread(str(scenes["lambert"] / "depth.png"), cv2.IMREAD_UNCHANGED)
        light = cv2.imread(str(scenes["pbr"] / "depth.png"), cv2.IMREAD_UNCHANGED)
        seen = light[(light > 0) & (light < 65535)]
        lo, hi = np.percentile(seen, 2), np.percentile(seen, 98)
        half = [
            cv2.resize(
                coloured_depth(d, lo, hi), None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA
            )
            for d in (stereo, light)
        ]
        depth = pair(*half, ("active stereo (default)", "structured light (pbr): holes black"))
        args.out.mkdir(parents=True, exist_ok=True)
        for name, image in (("metal", metal), ("dof", dof), ("noise", noise), ("depth", depth)):
            path = args.out / f"pbr_{name}.png"
            cv2.imwrite(str(path), image)
            print(f"  wrote {path}")


if __name__ == "__main__":
    main()
