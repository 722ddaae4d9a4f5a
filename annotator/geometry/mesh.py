"""Triangle meshes in millimetres: loading and exact surface integrals.

The surface moments are integrals over the triangles (not averages over vertices), so they
do not depend on how finely a part is tessellated. They are what the paper's pose distance
needs (section 4.1): the surface centroid and ``(1/S) * integral of x x^T ds`` about it.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from annotator.errors import UserError

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".glb")


@dataclass(frozen=True, eq=False)
class Mesh:
    """An indexed triangle mesh.

    Attributes:
        vertices: (N, 3) float64 vertex positions, mm, model frame.
        faces: (M, 3) int32 vertex indices, counter-clockwise seen from outside.
    """

    vertices: np.ndarray
    faces: np.ndarray

    @cached_property
    def triangles(self) -> np.ndarray:
        """(M, 3, 3) vertex positions of each triangle."""
        return self.vertices[self.faces]

    @cached_property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The axis-aligned bounding box's corners (lowest, highest), mm, model frame."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    @cached_property
    def face_areas(self) -> np.ndarray:
        """(M,) triangle areas, mm^2."""
        tri = self.triangles
        return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)

    @cached_property
    def face_normals(self) -> np.ndarray:
        """(M, 3) unit outward normals (zero for degenerate triangles)."""
        tri = self.triangles
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)

    @cached_property
    def digest(self) -> bytes:
        """A 16-byte fingerprint of the geometry: equal for equal vertices and faces (a mesh
        loaded twice), so that work on it can be cached across loads."""
        data = self.vertices.tobytes() + self.faces.tobytes()
        return hashlib.blake2b(data, digest_size=16).digest()

    @cached_property
    def moments(self) -> SurfaceMoments:
        """Exact surface moments (area, centroid, second moments about the centroid)."""
        return surface_moments(self.vertices, self.faces)

    @cached_property
    def signed_volume(self) -> float:
        """Enclosed volume (mm^3) by the divergence theorem: positive when the faces are
        counter-clockwise seen from outside, negative for a mesh wound inside out (only
        meaningful for a closed surface)."""
        tri = self.triangles
        return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6)

    @cached_property
    def is_flat(self) -> bool:
        """True if the vertices span no volume (they lie on a plane or a line): no solid,
        whatever its faces."""
        v = np.asarray(self.vertices, np.float64)
        if len(v) < 4:
            return True
        spread = np.linalg.svd(v - v.mean(axis=0), compute_uv=False)
        return bool(spread[2] <= 1e-9 * max(float(spread[0]), 1e-12))

    @cached_property
    def is_watertight(self) -> bool:
        """True if every edge is shared by exactly two triangles once coincident vertices
        are merged (a closed surface)."""
        # trimesh's rule (vertices merged to 8 decimals, every edge in exactly two faces),
        # without importing trimesh at start-up
        _, merged = np.unique(np.round(self.vertices, 8), axis=0, return_inverse=True)
        f = merged.reshape(-1)[self.faces]
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        return bool(len(counts) and np.all(counts == 2))

    def distance_to_surface(self, points: np.ndarray) -> np.ndarray:
        """(N,) distance in mm from each of ``points`` (N, 3) to the nearest point of the
        surface (:func:`closest_on_triangles`), in chunks to bound memory."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.empty(len(pts))
        step = max(1, 4_000_000 // max(1, len(self.faces)))
        for i in range(0, len(pts), step):
            p = pts[i : i + step]
            q = closest_on_triangles(p[:, None, :], self.triangles[None])
            out[i : i + step] = np.sqrt(((q - p[:, None, :]) ** 2).sum(-1)).min(axis=1)
        return out

    def to_trimesh(self):  # noqa: ANN201 - trimesh is imported lazily
        """This mesh as a ``trimesh.Trimesh`` (no processing)."""
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)


