"""Refining one instance's pose against the measured depth, jointly with its markers.

The measured points are those of the depth map inside the instance's rendered silhouette
(pixel-exact ray casting, :mod:`annotator.rendering.raycast`) grown by a margin (or shrunk,
away from its edges), less the pixels that another posed part explains (rendered there in
front of it, or at the measured depth): a neighbour's surface must not pull the part onto it.
Each measured point is matched to its nearest model point (a k-d tree of the model's samples,
within a gate that shrinks over the iterations, model normals facing the camera only) and the
pose minimises Huber's loss of the point-to-plane distances in mm
together with the reprojection errors of the instance's markers in px (:mod:`annotator.pnp`),
each over its noise (:data:`annotator.noise.NOISE`), on the project's one damped least-squares
iteration (:func:`annotator.geometry.least_squares.levenberg_marquardt`). Where the depth
alone is ambiguous (a cylinder about its axis, a face
seen flat) the marker term keeps the pose; where there are no markers, the depth alone
decides.

With ``RefineSettings.depth_offset_sigma_mm``, the measured points also share an offset along
their rays, solved for with that prior: a depth map biased by a fraction of a millimetre then
does not pull the pose along the view.

The result is kept only when it converged: the steps became small, enough measured points
lie on the refined surface, and the markers (if any) still reproject.
:func:`pose_covariance` gives the refined pose's covariance from both terms, with what errors
shared by many points or corners (the depth's offset, the markers' sites) do to it.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree

from annotator.dataset.review import RepairOp, RepairStep
from annotator.geometry import Rect
from annotator.geometry.camera import Camera
from annotator.geometry.least_squares import Damping, Stop, levenberg_marquardt
from annotator.geometry.lie import cross, norms, perturb
from annotator.geometry.mesh import Mesh, surface_samples
from annotator.geometry.robust import huber_cost, huber_weights
from annotator.noise import NOISE, NoiseModel
from annotator.pnp.multiview import (
    Observation,
    corner_residuals,
    reprojection_errors,
    residuals_jacobian,
)
from annotator.pnp.sites import site_jacobian
from annotator.refinement.nearest import TrackedNearest
from annotator.rendering.raycast import (
    Hits,
    PlacedMesh,
    cast_alone,
    clip_region,
    hit_bbox,
    reachable,
)

#: The model's surface samples are about this far apart (mm): well below the depth's own
#: spacing at the working distance.
MODEL_SPACING_MM = 0.7


@dataclass(frozen=True)
class RefineSettings:
    """Thresholds of the refinement (px, mm)."""

    #: The silhouette grows by this many pixels: a pose a few mm off has its part beside it
    #: (negative: the part's visible region shrinks by as many, away from its edges).
    margin_px: int = 15
    start_gate_mm: float = 15.0
    end_gate_mm: float = 3.0
    gate_iterations: int = 12  # the gate shrinks over these, then stays
    iterations: int = 40
    max_points: int = 4000
    depth_sigma_mm: float = NOISE.depth_mm
    marker_sigma_px: float = NOISE.refined_corner_px
    #: A pixel another part's surface is rendered within this of the measured depth is its.
    explained_mm: float = 4.0
    min_points: int = 30
    #: Converged: at least this share of the measured points on the refined surface ...
    min_inlier_fraction: float = 0.5
    #: ... and the markers (if any) within this RMS.
    max_marker_px: float = 2.0
    #: Converged when a step moves the residuals by less than this RMS (mm or px).
    converged_moves: float = 0.02
    #: 0: the depth is taken as measured. Else the measured points share an offset along
    #: their rays, solved for with a prior of this 1-sigma (mm): a biased depth map (a face
    #: seen flat gets one disparity) then does not pull the pose along the view.
    depth_offset_sigma_mm: float = 0.0


@dataclass(frozen=True)
class Residuals:
    """How well a pose explains the data: point-to-plane RMS (mm) of the measured points
    within the end gate and their share, marker corner RMS (px)."""

    depth_rms_mm: float | None
    depth_inliers: float | None
    depth_points: int
    marker_rms_px: float | None
    markers: int

    def text(self) -> str:
        parts = []
        if self.depth_rms_mm is not None:
            parts.append(
                f"depth {self.depth_rms_mm:.2f} mm RMS on {100 * (self.depth_inliers or 0):.0f}%"
                f" of {self.depth_points} points"
            )
        if self.marker_rms_px is not None:
            parts.append(f"markers {self.marker_rms_px:.2f} px RMS ({self.markers})")
        return ", ".join(parts) or "no depth and no markers"

    def to_json(self) -> dict[str, float | int | None]:
        return {
            "depth_rms_mm": None if self.depth_rms_mm is None else round(self.depth_rms_mm, 4),
            "depth_inliers": None if self.depth_inliers is None else round(self.depth_inliers, 4),
            "markers_px": None if self.marker_rms_px is None else round(self.marker_rms_px, 4),
        }


@dataclass(frozen=True)
class Refinement:
    """The refined ``rig_T_model`` (the start when it did not converge), and why."""

    T: np.ndarray
    start: np.ndarray
    converged: bool
    iterations: int
    before: Residuals
    after: Residuals
    why: str  # "" when converged, else the reason in a few words
    seconds: float
    depth_offset_mm: float = 0.0  # the measured points' offset along their rays, solved for

    def step(self) -> RepairStep:
        """The step review.json records for it."""
        details = {
            "before": self.before.to_json(),
            "after": self.after.to_json(),
            "iterations": self.iterations,
        }
        return RepairStep(RepairOp.REFINE, details)


_CLOUDS: dict[bytes, tuple[cKDTree, np.ndarray, np.ndarray]] = {}


def _model_cloud(mesh: Mesh) -> tuple[cKDTree, np.ndarray, np.ndarray]:
    """Evenly spread surface samples of a mesh (about two per mm^2), their search tree and
    their face normals, model frame, the same every time (seeded); kept by the mesh's
    content."""
    hit = _CLOUDS.get(mesh.digest)
    if hit is None:
        if len(_CLOUDS) >= 16:
            _CLOUDS.clear()
        pts, normals = surface_samples(mesh, MODEL_SPACING_MM, density=1.0)
        # Split at the middle of each cell, not the median of its points: the same nearest
        # samples (the search is exact), found sooner among samples spread this evenly.
        # Leaves of 32: a point several mm off the surface (a pose still far off, a
        # neighbour's surface) has many samples at about its distance, and visits fewer
        # cells so; near the surface it makes no difference.
        tree = cKDTree(pts, leafsize=32, balanced_tree=False)
        hit = _CLOUDS[mesh.digest] = (tree, pts, normals)
    return hit


#: Casts made already, as :func:`annotator.occlusion.scene_visibility`'s ``memo`` keeps them:
#: by (camera name, step, mesh digest, ``rig_T_model`` bytes), the placed mesh's rectangle on
#: the camera's grid of every step-th pixel and its hits there (None: out of view).
KnownCasts = Mapping[tuple[str, int, bytes, bytes], tuple[Rect | None, Hits | None]]


@dataclass(frozen=True)
class Known:
    """Casts made already at every ``step``-th pixel (:data:`KnownCasts`): their rays are
    every pixel's whose row and column are multiples of ``step`` (:meth:`Camera.pixel_rays`),
    so a cast of every pixel takes those hits from them and casts the rest."""

    casts: KnownCasts
    step: int


def measured_points(
    camera: Camera,
    depth: np.ndarray,
    mesh: Mesh,
    rig_T_model: np.ndarray,
    others: Sequence[PlacedMesh],
    settings: RefineSettings = RefineSettings(),
    known: Known | None = None,
) -> np.ndarray:
    """The measured points the instance is refined against and their surface normals,
    (N, 6) in the reference frame (mm): see the module docstring. ``others`` are the other
    posed parts, placed in the reference frame; ``known``: casts of them (and of the part)
    made already at these poses, whose rays are not cast again."""
    cam_T_model = camera.cam_T_rig @ rig_T_model
    # Two pixels around the rays that can hit the part: each of its pixels has its
    # neighbours (for the normals), and one beyond them is empty (as for the erosion).
    box = hit_bbox(camera, mesh, cam_T_model, margin=2)
    if box is None:
        return np.zeros((0, 6))
    m = settings.margin_px
    grow = max(m, 0)
    region = clip_region(
        (box[0] - grow, box[1] - grow, box[2] + grow, box[3] + grow), camera.width, camera.height
    )
    x0, y0, x1, y1 = region
    rays = camera.pixel_rays()[y0:y1, x0:x1]
    own = _cast_over(camera, PlacedMesh(mesh, rig_T_model), rays, region, None, known)
    mask = np.isfinite(own)
    if m > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * m + 1, 2 * m + 1))
        mask = cv2.dilate(mask.astype(np.uint8), kernel) > 0
    measured = depth[y0:y1, x0:x1]
    other = _nearest_other(camera, others, rays, region, mask, known)
    theirs = np.isfinite(other) & (
        (np.abs(measured - other) < settings.explained_mm) | (other < own)
    )
    mask &= ~theirs
    if m < 0:  # away from the edges of what the part shows (depth is least sure there)
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (1 - 2 * m, 1 - 2 * m))
        mask = cv2.erode(mask.astype(np.uint8), kernel, borderValue=0) > 0
    mask &= np.isfinite(measured) & (measured > 0)
    grid = rays.astype(np.float64) * measured[..., None]
    ys, xs = np.nonzero(mask)
    normals = _grid_normals(grid, ys, xs)
    good = np.isfinite(normals).all(axis=-1)
    ys, xs, normals = ys[good], xs[good], normals[good]
    if len(ys) > settings.max_points:  # evenly thinned, deterministically
        keep = np.linspace(0, len(ys) - 1, settings.max_points).astype(int)
        ys, xs, normals = ys[keep], xs[keep], normals[keep]
    R, t = camera.rig_T_cam[:3, :3], camera.rig_T_cam[:3, 3]
    points = np.take(grid.reshape(-1, 3), ys * grid.shape[1] + xs, axis=0)
    return np.concatenate([points @ R.T + t, normals @ R.T], axis=1)


def _nearest_other(
    camera: Camera,
    others: Sequence[PlacedMesh],
    rays: np.ndarray,
    region: tuple[int, int, int, int],
    need: np.ndarray,
    known: Known | None = None,
) -> np.ndarray:
    """The depth of the nearest of the ``others`` along each ray of ``rays`` (the grid of
    the camera's ``region``) where ``need`` holds (inf elsewhere, and where none is hit).
    Only those rays are cast: a pixel outside the part's region cannot be kept whatever is
    in front of it."""
    x0, y0, x1, y1 = region
    other = np.full(need.shape, np.inf, np.float32)
    for pm in others:
        cam_T_other = camera.cam_T_rig @ pm.cam_T_model
        ob = hit_bbox(camera, pm.mesh, cam_T_other)
        if ob is None:
            continue
        bx0, by0, bx1, by1 = max(ob[0], x0), max(ob[1], y0), min(ob[2], x1), min(ob[3], y1)
        if bx0 >= bx1 or by0 >= by1:
            continue
        window = (slice(by0 - y0, by1 - y0), slice(bx0 - x0, bx1 - x0))
        sub_need = need[window]
        if not sub_need.any():
            continue
        d = _cast_over(camera, pm, rays[window], (bx0, by0, bx1, by1), sub_need, known)
        sub = other[window]
        sub[sub_need] = np.minimum(sub[sub_need], d[sub_need])
    return other


def _cast_over(
    camera: Camera,
    placed: PlacedMesh,
    rays: np.ndarray,
    region: Rect,
    need: np.ndarray | None,
    known: Known | None,
) -> np.ndarray:
    """The depth of ``placed`` (in the reference frame) alone along each ray of ``rays``
    (the grid of the camera's ``region``) where ``need`` holds (everywhere: None); inf
    elsewhere and on a miss. The rays of a ``known`` cast of it at this pose are not cast
    again: its samples' hits are taken, and its rectangle holds every sample that can hit;
    nor are the rays that cannot reach it (:func:`reachable`: a part's rectangle at every
    pixel holds many)."""
    cam_T_model = camera.cam_T_rig @ placed.cam_T_model
    depth = np.full(rays.shape[:2], np.inf, np.float32)
    todo = np.ones(rays.shape[:2], bool) if need is None else need.copy()
    step = 0 if known is None else known.step
    key = (camera.name, step, placed.mesh.digest, np.asarray(placed.cam_T_model, float).tobytes())
    found = None if known is None or step < 2 else known.casts.get(key)
    if found is not None:
        x0, y0, x1, y1 = region
        # The known samples in the region: grid rows (columns) r0 to r1, at pixel r * step.
        r0, c0, r1, c1 = -(-y0 // step), -(-x0 // step), -(-y1 // step), -(-x1 // step)
        on = (slice(r0 * step - y0, None, step), slice(c0 * step - x0, None, step))
        seen = np.full((r1 - r0, c1 - c0), np.inf, np.float32)  # off its rectangle: a miss
        box, hits = found
        if box is not None and hits is not None:
            bc0, br0, bc1, br1 = max(box[0], c0), max(box[1], r0), min(box[2], c1), min(box[3], r1)
            if bc0 < bc1 and br0 < br1:
                seen[br0 - r0 : br1 - r0, bc0 - c0 : bc1 - c0] = hits.depth[
                    br0 - box[1] : br1 - box[1], bc0 - box[0] : bc1 - box[0]
                ]
        depth[on] = np.where(todo[on], seen, np.inf)
        todo[on] = False
    can = reachable(camera, placed.mesh, cam_T_model, region)
    at = np.flatnonzero(todo if can is None else todo & can)
    if len(at):
        # By flat index: a boolean mask gathers from a (rows, columns, 3) grid several
        # times slower (the copy of the window is cheap beside either).
        rays_at = np.take(rays.reshape(-1, 3), at, axis=0)
        depth.reshape(-1)[at] = cast_alone(placed.mesh, cam_T_model, rays_at).depth
    return depth


def _grid_normals(grid: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """Unit normals (towards the camera) of a grid of measured points (H, W, 3) at its
    pixels ``(ys, xs)``, from their neighbours: (N, 3), NaN where a neighbour is missing or
    the surface jumps (a depth edge). Only the pixels asked for: most of a part's rectangle
    is not its region."""
    h, w = grid.shape[:2]
    out = np.full((len(ys), 3), np.nan)
    inner = (ys > 0) & (ys < h - 1) & (xs > 0) & (xs < w - 1)
    # Rows of the flattened grid, by flat index: far faster than indexing it by (y, x).
    flat = grid.reshape(-1, 3)
    at = ys[inner] * w + xs[inner]
    dx = np.take(flat, at + 1, axis=0) - np.take(flat, at - 1, axis=0)
    dy = np.take(flat, at + w, axis=0) - np.take(flat, at - w, axis=0)
    centre = np.take(flat, at, axis=0)
    n = cross(dx, dy)
    norm = norms(n)[:, None]
    n = n / np.where(norm > 0, norm, np.nan)
    n *= -np.sign(np.einsum("ij,ij->i", n, centre))[..., None]
    # Across a depth edge the "surface" is the jump itself: a neighbour step far longer than
    # the pixel's footprint.
    footprint = np.abs(centre[:, 2]) / 500.0
    jump = np.maximum(norms(dx), norms(dy)) > 8 * footprint
    n[jump] = np.nan
    out[inner] = n
    return out


#: A measured point matches a model point whose normal is within 45 degrees of its own.
_SAME_NORMAL = float(np.cos(np.radians(45.0)))


class DepthTerm:
    """Point-to-plane residuals of the measured points against the model at a pose."""

    def __init__(self, mesh: Mesh, measured: np.ndarray, camera_centre: np.ndarray) -> None:
        self.tree, self.model, self.normals = _model_cloud(mesh)
        self.points = np.ascontiguousarray(measured[:, :3])
        # The pose moves little from one call to the next: most points keep their match.
        self.nearest = TrackedNearest(self.tree, self.model, len(self.points))
        self.point_normals = np.ascontiguousarray(measured[:, 3:])
        self.centre = camera_centre  # the depth camera's centre, reference frame
        rays = self.points - camera_centre
        self.rays = rays / np.maximum(norms(rays)[:, None], 1e-12)
        #: The measured points are taken this far (mm) along their rays from where measured.
        self.offset = 0.0
        # The last offset's moved points: an iteration asks for them several times.
        self._shifted: tuple[float, np.ndarray] = (0.0, self.points)
        # The last matches' samples turned by their pose (see :meth:`matches`).
        self._turned: tuple[bytes, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        # The last matches made, by pose, gate and offset: a refinement's result is matched
        # again for its residuals and then for its covariance.
        self._matched: tuple[tuple[bytes, float, float], np.ndarray, np.ndarray] | None = None

    def shifted(self, offset: float | None = None) -> np.ndarray:
        """The measured points moved by ``offset`` (default :attr:`offset`) along their
        rays."""
        offset = self.offset if offset is None else offset
        if not offset:
            return self.points
        if self._shifted[0] != offset:
            self._shifted = (offset, self.points + offset * self.rays)
        return self._shifted[1]

    def offset_derivative(self, J: np.ndarray, i: np.ndarray) -> np.ndarray:
        """The derivative of the residuals (Jacobian ``J`` at scene indices ``i``, as
        :meth:`residuals` gives them) with respect to :attr:`offset`."""
        return -np.einsum("ij,ij->i", J[:, 3:], np.take(self.rays, i, axis=0))

    def residuals(
        self, T: np.ndarray, gate: float, offset: float | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residuals (mm) and Jacobian (N, 6) of the matches within ``gate``, and their scene
        indices; the measured points moved by ``offset`` (default :attr:`offset`)."""
        i, j = self.matches(T, gate, offset)
        r, J = self.paired(T, i, j, offset)
        return r, J, i

    def matches(
        self, T: np.ndarray, gate: float, offset: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The measured points (scene indices) matched within ``gate`` at pose ``T``, and
        their model samples."""
        key = (T.tobytes(), gate, self.offset if offset is None else offset)
        if self._matched is not None and self._matched[0] == key:
            return self._matched[1], self._matched[2]
        i, j = self._match(T, gate, offset)
        self._matched = key, i, j
        return i, j

    def _match(
        self, T: np.ndarray, gate: float, offset: float | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`matches`, made."""
        none = np.zeros(0, int), np.zeros(0, int)
        if len(self.points) == 0:
            return none
        R, t = T[:3, :3], T[:3, 3]
        points = self.shifted(offset)
        # Each measured point, brought to the model frame, against its nearest model sample.
        dist, nearest = self.nearest.query((points - t) @ R, gate)
        i = np.flatnonzero(np.isfinite(dist))
        if len(i) == 0:
            return none
        j = nearest[i]
        # (Rows of (N, 3) arrays taken by index throughout: several times faster than by
        # fancy or boolean indexing.)
        n = np.take(self.normals, j, axis=0) @ R.T
        y = np.take(self.model, j, axis=0) @ R.T
        # A surface the camera can see, turned as the measured one: the floor beside a
        # part's end must not pull the part along onto it.
        ok = (np.einsum("ij,ij->i", n, y + t - self.centre) < 0) & (
            np.einsum("ij,ij->i", n, np.take(self.point_normals, i, axis=0)) > _SAME_NORMAL
        )
        k = np.flatnonzero(ok)
        i, j = i[k], j[k]
        # The matches' samples turned, kept for their residuals at the same pose.
        self._turned = (T.tobytes(), i, j, np.take(y, k, axis=0), np.take(n, k, axis=0))
        return i, j

    def paired(
        self, T: np.ndarray, i: np.ndarray, j: np.ndarray, offset: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (mm) and Jacobian (N, 6) at pose ``T`` of the measured points ``i``
        against the model samples ``j``: each one's distance to the sample's tangent plane."""
        if len(i) == 0:
            return np.zeros(0), np.zeros((0, 6))
        y, n, r = self._plane_distances(T, i, j, offset)
        return r, np.concatenate([cross(y, n), n], axis=1)

    def paired_residuals(
        self, T: np.ndarray, i: np.ndarray, j: np.ndarray, offset: float | None = None
    ) -> np.ndarray:
        """:meth:`paired`'s residuals alone (a step is judged by its cost: no Jacobian)."""
        if len(i) == 0:
            return np.zeros(0)
        return self._plane_distances(T, i, j, offset)[2]

    def _plane_distances(
        self, T: np.ndarray, i: np.ndarray, j: np.ndarray, offset: float | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The model samples ``j`` turned by ``T`` (about the reference origin), their
        normals turned, and the measured points' ``i`` distances to their tangent planes."""
        R, t = T[:3, :3], T[:3, 3]
        kept = self._turned
        if kept is not None and kept[1] is i and kept[2] is j and kept[0] == T.tobytes():
            y, n = kept[3], kept[4]
        else:
            y = np.take(self.model, j, axis=0) @ R.T
            n = np.take(self.normals, j, axis=0) @ R.T
        r = np.einsum("ij,ij->i", n, y + t - np.take(self.shifted(offset), i, axis=0))
        return y, n, r


#: Directions of the normal equations this much weaker than the strongest (after scaling)
#: are not moved along: what neither term sees (a cylinder's turn about its axis without
#: markers) stays as it was instead of wandering.
_WEAK = 1e-6


def _solve(H: np.ndarray, g: np.ndarray, damping: float) -> np.ndarray:
    """The damped step ``-(H + damping diag(H))^+ g``, scaled to unit diagonal first
    (rotations about the reference origin, far from the part, weigh far more than
    translations) and without the unobserved directions (judged undamped)."""
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hs = H / d[:, None] / d[None, :]
    w, V = np.linalg.eigh(Hs)
    keep = w > _WEAK * w.max()
    x = V[:, keep] @ ((V[:, keep].T @ (-g / d)) / (w[keep] + damping))
    return x / d


def residuals_at(
    T: np.ndarray,
    depth: DepthTerm | None,
    cameras: Sequence[Camera],
    obs: Sequence[Observation],
    settings: RefineSettings,
) -> Residuals:
    """:class:`Residuals` of pose T."""
    d_rms = d_in = None
    n_pts = 0
    if depth is not None and len(depth.points):
        n_pts = len(depth.points)
        r, _, _ = depth.residuals(T, settings.end_gate_mm)
        d_in = len(r) / n_pts
        d_rms = float(np.sqrt(np.mean(r**2))) if len(r) else float("inf")
    m_rms = None
    if obs:
        e = reprojection_errors(cameras, obs, T)
        m_rms = float(np.sqrt(np.mean(e**2)))
    return Residuals(d_rms, d_in, n_pts, m_rms, len(obs))


def refine_instance(
    mesh: Mesh,
    rig_T_model: np.ndarray,
    *,
    depth_camera: Camera | None,
    depth: np.ndarray | None,
    others: Sequence[PlacedMesh] = (),
    cameras: Sequence[Camera] = (),
    observations: Sequence[Observation] = (),
    settings: RefineSettings = RefineSettings(),
    points: np.ndarray | None = None,
    term: DepthTerm | None = None,
) -> Refinement:
    """Refine one instance's pose ``rig_T_model`` (see the module docstring).

    Args:
        mesh: The part's mesh (mm).
        depth_camera, depth: The depth map (mm, NaN = none) and the camera of its grid; None
            without depth.
        others: The other posed parts, placed in the reference frame.
        cameras, observations: The rig's cameras and the instance's markers as detected
            (:func:`annotator.repair.instance_observations`); none: depth only.
        points: The measured points, if already found (:func:`measured_points` at
            ``rig_T_model``).
        term: The :class:`DepthTerm` of the measured points, if already made (instead of
            ``points``; it keeps its matches, so a caller that goes on with the refined
            pose, as to its covariance, need not search them again); its offset is solved
            for in place.
    """
    started = time.perf_counter()
    T0 = np.array(rig_T_model, float)
    obs = list(observations)
    if depth is None or depth_camera is None:
        term = None
    elif term is None:
        pts = (
            measured_points(depth_camera, depth, mesh, T0, others, settings)
            if points is None
            else points
        )
        if len(pts) >= settings.min_points:
            term = DepthTerm(mesh, pts, depth_camera.rig_T_cam[:3, 3])
    elif len(term.points) < settings.min_points:
        term = None
    before = residuals_at(T0, term, cameras, obs, settings)
    if term is None and not obs:
        why = "no measured depth and no marker on it"
        return Refinement(T0, T0, False, 0, before, before, why, time.perf_counter() - started)
    markers = _MarkerTerm(cameras, obs, np.stack([o.image_corners for o in obs])) if obs else None
    T, offset, k, done = _minimise(T0, term, markers, settings)
    if term is not None:
        term.offset = offset
    after = residuals_at(T, term, cameras, obs, settings)
    why = _why_not_kept(done, term is not None, bool(obs), after, settings)
    converged = not why
    return Refinement(
        T if converged else T0,
        T0,
        converged,
        k,
        before,
        after,
        why,
        time.perf_counter() - started,
        term.offset if term is not None and converged else 0.0,
    )


@dataclass(frozen=True)
class _MarkerTerm:
    """The reprojection errors of an instance's markers (px), as the pose changes."""

    cameras: Sequence[Camera]
    observations: list[Observation]
    corners: np.ndarray  # the observations' image corners, stacked

    def residuals(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return residuals_jacobian(self.cameras, self.observations, T, self.corners)

    def residuals_alone(self, T: np.ndarray) -> np.ndarray:
        """:meth:`residuals` without the Jacobian (a trial step's cost)."""
        return corner_residuals(self.cameras, self.observations, T, self.corners)


#: The damping starts (and stays, while steps lower the cost) far below the scaled system's
#: unit diagonal: the steps are Gauss-Newton's; a step that raises the cost is damped.
_DAMPING = Damping(start=1e-12, floor=1e-12, ceiling=1e4, factor=100.0)


@dataclass(frozen=True)
class _State:
    """Where the iteration is: the pose and the measured points' offset along their rays."""

    T: np.ndarray
    offset: float


@dataclass(frozen=True)
class _Linear:
    """The Huber-weighted normal equations ``H step = -g`` at a state, the Jacobian of each
    term that has residuals, and the depth's matches they were made with (scene indices,
    model samples)."""

    H: np.ndarray
    g: np.ndarray
    jacobians: list[np.ndarray]
    pairs: tuple[np.ndarray, np.ndarray]


class _Problem:
    """The depth and marker terms of one refinement, as the damped iteration asks for them:
    the cost of a state, its normal equations, the state a damped step reaches.

    Its cost is Huber's loss of each term over its noise (the depth's threshold 1.5 sigma,
    the markers' 3 sigma) plus the offset's prior: the loss whose iteratively reweighted
    normal equations these are. As in ICP, the depth's matches (within :attr:`gate`) are
    made once per linearisation and a step is judged with them, against the tangent planes
    of the same model samples (matching again at every trial would judge a step by which
    samples lie nearest, a cost that jumps); the state a step reaches is matched afresh."""

    def __init__(
        self, term: DepthTerm | None, markers: _MarkerTerm | None, settings: RefineSettings
    ) -> None:
        self.term, self.markers, self.s = term, markers, settings
        #: The offset is a 7th unknown only with a prior on it.
        self.unknowns = 7 if term is not None and settings.depth_offset_sigma_mm > 0 else 6
        #: The depth's matches are sought within this (mm); :func:`_minimise` narrows it.
        self.gate = settings.start_gate_mm
        self._memo: tuple[tuple[bytes, float, float], tuple[np.ndarray, np.ndarray]] | None
        self._memo = None
        self._terms: tuple[tuple[bytes, float, int, int], Any, Any] | None = None

    def matched(self, state: _State) -> tuple[np.ndarray, np.ndarray]:
        """The depth's matches at a state; the last ones kept: a state's cost and its normal
        equations come from one search."""
        key = (state.T.tobytes(), state.offset, self.gate)
        if self._memo is None or self._memo[0] != key:
            none = np.zeros(0, int), np.zeros(0, int)
            term = self.term
            found = none if term is None else term.matches(state.T, self.gate, state.offset)
            self._memo = key, found
        return self._memo[1]

    def terms(self, state: _State, pairs: tuple[np.ndarray, np.ndarray]) -> Any:
        """Each term's residuals and Jacobian at a state (the depth's of ``pairs``); the
        last ones kept: a state taken has its cost and then its normal equations made from
        them."""
        key = (state.T.tobytes(), state.offset, id(pairs[0]), id(pairs[1]))
        if self._terms is None or self._terms[0] != key:
            term, markers = self.term, self.markers
            depth = None if term is None else term.paired(state.T, *pairs, state.offset)
            seen = None if markers is None else markers.residuals(state.T)
            self._terms = key, (depth, seen), pairs  # (pairs kept alive: their ids are key)
        return self._terms[1]

    def cost(
        self, state: _State, pairs: tuple[np.ndarray, np.ndarray], *, jacobians: bool = False
    ) -> float:
        """The state's cost with ``pairs``; ``jacobians``: its terms' Jacobians made (and
        kept, for :meth:`linearise` at the same state) on the way."""
        s = self.s
        if jacobians:
            depth, markers = self.terms(state, pairs)
            r_depth = None if depth is None else depth[0]
            r_markers = None if markers is None else markers[0]
        else:  # a trial's step: its residuals alone
            term = self.term
            r_depth = None if term is None else term.paired_residuals(state.T, *pairs, state.offset)
            r_markers = None if self.markers is None else self.markers.residuals_alone(state.T)
        out = 0.0
        if r_depth is not None:
            sd = s.depth_sigma_mm
            out += huber_cost(r_depth, 1.5 * sd) / sd**2
        if r_markers is not None:
            sm = s.marker_sigma_px
            out += huber_cost(r_markers, 3.0 * sm) / sm**2
        if self.unknowns == 7:
            out += 0.5 * (state.offset / s.depth_offset_sigma_mm) ** 2
        return out

    def cost_at(self, state: _State) -> float:
        """A state's cost with its own matches (the state is linearised next)."""
        return self.cost(state, self.matched(state), jacobians=True)

    def linearise(self, state: _State) -> _Linear:
        s, n = self.s, self.unknowns
        pairs = self.matched(state)
        depth, markers = self.terms(state, pairs)
        H, g = np.zeros((n, n)), np.zeros(n)
        jacobians = []
        if n == 7:
            H[6, 6] = 1.0 / s.depth_offset_sigma_mm**2
            g[6] = state.offset / s.depth_offset_sigma_mm**2
        if depth is not None and len(depth[0]):
            r, J = depth
            if n == 7:
                assert self.term is not None
                J = np.concatenate([J, self.term.offset_derivative(J, pairs[0])[:, None]], axis=1)
            w = huber_weights(r, 1.5 * s.depth_sigma_mm) / s.depth_sigma_mm**2
            H += J.T @ (J * w[:, None])
            g += J.T @ (r * w)
            jacobians.append(J)
        if markers is not None:
            r, J = markers
            if n == 7:
                J = np.concatenate([J, np.zeros((len(J), 1))], axis=1)
            w = huber_weights(r, 3.0 * s.marker_sigma_px) / s.marker_sigma_px**2
            H += J.T @ (J * w[:, None])
            g += J.T @ (r * w)
            jacobians.append(J)
        return _Linear(H, g, jacobians, pairs)

    def trial(
        self, state: _State, lin: _Linear, damping: float
    ) -> tuple[_State, float, float] | None:
        """The state a damped step reaches, its cost with the linearisation's matches, and
        how far the step moves the residuals (the larger RMS of the terms, mm or px); None
        when nothing is left to fit (no match within the gate, no marker)."""
        if not lin.jacobians:
            return None
        step = _solve(lin.H, lin.g, damping)
        offset = state.offset + (float(step[6]) if len(step) > 6 else 0.0)
        new = _State(perturb(state.T, step[:6]), offset)
        moved = max(float(np.sqrt(np.mean((J @ step) ** 2))) for J in lin.jacobians)
        return new, self.cost(new, lin.pairs), moved


def _minimise(
    T0: np.ndarray,
    term: DepthTerm | None,
    markers: _MarkerTerm | None,
    settings: RefineSettings,
) -> tuple[np.ndarray, float, int, bool]:
    """Iterate from ``T0``: the pose reached, the depth's offset along its rays, the
    iterations made, and whether it converged.

    The gate narrows from ``start_gate_mm`` to ``end_gate_mm`` with one step at each gate
    (a pose far off first finds its surface, then only the points near it) until a step
    moves the residuals by less than ``converged_moves``; at the end gate the iteration goes
    on until a step moves them that little (mm or px: a motion the data hardly sees, a
    faceted cylinder turning about its axis from facet to facet, is none) or no step lowers
    the cost (a minimum)."""
    problem = _Problem(term, markers, settings)
    state = _State(np.array(T0, float), 0.0)
    narrowing = max(settings.gate_iterations - 1, 1)
    spent = 0
    for k in range(min(narrowing, settings.iterations)):
        problem.gate = settings.start_gate_mm + (settings.end_gate_mm - settings.start_gate_mm) * (
            k / narrowing
        )
        step = levenberg_marquardt(
            state,
            problem.cost_at(state),
            problem.linearise,
            problem.trial,
            damping=_DAMPING,
            small=lambda cost, new, moved: moved < settings.converged_moves,
            max_iterations=1,
        )
        state, spent = step.state, spent + 1
        if step.stop is Stop.SINGULAR:
            return state.T, state.offset, spent, False
        if step.stop is Stop.SMALL_STEP and k > 0:
            # The pose has stopped moving under a narrowed gate: it sits on its surface, and
            # the gates between would each repeat that step of nothing (a pose on markers
            # starts there). The end gate's iteration takes over. (The first, widest gate
            # is not enough: a pose far off may sit still there between two surfaces.)
            break
    if spent == settings.iterations:
        return state.T, state.offset, spent, False
    problem.gate = settings.end_gate_mm
    found = levenberg_marquardt(
        state,
        problem.cost_at(state),
        problem.linearise,
        problem.trial,
        damping=_DAMPING,
        small=lambda cost, new, moved: moved < settings.converged_moves,
        max_iterations=settings.iterations - spent,
        refused_count=False,  # an iteration is a linearisation, damped as often as it takes
        cost_at=problem.cost_at,
    )
    converged = found.stop in (Stop.SMALL_STEP, Stop.NO_DESCENT)
    return found.state.T, found.state.offset, spent + found.iterations, converged


def _why_not_kept(
    done: bool, has_depth: bool, has_markers: bool, after: Residuals, settings: RefineSettings
) -> str:
    """Why the refined pose is not kept ("" when it is)."""
    if not done:
        return f"no convergence in {settings.iterations} iterations"
    if has_depth and (after.depth_inliers or 0.0) < settings.min_inlier_fraction:
        return (
            f"only {100 * (after.depth_inliers or 0):.0f}% of the measured points on the "
            "refined surface"
        )
    if has_markers and not (after.marker_rms_px or 0.0) <= settings.max_marker_px:
        return f"the markers reproject {after.marker_rms_px:.1f} px off"
    return ""


def pose_covariance(
    T: np.ndarray,
    *,
    depth: DepthTerm | None,
    cameras: Sequence[Camera],
    observations: Sequence[Observation],
    site_sigmas: dict[int, tuple[float, float]] | None = None,
    fitted_sites: dict[int, tuple[float, float]] | None = None,
    noise: NoiseModel = NOISE,
    settings: RefineSettings = RefineSettings(),
) -> np.ndarray:
    """The 6x6 covariance of ``(w, v)`` (the perturbation of :mod:`annotator.pnp`) of a pose
    refined against markers and depth: the inverse of both terms' information (depth
    within the end gate, Huber-weighted, its points counted ``depth_correlation`` times
    fewer), plus what errors that many points or corners share do to it: an offset of the
    depth along its rays (``noise.depth_bias_mm``), and the markers' site errors
    (``site_sigmas`` maps a marker id to the 1-sigma of its site's shifts in its plane, mm,
    each of two, and of its turn about its normal, rad; a marker's error is the same in every
    camera that sees it). ``fitted_sites`` (same form) are sites measured from this very pose
    (``annotator sites`` fitted them to the scene they were seen in): the pose and they are
    off together, with residuals that show nothing, so their errors are unknowns the markers
    must share with the pose (within those 1-sigma), not errors the pose merely follows: what
    the markers then still say of the pose. Infinite where the terms leave a motion free."""
    obs = list(observations)
    H = np.zeros((6, 6))
    B = np.zeros((6, 0))
    if obs:
        x = np.stack([o.image_corners for o in obs])
        r, Jm = residuals_jacobian(cameras, obs, T, x)
        dof = max(r.size - 6, 1)
        sm = max(float(np.sqrt(r @ r / dof)), noise.corner_px)
        H += Jm.T @ Jm / sm**2
        if fitted_sites:
            # The sites' errors, in units of their 1-sigma, solved for beside the pose and
            # eliminated (Schur complement): the information on the pose that is left.
            Jf, scale = site_jacobian(cameras, obs, T, fitted_sites)
            C = Jm.T @ (Jf * scale) / sm**2
            G = (Jf * scale).T @ (Jf * scale) / sm**2 + np.eye(len(scale))
            H -= C @ np.linalg.solve(G, C.T)
        if site_sigmas:
            Js, scale = site_jacobian(cameras, obs, T, site_sigmas)
            B = Jm.T @ (Js * scale) / sm**2
    if depth is not None:
        rd, Jd, i = depth.residuals(T, settings.end_gate_mm)
        if len(rd):
            sd = max(float(np.sqrt(np.mean(rd**2))), noise.depth_fit_mm)
            w = huber_weights(rd, 1.5 * sd) / (sd**2 * noise.depth_correlation)
            H += Jd.T @ (Jd * w[:, None])
            # The residuals' derivative with respect to the measured points' common offset
            # along their rays: r = n . (model point - measured point).
            dr = depth.offset_derivative(Jd, i)
            B = np.concatenate([B, (Jd.T @ (w * dr))[:, None] * noise.depth_bias_mm], axis=1)
    if np.linalg.cond(H) > 1e12:
        return np.full((6, 6), np.inf)
    Hinv = np.linalg.inv(H)
    return Hinv + Hinv @ B @ B.T @ Hinv
