"""The calibration board as the renderer sees it: a ChArUco board or a chessboard printed
on a thin slab, and its picture in one camera.

The board is OpenCV's own picture of it (``CharucoBoard.generateImage``, 20 texels per mm
for 30 mm squares, square edges exactly on texel edges) on the face of a thin slab with a
white margin. Each camera casts one ray per exact (distorted) OpenCV pixel centre
(:meth:`Camera.pixel_rays`) with the project's ray caster; pixels near a change of the
texture are supersampled on an ``n x n`` grid of sub-pixel rays; the image is lit from the
camera (Lambert plus ambient). The true chessboard corners therefore project exactly with
``cv2.projectPoints`` (:func:`true_corners`). Paper seen from behind: the print shows
through it mirrored, with less contrast (:data:`BACK_WHITE`, :data:`BACK_BLACK`).
"""

from __future__ import annotations

import cv2
import numpy as np
import trimesh

from annotator.calibration.board import BoardSpec
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.rendering.raycast import PlacedMesh, RayScene, clip_region, projected_bbox
from annotator.synthesis.shading import interpolate_rays

#: White margin around the chessboard, as a fraction of a square (OpenCV prints half).
MARGIN_SQUARES = 0.5
#: Thickness of the board slab, mm (its sides show at grazing angles).
THICKNESS_MM = 4.0
#: Texels per square of the board texture (square edges fall exactly on texel edges).
TEXELS_PER_SQUARE = 600

WHITE, BLACK, SIDE, BACKGROUND = 0.85, 0.06, 0.35, 0.22
#: The print seen through back-lit paper: paper and ink, as seen from behind.
BACK_WHITE, BACK_BLACK = 0.72, 0.3


class BoardModel:
    """The board's slab mesh and texture, built once per board."""

    def __init__(
        self,
        spec: BoardSpec,
        *,
        inverted: bool = False,
        printed_mirrored: bool = False,
        paper: bool = False,
        through_paper: tuple[float, float] = (BACK_WHITE, BACK_BLACK),
    ) -> None:
        self.spec = spec
        self.paper = paper
        w, h = spec.size_mm
        m = MARGIN_SQUARES * spec.square_mm
        if paper:  # a sheet of no thickness: the print lies at z = 0 from either side
            verts = np.array([[-m, -m, 0], [w + m, -m, 0], [w + m, h + m, 0], [-m, h + m, 0]])
            self.mesh = Mesh(verts.astype(float), np.array([[0, 1, 2], [0, 2, 3]], np.int32))
        else:
            slab = trimesh.creation.box([w + 2 * m, h + 2 * m, THICKNESS_MM])
            slab.apply_translation([w / 2, h / 2, THICKNESS_MM / 2])  # face at z = 0, body behind
            self.mesh = Mesh(np.asarray(slab.vertices), np.asarray(slab.faces, dtype=np.int32))
        texels = (spec.squares_x * TEXELS_PER_SQUARE, spec.squares_y * TEXELS_PER_SQUARE)
        if spec.has_markers:
            image = spec.cv_board.generateImage(texels, marginSize=0, borderBits=1)
        else:  # a plain chessboard, black at the board's origin
            rows, cols = np.indices((spec.squares_y, spec.squares_x))
            squares = np.where((rows + cols) % 2 == 0, 0, 255).astype(np.uint8)
            image = np.kron(squares, np.ones((TEXELS_PER_SQUARE, TEXELS_PER_SQUARE), np.uint8))
        if printed_mirrored:  # the print's column x shows the board's column W - x
            image = np.ascontiguousarray(image[:, ::-1])
        white, black = (BLACK, WHITE) if inverted else (WHITE, BLACK)
        self.texture = np.where(image > 127, white, black).astype(np.float32)
        self.margin = white
        self.texels_per_mm = TEXELS_PER_SQUARE / spec.square_mm
        # Through the paper, paper and ink keep their order, with less contrast between them.
        paper_white, ink = through_paper[::-1] if inverted else through_paper
        self.back_texture = np.where(image > 127, paper_white, ink).astype(np.float32)
        self.back_margin = paper_white

    def albedo(self, points: np.ndarray, *, back: bool = False) -> np.ndarray:
        """Albedo at board-frame points (..., 3) on the slab: the texture on the printed face,
        white in the margin, grey on the sides and back; for paper seen from behind
        (``back``), the print as it shows through."""
        x, y, z = points[..., 0], points[..., 1], points[..., 2]
        out = np.full(x.shape, SIDE, np.float32)
        face = np.abs(z) < 1e-3
        texture = self.back_texture if back else self.texture
        out[face] = self.back_margin if back else self.margin
        th, tw = self.texture.shape
        col = np.floor(x * self.texels_per_mm).astype(np.int64)
        row = np.floor(y * self.texels_per_mm).astype(np.int64)
        inside = face & (col >= 0) & (row >= 0) & (col < tw) & (row < th)
        out[inside] = texture[row[inside], col[inside]]
        return out


