"""Rig calibration accuracy on the reference setup: 30 shots of a 7x5 ChArUco board
(30 mm squares) at 520-760 mm seen by the synthetic two-camera rig, about 0.15 px of corner
noise (image noise 12 grey levels, blur 1 px). Ours (joint refinement over all corners)
against OpenCV's two-step pipeline (calibrateCamera, then stereoCalibrate with the
intrinsics fixed) and OpenCV's joint stereoCalibrate, on the same detections, over several
seeds. Targets: focal lengths within 0.2 %, principal points within 5 px, rig_T_cam within
0.3 mm and 0.2 degrees.

Also the held-out error (annotator.calibration.heldout: 5-fold over shots, each left-out
shot's board pose from one camera, its corners predicted in the other, px RMS) of each
pipeline fitted on the same folds: ours with OpenCV's five coefficients, ours with the model
chosen by the held-out error (``annotator calibrate``'s default), and OpenCV's pipeline
(per-camera calibrateCamera, then stereoCalibrate with the intrinsics fixed; and joint).

    .venv/bin/python -m benchmarks.bench_calibrate [--seeds 3] [--part reference|behind|webcams|real]
    .venv/bin/python -m benchmarks.bench_calibrate --part real [SESSION]

Four webcams as a real session records them (``--part webcams``, issue 48): a board printed
colour-inverted and mirrored, the fourth camera behind it, webcam noise, webcams not in step
while the hand-held board moves: whether all four join, none mirrored, and the held-out
transfer error of ours against OpenCV's pairwise pipeline given the right reading.

A camera behind the board (``--part behind``): a four-camera rig of 1280x720 cameras (the
synthetic pair and two more above and below the reference camera), 20 shots, the fourth
camera (``cam3``) turned round to the far side of a thin back-lit board, seeing its print
through the paper (mirrored, less contrast). The held-out cross-camera transfer error of
that rig, against the same rig without that camera, the same rig with that camera in front,
and OpenCV's pairwise pipeline (calibrateCamera per camera, stereoCalibrate with the
intrinsics fixed against the first camera) given the right reading; and whether any camera
was declared mirrored.

A real session (``--part real [SESSION]``, issue 54): four webcams as caliscope records them
(``charuco.toml``, ``calibration/extrinsic/cam_N.mp4``, ``timestamps.csv``; default the
trimmed copy ``tests/data/caliscope-4cam``, or the whole session given as SESSION), read and
calibrated as ``annotator calibrate`` does with no option. The held-out transfer error (the
same 5 folds, one camera's board pose predicting another's corners) of ours, of OpenCV's
pairwise pipeline (calibrateCamera per camera, stereoCalibrate against the first camera
with the intrinsics fixed), of caliscope's own ``camera_array.toml`` (measured on our
corners, and on corners mapped back from a flipped image its way) and of each pair
calibrated alone (the bar ``calibrate`` holds a rig to): on every view as read, and on the
views ours kept.

Seed 0 is the captures of tests/test_calibrate.py (``annotator synth --calibration OUT
--scenes 30 --noise 12 --blur 1``).
"""

from __future__ import annotations

import argparse
import time
import tomllib
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np

from annotator.calibration.captures import find_captures
from annotator.calibration.detect import BoardDetector, detect_captures
from annotator.calibration.heldout import held_out_error
from annotator.calibration.model_choice import calibrate_and_assess
from annotator.calibration.pairwise import pairwise_held_out
from annotator.calibration.readings import decide_readings
from annotator.calibration.records import CalibrationSettings, View
from annotator.calibration.rig import solve_rig
from annotator.calibration.workflow import resolve_board
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert, make_transform
from annotator.synthesis.board import CaptureSettings, plan_captures
from annotator.synthesis.board_render import BLACK, WHITE, true_corners

# OpenCV's pipelines, the reference, are test support code: they live beside the tests.
from devkit.opencv_baseline import opencv_rig, opencv_stereo

TARGET = {"focal %": 0.2, "pp px": 5.0, "t mm": 0.3, "R deg": 0.2}