@dataclass(frozen=True)
class SurfaceMoments:
    """Surface integrals of a mesh.

    Attributes:
        area: Surface area S, mm^2.
        centroid: (3,) surface centroid ``(1/S) * integral of x ds``, model frame.
        second: (3, 3) ``(1/S) * integral of (x - c)(x - c)^T ds`` about the centroid.
        radius: Largest distance from the centroid to a vertex (the enclosing sphere centred on
            the surface centroid has diameter ``2 * radius``: the paper's diameter).
    """

    area: float
    centroid: np.ndarray
    second: np.ndarray
    radius: float

    @property
    def diameter(self) -> float:
        """Diameter of the smallest sphere centred on the surface centroid enclosing the part."""
        return 2.0 * self.radius

    @property
    def Lambda(self) -> np.ndarray:  # noqa: N802 - the paper's symbol
        """The paper's Lambda: symmetric square root of ``second``."""
        w, V = np.linalg.eigh(self.second)
        return (V * np.sqrt(np.clip(w, 0.0, None))) @ V.T

    def rms_displacement(self, dR: np.ndarray, dt: np.ndarray) -> float:
        """RMS surface displacement of the rigid motion ``x -> dR x + dt`` (model frame, mm).

        Exact: ``sqrt(mean ||(dR - I)(x) + dt||^2)`` integrated over the surface.
        """
        A = np.asarray(dR, float) - np.eye(3)
        b = A @ self.centroid + np.asarray(dt, float)
        return float(np.sqrt(np.trace(A @ self.second @ A.T) + b @ b))


def surface_moments(vertices: np.ndarray, faces: np.ndarray) -> SurfaceMoments:
    """Exact area, centroid and second moments of a triangle surface.

    For a triangle with vertices a, b, c and area A, ``integral x ds = A (a + b + c) / 3`` and
    ``integral x x^T ds = A / 12 (a a^T + b b^T + c c^T + s s^T)`` with ``s = a + b + c``.
    """
    v = np.asarray(vertices, dtype=np.float64)
    tri = v[np.asarray(faces)]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    S = float(areas.sum())
    if S <= 0:
        raise ValueError("mesh has zero surface area")
    s = tri.sum(axis=1)
    centroid = (areas[:, None] * s).sum(axis=0) / (3.0 * S)
    tri_c = tri - centroid
    s_c = tri_c.sum(axis=1)
    outer = np.einsum("mki,mkj->mij", tri_c, tri_c) + np.einsum("mi,mj->mij", s_c, s_c)
    second = np.einsum("m,mij->ij", areas, outer) / (12.0 * S)
    used = np.unique(np.asarray(faces))
    radius = float(np.linalg.norm(v[used] - centroid, axis=1).max())
    return SurfaceMoments(
        area=S, centroid=centroid, second=0.5 * (second + second.T), radius=radius
    )


#: The mesh files :func:`load_mesh` reads, by name ending.
MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".glb")


