"""What the overlays are drawn from, prepared once per scene on the server.

:func:`prepare` reads a scene's images and depth and ray casts the proposed poses in every
camera with the real intrinsics and lens distortion (pixel-exact: the same renderer as the
synthetic images and the occlusion rates). It keeps everything at **full resolution**, so the
mosaic can be scaled to any browser viewport and the zoom can crop at full resolution:

- per camera: the grey image, a map of which instance covers each pixel, a shaded rendering
  of the parts (for blinking), and each instance's silhouette contours, box and centre;
- on the depth camera's grid: the colourised depth, the disagreement between measured and
  rendered depth, and the unexplained-depth mask (``unexplained.png``) if there is one;
- the depth point cloud for the 3D view, downsampled once here.

Drawing is done elsewhere (:mod:`viewer.drawing.mosaic`, :mod:`viewer.drawing.zoom`): a decision only
re-colours what was prepared. A repaired pose is rendered again only where it changes
anything (:func:`repose`: the instance's old and new rectangles, every part cast there), so
that the new overlay is on screen at once; each part's cast there is kept
(:attr:`CameraLayer.alone`), in the new layers and in those the repair started from (the
neighbours stand in both where they were), so the next repair of the instance, or the one
after an undo, casts only the part itself. They are the same arrays in both, weighed once
in the cache, by the prepared scene that made them.
What is drawn from a prepared scene for the pages (panels resized to a page's canvas,
mosaics) is kept with it, within :data:`SCALED_BYTES` and :data:`PICTURE_BYTES`
(:mod:`viewer.drawing.memory`): the sizes are the pages' to choose.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, overload

import cv2
import numpy as np

from annotator.dataset import Dataset, Scene
from annotator.dataset.records import InstanceAnnotation
from annotator.geometry import MM_PER_M
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.io.images import read_image, to_gray8
from annotator.rendering.raycast import PlacedMesh, RayScene, cast_alone, projected_bbox
from viewer.drawing.memory import BytesLRU

DISAGREEMENT_RANGE_MM = 10.0
#: Every CLOUD_STEP-th pixel of every CLOUD_STEP-th row of the depth map goes to the 3D view.
CLOUD_STEP = 8
CONTOUR_TOLERANCE_PX = 0.7
#: Per scene: the panels resized for the pages' canvases (an 8K page's are about 70 MB) ...
SCALED_BYTES = 96 * 2**20
#: ... and the mosaics made of them (an 8K mosaic is 100 MB; a 1400 x 1000 one 4 MB).
PICTURE_BYTES = 160 * 2**20
#: Pixels cast around a neighbour's share of a repair's rectangle, kept for the next repair.
ALONE_MARGIN = 24
DEPTH_PANEL = "depth"
DISAGREEMENT_PANEL = "disagreement"

Box = tuple[int, int, int, int]  # x0, y0, x1, y1 in pixels, end exclusive
#: Where the shaded rendering of the parts (for blinking) is lit from, camera frame.
_LIGHT = np.array([0.3, -0.5, -1.0]) / np.linalg.norm([0.3, -0.5, -1.0])


@dataclass
class CameraLayer:
    """One camera's image and the silhouettes of the posed instances in it, full resolution."""

    name: str
    image: np.ndarray  # grey uint8
    instance: np.ndarray  # int16: index into Prepared.keys of the visible instance, -1 none
    shade: np.ndarray  # uint8 shading of the rendered parts (0 where none)
    contours: list[list[np.ndarray]]  # per instance: (N, 2) int32 pixel outlines
    boxes: list[Box | None]  # per instance: its visible pixels
    centres: list[tuple[int, int] | None]  # per instance: centre of its visible pixels
    #: per instance: the rectangle its projection can cover (``projected_bbox``)
    projected: list[Box | None] = field(default_factory=list)
    #: per instance index, what it alone gives over a rectangle of its projection (kept
    #: from the repairs' casts: the parts that did not move need not be cast again)
    alone: dict[int, Alone] = field(default_factory=dict)


