"""Running Cycles: the scene written as a job (JSON and npz), rendered by ``bpy`` in a child
process (:mod:`.cycles_worker`), the images read back.

``bpy`` is Blender as a Python module: it wants Python 3.11 and numpy < 2, which the rest of
the project does not, so it usually lives in an environment of its own. The interpreter that
runs the worker is, in order: the one ``ANNOTATOR_BPY_PYTHON`` names; this one, if it can
import ``bpy`` (``pip install 'bin-annotator[pbr]'`` in a Python 3.11 environment); the
project's ``.venv-pbr`` (what ``make test`` builds).
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from annotator.dataset.materials import PAPER, Material
from annotator.errors import UserError
from annotator.geometry.mesh import Mesh

#: The environment variable naming the Python that has ``bpy``.
BPY_PYTHON_ENV = "ANNOTATOR_BPY_PYTHON"

#: What a missing extra is told to do.
INSTALL_HINT = (
    "--render pbr needs Blender's bpy, which wants Python 3.11 and numpy < 2: "
    "`pip install 'bin-annotator[pbr]'` in a Python 3.11 environment, or make one for it "
    "alone (`python3.11 -m venv .venv-pbr && .venv-pbr/bin/pip install bpy==5.0.1`) and set "
    f"{BPY_PYTHON_ENV}=.venv-pbr/bin/python"
)

WORKER = Path(__file__).with_name("cycles_worker.py")

#: OpenCV camera (+z forward, +y down) -> Blender camera (-z forward, +y up).
_CV_TO_BLENDER = np.diag([1.0, -1.0, -1.0, 1.0])


class CyclesError(Exception):
    """Cycles failed to render a scene (the worker's last words)."""


@dataclass(frozen=True)
class Quality:
    """Cycles' sampling: samples per pixel (adaptive, stopping at ``adaptive_threshold``),
    OpenImageDenoise on the albedo and normal passes, light bounces."""

    samples: int = 16
    denoise: bool = True
    adaptive_threshold: float = 0.03
    bounces: int = 4

    def to_json(self) -> dict[str, Any]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class CyclesCamera:
    """A distortion-free camera: ``world_T_cam`` (OpenCV frame, mm), focal length ``f`` (px)
    with the principal point at the image centre, ``size`` (px), the pixel pitch (mm) and
    optionally depth of field (``focus_mm``, ``fstop``)."""

    name: str
    world_T_cam: np.ndarray
    f: float
    size: tuple[int, int]
    pixel_pitch_mm: float = 0.0048
    focus_mm: float | None = None
    fstop: float | None = None


@dataclass(frozen=True)
class AreaLight:
    """A rectangular area light at ``position`` (mm, world) facing ``target``, ``size``
    (mm) and power (W)."""

    position: tuple[float, float, float]
    target: tuple[float, float, float]
    size: tuple[float, float]
    power: float


@dataclass
class CyclesScene:
    """What Cycles renders: meshes (mm) placed with materials, printed marker quads, lights
    and a uniform environment (linear grey colour and strength).

    Attributes:
        marker_quads: (M, 4, 3) world corners (mm) of each printed square, TL TR BR BL as
            printed; ``marker_tiles`` (M, n, n) each one's printed grey (0..1).
    """

    meshes: list[Mesh] = field(default_factory=list)
    objects: list[tuple[int, np.ndarray, int]] = field(default_factory=list)
    materials: list[Material] = field(default_factory=list)
    marker_quads: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 3)))
    marker_tiles: np.ndarray = field(default_factory=lambda: np.zeros((0, 1, 1)))
    lights: list[AreaLight] = field(default_factory=list)
    environment: tuple[float, float] = (0.6, 0.15)

    def add(self, mesh: Mesh, world_T: np.ndarray, material: Material) -> None:
        """Place ``mesh`` (shared between objects by identity) with ``material``."""
        mi = next((k for k, m in enumerate(self.meshes) if m is mesh), None)
        if mi is None:
            self.meshes.append(mesh)
            mi = len(self.meshes) - 1
        if material not in self.materials:
            self.materials.append(material)
        self.objects.append((mi, np.asarray(world_T, float), self.materials.index(material)))