def errors(Ks, rig_T_cam1, rig) -> dict[str, float]:  # noqa: ANN001
    """Worst errors over both cameras."""
    cams = rig.cameras
    d = invert(cams[1].rig_T_cam) @ rig_T_cam1
    return {
        "focal %": max(
            abs(K[i, i] / c.K[i, i] - 1) * 100 for K, c in zip(Ks, cams) for i in (0, 1)
        ),
        "pp px": max(float(np.linalg.norm(K[:2, 2] - c.K[:2, 2])) for K, c in zip(Ks, cams)),
        "t mm": float(np.linalg.norm(rig_T_cam1[:3, 3] - cams[1].rig_T_cam[:3, 3])),
        "R deg": float(np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))),
    }


def opencv_fit(sizes, board, *, joint: bool):  # noqa: ANN001, ANN201
    """OpenCV's pipeline as a fit for the held-out error: its two cameras."""

    def fit(views):  # noqa: ANN001, ANN202
        r = opencv_stereo(views, board, sizes, joint=joint)
        return [
            Camera("left", *sizes[0], r.K[0], r.dist[0]),
            Camera("right", *sizes[1], r.K[1], r.dist[1], r.rig_T_cam1),
        ]

    return fit


def held_out_table(views, plan, cfg) -> dict[str, float]:  # noqa: ANN001
    """Held-out RMS (px) of each pipeline on the same folds."""
    names = [c.name for c in plan.rig.cameras]
    sizes = [c.size for c in plan.rig.cameras]
    common = {"cameras": names, "sizes": sizes, "shots": plan.shot_names, "board": cfg.board}

    def ours(views):  # noqa: ANN001, ANN202
        return solve_rig(views, **common, options=CalibrationSettings(min_shots=3)).rig_cameras

    chosen = calibrate_and_assess(views, **common)
    return {
        "ours, 5 coefficients": held_out_error(views, ours, cfg.board, names).rms_px,
        f"ours, chosen ({chosen.model_choice.dist_coeffs})": chosen.held_out.rms_px,
        "OpenCV two-step": held_out_error(
            views, opencv_fit(sizes, cfg.board, joint=False), cfg.board, names
        ).rms_px,
        "OpenCV joint": held_out_error(
            views, opencv_fit(sizes, cfg.board, joint=True), cfg.board, names
        ).rms_px,
    }


def detect_plan(plan) -> list[View]:  # noqa: ANN001
    """Every camera's view of every shot, as ``detect_captures`` makes them (a board read
    only flipped mapped back to the image as recorded)."""
    detector = BoardDetector(plan.config.board)
    views = []
    for k in range(len(plan.poses)):
        for c, img in enumerate(plan.render(k)):
            det = detector.detect(img)
            corners = det.corners.copy()
            if det.mirrored:
                corners[:, 0] = img.shape[1] - 1 - corners[:, 0]
            views.append(View(c, k, det.ids, corners, det.markers, det.mirrored and det.found))
    return views


def used_views(cal, views):  # noqa: ANN001, ANN201
    """The views a calibration kept (the ones its held-out error predicts)."""
    kept = {
        (int(c), int(s)) for c, s in zip(cal.corners.camera[cal.used], cal.corners.shot[cal.used])
    }
    return [v for v in views if (v.camera, v.shot) in kept]


def fixed(cameras):  # noqa: ANN001, ANN201
    """A fit that ignores its shots: the given cameras (the true rig)."""
    return lambda train: cameras


def pair_rms(held, skip: str | None = None) -> float:  # noqa: ANN001
    """Held-out RMS over the pairs (corners weighted) not involving camera ``skip``."""
    pairs = [p for p in held.pairs if skip not in (p.source, p.target)]
    n = sum(p.corners for p in pairs)
    return float(np.sqrt(sum(p.rms_px**2 * p.corners for p in pairs) / n))


def rendered_and_calibrated(cfg: CaptureSettings):  # noqa: ANN201
    """The captures of ``cfg`` rendered and detected, and ``annotator calibrate``'s
    calibration of them: the plan, the views and the calibration."""
    plan = plan_captures(cfg)
    views = detect_plan(plan)
    cal = calibrate_and_assess(
        views,
        cameras=[c.name for c in plan.rig.cameras],
        sizes=[c.size for c in plan.rig.cameras],
        shots=plan.shot_names,
        board=cfg.board,
    )
    return plan, views, cal