@dataclass(frozen=True)
class Alone:
    """One part cast alone over ``rect``: depth (inf: missed) and triangle hit per pixel."""

    rect: Box
    depth: np.ndarray
    triangle: np.ndarray

    def covers(self, rect: Box) -> bool:
        r = self.rect
        return r[0] <= rect[0] and r[1] <= rect[1] and rect[2] <= r[2] and rect[3] <= r[3]

    def crop(self, rect: Box) -> tuple[np.ndarray, np.ndarray]:
        """Depth and triangles over ``rect``, which :meth:`covers` must be true of."""
        x0, y0 = rect[0] - self.rect[0], rect[1] - self.rect[1]
        sub = (slice(y0, y0 + rect[3] - rect[1]), slice(x0, x0 + rect[2] - rect[0]))
        return self.depth[sub], self.triangle[sub]


@dataclass
class Panel:
    """A picture of the mosaic: a camera image, or a depth picture on the depth camera's grid."""

    name: str
    image: np.ndarray  # full resolution, grey or BGR
    layer: CameraLayer  # the silhouettes drawn on it, and the camera its pixels belong to

    @property
    def camera(self) -> str:
        return self.layer.name

    @property
    def is_depth(self) -> bool:
        return self.name in (DEPTH_PANEL, DISAGREEMENT_PANEL)


@dataclass
class Prepared:
    """Everything drawn for one scene, ready before the reviewer gets there."""

    scene_id: str
    keys: list[str]
    layers: list[CameraLayer]
    depth: np.ndarray | None = None  # BGR colourised depth
    disagreement: np.ndarray | None = None  # BGR
    depth_layer: CameraLayer | None = None
    unexplained: np.ndarray | None = None  # bool mask on the depth grid
    cloud: np.ndarray | None = None  # (N, 3) float32 points in the reference frame, metres
    messages: list[str] = field(default_factory=list)
    measured: np.ndarray | None = None  # float32 measured depth (mm, NaN none), depth grid
    rendered: np.ndarray | None = None  # float32 depth of the posed parts (mm, inf none)
    #: ``(panel name, width, height)`` -> the panel resized, BGR (:meth:`scaled`)
    resized: BytesLRU[tuple[str, int, int], np.ndarray] = field(
        default_factory=lambda: BytesLRU(SCALED_BYTES, _nbytes), repr=False
    )
    #: ``(width, height, look)`` -> a :class:`viewer.drawing.mosaic.Picture` (kept by viewer.mosaic)
    pictures: BytesLRU[tuple, Any] = field(
        default_factory=lambda: BytesLRU(PICTURE_BYTES, _nbytes), repr=False
    )

    @property
    def nbytes(self) -> int:
        """The memory held: the full-resolution arrays and what was drawn from them."""
        arrays = [self.depth, self.disagreement, self.unexplained, self.cloud]
        arrays += [self.measured, self.rendered]
        for layer in self.layers:
            arrays += [layer.image, layer.instance, layer.shade]
            casts = list(layer.alone.values())  # one step: a repair may add to it meanwhile
            arrays += [a for cast in casts for a in (cast.depth, cast.triangle)]
        own = sum(a.nbytes for a in arrays if a is not None)
        return own + self.resized.nbytes + self.pictures.nbytes

    @property
    def panels(self) -> list[Panel]:
        """Cameras first, then depth and disagreement (if the rig has depth)."""
        out = [Panel(layer.name, layer.image, layer) for layer in self.layers]
        if self.depth_layer is not None and self.depth is not None:
            out.append(Panel(DEPTH_PANEL, self.depth, self.depth_layer))
            if self.disagreement is not None:
                out.append(Panel(DISAGREEMENT_PANEL, self.disagreement, self.depth_layer))
        return out

    def scaled(self, panel: Panel, width: int, height: int) -> np.ndarray:
        """``panel``'s picture resized to ``width`` x ``height`` as BGR (memoised: several
        pages and several re-colourings use the same sizes)."""
        key = (panel.name, width, height)
        out = self.resized.get(key)
        if out is None:
            img = panel.image
            if (img.shape[1], img.shape[0]) != (width, height):
                img = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
            out = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img
            self.resized.put(key, out)
        return out

    def instance_at(self, camera: str, x: float, y: float, radius: float = 0.0) -> str | None:
        """The instance seen at full-resolution pixel (x, y) of ``camera``; within ``radius``
        pixels, the one covering most of the disc, if none is exactly there."""
        layer = next((la for la in self.layers if la.name == camera), None)
        if layer is None:
            return None
        h, w = layer.instance.shape
        xi, yi = int(round(x)), int(round(y))
        if 0 <= xi < w and 0 <= yi < h and layer.instance[yi, xi] >= 0:
            return self.keys[int(layer.instance[yi, xi])]
        r = int(np.ceil(radius))
        if r <= 0:
            return None
        x0, y0, x1, y1 = max(0, xi - r), max(0, yi - r), min(w, xi + r + 1), min(h, yi + r + 1)
        if x0 >= x1 or y0 >= y1:
            return None
        sub = layer.instance[y0:y1, x0:x1]
        yy, xx = np.mgrid[y0:y1, x0:x1]
        near = sub[((xx - x) ** 2 + (yy - y) ** 2 <= radius**2) & (sub >= 0)]
        if near.size == 0:
            return None
        return self.keys[int(np.bincount(near).argmax())]


