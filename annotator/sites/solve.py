"""The joint solve for one instance: every scene's pose of it and every marker's correction
on its site, from the marker corners in every camera (and the measured depth).

Unknowns: per scene ``s`` the pose ``rig_T_model`` (a left perturbation ``(w, v)`` of the
annotated pose, as in :mod:`annotator.pnp.multiview`), per observed site ``k`` its correction
``(du, dv, dtheta)`` in its own plane (:mod:`annotator.markers.glue`). Residuals, each divided
by its standard deviation:

- **corners**: every detected corner of every marker of the instance in every camera against
  its projection (lens distortion included), ``sigma_px``;
- **depth** (where there is a depth map): measured points on the part's visible surface,
  away from its silhouette's edge, against the posed mesh, point to plane,
  ``depth_sigma_mm``, with a free offset of the sensor along its rays per view (real depth
  is biased by a millimetre or so, which would otherwise move the pose and every site with
  it); the closest points are found again between rounds, as in ICP;
- **prior**: each correction against zero, ``prior_mm`` and ``prior_deg``: a marker seen in
  few scenes stays near its layout.

The loss is robust (``soft_l1`` beyond ``robust_sigmas`` standard deviations), so a misread
marker or a false detection left in weighs little.

**The gauge.** Moving all sites by one rigid motion and every pose by its inverse changes no
projection. Keeping the corrections in the sites' own planes removes every such motion that
would take a site off its face: on a part with markers on three faces that are not parallel to
one common line, none is left. What remains (markers all on one plane: two shifts in it and a
turn about its normal; on one family of parallel planes the same; on a surface of revolution,
the turn about the axis) is fixed by the depth where the part's shape shows it, and otherwise
by the prior, which keeps the layout's placement: such a direction is reported as not
observable rather than guessed. :func:`unobservable_directions` finds them: the rigid motions
of the part (shifts along and turns about its model axes, through its centroid) that the
sites can follow in their planes and that no residual but the prior sees.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from annotator.geometry.camera import Camera
from annotator.geometry.robust import robust_sigma
from annotator.markers.glue import site_frames
from annotator.noise import NOISE

#: The 1-sigma prior on the depth sensor's offset per view (mm).
OFFSET_PRIOR_MM = 5.0


@dataclass(frozen=True)
class SiteSettings:
    """Standard deviations and bounds of the solve (px, mm, degrees)."""

    sigma_px: float = NOISE.site_corner_px
    depth_sigma_mm: float = NOISE.depth_mm
    prior_mm: float = 1.0
    prior_deg: float = 3.0
    #: Residuals beyond this many standard deviations weigh less and less (soft_l1).
    robust_sigmas: float = 3.0
    #: A marker whose projection is this far from its detection under the annotated pose is
    #: left out from the start (a misread id that annotate kept would be farther still).
    outlier_px: float = 8.0
    #: Corrections beyond this (mm) are flagged: probably glued on the wrong site or copy.
    max_move_mm: float = 2.0
    #: Depth rounds (closest points found again between them).
    rounds: int = 3
    #: A rigid motion whose standard deviation (mm at the part's radius) is above this,
    #: without the prior, is reported as not observable.
    unobservable_mm: float = 0.2


@dataclass(frozen=True)
class MarkerView:
    """One detected marker of the instance in one camera of one scene."""

    view: int  # index of the scene among the instance's views
    camera: int
    site: int
    corners: np.ndarray  # (4, 2) px, ArUco order


@dataclass
class InstanceData:
    """What the solve needs of one instance: its layout, its annotated poses, the markers
    seen, and the measured surface points per view (rig frame, mm; may be empty)."""

    layout: np.ndarray  # (S, 4, 3)
    poses: list[np.ndarray]  # rig_T_model per view
    markers: list[MarkerView]
    depth_points: list[np.ndarray] = field(default_factory=list)
    #: Per view, per point: the point's motion (rig frame) for 1 mm more measured depth.
    depth_rays: list[np.ndarray] = field(default_factory=list)


@dataclass
class SiteSolution:
    """The solve's outcome for one instance.

    Attributes:
        corrections: (S, 3) ``(du, dv, dtheta)`` per site (mm, mm, rad); zero where unseen.
        std: (S, 3) their standard deviations (NaN where unseen).
        seen: (S,) number of views in which each site's marker was used.
        poses: The refined ``rig_T_model`` per view.
        rms_before, rms_after: Corner RMS (px) on the markers used, layout and annotated
            poses against measured sites and refined poses.
        used, left_out: Marker views used and left out as outliers.
        unobservable: Rigid motions of the part that nothing but the prior fixed.
    """

    corrections: np.ndarray
    std: np.ndarray
    seen: np.ndarray
    poses: list[np.ndarray]
    rms_before: float
    rms_after: float
    used: int
    left_out: int
    unobservable: list[str]


def solve_sites(
    cameras: Sequence[Camera],
    data: InstanceData,
    mesh_closest: ClosestPoints | None = None,
    *,
    settings: SiteSettings = SiteSettings(),
    start: np.ndarray | None = None,
) -> SiteSolution:
    """Measure one instance's sites (see the module docstring).

    Args:
        cameras: The rig.
        data: The instance's layout, annotated poses, markers and depth points.
        mesh_closest: Closest points on the part's surface (for the depth residuals); None
            without depth.
        start: (S, 3) corrections to start from (default: the layout, zero); the result
            does not depend on it.
    """
    layout = np.asarray(data.layout, float)
    marks = _inliers(cameras, data, settings)
    sites = sorted({m.site for m in marks})
    if not marks:
        return _nothing_seen(len(layout), data)
    problem = _Problem(cameras, layout, data.poses, marks, sites, settings)
    x = np.zeros(problem.n_params)
    rms_before = problem.corner_rms(x)
    if start is not None and sites:
        x[problem.first_site :] = (np.asarray(start, float)[sites].ravel()) / problem.scale[
            problem.first_site :
        ]
    result = _solve_rounds(problem, x, data, mesh_closest)
    x = result.x
    J = _jacobian(result)
    unobservable = unobservable_directions(problem, x, J[problem.data_rows(J.shape[0])], settings)
    corrections, std = _corrections_and_std(problem, x, J, len(layout))
    seen = np.zeros(len(layout), int)
    for _, site in {(m.view, m.site) for m in marks}:
        seen[site] += 1
    return SiteSolution(
        corrections=corrections,
        std=std,
        seen=seen,
        poses=problem.poses(x),
        rms_before=rms_before,
        rms_after=problem.corner_rms(x),
        used=len(marks),
        left_out=len(data.markers) - len(marks),
        unobservable=unobservable,
    )


def _nothing_seen(n_sites: int, data: InstanceData) -> SiteSolution:
    """The solution when no marker view fits: the layout and the annotated poses kept."""
    zeros = np.zeros((n_sites, 3))
    return SiteSolution(
        zeros,
        zeros * np.nan,
        np.zeros(n_sites, int),
        list(data.poses),
        0.0,
        0.0,
        0,
        len(data.markers),
        [],
    )


def _solve_rounds(
    problem: _Problem, x: np.ndarray, data: InstanceData, mesh_closest: ClosestPoints | None
) -> Any:
    """The robust solve from ``x``; with depth, its point pairs are found again between
    rounds, as in ICP."""
    has_depth = mesh_closest is not None and any(len(p) for p in data.depth_points)
    for _ in range(problem.settings.rounds if has_depth else 1):
        result = _least_squares(problem, x, data if has_depth else None, mesh_closest)
        x = result.x
    return result


def _corrections_and_std(
    problem: _Problem, x: np.ndarray, J: np.ndarray, n_sites: int
) -> tuple[np.ndarray, np.ndarray]:
    """(n_sites, 3) corrections (zero where unseen) and their standard deviations (NaN
    where unseen)."""
    corrections = np.zeros((n_sites, 3))
    std = np.full((n_sites, 3), np.nan)
    # The corners' real noise, from the residuals (robustly), rather than the assumed one:
    # the uncertainties reported are then those the data support.
    noise = robust_sigma(problem.projections(x) - problem.detected)
    cov = _covariance(J) * (max(noise, 0.02) / problem.settings.sigma_px) ** 2
    if problem.sites:
        first = problem.first_site
        corrections[problem.sites] = problem.site_params(x)
        variance = np.maximum(np.diag(cov)[first:], 0)
        std[problem.sites] = (np.sqrt(variance) * problem.scale[first:]).reshape(-1, 3)
    return corrections, std


class ClosestPoints:
    """Closest points and outward normals on a mesh's surface (open3d, model frame)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        from annotator.geometry.open3d_lib import o3d

        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(np.asarray(vertices, np.float32)),
            o3d.core.Tensor(np.asarray(faces, np.uint32)),
        )
        self._o3d = o3d

    def __call__(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) closest points and (N, 3) unit normals of their triangles."""
        ans = self._scene.compute_closest_points(
            self._o3d.core.Tensor(np.asarray(points, np.float32))
        )
        return ans["points"].numpy().astype(float), ans["primitive_normals"].numpy().astype(float)


def unobservable_directions(
    problem: _Problem, x: np.ndarray, J_data: np.ndarray, settings: SiteSettings
) -> list[str]:
    """The rigid motions of the part (shift along or turn about a model axis, through the
    sites' centroid; a turn measured by the motion at the part's radius) that the sites can
    follow within their planes and that the data (corners, depth) do not fix: their standard
    deviation without the prior is above ``settings.unobservable_mm``."""
    if not problem.sites:
        return []
    sites = problem.site_corners(x)[problem.sites]
    centre = sites.reshape(-1, 3).mean(axis=0)
    radius = max(float(np.linalg.norm(sites - centre, axis=-1).max()), 1.0)
    poses = problem.poses(x)
    _, u, v, n = site_frames(sites)
    names = [f"shift along {a}" for a in "xyz"] + [f"turn about {a}" for a in "xyz"]
    out = []
    for g in range(6):
        axis = np.eye(3)[g % 3]
        rot = axis / radius if g >= 3 else np.zeros(3)
        shift = axis if g < 3 else np.zeros(3)
        motion = np.cross(rot, sites - centre) + shift  # (K, 4, 3): 1 mm at the radius
        # The in-plane correction that follows the motion best, and what it leaves out.
        dX = np.stack(
            [
                np.broadcast_to(u[:, None], sites.shape),
                np.broadcast_to(v[:, None], sites.shape),
                np.cross(n[:, None], sites - sites.mean(axis=1, keepdims=True)),
            ],
            axis=-1,
        )  # (K, 4, 3, 3): d corner / d (du, dv, dtheta)
        A = dX.reshape(len(sites), 12, 3)
        b = motion.reshape(len(sites), 12)
        coef = np.stack([np.linalg.lstsq(A[k], b[k], rcond=None)[0] for k in range(len(sites))])
        left = np.sqrt(np.mean((np.einsum("kij,kj->ki", A, coef) - b) ** 2))
        if left > 0.05:  # the sites cannot follow it: their faces fix it
            continue
        z = np.zeros(problem.n_params)
        for s, T in enumerate(poses):
            R = T[:3, :3]
            z[6 * s : 6 * s + 3] = -R @ rot
            z[6 * s + 3 : 6 * s + 6] = R @ (np.cross(rot, centre) - shift)
        z[problem.first_site :] = coef.reshape(-1) / problem.scale[problem.first_site :]
        seen = float(np.linalg.norm(J_data @ z))
        if seen == 0 or 1.0 / seen > settings.unobservable_mm:
            out.append(names[g])
    return out


# ------------------------------------------------------------------------------ internals


def _inliers(
    cameras: Sequence[Camera], data: InstanceData, settings: SiteSettings
) -> list[MarkerView]:
    """The marker views whose layout projection under the annotated pose is within
    ``outlier_px`` of the detection."""
    keep = []
    for m in data.markers:
        T = cameras[m.camera].cam_T_rig @ data.poses[m.view]
        X = data.layout[m.site] @ T[:3, :3].T + T[:3, 3]
        uv = cameras[m.camera].project(X)
        if np.all(np.isfinite(uv)) and np.abs(uv - m.corners).max() <= settings.outlier_px:
            keep.append(m)
    return keep


def _least_squares(
    problem: _Problem, x: np.ndarray, data: InstanceData | None, closest: ClosestPoints | None
) -> Any:
    """One robust solve from ``x`` with the depth pairs found at ``x`` (none without
    ``data``'s depth)."""
    points = data.depth_points if data is not None else []
    rays = data.depth_rays if data is not None else []
    problem.set_depth(points, rays, closest, x)
    return least_squares(
        problem.residuals,
        x,
        jac_sparsity=problem.sparsity(),
        method="trf",
        loss="soft_l1",
        f_scale=problem.settings.robust_sigmas,
        x_scale="jac",
        max_nfev=200,
    )


def _jacobian(result: Any) -> np.ndarray:
    jac = result.jac
    return jac.toarray() if hasattr(jac, "toarray") else np.asarray(jac)


def _covariance(J: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(J.T @ J)


class _Problem:
    """The least-squares problem of :func:`solve_sites` (parameters scaled to unit priors)."""

    def __init__(
        self,
        cameras: Sequence[Camera],
        layout: np.ndarray,
        poses: Sequence[np.ndarray],
        marks: Sequence[MarkerView],
        sites: Sequence[int],
        settings: SiteSettings,
    ) -> None:
        self.cameras = cameras
        self.layout = layout
        self.R0 = np.stack([T[:3, :3] for T in poses]) if poses else np.zeros((0, 3, 3))
        self.t0 = np.stack([T[:3, 3] for T in poses]) if poses else np.zeros((0, 3))
        self.marks = list(marks)
        self.sites = list(sites)
        self.settings = settings
        self.n_pose = 6 * len(poses)
        # Per view, the depth sensor's offset along its rays (mm) against the rig: real depth
        # is biased by a millimetre or so, which would otherwise move the pose.
        self.first_site = self.n_pose + len(poses)
        self.n_params = self.first_site + 3 * len(self.sites)
        self.scale = np.concatenate(
            [
                np.ones(self.first_site),
                np.tile(
                    [settings.prior_mm, settings.prior_mm, np.radians(settings.prior_deg)],
                    len(self.sites),
                ),
            ]
        )
        self.view = np.array([m.view for m in self.marks], int)
        self.site = np.array([m.site for m in self.marks], int)
        self.camera = np.array([m.camera for m in self.marks], int)
        self.detected = (
            np.stack([m.corners for m in self.marks]) if self.marks else np.zeros((0, 4, 2))
        )
        self.column = {k: i for i, k in enumerate(self.sites)}
        centre, u, v, n = site_frames(layout)
        self.frames = (centre, u, v, n)
        self.depth: list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.prior_rows = np.arange(0)

    # -- parameters
    def site_params(self, x: np.ndarray) -> np.ndarray:
        return (x[self.first_site :] * self.scale[self.first_site :]).reshape(-1, 3)

    def site_corners(self, x: np.ndarray) -> np.ndarray:
        corr = np.zeros((len(self.layout), 3))
        if self.sites:
            corr[self.sites] = self.site_params(x)
        centre, u, v, n = self.frames
        a = self.layout - centre[:, None]
        theta = corr[:, 2][:, None, None]
        k = n[:, None]
        rotated = (
            a * np.cos(theta)
            + np.cross(k, a) * np.sin(theta)
            + k * (a * k).sum(-1, keepdims=True) * (1 - np.cos(theta))
        )
        return rotated + (centre + corr[:, :1] * u + corr[:, 1:2] * v)[:, None]

    def rotations(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = x[: self.n_pose].reshape(-1, 6)
        R = Rotation.from_rotvec(p[:, :3]).as_matrix() @ self.R0 if len(p) else self.R0
        return R, self.t0 + p[:, 3:]

    def poses(self, x: np.ndarray) -> list[np.ndarray]:
        R, t = self.rotations(x)
        out = []
        for Ri, ti in zip(R, t):
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = Ri, ti
            out.append(T)
        return out

    # -- residuals
    def projections(self, x: np.ndarray) -> np.ndarray:
        sites = self.site_corners(x)
        R, t = self.rotations(x)
        Y = np.einsum("mij,mkj->mki", R[self.view], sites[self.site]) + t[self.view][:, None]
        uv = np.empty((len(self.marks), 4, 2))
        for j, cam in enumerate(self.cameras):
            sel = self.camera == j
            if not sel.any():
                continue
            Yc = Y[sel] @ cam.cam_T_rig[:3, :3].T + cam.cam_T_rig[:3, 3]
            p, _ = cv2.projectPoints(Yc.reshape(-1, 3), np.zeros(3), np.zeros(3), cam.K, cam.dist)
            uv[sel] = p.reshape(-1, 4, 2)
        return uv

    def corner_rms(self, x: np.ndarray) -> float:
        if not self.marks:
            return 0.0
        d = self.projections(x) - self.detected
        return float(np.sqrt(np.mean(np.sum(d**2, axis=-1))))

    def residuals(self, x: np.ndarray) -> np.ndarray:
        parts = [((self.projections(x) - self.detected) / self.settings.sigma_px).ravel()]
        offsets = x[self.n_pose : self.first_site]
        if self.depth:
            R, t = self.rotations(x)
            for s, p, ray, q, nrm in self.depth:
                m = (p + offsets[s] * ray - t[s]) @ R[s]  # R^T (p - t), in the model frame
                parts.append(((m - q) * nrm).sum(1) / self.settings.depth_sigma_mm)
        parts.append(offsets / OFFSET_PRIOR_MM)
        parts.append(x[self.first_site :])  # the prior: corrections in units of their sigma
        return np.concatenate(parts)

    def set_depth(
        self,
        points: Sequence[np.ndarray],
        rays: Sequence[np.ndarray],
        closest: ClosestPoints | None,
        x: np.ndarray,
    ) -> None:
        """Point-to-plane pairs at the current poses: measured points within 3 sigma (and
        3 mm at most) of the posed surface, with their closest points and normals."""
        self.depth = []
        if closest is None:
            self._rows()
            return
        R, t = self.rotations(x)
        offsets = x[self.n_pose : self.first_site]
        near = min(3.0, 6 * self.settings.depth_sigma_mm)
        for s, (p, ray) in enumerate(zip(points, rays)):
            if len(p) == 0:
                continue
            m = (p + offsets[s] * ray - t[s]) @ R[s]
            q, nrm = closest(m)
            ok = np.linalg.norm(m - q, axis=1) < near
            if ok.sum() >= 10:
                self.depth.append((s, p[ok], ray[ok], q[ok], nrm[ok]))
        self._rows()

    def _rows(self) -> None:
        n_corner = 8 * len(self.marks)
        n_depth = sum(len(d[1]) for d in self.depth)
        start = n_corner + n_depth
        self.prior_rows = np.arange(
            start, start + self.first_site - self.n_pose + 3 * len(self.sites)
        )

    def data_rows(self, n_rows: int) -> np.ndarray:
        """Which of the residual rows are data (corners, depth), not the prior."""
        rows = np.ones(n_rows, bool)
        rows[self.prior_rows] = False
        return rows

    def sparsity(self) -> lil_matrix:
        n_views = self.first_site - self.n_pose
        n_rows = (
            8 * len(self.marks) + sum(len(d[1]) for d in self.depth) + n_views + 3 * len(self.sites)
        )
        A = lil_matrix((n_rows, self.n_params), dtype=np.int8)
        for i, m in enumerate(self.marks):
            rows = slice(8 * i, 8 * i + 8)
            A[rows, 6 * m.view : 6 * m.view + 6] = 1
            c = self.first_site + 3 * self.column[m.site]
            A[rows, c : c + 3] = 1
        row = 8 * len(self.marks)
        for s, p, _, _, _ in self.depth:
            A[row : row + len(p), 6 * s : 6 * s + 6] = 1
            A[row : row + len(p), self.n_pose + s] = 1
            row += len(p)
        for v in range(n_views):
            A[row + v, self.n_pose + v] = 1
        row += n_views
        for k in range(len(self.sites)):
            for d in range(3):
                A[row + 3 * k + d, self.first_site + 3 * k + d] = 1
        return A