def print_rows(title: str, rows: dict[str, list[float]]) -> None:
    """A table of figures over seeds: each row's median and maximum."""
    print(f"\n{title}, median (max):")
    for k, vals in rows.items():
        print(f"  {k:60s} {np.median(vals):.3f} ({max(vals):.3f})")


def behind_part(n_seeds: int) -> None:
    """The camera behind the board (see the module docstring)."""
    rows: dict[str, list[float]] = {}
    for seed in range(n_seeds):
        base = {"shots": 20, "seed": seed, "noise": 12.0, "blur": 1.0, "size": (1280, 720)}
        cfg = CaptureSettings(**base, extra_cameras=2, behind=("cam3",))
        plan, views, cal = rendered_and_calibrated(cfg)
        names = [c.name for c in plan.rig.cameras]
        sizes = [c.size for c in plan.rig.cameras]
        common = {"sizes": sizes, "shots": plan.shot_names, "board": cfg.board}
        mirrored = cal.readings.mirrored
        used = sum(rep.shots > 0 for rep in cal.cameras)
        # The same rig without that camera.
        without = calibrate_and_assess(
            [v for v in views if v.camera < 3], cameras=names[:3], **{**common, "sizes": sizes[:3]}
        )
        # The same rig with that camera in front.
        front_plan = plan_captures(CaptureSettings(**base, extra_cameras=2))
        front_views = detect_plan(front_plan)
        front = calibrate_and_assess(front_views, cameras=names, **common)
        # The same rig, the back seen as sharply as the front (the print's own greys): what
        # is left is the reading from behind alone, without the paper's loss of contrast.
        sharp_plan = plan_captures(
            CaptureSettings(**base, extra_cameras=2, behind=("cam3",), through_paper=(WHITE, BLACK))
        )
        sharp = calibrate_and_assess(detect_plan(sharp_plan), cameras=names, **common)
        # OpenCV's pairwise pipeline, given the right reading.
        read = decide_readings(views, cameras=names, **common).views
        opencv = held_out_error(
            read, partial(opencv_rig, board=cfg.board, sizes=sizes, names=names), cfg.board, names
        )
        # The true rig measured the same way: the floor of this measure on these shots (a
        # board pose from one camera alone is least sure along its own line of sight, which a
        # camera facing it from the far side sees side-on).
        truth = held_out_error(used_views(cal, views), fixed(plan.rig.cameras), cfg.board, names)
        front_truth = held_out_error(
            used_views(front, front_views), fixed(front_plan.rig.cameras), cfg.board, names
        )
        row = {
            "the true rig, cam3 behind: all pairs": truth.rms_px,
            "the true rig, cam3 in front: all pairs": front_truth.rms_px,
            "ours, cam3 behind: all pairs": cal.held_out.rms_px,
            "ours, cam3 behind: pairs without cam3": pair_rms(cal.held_out, "cam3"),
            "ours, the rig without cam3": without.held_out.rms_px,
            "ours, cam3 in front: all pairs": front.held_out.rms_px,
            "ours, cam3 behind, its back as sharp as a front: all pairs": sharp.held_out.rms_px,
            "OpenCV pairwise, cam3 behind read right: all pairs": opencv.rms_px,
            "corner noise of cam3 alone (its held-out error)": cal.camera_held_out[3],
        }
        for k, v in row.items():
            rows.setdefault(k, []).append(v)
        print(
            f"behind, seed {seed}: cameras used {used} of {len(names)}, declared mirrored: "
            f"{mirrored or 'none'}, refused: {[str(p) for p in cal.problems] or 'no'}; "
            + "; ".join(f"{k} {v:.3f}" for k, v in row.items())
        )
    print_rows(f"a camera behind the board, {n_seeds} seeds, held-out error (px RMS)", rows)
    ratio = [
        a / b
        for a, b in zip(
            rows["ours, cam3 behind: pairs without cam3"], rows["ours, the rig without cam3"]
        )
    ]
    print(
        "  pairs without cam3, with it against without it: x"
        + ", x".join(f"{r:.3f}" for r in ratio)
        + " (target: within 10%)"
    )
    sharp = [
        a / b
        for a, b in zip(
            rows["ours, cam3 behind, its back as sharp as a front: all pairs"],
            rows["ours, cam3 in front: all pairs"],
        )
    ]
    print(
        "  all pairs, cam3 behind (back as sharp as a front) against cam3 in front: x"
        + ", x".join(f"{r:.3f}" for r in sharp)
    )