def _nbytes(value: Any) -> int:
    return int(value.nbytes)


def _read_unexplained(scene: Scene, shape: tuple[int, int], prep: Prepared) -> np.ndarray | None:
    path = scene.unexplained_path
    if not path.exists():
        return None
    try:
        mask = read_image(path)
    except Exception as exc:  # shown in the page; the scene stays reviewable
        prep.messages.append(str(exc))
        return None
    if mask.ndim == 3:
        mask = mask.max(axis=2)
    if mask.shape != shape:
        prep.messages.append(
            f"{path}: {mask.shape[1]}x{mask.shape[0]} is not the depth camera's size "
            f"{shape[1]}x{shape[0]}; not drawn"
        )
        return None
    return mask > 0


def prepare(ds: Dataset, scene: Scene, poses: list[InstanceAnnotation]) -> Prepared:
    """Read the images and render the silhouettes of ``poses`` in every camera."""
    prep = Prepared(scene.id, [p.key for p in poses], [])
    meshes = [ds.objects[p.object].mesh if p.object in ds.objects else None for p in poses]
    known = [(k, m) for k, m in enumerate(meshes) if m is not None]
    index = [k for k, _ in known]  # placed -> pose index
    rendered_depth = None
    for cam in ds.rig.cameras:
        try:
            gray = to_gray8(scene.read_image(cam))
        except Exception as exc:  # a vanished or corrupt image must not stop the viewer
            prep.messages.append(str(exc))
            gray = np.zeros((cam.height, cam.width), np.uint8)
        placed = [PlacedMesh(m, cam.cam_T_rig @ poses[k].T) for k, m in known]
        boxes = [projected_bbox(cam, pm.mesh, pm.cam_T_model) for pm in placed]
        mask = np.zeros((cam.height, cam.width), bool)
        for b in boxes:
            if b is not None:
                mask[b[1] : b[3], b[0] : b[2]] = True
        instance = np.full(mask.shape, -1, np.int16)
        depth = np.full(mask.shape, np.inf, np.float32)
        shade = np.zeros(mask.shape, np.uint8)
        if placed:
            hits = RayScene(placed).cast(cam.pixel_rays()[mask])
            hit_pose = np.where(hits.hit, np.asarray(index + [-1])[hits.instance], -1)
            instance[mask] = hit_pose
            depth[mask] = hits.depth
            lambert = np.abs(hits.normals(placed) @ _LIGHT)
            shade[mask] = np.where(hits.hit, 60 + 195 * lambert, 0).astype(np.uint8)
        contours: list[list[np.ndarray]] = [[] for _ in poses]
        vis_boxes: list[Box | None] = [None] * len(poses)
        centres: list[tuple[int, int] | None] = [None] * len(poses)
        for j, b in enumerate(boxes):
            if b is not None:
                k = index[j]
                contours[k], vis_boxes[k], centres[k] = _outline(instance, k, b)
        projected: list[Box | None] = [None] * len(poses)
        for j, b in enumerate(boxes):
            projected[index[j]] = b
        layer = CameraLayer(
            cam.name, gray, instance, shade, contours, vis_boxes, centres, projected
        )
        prep.layers.append(layer)
        if ds.rig.depth is not None and cam.name == ds.rig.depth.camera:
            prep.depth_layer = layer
            rendered_depth = depth
    if prep.depth_layer is not None and rendered_depth is not None:
        _add_depth(ds, scene, prep, rendered_depth)
    return prep


