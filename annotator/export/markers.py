"""Where every marker is in an exported image: per marker its projected quad, and the pixels
where the image shows it, on its own instance's surface, in front of every other part.

A marker is a printed square on a site of its instance (the instance's measured sites where
``annotator sites`` ran, else the object's layout). A pixel shows it when the ray through the
pixel meets the instance's own surface (a cast of the instance alone, the export's own) at a
point of the square widened by its white border, within :data:`SLAB_MM` of the square's plane
on a face that looks the square's way, and when no other posed instance is in front. So a
marker on the part's far side, or behind the part's own flange, or behind another part, shows
nowhere; the occluder's pixels are never the marker's.

Seen edge-on, a marker's ink is squeezed between pixel centres, where no ray meets it: when
some of the surface it is printed on faces the camera (its square may be turned a little
away on a curved part), the part's outline inside the square's projection is taken too, and
all of a projection narrower than :data:`EDGE_ON_PX` on the part (its ink lands there even
where the part's own faces lie behind it).

Measured depth does not clip markers (it does clip the exported visible masks): a stereo
sensor's depth is noisy at a marker's high-contrast edges, and would leave ink unerased.

The mask of an image is the union of those pixels, grown by ``margin_px``: blur, the
undistortion's resampling and the anti-aliasing of the square's edges carry the ink a few
pixels beyond it. Everything here works on one image and one set of poses, so a sequence is
the same call once per frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from annotator.dataset.model import Rig
from annotator.geometry import Rect
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.occlusion import InstanceVisibility, scene_visibility
from annotator.rendering.raycast import Hits, cast_alone, projected_bbox

#: A surface point belongs to a marker within this distance (mm) of its plane: a part's curved
#: surface bends away from the flat printed square (the synthetic renderer's own rule).
SLAB_MM = 2.0
#: ... on a face whose normal is within about 45 degrees of the square's (cosine).
FACING = 0.7
#: The white border printed around the black square, in cells of the marker's grid (ArUco
#: needs one cell of quiet zone to find the square).
BORDER_CELLS = 1.0
#: Blur (Gaussian sigma, px) assumed when a scene has no measured one (annotation.json's
#: ``image_quality``): the synthetic default's measured value, on the heavy side of real rigs.
DEFAULT_BLUR_PX = 1.0
#: A marker whose projection (white border included) is narrower than this (px) is seen
#: edge-on: its ink is squeezed into the few pixels of its projection.
EDGE_ON_PX = 2.0


def margin_for_blur(sigma_px: float | None) -> int:
    """Pixels a mask is grown by for images of blur ``sigma_px``: the ink blurs out to three
    sigma (a hundredth of its contrast beyond, which still turns the rounding of a grey level
    now and then), plus one pixel each for the undistortion's bilinear resampling and the
    anti-aliased edge."""
    sigma = DEFAULT_BLUR_PX if sigma_px is None or not math.isfinite(sigma_px) else sigma_px
    return int(math.ceil(3.0 * max(sigma, 0.0))) + 2


@dataclass(frozen=True)
class MarkedInstance:
    """A posed instance with the markers glued on it.

    Attributes:
        object, instance: Its names.
        mesh: The part's mesh (model frame, mm).
        rig_T_model: Its pose in the reference camera (4x4).
        sites: (S, 4, 3) corners of its markers (model frame, ArUco order), one per id.
        marker_ids: (S,) the id glued on each site.
        cells: Cells per side of a marker, its black border included (6 for 4x4 markers).
    """

    object: str
    instance: str
    mesh: Mesh
    rig_T_model: np.ndarray
    sites: np.ndarray
    marker_ids: tuple[int, ...]
    cells: int = 6


@dataclass
class MarkerRegion:
    """One marker in one image.

    Attributes:
        instance: Index of its instance in the scene's list.
        marker_id, site: Its id and site index.
        corners: (4, 2) the printed square's corners in pixels (ArUco order), wherever they
            are: behind another part, on the far side, out of the image (NaN behind the
            camera).
        facing: Whether its face is turned towards the camera.
        px_surface: Pixels where the ray meets the marker (with its white border) on its own
            instance's surface, other instances ignored.
        px_visib: Of those, the pixels no other part hides: where the image shows it.
        bbox_visib: ``(x, y, w, h)`` of :attr:`pixels`, or None.

    >>> import numpy as np
    >>> corners = np.array([[10.0, 10.0], [30.0, 10.0], [30.0, 30.0], [10.0, 30.0]])
    >>> r = MarkerRegion(instance=0, marker_id=18, site=2, corners=corners, facing=True,
    ...                  px_surface=400, px_visib=250)
    >>> r.px_visib / r.px_surface
    0.625
    """

    instance: int
    marker_id: int
    site: int
    corners: np.ndarray
    facing: bool
    px_surface: int
    px_visib: int
    bbox_visib: tuple[int, int, int, int] | None = None
    #: (N, 2) int ``(row, column)`` of the pixels that show some of it: the visible ones,
    #: and the part's outline inside the square's projection (a face seen edge-on).
    pixels: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int32), repr=False)

    @property
    def visib_fract(self) -> float:
        """Visible share of the marker's own surface pixels (0 when it has none)."""
        return self.px_visib / self.px_surface if self.px_surface else 0.0

    def mask(self, width: int, height: int) -> np.ndarray:
        """(height, width) bool mask of :attr:`pixels`."""
        m = np.zeros((height, width), bool)
        m[self.pixels[:, 0], self.pixels[:, 1]] = True
        return m


