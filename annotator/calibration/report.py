"""What a calibration shows its user: per camera and per shot RMS, rejected shots and why,
and how much of each image the board's corners covered (a picture per camera).

Coverage: the image is divided into ``COVERAGE_GRID`` cells; a cell is covered if at least
one corner used by the calibration fell in it. Lens distortion is only measured where
corners were seen, so uncovered cells (typically the image corners) are where the model is
extrapolated. The picture (``coverage_<camera>.png``) shades each cell by its number of
corners, draws every used corner (green) and every outlier (red) with its residual
magnified (by the factor printed at the top, the median residual drawn 8 px long), and
prints the figures at the top. Where the distortion model is extrapolated
(:mod:`.extrapolation`) is drawn too: the convex hull of the corners used (yellow), and the
cells outside it where the distortion moves pixels further than anywhere inside (orange,
with the displacement in px).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from annotator.calibration.board import BoardSpec
from annotator.calibration.captures import Captures
from annotator.calibration.checks import both_ways
from annotator.calibration.extrapolation import Extrapolation, displacement
from annotator.calibration.records import Calibration
from annotator.io.atomic import write_json
from annotator.io.images import write_png

#: Columns and rows of the coverage grid.
COVERAGE_GRID = (8, 6)
#: Residual vectors are magnified so that the median one is drawn this long (picture px).
RESIDUAL_LENGTH = 8.0
#: The picture is at most this wide (px).
PICTURE_WIDTH = 1024


def coverage(cal: Calibration, camera: int) -> tuple[float, np.ndarray]:
    """Fraction of the grid cells covered by used corners, and the (rows, cols) counts."""
    w, h = cal.sizes[camera]
    sel = cal.used & (cal.corners.camera == camera)
    uv = cal.corners.pixel[sel]
    cols, rows = COVERAGE_GRID
    i = np.clip(((uv[:, 1] + 0.5) / h * rows).astype(int), 0, rows - 1)
    j = np.clip(((uv[:, 0] + 0.5) / w * cols).astype(int), 0, cols - 1)
    counts = np.zeros((rows, cols), int)
    np.add.at(counts, (i, j), 1)
    return float((counts > 0).mean()), counts


def coverage_picture(cal: Calibration, camera: int) -> np.ndarray:
    """The coverage picture of a camera (BGR uint8, at most ``PICTURE_WIDTH`` wide)."""
    w, h = cal.sizes[camera]
    s = min(1.0, PICTURE_WIDTH / w)
    W, H = round(w * s), round(h * s)
    banner = 62
    img = np.full((H + banner, W, 3), 24, np.uint8)
    frac, counts = coverage(cal, camera)
    _draw_cells(img, counts, banner)
    ex = cal.extrapolation[camera] if len(cal.extrapolation) > camera else None
    if ex is not None:
        _draw_extrapolation(img, cal, camera, ex, s, banner)
    magnify = _draw_corners(img, cal, camera, s, banner)
    lines = _banner_lines(cal, camera, frac, counts.size, magnify, ex)
    for k, text in enumerate(lines):
        cv2.putText(
            img,
            text,
            (8, 18 + 18 * k),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5,
            (230, 230, 230),
            1,
            cv2.LINE_AA,
        )
    return img


def _draw_cells(img: np.ndarray, counts: np.ndarray, banner: int) -> None:
    """The grid below the banner, each cell green by its corner count or dull red if none."""
    H, W = img.shape[0] - banner, img.shape[1]
    rows, cols = counts.shape
    top = counts.max() if counts.max() > 0 else 1
    for r in range(rows):
        for c in range(cols):
            x0, x1 = round(c * W / cols), round((c + 1) * W / cols)
            y0, y1 = banner + round(r * H / rows), banner + round((r + 1) * H / rows)
            if counts[r, c]:
                level = 0.25 + 0.75 * counts[r, c] / top
                img[y0:y1, x0:x1] = (int(40 * level), int(110 * level), int(40 * level))
            else:
                img[y0:y1, x0:x1] = (40, 40, 90)  # dull red: never seen
            cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), (70, 70, 70), 1)


def _draw_corners(img: np.ndarray, cal: Calibration, camera: int, s: float, banner: int) -> float:
    """Every corner of the camera (green: used, red: outlier) with its residual magnified;
    returns the magnification (the median residual drawn ``RESIDUAL_LENGTH`` long)."""
    sel = cal.corners.camera == camera
    norms = np.linalg.norm(cal.residuals[sel & cal.used], axis=1)
    median = float(np.median(norms)) if len(norms) else 0.0
    magnify = float(f"{RESIDUAL_LENGTH / (median * s):.1g}") if median > 0 else 1.0
    for used, colour in ((True, (120, 255, 120)), (False, (60, 60, 255))):
        pick = sel & (cal.used == used)
        uv = cal.corners.pixel[pick] * s
        res = cal.residuals[pick] * s * magnify
        # A rig that ran off has residuals of any size, or none: drawn at most a picture long.
        res = np.nan_to_num(res, nan=0.0, posinf=0.0, neginf=0.0)
        longest = float(img.shape[1])
        norm = np.linalg.norm(res, axis=1, keepdims=True)
        res = np.where(norm > longest, res * longest / np.maximum(norm, 1e-12), res)
        for (u, v), (du, dv) in zip(uv, res):
            p = (int(round(u)), banner + int(round(v)))
            cv2.circle(img, p, 1 if used else 3, colour, -1, cv2.LINE_AA)
            if not used or np.hypot(du, dv) > 2:
                q = (int(round(u + du)), banner + int(round(v + dv)))
                cv2.line(img, p, q, colour, 1, cv2.LINE_AA)
    return magnify


def _banner_lines(
    cal: Calibration,
    camera: int,
    frac: float,
    cells: int,
    magnify: float,
    ex: Extrapolation | None,
) -> list[str]:
    """The figures printed at the top of the picture, and what its colours mean."""
    w, h = cal.sizes[camera]
    rep = cal.cameras[camera]
    lines = [
        f"{rep.camera.name}: {w}x{h}, {rep.shots} shots, {rep.corners} corners, "
        f"RMS {rep.rms_px:.3f} px, coverage {100 * frac:.0f}% of {cells} cells",
        f"green: corners used, red: outliers; residuals x{magnify:g}; "
        "dull red cells: no corner, the distortion there is extrapolated",
    ]
    if ex is not None:
        lines.append(
            f"yellow: covered region ({100 * ex.coverage:.0f}% of the image); distortion "
            f"{ex.corner_px:.1f} px at the image corners, at most {ex.covered_px:.1f} px inside"
            + ("; orange: extrapolated" if ex.extrapolated else "")
        )
    return lines


def _draw_extrapolation(
    img: np.ndarray, cal: Calibration, camera: int, ex: Extrapolation, s: float, banner: int
) -> None:
    """The covered region's outline, and the cells beyond it where the model extrapolates."""
    w, h = cal.sizes[camera]
    H, W = img.shape[0] - banner, img.shape[1]
    cols, rows = COVERAGE_GRID
    cam = cal.cameras[camera].camera
    if ex.extrapolated:
        for r in range(rows):
            for c in range(cols):
                centre = ((c + 0.5) * w / cols - 0.5, (r + 0.5) * h / rows - 0.5)
                if (
                    len(ex.hull) >= 3
                    and cv2.pointPolygonTest(ex.hull.astype(np.float32), centre, False) >= 0
                ):
                    continue
                d = float(displacement(cam, np.array([centre]))[0])
                if d <= ex.covered_px:
                    continue
                x0, x1 = round(c * W / cols), round((c + 1) * W / cols)
                y0, y1 = banner + round(r * H / rows), banner + round((r + 1) * H / rows)
                tint = (
                    img[y0:y1, x0:x1].astype(np.float32) * 0.4
                    + np.array((0, 110, 230), np.float32) * 0.6
                )
                img[y0:y1, x0:x1] = tint.astype(np.uint8)
                cv2.putText(
                    img,
                    f"{d:.0f}px",
                    (x0 + 4, y1 - 6),
                    cv2.FONT_HERSHEY_SIMPLEX,
                    0.4,
                    (255, 255, 255),
                    1,
                    cv2.LINE_AA,
                )
    if len(ex.hull) >= 3:
        pts = np.round(ex.hull * s + [0, banner]).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], True, (0, 230, 255), 2, cv2.LINE_AA)