def load_mesh(path: str | Path) -> Mesh:
    """Load a triangle mesh (PLY, OBJ, STL, OFF, GLB) in millimetres.

    A file is read once per process: a second load of the same file, unchanged (same size
    and modification time), returns the same :class:`Mesh`. Its arrays are shared, so no
    caller may change them in place (none does; they stay writeable because open3d
    refuses read-only arrays).

    Raises:
        UserError: naming the file, if it is missing, unreadable or has no triangles.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError("mesh file is missing", path=path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise UserError(
            f"not a mesh file type this tool reads ({', '.join(MESH_SUFFIXES)})", path=path
        )
    stat = path.stat()
    key = (str(path.resolve()), stat.st_mtime_ns, stat.st_size)
    mesh = _LOADED.get(key)
    if mesh is None:
        mesh = _read_mesh(path)
        if len(_LOADED) >= _LOADED_MAX:
            del _LOADED[next(iter(_LOADED))]
        _LOADED[key] = mesh
    return mesh


#: Meshes read in this process, by (resolved path, mtime_ns, size), oldest first.
_LOADED: dict[tuple[str, int, int], Mesh] = {}
_LOADED_MAX = 256


def _read_mesh(path: Path) -> Mesh:
    try:
        if path.suffix.lower() == ".ply":
            vertices, faces = _read_ply(path)
        else:
            import trimesh

            loaded = trimesh.load(path, force="mesh", process=False)
            faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int32)
            vertices = np.asarray(getattr(loaded, "vertices", np.zeros((0, 3))), dtype=np.float64)
    except Exception as exc:  # the readers raise many types for corrupt files
        raise UserError(
            f"unreadable mesh ({type(exc).__name__}: {exc})".split("\n")[0], path=path
        ) from None
    if faces.ndim != 2 or faces.shape[0] == 0 or faces.shape[1] != 3:
        raise UserError("mesh has no triangles", path=path)
    mesh = Mesh(vertices=vertices, faces=faces)
    if mesh.face_areas.sum() <= 0 or not np.all(np.isfinite(vertices)):
        raise UserError("mesh is degenerate (zero area or non-finite vertices)", path=path)
    return mesh


def surface_samples(
    mesh: Mesh, spacing: float, *, density: float = 12.0, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) and outward normals (N, 3) drawn on the surface, about ``density`` per
    ``spacing``^2 of area, in proportion to area (seeded)."""
    rng = np.random.default_rng(seed)
    areas = mesh.face_areas
    n = max(int(density * areas.sum() / spacing**2), 100)
    face = rng.choice(len(areas), size=n, p=areas / areas.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    tri = mesh.triangles[face]
    pts = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    return pts, mesh.face_normals[face]


def closest_on_triangles(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """The point of each triangle nearest to ``p``: ``p`` (..., 3) and ``tri`` (..., 3, 3)
    broadcast together; by the Voronoi regions of the vertices, edges and face (Ericson,
    *Real-Time Collision Detection*, 5.1.5)."""
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v, w = vb / denom, vc / denom
        out = a + ab * v[..., None] + ac * w[..., None]  # inside the face
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    regions = [  # later regions win, as the early returns of the original do
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + (c - b) * t_bc[..., None]),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * t_ac[..., None]),
        ((d6 >= 0) & (d5 <= d6), c),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * t_ab[..., None]),
        ((d3 >= 0) & (d4 <= d3), b),
        ((d1 <= 0) & (d2 <= 0), a),
    ]
    for where, point in regions:
        out = np.where(where[..., None], np.broadcast_to(point, out.shape), out)
    return out


def _read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a PLY file (ASCII or binary) as written, polygons split
    into fans as trimesh splits them. plyfile reads it: a PLY needs no more, and trimesh
    costs a second of start-up."""
    from plyfile import PlyData, PlyElementParseError

    try:
        # A binary file of triangles only is memory-mapped as one array: plyfile reads
        # variable-length lists one face at a time in Python, 0.3 s for a mesh of LM's size.
        ply = PlyData.read(str(path), known_list_len={"face": _TRIANGLE_LISTS})
    except PlyElementParseError:  # faces that are not all triangles
        ply = PlyData.read(str(path))
    v = ply["vertex"]
    vertices = np.column_stack([v["x"], v["y"], v["z"]]).astype(np.float64)
    if "face" not in ply or not len(ply["face"].properties):
        return vertices, np.zeros((0, 3), np.int32)
    face = ply["face"]
    polygons = face[face.properties[0].name]
    if isinstance(polygons, np.ndarray) and polygons.ndim == 2:  # memory-mapped triangles
        return vertices, np.array(polygons, np.int32)
    if len(polygons) and all(len(q) == 3 for q in polygons):
        return vertices, np.asarray(np.stack(polygons), np.int32)
    fans = [[q[0], q[k], q[k + 1]] for q in polygons for k in range(1, len(q) - 1)]
    return vertices, np.asarray(fans, np.int32).reshape(-1, 3)


#: The names a PLY's face list goes by, each of fixed length 3 for plyfile's fast path.
_TRIANGLE_LISTS = {"vertex_indices": 3, "vertex_index": 3}