@dataclass
class ImageMarkers:
    """Every marker of one image, and what removing them needs.

    Attributes:
        camera: The camera's name.
        regions: One per marker of every instance.
        mask: (H, W) bool: the markers' visible pixels grown by ``margin_px``; the pixels to
            fill.
        labels: (H, W) int32: which instance each pixel shows (the nearest posed one), -1
            for everything else (bin, table, unannotated parts).
        margin_px: How much the mask was grown.
        normals: (H, W, 3) float32 unit normals (camera frame) of the surface ``labels``
            names at each pixel of the mask's bounding box, 0 elsewhere: where a part's
            faces meet at a crease.
    """

    camera: str
    regions: list[MarkerRegion]
    mask: np.ndarray
    labels: np.ndarray
    margin_px: int
    normals: np.ndarray | None = None


def image_markers(
    camera: Camera,
    instances: Sequence[MarkedInstance],
    own: Sequence[tuple[Rect, Hits] | None],
    front: np.ndarray,
    *,
    margin_px: int,
) -> ImageMarkers:
    """The markers of one image, from each instance cast alone over its rectangle (``own``,
    as :func:`annotator.rendering.raycast.cast_separately` gives it) and the nearest instance
    at every pixel (``front``, (H, W), ``NO_HIT`` where none)."""
    h, w = camera.height, camera.width
    labels = np.where(front >= 0, front, -1).astype(np.int32)
    union = np.zeros((h, w), bool)
    regions: list[MarkerRegion] = []
    for k, inst in enumerate(instances):
        cam_T = camera.cam_T_rig @ inst.rig_T_model
        cast = own[k] if k < len(own) else None
        for s, marker_id in enumerate(inst.marker_ids[: len(inst.sites)]):
            region = _marker(camera, inst, s, marker_id, cam_T, cast, labels, k)
            region.instance = k
            union[region.pixels[:, 0], region.pixels[:, 1]] = True
            regions.append(region)
    mask = union
    if margin_px > 0 and union.any():
        d = 2 * margin_px + 1
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))
        mask = cv2.dilate(union.astype(np.uint8), disk) > 0
    normals = _normals(camera, instances, own, labels, mask)
    return ImageMarkers(camera.name, regions, mask, labels, margin_px, normals)


def _normals(
    camera: Camera,
    instances: Sequence[MarkedInstance],
    own: Sequence[tuple[Rect, Hits] | None],
    labels: np.ndarray,
    mask: np.ndarray,
) -> np.ndarray:
    """Per pixel near the mask, the camera-frame normal of the face of its instance the
    pixel shows (0 on no instance)."""
    out = np.zeros((*labels.shape, 3), np.float32)
    if not mask.any():
        return out
    grown = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    for k, (inst, cast) in enumerate(zip(instances, own)):
        if cast is None:
            continue
        (x0, y0, x1, y1), hits = cast
        sel = grown[y0:y1, x0:x1] & (labels[y0:y1, x0:x1] == k) & (hits.triangle >= 0)
        if not sel.any():
            continue
        R = (camera.cam_T_rig @ inst.rig_T_model)[:3, :3]
        rows, cols = np.nonzero(sel)
        n = inst.mesh.face_normals[hits.triangle[rows, cols]] @ R.T
        out[rows + y0, cols + x0] = n
    return out