def report_dict(
    cal: Calibration, board: BoardSpec, *, captures: Captures, flipped: Sequence[str] = ()
) -> dict[str, Any]:
    """Everything about a calibration, for ``report.json`` and ``--json``."""
    out: dict[str, Any] = {
        "captures": str(captures.root),
        "board": board.to_yaml(),
        "rms_px": round(cal.rms_px, 4),
        "iterations": cal.iterations,
        "cameras": [_camera_entry(cal, k, flipped) for k in range(len(cal.cameras))],
        "shots": [
            {
                "name": s.name,
                "used": s.used,
                "rms_px": {k: round(v, 4) for k, v in s.rms_px.items()},
                "corners": s.corners,
            }
            for s in cal.shots
        ],
        "rejected": [
            {"shot": r.shot, "camera": r.camera, "reason": r.reason} for r in cal.rejections
        ],
        "warnings": list(cal.warnings),
        "converged": cal.converged,
        "refused": [p.to_dict() for p in cal.problems],
    }
    if cal.camera_held_out:
        out["camera_held_out_rms_px"] = {
            rep.camera.name: None if not np.isfinite(e) else round(e, 4)
            for rep, e in zip(cal.cameras, cal.camera_held_out)
        }
    if cal.held_out is not None:
        out["held_out"] = cal.held_out.to_dict()
    if cal.pair_held_out is not None:
        out["pair_held_out"] = cal.pair_held_out.to_dict()
    if cal.model_choice is not None:
        out["distortion_model"] = {
            "coefficients": cal.model_choice.dist_coeffs,
            "reason": cal.model_choice.reason,
            "held_out_rms_px": {
                str(m): round(h.rms_px, 4) for m, h in cal.model_choice.held_out.items()
            },
        }
    if captures.videos:
        out["videos"] = _videos_entry(captures)
    return out