def render_board(
    camera: Camera,
    cam_T_board: np.ndarray,
    model: BoardModel,
    *,
    supersample: int = 4,
    ambient: float = 0.3,
) -> np.ndarray:
    """Float32 intensity image in [0, 1] of the board seen by ``camera`` (no blur, no noise)."""
    img = np.full((camera.height, camera.width), BACKGROUND, np.float32)
    box = projected_bbox(camera, model.mesh, cam_T_board, margin=2)
    if box is None:
        return img
    x0, y0, x1, y1 = clip_region(box, camera.width, camera.height)
    scene = RayScene([PlacedMesh(model.mesh, cam_T_board)])
    rays = camera.pixel_rays()
    albedo, light = _sample(scene, model, cam_T_board, rays[y0:y1, x0:x1], ambient)
    value = albedo * light
    if supersample > 1:
        # Supersample wherever the albedo changes within a pixel's 3x3 neighbourhood (texture
        # and slab edges); shading alone varies too slowly across a pixel to matter.
        kernel = np.ones((3, 3), np.uint8)
        edge = cv2.dilate(albedo, kernel) - cv2.erode(albedo, kernel) > 1e-6
        vs, us = np.nonzero(edge)
        offs = (np.arange(supersample) + 0.5) / supersample - 0.5
        acc = np.zeros(len(us), np.float64)
        for dy in offs:
            for dx in offs:
                sub = interpolate_rays(rays, us + x0 + dx, vs + y0 + dy)
                a, lit = _sample(scene, model, cam_T_board, sub, ambient)
                acc += a * lit
        value[vs, us] = acc / supersample**2
    img[y0:y1, x0:x1] = value
    return img


def _sample(
    scene: RayScene, model: BoardModel, cam_T_board: np.ndarray, rays: np.ndarray, ambient: float
) -> tuple[np.ndarray, np.ndarray]:
    """Albedo and lighting factor along rays ``(x, y, 1)``: Lambert with a light at the camera
    centre plus ``ambient``; the background's albedo with full light where rays miss."""
    hits = scene.cast(rays)
    albedo = np.full(hits.instance.shape, BACKGROUND, np.float32)
    light = np.ones(hits.instance.shape, np.float32)
    hit = hits.hit
    if np.any(hit):
        r = rays[hit].astype(np.float64)
        p_cam = r * hits.depth[hit][:, None]  # the ray parameter is the z-depth
        R, t = cam_T_board[:3, :3], cam_T_board[:3, 3]
        # The camera centre on the board's +z side (the side away from the print).
        back = model.paper and float((-t) @ R[:, 2]) > 0
        albedo[hit] = model.albedo((p_cam - t) @ R, back=back)
        if back:  # lit through the paper by the light behind it: evenly
            return albedo, light
        n_cam = model.mesh.face_normals[hits.triangle[hit]] @ R.T
        cos = -(n_cam * r).sum(axis=-1) / np.linalg.norm(r, axis=-1)
        if model.paper:  # a sheet's triangles may be wound either way
            cos = np.abs(cos)
        light[hit] = ambient + (1.0 - ambient) * np.clip(cos, 0.0, 1.0)
    return albedo, light


def true_corners(cam: Camera, rig_T_board: np.ndarray, spec: BoardSpec) -> np.ndarray:
    """(corner_count, 2) exact pixel positions of the chessboard corners in ``cam``."""
    T = cam.cam_T_rig @ rig_T_board
    return cam.project(spec.corners @ T[:3, :3].T + T[:3, 3])