def _rows(T: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(T, float).reshape(-1)]


def _metres(T: np.ndarray) -> np.ndarray:
    out = np.array(T, float)
    out[:3, 3] /= 1000.0
    return out


def _facing(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """A pose at ``position`` whose -z points at ``target`` (how Blender's lights shine)."""
    back = position - target
    z = back / np.linalg.norm(back)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = position
    return T


def _atlas(tiles: np.ndarray, cell_px: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """The tiles side by side in one image (``cell_px`` px a cell) and each quad's UVs
    (M, 4 corners, 2), in the worker's corner order (TL BL BR TR)."""
    m, n = tiles.shape[:2]
    cols = max(1, int(np.ceil(np.sqrt(m))))
    rows = max(1, int(np.ceil(m / cols)))
    t = n * cell_px
    atlas = np.zeros((rows * t, cols * t), np.float32)
    uv = np.zeros((m, 4, 2), np.float32)
    for k in range(m):
        r, c = divmod(k, cols)
        atlas[r * t : (r + 1) * t, c * t : (c + 1) * t] = np.kron(
            tiles[k], np.ones((cell_px, cell_px))
        )
        u0, u1 = c / cols, (c + 1) / cols
        v1, v0 = 1 - r / rows, 1 - (r + 1) / rows  # UV v runs bottom to top
        uv[k] = [(u0, v1), (u0, v0), (u1, v0), (u1, v1)]
    return atlas, uv


def write_job(
    folder: Path,
    scene: CyclesScene,
    cameras: Sequence[CyclesCamera],
    *,
    quality: Quality,
    seed: int,
    device: str = "auto",
    threads: int = 0,
) -> Path:
    """The job of rendering ``scene`` by ``cameras`` in ``folder`` (``job.json``, its arrays
    in ``job.npz``); each camera's image will be ``<name>.npy``. Returns the job's path."""
    arrays: dict[str, np.ndarray] = {}
    for k, mesh in enumerate(scene.meshes):
        arrays[f"v{k}"] = (mesh.vertices / 1000.0).astype(np.float32)
        arrays[f"f{k}"] = mesh.faces.astype(np.int32)
    if len(scene.marker_quads):
        atlas, uv = _atlas(scene.marker_tiles)
        cv2.imwrite(str(folder / "atlas.png"), np.round(atlas * 255).astype(np.uint8))
        arrays["marker_quads"] = (scene.marker_quads / 1000.0).astype(np.float32)
        arrays["marker_uv"] = uv
    job = {
        "seed": int(seed),
        "atlas": "atlas.png" if len(scene.marker_quads) else None,
        "device": device,
        "threads": int(threads),
        "quality": quality.to_json(),
        "environment": {
            "color": [scene.environment[0]] * 3,
            "strength": scene.environment[1],
        },
        "meshes": len(scene.meshes),
        "materials": [m.to_json() for m in scene.materials],
        "paper": PAPER.to_json(),
        "objects": [
            {"mesh": mi, "world_T": _rows(_metres(T)), "material": ma}
            for mi, T, ma in scene.objects
        ],
        "lights": [
            {
                "world_T": _rows(
                    _metres(_facing(np.asarray(li.position, float), np.asarray(li.target, float)))
                ),
                "size": [li.size[0] / 1000.0, li.size[1] / 1000.0],
                "power": li.power,
            }
            for li in scene.lights
        ],
        "cameras": [
            {
                "name": c.name,
                "out": f"{c.name}.npy",
                "world_T": _rows(_metres(np.asarray(c.world_T_cam) @ _CV_TO_BLENDER)),
                "f": c.f,
                "width": c.size[0],
                "height": c.size[1],
                "pixel_pitch_mm": c.pixel_pitch_mm,
                "dof": None
                if c.focus_mm is None or c.fstop is None
                else {"focus": c.focus_mm / 1000.0, "fstop": c.fstop},
            }
            for c in cameras
        ],
    }
    path = folder / "job.json"
    np.savez(folder / "job.npz", **arrays)  # type: ignore[arg-type]
    path.write_text(json.dumps(job))
    return path


def bpy_python() -> str:
    """The interpreter that runs the worker (see the module docstring).

    Raises:
        UserError: none can import ``bpy`` (:data:`INSTALL_HINT`).
    """
    return _bpy_python(os.environ.get(BPY_PYTHON_ENV) or None)


@cache
def _bpy_python(named: str | None) -> str:
    """:func:`bpy_python` for the interpreter the environment names (looked for once)."""
    if named:
        if not _imports_bpy(named):
            raise UserError(f"{BPY_PYTHON_ENV}={named} cannot import bpy. {INSTALL_HINT}")
        return named
    if importlib.util.find_spec("bpy") is not None:
        return sys.executable
    local = Path(__file__).resolve().parents[3] / ".venv-pbr" / "bin" / "python"
    if local.exists() and _imports_bpy(str(local)):
        return str(local)
    raise UserError(INSTALL_HINT)


def _imports_bpy(python: str) -> bool:
    try:
        done = subprocess.run(
            [
                python,
                "-c",
                "import importlib.util, sys; sys.exit(importlib.util.find_spec('bpy') is None)",
            ],
            capture_output=True,
            timeout=60,
        )
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


#: ``progress(camera, fraction)`` while a camera renders.
Progress = Callable[[str, float], None]


def render(
    scene: CyclesScene,
    cameras: Sequence[CyclesCamera],
    *,
    quality: Quality = Quality(),
    seed: int = 0,
    device: str = "auto",
    threads: int = 0,
    progress: Progress | None = None,
) -> dict[str, np.ndarray]:
    """Each camera's linear RGB image (float32, (H, W, 3)), rendered by Cycles.

    Raises:
        UserError: no interpreter has ``bpy``.
        CyclesError: the render failed (its last lines of output).
    """
    python = bpy_python()
    with tempfile.TemporaryDirectory(prefix="annotator-cycles-") as tmp:
        job = write_job(
            Path(tmp), scene, cameras, quality=quality, seed=seed, device=device, threads=threads
        )
        tail = _run(python, job, progress)
        out = {}
        for c in cameras:
            path = Path(tmp) / f"{c.name}.npy"
            if not path.exists():
                raise CyclesError(f"Cycles wrote no image for {c.name}: {tail}")
            out[c.name] = np.load(path)
    return out


def _run(python: str, job: Path, progress: Progress | None) -> str:
    """Run the worker on ``job``, passing its progress on; the last lines it printed."""
    env = {**os.environ, "PYTHONNOUSERSITE": "1"}
    env.pop("PYTHONPATH", None)  # the project's own path holds nothing the worker needs
    last: list[str] = []
    with subprocess.Popen(
        [python, str(WORKER), str(job)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        cwd=job.parent,
    ) as proc:
        assert proc.stdout is not None
        for line in proc.stdout:
            line = line.rstrip()
            last = (last + [line])[-5:]
            if progress is not None:
                _progress(line, progress)
        code = proc.wait()
    tail = " | ".join(x for x in last if x)
    if code != 0:
        raise CyclesError(f"Cycles exited with status {code}: {tail[-400:]}")
    return tail


def _progress(line: str, progress: Progress) -> None:
    """The worker's ``PROGRESS <camera> <sample> <samples>`` lines as a fraction."""
    words = line.split()
    if len(words) == 4 and words[0] == "PROGRESS":
        try:
            progress(words[1], int(words[2]) / max(int(words[3]), 1))
        except ValueError:
            pass