def _camera_entry(cal: Calibration, k: int, flipped: Sequence[str]) -> dict[str, Any]:
    """One camera of ``report.json``: the calibrated camera, its figures, its flip and where
    its distortion is extrapolated."""
    rep = cal.cameras[k]
    cam = rep.camera
    frac, _ = coverage(cal, k)
    ex = cal.extrapolation[k] if len(cal.extrapolation) > k else None
    extra: dict[str, Any] = {"flip": "horizontal" if cam.name in flipped else None}
    if cal.readings is not None:
        extra["reading"] = cal.readings.cameras[k].to_dict()
    if ex is not None:
        extra["extrapolation"] = {
            "covered_fraction": round(ex.coverage, 3),
            "corner_displacement_px": round(ex.corner_px, 2),
            "covered_displacement_px": round(ex.covered_px, 2),
            "extrapolated": ex.extrapolated,
        }
    return {
        "name": cam.name,
        "size": [cam.width, cam.height],
        "K": cam.K.ravel().tolist(),
        "dist": cam.dist.tolist(),
        "rig_T_cam": cam.rig_T_cam.ravel().tolist(),
        "rms_px": round(rep.rms_px, 4),
        "initial_rms_px": round(rep.initial_rms_px, 4),
        "initial_focal_px": [round(f, 2) for f in rep.initial_focal_px],
        "shots": rep.shots,
        "corners": rep.corners,
        "outlier_corners": rep.outlier_corners,
        "coverage": round(frac, 3),
        "std": {k: float(f"{v:.3g}") for k, v in rep.std.items()},
        **extra,
    }


def _videos_entry(captures: Captures) -> dict[str, Any]:
    """The videos of ``report.json``: the files, the pairing, each shot's frames (and their
    times, when the recording gives them)."""
    out: dict[str, Any] = {
        "files": {c: str(p) for c, p in captures.videos.items()},
        "pairing": captures.pairing,
        "frames": {
            shot: {c: captures.frames[(c, shot)] for c in captures.cameras}
            for shot in captures.shots
        },
        "unpaired": list(captures.unpaired),
    }
    if captures.times:
        out["times_s"] = {
            shot: {c: captures.times[(c, shot)] for c in captures.cameras}
            for shot in captures.shots
        }
    return out