#: The four-webcam session of issue 48 (``--part webcams``): a board printed colour-inverted
#: and mirrored, the fourth camera behind it (through the paper, dimmer and blurred), webcam
#: noise, each webcam 33 ms after the one before (give or take 10 ms) while the hand-held
#: board is mostly still, now and then moving.
WEBCAMS = {
    "shots": 20,
    "noise": 14.0,
    "blur": 1.3,
    "size": (1280, 720),
    "extra_cameras": 2,
    "behind": ("cam3",),
    "inverted": True,
    "printed_mirrored": True,
    "paper_blur": 1.5,
    "timing_ms": 10.0,
    "rolling_ms": 33.0,
}


def webcams_part(n_seeds: int) -> None:
    """The four-webcam session (see :data:`WEBCAMS`), the board moving at up to 40 and 60 mm/s:
    cameras joined, mirrored, views left out, the held-out transfer error of ours and of
    OpenCV's pairwise pipeline given the right reading (no camera mirrored), on every view and
    on the views ours kept, and of the true rig on those."""
    rows: dict[str, list[float]] = {}
    for speed in (40.0, 60.0):
        for seed in range(n_seeds):
            cfg = CaptureSettings(**WEBCAMS, seed=seed, speed=(speed, speed / 5))  # type: ignore[arg-type]
            plan, views, cal = rendered_and_calibrated(cfg)
            names = [c.name for c in plan.rig.cameras]
            sizes = [c.size for c in plan.rig.cameras]
            kept = used_views(cal, views)
            # The right reading: nobody mirrored, every view's corners as recorded.
            right = [v for v in views if not v.rejected]
            fit = partial(opencv_rig, board=cfg.board, sizes=sizes, names=names)
            opencv_all = held_out_error(right, fit, cfg.board, names).rms_px
            opencv_kept = held_out_error(kept, fit, cfg.board, names).rms_px
            truth = held_out_error(kept, fixed(plan.rig.cameras), cfg.board, names).rms_px
            moved = sum("another moment" in r.reason for r in cal.rejections)
            row = {
                f"{speed:.0f} mm/s: ours": cal.held_out.rms_px,
                f"{speed:.0f} mm/s: OpenCV pairwise, every view": opencv_all,
                f"{speed:.0f} mm/s: OpenCV pairwise, the views ours kept": opencv_kept,
                f"{speed:.0f} mm/s: the true rig, the views ours kept": truth,
            }
            for k, v in row.items():
                rows.setdefault(k, []).append(v)
            print(
                f"webcams, {speed:.0f} mm/s, seed {seed}: cameras used "
                f"{sum(rep.shots > 0 for rep in cal.cameras)} of {len(names)}, declared mirrored: "
                f"{cal.readings.mirrored or 'none'}, refused: "
                f"{[str(p) for p in cal.problems] or 'no'}; views left out as of another moment "
                f"{moved} of {len(kept) + moved}; "
                + "; ".join(f"{k.split(': ')[1]} {v:.3f}" for k, v in row.items())
            )
    print_rows(f"four webcams, {n_seeds} seeds, held-out transfer error (px RMS)", rows)


#: The session ``--part real`` measures by default: the trimmed copy the tests calibrate.
REAL_SESSION = Path(__file__).resolve().parent.parent / "tests" / "data" / "caliscope-4cam"


