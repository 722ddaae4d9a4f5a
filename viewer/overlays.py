"""Server-side overlays: silhouette contours of every proposed pose on each camera's image,
on the colourised depth map, and the disagreement between measured and rendered depth.

The silhouettes are ray cast with the real intrinsics and lens distortion (pixel-exact, the
same renderer as the synthetic images and the occlusion rates). :func:`prepare` does the heavy
part once per scene (images, instance maps, contours); :func:`compose` only draws, so that a
decision re-colours the overlays at once.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from annotator.dataset import Dataset, InstancePose, Scene
from annotator.io.images import to_gray8
from annotator.rendering.raycast import PlacedMesh, RayScene, projected_bbox

#: BGR colours by state.
COLOURS = {"pending": (0, 220, 255), "accepted": (60, 220, 60), "rejected": (40, 40, 255)}
FLAG_COLOUR = (255, 0, 255)
SELECTED_COLOUR = (255, 255, 255)
DISAGREEMENT_RANGE_MM = 10.0


@dataclass
class CameraLayer:
    name: str
    image: np.ndarray  # display-size grey
    scale: float  # display / full resolution
    contours: list[list[np.ndarray]]  # per instance, in display pixels
    centres: list[tuple[int, int] | None]


@dataclass
class Prepared:
    scene_id: str
    keys: list[str]
    layers: list[CameraLayer]
    depth: np.ndarray | None = None  # display-size BGR colourised depth
    disagreement: np.ndarray | None = None  # display-size BGR
    depth_layer: CameraLayer | None = None
    messages: list[str] = field(default_factory=list)


def _display(img: np.ndarray, max_width: int) -> tuple[np.ndarray, float]:
    s = min(1.0, max_width / img.shape[1])
    if s < 1.0:
        img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    return img, s


def prepare(
    ds: Dataset, scene: Scene, poses: list[InstancePose], *, max_width: int = 960
) -> Prepared:
    """Read the images and render the silhouettes of ``poses`` in every camera."""
    prep = Prepared(scene.id, [p.key for p in poses], [])
    meshes = [ds.objects[p.object].mesh if p.object in ds.objects else None for p in poses]
    rendered_depth = None
    for cam in ds.rig.cameras:
        try:
            gray = to_gray8(scene.read_image(cam))
        except Exception as exc:  # a vanished or corrupt image must not stop the viewer
            prep.messages.append(str(exc))
            gray = np.zeros((cam.height, cam.width), np.uint8)
        placed = [
            PlacedMesh(m, cam.cam_T_rig @ p.T) for m, p in zip(meshes, poses) if m is not None
        ]
        boxes = [projected_bbox(cam, pm.mesh, pm.cam_T_model) for pm in placed]
        mask = np.zeros((cam.height, cam.width), bool)
        for b in boxes:
            if b is not None:
                mask[b[1] : b[3], b[0] : b[2]] = True
        instance = np.full(mask.shape, -1, np.int32)
        depth = np.full(mask.shape, np.inf, np.float32)
        if placed:
            hits = RayScene(placed).cast(cam.pixel_rays()[mask])
            instance[mask] = hits.instance
            depth[mask] = hits.depth
        img, s = _display(gray, max_width)
        contours, centres = [], []
        for k in range(len(placed)):
            b = boxes[k]
            if b is None:
                contours.append([])
                centres.append(None)
                continue
            sub = (instance[b[1] : b[3], b[0] : b[2]] == k).astype(np.uint8)
            cs, _ = cv2.findContours(sub, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            cs = [
                ((c.reshape(-1, 2) + [b[0], b[1]]) * s).astype(np.int32) for c in cs if len(c) > 2
            ]
            contours.append(cs)
            ys, xs = np.nonzero(sub)
            centres.append(
                (int((xs.mean() + b[0]) * s), int((ys.mean() + b[1]) * s)) if len(xs) else None
            )
        layer = CameraLayer(cam.name, img, s, contours, centres)
        prep.layers.append(layer)
        if ds.rig.depth is not None and cam.name == ds.rig.depth.camera:
            prep.depth_layer = layer
            rendered_depth = depth
    if prep.depth_layer is not None:
        try:
            measured = scene.read_depth(ds.rig)
        except Exception as exc:
            prep.messages.append(str(exc))
            measured = None
        if measured is not None:
            prep.depth, _ = _display(colourise_depth(measured), max_width)
            diff = np.abs(measured - rendered_depth)
            show = np.isfinite(rendered_depth) & np.isfinite(measured)
            heat = np.nan_to_num(
                np.clip(diff / DISAGREEMENT_RANGE_MM * 255, 0, 255), nan=255.0
            ).astype(np.uint8)
            out = cv2.cvtColor(
                (np.nan_to_num(measured, nan=0) > 0).astype(np.uint8) * 60, cv2.COLOR_GRAY2BGR
            )
            out[show] = cv2.applyColorMap(heat, cv2.COLORMAP_INFERNO)[show]
            prep.disagreement, _ = _display(out, max_width)
    return prep


def colourise_depth(depth: np.ndarray) -> np.ndarray:
    """Depth (mm, NaN = none) as a BGR image, near = warm, holes black."""
    ok = np.isfinite(depth)
    out = np.zeros((*depth.shape, 3), np.uint8)
    if ok.any():
        lo, hi = np.percentile(depth[ok], [2, 98])
        norm = np.nan_to_num(np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1))
        col = cv2.applyColorMap((255 - norm * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
        out[ok] = col[ok]
    return out


def draw(
    base: np.ndarray,
    layer: CameraLayer,
    keys: list[str],
    states: dict[str, str],
    flagged: set[str],
    selected: str | None,
) -> np.ndarray:
    """Contours coloured by state on ``base`` (grey or BGR, display size); returns RGB."""
    img = cv2.cvtColor(base, cv2.COLOR_GRAY2BGR) if base.ndim == 2 else base.copy()
    for k, key in enumerate(keys):
        if k >= len(layer.contours) or not layer.contours[k]:
            continue
        colour = COLOURS[states.get(key, "pending")]
        if key in flagged:
            cv2.polylines(img, layer.contours[k], True, FLAG_COLOUR, 4, cv2.LINE_AA)
        cv2.polylines(
            img,
            layer.contours[k],
            True,
            SELECTED_COLOUR if key == selected else colour,
            2,
            cv2.LINE_AA,
        )
        if layer.centres[k] is not None:
            label = key.split("/")[0][:3] + key.split("/")[-1] + ("!" if key in flagged else "")
            x, y = layer.centres[k]
            cv2.putText(
                img, label, (x - 12, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA
            )
            cv2.putText(
                img, label, (x - 12, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA
            )
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def compose(
    prep: Prepared, states: dict[str, str], flagged: set[str], selected: str | None
) -> dict[str, np.ndarray]:
    """All panels as RGB images: one per camera, ``depth`` and ``disagreement`` if available."""
    out = {
        layer.name: draw(layer.image, layer, prep.keys, states, flagged, selected)
        for layer in prep.layers
    }
    if prep.depth is not None and prep.depth_layer is not None:
        out["depth"] = draw(prep.depth, prep.depth_layer, prep.keys, states, flagged, selected)
        out["disagreement"] = draw(
            prep.disagreement, prep.depth_layer, prep.keys, states, flagged, selected
        )
    return out


def mosaic(panels: dict[str, np.ndarray]) -> np.ndarray:
    """Panels side by side, two per row (cameras first, then depth and disagreement), each
    titled; RGB."""
    tiles = []
    for name, img in panels.items():
        t = img.copy()
        cv2.rectangle(t, (0, 0), (8 + 11 * len(name), 24), (0, 0, 0), -1)
        cv2.putText(
            t, name, (4, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA
        )
        tiles.append(t)
    h = max(t.shape[0] for t in tiles)
    w = max(t.shape[1] for t in tiles)
    tiles = [
        cv2.copyMakeBorder(t, 0, h - t.shape[0], 0, w - t.shape[1], cv2.BORDER_CONSTANT)
        for t in tiles
    ]
    if len(tiles) % 2:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.hstack(tiles[k : k + 2]) for k in range(0, len(tiles), 2)]
    return np.vstack(rows)