def _add_depth(ds: Dataset, scene: Scene, prep: Prepared, rendered: np.ndarray) -> None:
    """The depth pictures and the point cloud of ``prep``, from the measured depth and the
    depth of the posed parts ``rendered`` on its grid (none if the depth cannot be read)."""
    try:
        measured = scene.read_depth(ds.rig)
    except Exception as exc:  # shown in the page; the scene stays reviewable
        prep.messages.append(str(exc))
        return
    if measured is None:
        return
    prep.depth = colourise_depth(measured)
    prep.measured = measured.astype(np.float32)
    prep.rendered = rendered
    prep.disagreement = _disagreement(measured, rendered)
    prep.unexplained = _read_unexplained(scene, measured.shape, prep)
    prep.cloud = depth_cloud(ds.rig.depth_camera, measured)


def _outline(
    instance: np.ndarray, k: int, box: Box
) -> tuple[list[np.ndarray], Box | None, tuple[int, int] | None]:
    """Instance ``k``'s silhouette contours, visible box and centre, from the instance map
    within ``box`` (which holds all its pixels)."""
    x0, y0, x1, y1 = box
    sub = (instance[y0:y1, x0:x1] == k).astype(np.uint8)
    # The box from OpenCV and the centre from the row and column counts: the same figures
    # as from numpy's nonzero (integer sums, exact), which took most of an outline's time
    # on large parts.
    bx, by, bw, bh = cv2.boundingRect(sub)
    if bw == 0:
        return [], None, None
    cols, rows = sub.sum(axis=0, dtype=np.int64), sub.sum(axis=1, dtype=np.int64)
    n = int(cols.sum())
    cx, cy = int(cols @ np.arange(len(cols))) / n, int(rows @ np.arange(len(rows))) / n
    cs, _ = cv2.findContours(sub, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    # Within 0.7 px of the pixel outline: below a pixel of the mosaic, which shows the
    # images at half size or less, and many times fewer points to draw.
    cs = [cv2.approxPolyDP(c, CONTOUR_TOLERANCE_PX, True) for c in cs if len(c) > 2]
    contours = [(c.reshape(-1, 2) + [x0, y0]).astype(np.int32) for c in cs if len(c) > 2]
    vis = (x0 + bx, y0 + by, x0 + bx + bw, y0 + by + bh)
    return contours, vis, (int(cx + x0), int(cy + y0))


def _disagreement(measured: np.ndarray, rendered: np.ndarray) -> np.ndarray:
    """Measured against rendered depth (mm) as a BGR picture: bright where they disagree."""
    show = np.isfinite(rendered) & np.isfinite(measured)
    with np.errstate(invalid="ignore"):  # inf - inf where neither has depth: not shown
        heat = np.abs(measured - rendered) * np.float32(255.0 / DISAGREEMENT_RANGE_MM)
    heat = np.clip(heat, 0, 255, out=heat, where=show)
    heat8 = np.where(show, heat, 0).astype(np.uint8)
    with np.errstate(invalid="ignore"):  # NaN: no measurement, dark
        measured_here = (measured > 0).astype(np.uint8) * np.uint8(60)
    out = cv2.cvtColor(measured_here, cv2.COLOR_GRAY2BGR)
    np.copyto(out, cv2.applyColorMap(heat8, cv2.COLORMAP_INFERNO), where=show[..., None])
    return out


@overload
def _union(a: Box | None, b: Box) -> Box: ...
@overload
def _union(a: Box | None, b: Box | None) -> Box | None: ...
def _union(a: Box | None, b: Box | None) -> Box | None:
    if a is None or b is None:
        return a or b
    return (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))