def _marker(
    camera: Camera,
    inst: MarkedInstance,
    s: int,
    marker_id: int,
    cam_T: np.ndarray,
    cast: tuple[Rect, Hits] | None,
    labels: np.ndarray,
    k: int,
) -> MarkerRegion:
    X = np.asarray(inst.sites[s], float)
    R, t = cam_T[:3, :3], cam_T[:3, 3]
    Xc = X @ R.T + t
    corners = camera.project(Xc)
    ex, ey = X[1] - X[0], X[3] - X[0]
    normal = np.cross(ey, ex)
    normal /= np.linalg.norm(normal)
    facing = bool(np.dot(R @ normal, Xc.mean(axis=0)) < 0)
    region = MarkerRegion(-1, int(marker_id), s, corners, facing, 0, 0)
    # Not ``facing`` alone does not hide a marker: on a curved part, the surface under the
    # edge of a marker seen edge-on can still face the camera (and the square is drawn there).
    if cast is None or not np.all(np.isfinite(corners)):
        return region
    b = BORDER_CELLS / inst.cells
    centre = X.mean(axis=0)
    wide = centre + (1.0 + 2.0 * b) * (X - centre)
    uv = camera.project(wide @ R.T + t)
    if not np.all(np.isfinite(uv)):
        return region
    (bx0, by0, bx1, by1), hits = cast
    x0 = max(bx0, int(np.floor(uv[:, 0].min())) - 1)
    y0 = max(by0, int(np.floor(uv[:, 1].min())) - 1)
    x1 = min(bx1, int(np.ceil(uv[:, 0].max())) + 2)
    y1 = min(by1, int(np.ceil(uv[:, 1].max())) + 2)
    if x0 >= x1 or y0 >= y1:
        return region
    sub = (slice(y0 - by0, y1 - by0), slice(x0 - bx0, x1 - bx0))
    tri = hits.triangle[sub]
    hit = hits.instance[sub] >= 0
    rows, cols = np.nonzero(hit)
    if not len(rows):
        return region
    faces = tri[rows, cols]
    uvb = hits.barycentric[sub][rows, cols].astype(np.float64)
    T3 = inst.mesh.triangles[faces]
    p = (1.0 - uvb[:, :1] - uvb[:, 1:]) * T3[:, 0] + uvb[:, :1] * T3[:, 1] + uvb[:, 1:] * T3[:, 2]
    frame = np.stack([ex / ex.dot(ex), ey / ey.dot(ey), normal])  # p - TL -> (s, t, d)
    std = (p - X[0]) @ frame.T
    on = (
        (std[:, 0] >= -b)
        & (std[:, 0] <= 1.0 + b)
        & (std[:, 1] >= -b)
        & (std[:, 1] <= 1.0 + b)
        & (np.abs(std[:, 2]) < SLAB_MM)
        & (inst.mesh.face_normals[faces] @ normal > FACING)
    )
    rows, cols = rows[on] + y0, cols[on] + x0
    region.px_surface = int(len(rows))
    seen = labels[rows, cols] == k
    rows, cols = rows[seen], cols[seen]
    region.px_visib = int(len(rows))
    if facing or _turned_to_camera(inst.mesh, X, frame, normal, b, cam_T):
        # A face seen edge-on shows its marker between pixel centres only (a sliver along
        # the part's outline that no centre ray meets): the outline's pixels inside the
        # square's projection are taken too. On a curved part the square's plane may be
        # turned a little away while the surface under its edge still faces the camera.
        er, ec = _outline(uv, labels, k, (x0, y0, x1, y1), hit, edge_on=_thin(uv))
        rows, cols = np.r_[rows, er], np.r_[cols, ec]
    if len(rows):
        px = np.unique(np.stack([rows, cols], axis=1).astype(np.int32), axis=0)
        region.pixels = px
        r, c = px[:, 0], px[:, 1]
        region.bbox_visib = (
            int(c.min()),
            int(r.min()),
            int(c.max() - c.min()) + 1,
            int(r.max() - r.min()) + 1,
        )
    return region


def _turned_to_camera(
    mesh: Mesh, X: np.ndarray, frame: np.ndarray, normal: np.ndarray, b: float, cam_T: np.ndarray
) -> bool:
    """Whether a face of ``mesh`` that can carry some of the marker ``X`` (model frame; its
    square widened by ``b`` and its slab, on a face looking its way: the renderer's rule)
    is turned towards the camera. ``frame`` maps ``p - X[0]`` to the square's (s, t, d)."""
    std = (mesh.triangles - X[0]) @ frame.T  # (F, 3 vertices, 3)
    lo, hi = std.min(axis=1), std.max(axis=1)
    under = (
        (hi[:, 0] >= -b)
        & (lo[:, 0] <= 1.0 + b)
        & (hi[:, 1] >= -b)
        & (lo[:, 1] <= 1.0 + b)
        & (hi[:, 2] > -SLAB_MM)
        & (lo[:, 2] < SLAB_MM)
        & (mesh.face_normals @ normal > FACING)
    )
    if not under.any():
        return False
    R, t = cam_T[:3, :3], cam_T[:3, 3]
    centres = mesh.triangles[under].mean(axis=1) @ R.T + t
    n = mesh.face_normals[under] @ R.T
    return bool(np.any(np.einsum("ij,ij->i", n, centres) < 0))


