"""``export --remove-markers`` on synthetic twins: the same scenes rendered with and without
markers (``synth --no-markers``, same seed), 1280x1024 unless ``--size``, two cameras, fixed
rigs or sequences (``--frames``).

Prints the markers OpenCV's ArUco detector finds in the exported images before and after, at
each of the settings of ``devkit/aruco_settings.py`` (its defaults and each knob turned to
find more), and of those after, the ones it does not also find in the bare render (target 0);
the marker ink left outside the masks (pixels where the marked render differs from the bare
one) and the filled area; the PSNR inside the marker regions against the bare render (the
marked image, our fill and OpenCV's inpainting) and the sensor noise left there; whether
every pixel outside the regions is byte for byte the plain export's and the bare render's;
and the time of the whole ``annotator export`` process with ``--remove-markers`` over a
plain one (target: at most 2x).

    .venv/bin/python -m benchmarks.bench_remove_markers [--scenes 4] [--frames 0] [--parts P]
        [--seed S] [--size WxH] [--instances MIN-MAX] [--repeat 3]
        [--poses annotation [--misplace K]]

``--poses annotation`` exports the poses ``annotate`` gave (the scenes annotated first) rather
than the true ones; ``--misplace K`` then moves K of each scene's annotated instances 8 mm
and 6 degrees away and flags them, as a wrong pose nobody repaired: their markers must be
masked all the same.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from annotator.export.fill import noise_sigma
from devkit.aruco_settings import SETTINGS, detections, detector, new_in

SYNTH = ["--quiet"]
EXPORT = ["--format", "bop", "--poses", "gt", "--include-pending", "--quiet"]
#: The render without markers is never annotated: its export takes the true poses.
BARE_EXPORT = ["--format", "bop", "--poses", "gt", "--include-pending", "--quiet"]


def _annotator(*args: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "annotator", *args], check=True)
    return time.perf_counter() - t0


def _read(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SystemExit(f"cannot read {path}")
    return img


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--parts", default="bracket,brick,cylinder", help="synth --parts")
    ap.add_argument("--seed", default="11", help="synth --seed")
    ap.add_argument("--instances", default="10-16", help="synth --instances")
    ap.add_argument(
        "--size", default="1280x1024", help="synth --size (--supersample 1 below 1280x1024)"
    )
    ap.add_argument("--frames", type=int, default=0, help="sequences of N frames per scene")
    ap.add_argument("--repeat", type=int, default=3, help="timed runs of each export")
    ap.add_argument("--poses", choices=("gt", "annotation"), default="gt")
    ap.add_argument("--misplace", type=int, default=0, help="wrong annotated poses per scene")
    opts = ap.parse_args()
    EXPORT[EXPORT.index("--poses") + 1] = opts.poses
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        n = ["--scenes", str(opts.scenes), "--parts", opts.parts, "--seed", opts.seed]
        n += ["--size", opts.size, "--instances", opts.instances]
        if opts.size != "1280x1024":  # the tests' quick renders
            n += ["--supersample", "1"]
        if opts.frames:
            n += ["--frames", str(opts.frames)]
        _annotator("synth", str(base / "marked"), *SYNTH, *n)
        _annotator("synth", str(base / "bare"), *SYNTH, *n, "--no-markers")
        if opts.poses == "annotation":
            _annotator("annotate", str(base / "marked"), "--quiet")
            _misplace(base / "marked", opts.misplace)
        _annotator(
            "export",
            str(base / "marked"),
            str(base / "telea"),
            *EXPORT,
            "--remove-markers",
            "--marker-fill",
            "telea",
        )
        plain_t, removed_t = [], []
        for _ in range(opts.repeat):  # alternated, so that a busy machine weighs on both
            for out, extra, times in (
                ("plain", [], plain_t),
                ("removed", ["--remove-markers"], removed_t),
            ):
                times.append(
                    _annotator(
                        "export",
                        str(base / "marked"),
                        str(base / out),
                        *EXPORT,
                        *extra,
                        "--overwrite",
                    )
                )
        _annotator("export", str(base / "bare"), str(base / "bare_bop"), *BARE_EXPORT)
        _report(base, plain_t, removed_t)


def _misplace(ds: Path, k: int) -> None:
    """Move ``k`` annotated instances of each scene 8 mm and 6 degrees, and flag them."""
    from annotator.geometry.lie import rotvec_to_matrix

    turn = rotvec_to_matrix(np.radians([6.0, 0.0, 0.0]))
    for path in sorted(ds.glob("scenes/*/annotation.json")):
        doc = json.loads(path.read_text())
        for inst in doc["instances"][:k]:
            R = np.asarray(inst["cam_R_m2c"], float).reshape(3, 3) @ turn
            inst["cam_R_m2c"] = R.reshape(-1).tolist()
            inst["cam_t_m2c"] = (np.asarray(inst["cam_t_m2c"], float) + [8.0, 0, 0]).tolist()
            inst["flags"] = sorted({*inst.get("flags", []), "high_uncertainty"})
        path.write_text(json.dumps(doc))


def _report(base: Path, plain_t: list[float], removed_t: list[float]) -> None:
    det = detector("default")

    def found(img: np.ndarray) -> set[int]:
        return {i for i, _ in detections(det, img)}

    counts = {"marked": 0, "removed": 0, "telea": 0, "bare_bop": 0}
    # ArUco now and then reads an id in the parts' own edges: the bare render has those too.
    not_bare = {"removed": 0, "telea": 0}
    grain: dict[str, list[float]] = {"bare_bop": [], "removed": [], "telea": []}
    err = {"marked": 0.0, "removed": 0.0, "telea": 0.0}
    pixels = images = ink_px = ink_out = 0
    identical = {"plain export": True, "bare render": True}
    files = sorted((base / "plain" / "test").glob("*/gray_*/*.png"))
    for f in files:
        rel = f.relative_to(base / "plain")
        cam = rel.parent.name[len("gray") :]
        mask = _read(base / "removed" / rel.parents[1] / f"mask_markers{cam}" / rel.name) > 0
        img = {
            "marked": _read(f),
            **{k: _read(base / k / rel) for k in ("removed", "telea", "bare_bop")},
        }
        bare = img["bare_bop"].astype(np.float64)
        ids = {k: found(img[k]) for k in counts}
        for k in counts:
            counts[k] += len(ids[k])
        for k in not_bare:
            not_bare[k] += len(ids[k] - ids["bare_bop"])
        for k in err:
            err[k] += float(np.sum((img[k][mask] - bare[mask]) ** 2))
        pixels += int(mask.sum())
        ink_px += int((img["marked"] != img["bare_bop"]).sum())
        ink_out += int(((img["marked"] != img["bare_bop"]) & ~mask).sum())
        inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        for k in grain:
            grain[k].append(noise_sigma(img[k], inner))
        images += 1
        identical["plain export"] &= bool(
            np.array_equal(img["removed"][~mask], img["marked"][~mask])
        )
        identical["bare render"] &= bool(
            np.array_equal(img["removed"][~mask], img["bare_bop"][~mask])
        )
    h, w = img["marked"].shape[:2]

    def psnr(k: str) -> float:
        return 10 * np.log10(255.0**2 * pixels / err[k])

    print(
        f"remove markers: {images} images ({w}x{h}), {pixels / images:.0f} px of marker "
        f"regions per image ({100 * pixels / images / (w * h):.1f} %)"
    )
    print(
        f"  ArUco markers found: {counts['marked']} in the plain export, "
        f"{counts['removed']} after --remove-markers ({not_bare['removed']} not also in the bare "
        f"render: target 0), {counts['telea']} with --marker-fill telea "
        f"({not_bare['telea']}), {counts['bare_bop']} in the bare render"
    )
    print(
        "  PSNR in the regions against the bare render: "
        f"marked {psnr('marked'):.1f} dB -> filled {psnr('removed'):.1f} dB "
        f"(OpenCV's inpainting: {psnr('telea'):.1f} dB)"
    )
    g = {k: statistics.median(v) for k, v in grain.items()}
    print(
        f"  sensor noise inside the regions (sigma, grey levels): bare {g['bare_bop']:.2f}, "
        f"filled {g['removed']:.2f}, OpenCV's inpainting {g['telea']:.2f}"
    )
    print(
        f"  marker ink (marked render != bare render): {ink_px / images:.0f} px per image; "
        f"the masks cover {pixels / max(ink_px, 1):.2f}x that; ink outside them: {ink_out} px "
        "(target 0)"
    )
    _opencv(base, files)
    for k, v in identical.items():
        print(f"  outside the regions, byte-identical to the {k}: {'yes' if v else 'NO'}")
    p, r = statistics.median(plain_t), statistics.median(removed_t)
    print(
        f"  annotator export, whole process (median of {len(plain_t)}): plain {p:.2f} s, "
        f"--remove-markers {r:.2f} s: ratio {r / p:.2f} (target 2)"
    )


def _opencv(base: Path, files: list[Path]) -> None:
    """Per setting of OpenCV's detector: markers found in the plain export, in the filled
    images, and of those, the ones the bare render does not give it too."""
    print("  OpenCV's detector per setting: plain export -> filled (not in the bare render)")
    for setting in SETTINGS:
        det = detector(setting)
        plain = filled = new = 0
        for f in files:
            rel = f.relative_to(base / "plain")
            bare = detections(det, _read(base / "bare_bop" / rel))
            plain += len(new_in(detections(det, _read(f)), bare))
            found = detections(det, _read(base / "removed" / rel))
            filled += len(found)
            new += len(new_in(found, bare))
        print(f"    {setting:32s} {plain:5d} -> {filled} ({new}; target 0)")


if __name__ == "__main__":
    main()