def _meets(a: Box | None, b: Box) -> bool:
    return a is not None and a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def repose(
    ds: Dataset,
    prep: Prepared,
    poses: list[InstanceAnnotation],
    key: str,
    *,
    parallel: bool = True,
) -> Prepared | None:
    """``prep`` with instance ``key`` moved to its pose in ``poses`` (the scene's poses, the
    others as in ``prep``; ``key`` may be new, last): only the rectangles its old and new
    silhouettes cover are cast again, every part there. None when ``poses`` is not ``prep``'s
    with that one change (an instance removed): prepare the scene anew then. The neighbours
    cast are also kept in ``prep``'s layers (see the module docstring). ``parallel``:
    the cameras at once, in :data:`_POOL` (work done ahead of a key runs in its own thread
    instead: it must not hold up the pool a key's repose needs)."""
    keys = [p.key for p in poses]
    if key not in keys or keys[: len(prep.keys)] != prep.keys or len(keys) > len(prep.keys) + 1:
        return None
    k = keys.index(key)
    out = Prepared(
        prep.scene_id,
        keys,
        [],
        depth=prep.depth,
        unexplained=prep.unexplained,
        cloud=prep.cloud,
        messages=list(prep.messages),
        measured=prep.measured,
        rendered=None if prep.rendered is None else prep.rendered.copy(),
    )
    for name in prep.resized.keys():  # the images and the depth do not change
        if name[0] != DISAGREEMENT_PANEL:
            scaled = prep.resized.get(name)
            if scaled is not None:
                out.resized.put(name, scaled)
    meshes = [ds.objects[p.object].mesh if p.object in ds.objects else None for p in poses]
    if parallel:
        jobs = [_POOL.submit(_repose_layer, ds, la, poses, meshes, k) for la in prep.layers]
        results = [job.result() for job in jobs]
    else:
        results = [_repose_layer(ds, la, poses, meshes, k) for la in prep.layers]
    changed: Box | None = None
    for layer, (new, region, depth) in zip(prep.layers, results):
        out.layers.append(new)
        if prep.depth_layer is layer:
            out.depth_layer = new
            if region is not None and out.rendered is not None:
                x0, y0, x1, y1 = region
                out.rendered[y0:y1, x0:x1] = depth
                changed = region
    out.disagreement = prep.disagreement
    if (
        changed is not None
        and prep.disagreement is not None
        and prep.measured is not None
        and out.rendered is not None
    ):
        x0, y0, x1, y1 = changed
        out.disagreement = prep.disagreement.copy()
        out.disagreement[y0:y1, x0:x1] = _disagreement(
            prep.measured[y0:y1, x0:x1], out.rendered[y0:y1, x0:x1]
        )
    return out


#: The cameras of a repaired pose are cast at once (open3d's casts let go of the GIL).
_POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix="repose")


#: A part placed in a camera: its mesh and ``cam_T_model`` (None: an unknown object).
_Placed = tuple[Mesh, np.ndarray] | None


def _repose_layer(
    ds: Dataset,
    layer: CameraLayer,
    poses: list[InstanceAnnotation],
    meshes: list[Mesh | None],
    k: int,
) -> tuple[CameraLayer, Box | None, np.ndarray | None]:
    """One camera's layer with pose ``k`` changed (see :func:`repose`), the rectangle cast
    again and the depth rendered there."""
    n = len(poses)
    cam = ds.rig.camera(layer.name)
    grow = n - len(layer.contours)
    contours, boxes = list(layer.contours) + [[]] * grow, list(layer.boxes) + [None] * grow
    centres = list(layer.centres) + [None] * grow
    placed: list[_Placed] = [
        None if m is None else (m, cam.cam_T_rig @ p.T) for m, p in zip(meshes, poses)
    ]
    # The other parts have not moved: their rectangles are those of the layer's last cast.
    known = layer.projected + [None] * (n - len(layer.projected))
    bboxes = [
        None
        if q is None
        else (projected_bbox(cam, q[0], q[1]) if j == k or not layer.projected else known[j])
        for j, q in enumerate(placed)
    ]
    region = _union(boxes[k], bboxes[k])
    instance, shade = layer.instance, layer.shade
    # The unmoved parts' casts carry over (the dict is the new layer's). dict() copies in
    # one step: another repair from the same layer may add to it meanwhile.
    alone = dict(layer.alone)
    alone.pop(k, None)
    depth = None
    if region is not None:
        instance, shade = instance.copy(), shade.copy()
        x0, y0, x1, y1 = region
        depth, index, lambert = _cast_region(cam, placed, bboxes, alone, k, region)
        # The neighbours cast now stand where they stood in the layer this one came from:
        # kept there too, for the next repair that starts from it (after an undo, the
        # layer shown again is that one, and its neighbours need not be cast again).
        for j, cast in alone.items():
            if j != k and layer.alone.get(j) is not cast:
                layer.alone[j] = cast
        before = instance[y0:y1, x0:x1]
        moved = before != index
        # Whose silhouettes changed (the part, and those it uncovers or covers): re-outlined.
        touched = set(np.unique(before[moved]).tolist()) | set(np.unique(index[moved]).tolist())
        instance[y0:y1, x0:x1] = index
        shade[y0:y1, x0:x1] = np.where(index >= 0, 60 + 195 * lambert, 0).astype(np.uint8)
        for j in (touched | {k}) - {-1}:
            contours[j], boxes[j], centres[j] = _outline(instance, j, _union(boxes[j], region))
    new = CameraLayer(
        layer.name, layer.image, instance, shade, contours, boxes, centres, bboxes, alone
    )
    return new, region, depth