def _thin(uv: np.ndarray) -> bool:
    """Whether the quad ``uv`` (pixels) is a sliver narrower than :data:`EDGE_ON_PX`: its
    area over its longest side."""
    x, y = uv[:, 0], uv[:, 1]
    area = 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))
    side = float(np.linalg.norm(uv - np.roll(uv, -1, axis=0), axis=1).max())
    return area < EDGE_ON_PX * side


def _outline(
    uv: np.ndarray,
    labels: np.ndarray,
    k: int,
    rect: Rect,
    hit: np.ndarray,
    *,
    edge_on: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """(rows, columns) of the pixels inside the quad ``uv`` (pixels) on the outline of
    instance ``k`` (``labels``), either side of it, within ``rect``; ``hit``: where the
    instance alone is hit in ``rect``. The side of an outline where another part is in front
    (the instance is hit there, but hidden) is the occluder's, and left out. ``edge_on``:
    every pixel of the quad is taken, outline or not (a marker seen edge-on in front of its
    own part's other faces leaves its ink where both sides of it are the part)."""
    x0, y0, x1, y1 = rect
    shift = 4  # fixed-point bits: the quad is rasterised to a sixteenth of a pixel
    quad = np.round((uv - [x0, y0]) * (1 << shift)).astype(np.int32)
    poly = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillConvexPoly(poly, quad, 1, lineType=cv2.LINE_8, shift=shift)
    own = (labels[y0:y1, x0:x1] == k).astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    edge = poly > 0
    if not edge_on:
        edge &= cv2.dilate(own, kernel) > cv2.erode(own, kernel)
    edge &= (own > 0) | ~hit
    r, c = np.nonzero(edge)
    return r + y0, c + x0


def scene_markers(
    rig: Rig,
    instances: Sequence[MarkedInstance],
    *,
    cameras: Sequence[str],
    depth: np.ndarray | None = None,
    margin_px: int | dict[str, int] = 4,
) -> tuple[list[InstanceVisibility], dict[str, ImageMarkers]]:
    """Masks and occlusion of every instance (what :func:`scene_visibility` gives with
    ``masks=True``) and the markers of every camera's image, from one cast of each instance
    per camera: the casts the visibility needs are the ones the markers need.

    >>> from annotator import load_dataset
    >>> from annotator.dataset import read_poses
    >>> ds = load_dataset("sample_scenes")
    >>> p = read_poses(ds.scene("000000").gt_path)[0]  # brick/01, alone in the scene
    >>> brick = ds.objects[p.object]
    >>> ids = tuple(brick.instance(p.instance).marker_ids)
    >>> part = MarkedInstance(p.object, p.instance, brick.mesh, p.T, brick.site_corners(p.instance), ids)
    >>> seen, images = scene_markers(ds.rig, [part], cameras=["left"])
    >>> seen[0].occlusion, sum(r.px_visib > 0 for r in images["left"].regions)  # markers in view
    (0.0, 13)

    Args:
        rig: The cameras (the export's pinhole ones).
        instances: The posed instances and their markers.
        cameras: The cameras to process, in order.
        depth: The depth camera's measured depth (mm, NaN = none), for the visible masks.
        margin_px: How much each camera's mask is grown (see :func:`margin_for_blur`).
    """
    casts: dict[str, list[tuple[Rect, Hits] | None]] = {}
    for name in cameras:
        cam = rig.camera(name)
        rays = cam.pixel_rays()
        per: list[tuple[Rect, Hits] | None] = []
        for inst in instances:
            T = cam.cam_T_rig @ inst.rig_T_model
            box = projected_bbox(cam, inst.mesh, T)
            if box is None:
                per.append(None)
                continue
            x0, y0, x1, y1 = box
            per.append((box, cast_alone(inst.mesh, T, rays[y0:y1, x0:x1])))
        casts[name] = per
    renders: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    vis = scene_visibility(
        rig,
        [i.mesh for i in instances],
        [i.rig_T_model for i in instances],
        depth=depth,
        cameras=cameras,
        masks=True,
        casts=casts,
        renders=renders,
    )
    out = {}
    for name in cameras:
        margin = margin_px[name] if isinstance(margin_px, dict) else margin_px
        front = renders[name][1]
        out[name] = image_markers(rig.camera(name), instances, casts[name], front, margin_px=margin)
    return vis, out
