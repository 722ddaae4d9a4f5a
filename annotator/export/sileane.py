"""The export to the paper's own dataset format (the "Siléane dataset"): the files that
:mod:`annotator.formats.sileane` describes and reads, written from accepted scenes of one of
our datasets (the reference camera, undistorted; each part in its canonical frame).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset import Dataset
from annotator.errors import UserError
from annotator.export.inputs import read_scene_inputs
from annotator.export.removal import remove_scene_markers
from annotator.export.selection import Selected
from annotator.export.undistort import pinhole_rig
from annotator.formats.sileane import NO_SEGMENT, M, canonical_frame, poseutils_to_json
from annotator.geometry.mesh import Mesh
from annotator.io.atomic import write_json, write_text
from annotator.io.images import write_png
from annotator.io.ply import write_ply
from annotator.occlusion import scene_visibility
from annotator.symmetry.space import MATCH_THRESHOLD_FRACTION, PoseSpace


def export_sileane(
    ds: Dataset,
    selected: Sequence[Selected],
    out: Path,
    *,
    cameras: Sequence[str] = (),
    progress: Callable[[], None] | None = None,
    remove_markers: bool = False,
    fill: str = "surface",
    markers_filled: Callable[[int, int], None] | None = None,
) -> dict[str, str]:
    """Write ``selected`` scenes into the empty folder ``out`` (the reference camera only);
    returns the scenes left out because an input was unreadable (scene id -> reason).
    ``remove_markers``: the images with their markers filled in by ``fill``
    (:mod:`annotator.export.fill`), and ``mask_markers/``; ``markers_filled`` is told how
    many markers each scene's image had filled in, and how many of them were found where no
    pose put one."""

    rig = pinhole_rig(ds.rig)
    ref = rig.cameras[0]
    with_depth = ds.rig.depth is not None and ds.rig.depth.camera == ref.name
    failed: dict[str, str] = {}
    inputs = {}
    for item in selected:  # everything is read first: the depth range sets the encoding
        try:
            inputs[item.scene.id] = read_scene_inputs(ds, item.scene, [ref.name], depth=with_depth)
        except UserError as exc:
            failed[item.scene.id] = str(exc)
    clip = _clip_range([i.depth for i in inputs.values()])
    frames = _write_objects(ds, out, ref.K, clip)
    for item in selected:
        if item.scene.id in inputs:
            filled = _write_scene(
                ds, rig, item, inputs[item.scene.id], out, frames, clip, remove_markers, fill
            )
            if markers_filled and remove_markers:
                markers_filled(*filled)
        if progress:
            progress()
    return failed


def _clip_range(depths: Sequence[np.ndarray | None]) -> tuple[float, float]:
    """The depth range (m) the 16-bit depth images encode: every measured depth, 50 mm
    either side (0.1-2 m without depth)."""
    finite = [d[np.isfinite(d)] for d in depths if d is not None and np.isfinite(d).any()]
    if not finite:
        return 0.1, 2.0
    lo = min(float(f.min()) for f in finite)
    hi = max(float(f.max()) for f in finite)
    return (lo - 50.0) / M, (hi + 50.0) / M


def _write_objects(
    ds: Any, out: Path, K: np.ndarray, clip: tuple[float, float]
) -> dict[str, np.ndarray]:
    """Each object's folder: its mesh in the canonical frame (m), its poseutils.json and
    the camera's parameters; returns each object's ``model_T_canonical``."""

    frames = {}
    for name, obj in ds.objects.items():
        space = PoseSpace.from_moments(obj.mesh.moments, obj.symmetry)
        frames[name] = canonical_frame(space)
        folder = out / name
        c, B = space.centroid, space.B
        write_ply(folder / "mesh.ply", Mesh((obj.mesh.vertices - c) @ B / M, obj.mesh.faces))
        write_json(
            folder / "poseutils.json",
            poseutils_to_json(space, threshold_mm=MATCH_THRESHOLD_FRACTION * space.diameter),
        )
        write_text(
            folder / "camera_params.txt",
            f"fu\t{K[0, 0]:.6f}\nfv\t{K[1, 1]:.6f}\ncu\t{K[0, 2]:.6f}\ncv\t{K[1, 2]:.6f}\n"
            f"clip_start\t{clip[0]:.6f}\nclip_end\t{clip[1]:.6f}\n"
            "location\t0.0\t0.0\t0.0\nrotation\t1.0\t0.0\t0.0\t0.0\n",
        )
    return frames


def _write_scene(
    ds: Any,
    rig: Any,
    item: Any,
    inputs: Any,
    out: Path,
    frames: dict[str, np.ndarray],
    clip: tuple[float, float],
    remove_markers: bool = False,
    fill: str = "surface",
) -> tuple[int, int]:
    """One scene in every object's folder: the image, the encoded depth, the segmentation
    of that object's instances and their poses in its canonical frame (``remove_markers``:
    the image with its markers filled in, and their mask). Returns the markers filled in
    and those of them found beyond where the poses put them."""

    ref = rig.cameras[0]
    sid = item.scene.id
    depth = inputs.depth
    image = inputs.images[ref.name]
    marker_mask = None
    filled = (0, 0)
    if remove_markers:
        removed = remove_scene_markers(
            ds,
            rig,
            item.scene,
            item.poses,
            inputs.images,
            cameras=[ref.name],
            depth=depth,
            fill=fill,
        )
        vis, image = removed.visibility, removed.images[ref.name]
        filled = (removed.filled, sum(removed.found_beyond.values()))
        marker_mask = removed.markers[ref.name].mask.astype(np.uint8) * 255
    else:
        meshes = [ds.objects[p.object].mesh for p in item.poses]
        vis = scene_visibility(
            rig, meshes, [p.T for p in item.poses], depth=depth, cameras=[ref.name], masks=True
        )
    for name in ds.objects:
        folder = out / name
        write_png(folder / "rgb" / f"{sid}.PNG", image)
        if marker_mask is not None:
            write_png(folder / "mask_markers" / f"{sid}.PNG", marker_mask)
        if depth is not None:
            z = depth / M
            enc = np.clip((z - clip[0]) / (clip[1] - clip[0]), 0, 1) * 65535
            enc = np.where(np.isfinite(z), np.round(enc), 65535).astype(np.uint16)
            write_png(folder / "depth" / f"{sid}.PNG", enc)
        seg = np.full((ref.height, ref.width), NO_SEGMENT, np.uint8)
        gt: list[dict[str, Any]] = []
        for p, v in zip(item.poses, vis):
            if p.object != name:
                continue
            seg_id = len(gt)
            seg[v.cameras[0].mask_visib] = seg_id
            T = p.T @ frames[name]
            gt.append(
                {
                    "R": T[:3, :3].tolist(),
                    "t": (T[:3, 3] / M).tolist(),
                    "occlusion_rate": float(v.occlusion),
                    "segmentation_id": seg_id,
                    "instance": p.instance,
                }
            )
        write_png(folder / "segmentation" / f"{sid}.PNG", seg)
        write_json(folder / "gt" / f"{sid}.json", gt)
    return filled