def caliscope_rig(session: Path, names: list[str], sizes: list[tuple[int, int]]) -> list[Camera]:
    """caliscope's own calibration of a session (``camera_array.toml``: per ``cam_id`` K,
    distortion and the world-to-camera rotation and translation in metres) in our terms:
    the first camera is the rig frame, millimetres."""
    doc = tomllib.loads((session / "camera_array.toml").read_text())["cameras"]
    entry = {f"cam_{k}": v for k, v in doc.items()}
    cam_T_world = [
        make_transform(np.array(entry[n]["rotation"]), 1000.0 * np.array(entry[n]["translation"]))
        for n in names
    ]
    return [
        Camera(
            n,
            *sizes[k],
            np.array(entry[n]["matrix"], float),
            np.array(entry[n]["distortions"], float),
            cam_T_world[0] @ invert(cam_T_world[k]),
        )
        for k, n in enumerate(names)
    ]


def pair_medians(held) -> str:  # noqa: ANN001
    """``a->b median`` of every pair between two cameras, the camera names' last characters."""
    return " ".join(
        f"{p.source[-1]}{p.target[-1]} {p.median_px:.2f}"
        for p in held.pairs
        if p.source != p.target
    )


def real_part(session: Path) -> None:
    """A real session as caliscope records it (see the module docstring)."""
    t0 = time.perf_counter()
    caps = find_captures(session)
    board = resolve_board(session, None, {}, caps.board_file)
    found = detect_captures(caps, board)
    names, sizes = list(caps.cameras), found.sizes
    common = {"cameras": names, "sizes": sizes, "shots": caps.shots, "board": board}
    cal = calibrate_and_assess(found.views, **common)
    seconds = time.perf_counter() - t0
    model = cal.model_choice.dist_coeffs
    read = [v for v in cal.readings.views if not v.rejected]
    kept = used_views(cal, read)

    def ours(train):  # noqa: ANN001, ANN202
        opts = CalibrationSettings(min_shots=3, dist_coeffs=model)
        return solve_rig(train, **common, options=opts).rig_cameras

    peer = caliscope_rig(session, names, sizes)
    # caliscope maps a board read in the flipped image back with u -> W - u, one pixel off
    # OpenCV's u -> W - 1 - u (detect.py): its rig measured on corners mapped its way too.
    shifted = [replace(v, corners=v.corners + [1.0, 0.0]) if v.flipped else v for v in read]
    shifted_kept = [replace(v, corners=v.corners + [1.0, 0.0]) if v.flipped else v for v in kept]
    opencv = partial(opencv_rig, board=board, sizes=sizes, names=names)
    rows = {}
    for label, views, alt in (
        ("every view", read, shifted),
        ("the views ours kept", kept, shifted_kept),
    ):
        rows[f"ours ({model} coefficients), {label}"] = held_out_error(views, ours, board, names)
        rows[f"OpenCV pairwise pipeline, {label}"] = held_out_error(views, opencv, board, names)
        rows[f"caliscope's camera_array.toml, {label}"] = held_out_error(
            views, fixed(peer), board, names
        )
        rows[f"caliscope's, its own flip (u -> W - u), {label}"] = held_out_error(
            alt, fixed(peer), board, names
        )
        rows[f"each pair alone (OpenCV stereo), {label}"] = pairwise_held_out(
            views, cameras=names, sizes=sizes, board=board, dist_coeffs=model, folds=5
        )
    print(
        f"\nreal session {session}: {len(caps.shots)} shots, cameras used "
        f"{sum(rep.shots > 0 for rep in cal.cameras)} of {len(names)}, refused: "
        f"{[str(p) for p in cal.problems] or 'no'}, behind the board: "
        f"{[r.camera for r in cal.readings.cameras if r.behind] or 'none'}; views kept "
        f"{len(kept)} of {len(read)}; calibrate's solve {seconds:.1f} s (detection included)"
    )
    print(
        "held-out transfer error between cameras, 5-fold (px): median over every corner, RMS; per pair median"
    )
    for label, held in rows.items():
        print(f"  {label:62s} {held.median_px:6.3f} {held.rms_px:7.3f} | {pair_medians(held)}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=3, help="sets of captures (default 3)")
    parser.add_argument(
        "--part",
        choices=("all", "reference", "behind", "webcams", "real"),
        default="all",
        help="what to measure",
    )
    parser.add_argument(
        "session",
        nargs="?",
        type=Path,
        default=REAL_SESSION,
        help="--part real: a caliscope session (default: the trimmed copy in tests/data)",
    )
    args = parser.parse_args()
    n_seeds = args.seeds
    if args.part in ("all", "real"):
        real_part(args.session)
    if args.part == "real":
        return
    if args.part in ("all", "webcams"):
        webcams_part(n_seeds)
    if args.part == "webcams":
        return
    if args.part in ("all", "behind"):
        behind_part(n_seeds)
    if args.part == "behind":
        return
    table: dict[str, list[dict[str, float]]] = {"ours": [], "two-step": [], "joint": []}
    solve_s, noise = [], []
    held: list[dict[str, float]] = []
    for seed in range(n_seeds):
        cfg = CaptureSettings(shots=30, seed=seed, noise=12.0, blur=1.0)
        plan = plan_captures(cfg)
        detector = BoardDetector(cfg.board)
        views, err = [], []
        for k, T in enumerate(plan.poses):
            for c, (cam, img) in enumerate(zip(plan.rig.cameras, plan.render(k))):
                det = detector.detect(img)
                views.append(View(c, k, det.ids, det.corners, det.markers))
                err.append(det.corners - true_corners(cam, T, cfg.board)[det.ids])
        noise.append(float(np.sqrt(np.mean(np.sum(np.concatenate(err) ** 2, axis=1)))))
        sizes = [c.size for c in plan.rig.cameras]
        t0 = time.perf_counter()
        cal = solve_rig(
            views,
            cameras=[c.name for c in plan.rig.cameras],
            sizes=sizes,
            shots=plan.shot_names,
            board=cfg.board,
        )
        solve_s.append(time.perf_counter() - t0)
        table["ours"].append(
            errors([c.camera.K for c in cal.cameras], cal.cameras[1].camera.rig_T_cam, plan.rig)
        )
        for name, joint in (("two-step", False), ("joint", True)):
            r = opencv_stereo(views, cfg.board, sizes, joint=joint)
            table[name].append(errors(r.K, r.rig_T_cam1, plan.rig))
        held.append(held_out_table(views, plan, cfg))
        print(
            f"seed {seed}: held-out error (px) "
            + "; ".join(f"{k} {v:.4f}" for k, v in held[-1].items())
        )
        print(
            f"seed {seed}: corner noise {noise[-1]:.3f} px; "
            + "; ".join(
                f"{name} " + " ".join(f"{v:.3g}" for v in table[name][-1].values())
                for name in table
            )
        )
    print(
        f"\n{n_seeds} sets of 30 shots, corner noise {np.mean(noise):.3f} px RMS; "
        f"our calibration {np.mean(solve_s):.2f} s per set (detection not counted)"
    )
    print(f"{'median (max)':28s}" + "".join(f"{k:>18s}" for k in TARGET))
    for name, label in (
        ("ours", "ours: joint, all corners"),
        ("two-step", "OpenCV two-step"),
        ("joint", "OpenCV joint stereoCalibrate"),
    ):
        cells = []
        for k in TARGET:
            vals = [row[k] for row in table[name]]
            cells.append(f"{np.median(vals):.3f} ({max(vals):.3f})")
        print(f"{label:28s}" + "".join(f"{c:>18s}" for c in cells))
    print(
        "\nheld-out error, 5-fold over shots, left->right and right->left (px RMS), median (max):"
    )
    for k in held[0]:
        label = k if not k.startswith("ours, chosen") else "ours, chosen model"
        vals = [
            next(v for kk, v in row.items() if kk.split(" (")[0] == k.split(" (")[0])
            for row in held
        ]
        print(f"  {label:28s} {np.median(vals):.4f} ({max(vals):.4f})")
    worst = {k: max(row[k] for row in table["ours"]) for k in TARGET}
    print(
        "ours, worst / target: " + ", ".join(f"{k} {worst[k] / t:.2f}" for k, t in TARGET.items())
    )


if __name__ == "__main__":
    main()