def _cast_region(
    cam: Camera,
    placed: list[_Placed],
    bboxes: list[Box | None],
    alone: dict[int, Alone],
    k: int,
    region: Box,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth, instance index and Lambert shading over ``region``, every part that can be
    seen there cast alone and the nearest kept: part ``k`` (the one moved) always, the
    others only where ``alone`` (updated here) has no cast of them yet."""
    x0, y0, x1, y1 = region
    shape = (y1 - y0, x1 - x0)
    depth = np.full(shape, np.inf, np.float32)
    index = np.full(shape, -1, np.int16)
    lambert = np.zeros(shape, np.float32)
    for j, (q, b) in enumerate(zip(placed, bboxes)):
        if q is None or b is None or not _meets(b, region):
            continue
        rect = (max(b[0], x0), max(b[1], y0), min(b[2], x1), min(b[3], y1))
        sub = (slice(rect[1] - y0, rect[3] - y0), slice(rect[0] - x0, rect[2] - x0))
        cast = alone.get(j) if j != k else None
        if cast is None or not cast.covers(rect):
            cast = _cast_alone(cam, q, rect, b if j != k else None, cast)
            alone[j] = cast
        hit_depth, triangle = cast.crop(rect)
        closer = hit_depth < depth[sub]
        np.copyto(depth[sub], hit_depth, where=closer)
        np.copyto(index[sub], np.int16(j), where=closer)
        # Shaded where this part is the nearest only: the rest of its box is not drawn.
        light = q[0].face_normals[triangle[closer]] @ (q[1][:3, :3].T @ _LIGHT)
        lambert[sub][closer] = np.abs(light)
    return depth, index, lambert


def _cast_alone(
    camera: Camera,
    placed: tuple[Mesh, np.ndarray],
    rect: Box,
    bound: Box | None,
    earlier: Alone | None,
) -> Alone:
    """A part (mesh, cam_T_model) cast alone over ``rect``; a neighbour of the part being
    repaired (``bound``: its own rectangle) over more, kept for the next repairs: what was
    cast of it ``earlier`` and :data:`ALONE_MARGIN` around (the next nudge's rectangle is a
    few pixels off this one's)."""
    if bound is not None:
        if earlier is not None:
            rect = _union(rect, earlier.rect)
        m = ALONE_MARGIN
        rect = (
            max(rect[0] - m, bound[0]),
            max(rect[1] - m, bound[1]),
            min(rect[2] + m, bound[2]),
            min(rect[3] + m, bound[3]),
        )
    x0, y0, x1, y1 = rect
    hits = cast_alone(placed[0], placed[1], camera.pixel_rays()[y0:y1, x0:x1])
    return Alone(rect, hits.depth, hits.triangle)


def depth_cloud(camera, depth: np.ndarray, step: int = CLOUD_STEP) -> np.ndarray:
    """Every ``step``-th measured point of a depth map, in the reference frame, metres."""
    rays = camera.pixel_rays(step)
    d = depth[::step, ::step]
    ok = np.isfinite(d) & (d > 0)
    pts = rays[ok] * d[ok][:, None]
    pts = pts @ camera.rig_T_cam[:3, :3].T + camera.rig_T_cam[:3, 3]
    return (pts / MM_PER_M).astype(np.float32)


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