def write_report(
    folder: Path,
    cal: Calibration,
    board: BoardSpec,
    *,
    captures: Captures,
    flipped: Sequence[str] = (),
) -> list[Path]:
    """Write ``report.json`` and ``coverage_<camera>.png`` into ``folder``; return the paths."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = [folder / "report.json"]
    write_json(paths[0], report_dict(cal, board, captures=captures, flipped=flipped))
    for k, rep in enumerate(cal.cameras):
        path = folder / f"coverage_{rep.camera.name}.png"
        write_png(path, coverage_picture(cal, k))
        paths.append(path)
    return paths


def summary_lines(cal: Calibration) -> list[str]:
    """The terminal summary: one line per camera, the shots, the rejections."""
    out = []
    for k, rep in enumerate(cal.cameras):
        cam = rep.camera
        frac, _ = coverage(cal, k)
        where = ""
        if k > 0:
            t = cam.rig_T_cam[:3, 3]
            where = (
                f", at ({t[0]:.1f}, {t[1]:.1f}, {t[2]:.1f}) mm "
                f"+- {rep.std['position_mm']:.2f} mm, +- {rep.std['rotation_deg']:.3f} deg"
            )
        out.append(
            f"{cam.name}: RMS {rep.rms_px:.3f} px ({rep.shots} shots, {rep.corners} corners, "
            f"{rep.outlier_corners} outlier{'' if rep.outlier_corners == 1 else 's'}), f = {cam.K[0, 0]:.1f} +- {rep.std['fx']:.2f} px, "
            f"c = ({cam.K[0, 2]:.1f}, {cam.K[1, 2]:.1f}) +- {max(rep.std['cx'], rep.std['cy']):.2f} px, "
            f"coverage {100 * frac:.0f}%{where}"
        )
    used = sum(s.used for s in cal.shots)
    worst = sorted((max(s.rms_px.values()), s.name) for s in cal.shots if s.used)[-3:]
    out.append(
        f"shots: {used} of {len(cal.shots)} used, RMS {cal.rms_px:.3f} px over all; worst: "
        + ", ".join(f"{name} {rms:.3f} px" for rms, name in reversed(worst))
    )
    names = [rep.camera.name for rep in cal.cameras]
    cells = [
        f"{s.name} " + "/".join(f"{s.rms_px[n]:.2f}" if n in s.rms_px else "-" for n in names)
        for s in cal.shots
    ]
    line = f"RMS per shot (px, {'/'.join(names)}):"
    for cell in cells:
        if len(line) + len(cell) + 2 > 100:
            out.append(line)
            line = " "
        line += f" {cell},"
    out.append(line.rstrip(","))
    if cal.held_out is not None:
        pairs = ", ".join(f"{p.source}->{p.target} {p.rms_px:.3f}" for p in cal.held_out.pairs)
        out.append(
            f"held-out error: RMS {cal.held_out.rms_px:.3f} px over {cal.held_out.corners} corners "
            f"of left-out shots ({cal.held_out.folds}-fold; {pairs or 'no pair'})"
        )
        out.extend(_transfer_lines(cal))
    if cal.camera_held_out:
        out.append(
            "held-out error of each camera alone: "
            + ", ".join(
                f"{rep.camera.name} {e:.3f}" for rep, e in zip(cal.cameras, cal.camera_held_out)
            )
            + " px"
        )
    if cal.model_choice is not None:
        out.append(f"distortion model: {cal.model_choice.reason}")
    for r in cal.rejections:
        out.append(f"rejected: {r}")
    for w in cal.warnings:
        out.append(f"warning: {w}")
    return out


def _transfer_lines(cal: Calibration) -> list[str]:
    """The held-out transfer error between cameras (median per pair), beside what each pair
    reaches calibrated alone as a stereo pair."""
    held = cal.held_out
    cross = [p for p in held.pairs if p.source != p.target]
    if not cross:
        return []
    line = (
        f"held-out transfer error between cameras: median {held.median_px:.3f} px ("
        + ", ".join(f"{p.source}->{p.target} {p.median_px:.2f}" for p in cross)
        + ")"
    )
    alone = both_ways(cal.pair_held_out)
    if not alone:
        return [line]
    ours = both_ways(held)
    names = [rep.camera.name for rep in cal.cameras]
    order = sorted((k for k in ours if k in alone), key=lambda k: sorted(map(names.index, k)))
    cells = [
        f"{'<->'.join(sorted(k, key=names.index))} {ours[k][0]:.2f} ({alone[k][0]:.2f})"
        for k in order
    ]
    return [
        line,
        "both ways, against each pair calibrated alone as a stereo pair (OpenCV, the same "
        "folds; in brackets): " + ", ".join(cells) + " px median",
    ]
