"""Records of a dataset (FORMAT.md), as read by :mod:`annotator.dataset.load`."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh, load_mesh
from annotator.markers.sites import MarkerSites
from annotator.symmetry.classes import SYMMETRY_CLASSES, Symmetry

#: The version of the on-disk contract (docs/FORMAT.md), written as ``format`` in dataset.yaml,
#: gt.json and annotation.json.
FORMAT_VERSION = 1

#: The folder of a dataset that holds one folder per scene (docs/FORMAT.md).
SCENES_DIR = "scenes"

#: The unexplained-depth mask beside a scene's annotation.json (annotate writes it, and names
#: it in annotation.json's ``unexplained_mask``).
UNEXPLAINED_MASK = "unexplained.png"

__all__ = ["SYMMETRY_CLASSES", "Symmetry"]  # re-exported: object.yaml records use them


@dataclass(frozen=True)
class DepthSpec:
    """Where depth maps live: the pixel grid/frame of ``camera``, ``scale`` mm per unit, and
    optionally ``background``, a depth map of the empty bin or support (a file name relative
    to the dataset folder, same grid and scale)."""

    camera: str
    scale: float
    background: str | None = None


#: The one image flip a rig camera can declare (``flip: horizontal``): a mirrored camera.
FLIP_HORIZONTAL = "horizontal"


def orient_image(image: np.ndarray, flipped: bool) -> np.ndarray:
    """A camera's image as stored turned into the image its calibration describes, or back
    (the mirror is its own inverse): flipped left to right for a camera with ``flip:
    horizontal`` (a webcam in "selfie" mode), unchanged otherwise."""
    return np.ascontiguousarray(image[:, ::-1]) if flipped else image


@dataclass(frozen=True)
class Rig:
    """The calibrated cameras; ``cameras[0]`` is the reference frame of every pose.

    ``flipped``: names of the cameras whose stored images are mirrored (``flip: horizontal``
    in dataset.yaml); their calibration describes the images flipped back, which is what
    :meth:`Scene.read_image` returns.

    >>> from annotator import load_dataset
    >>> rig = load_dataset("sample_scenes").rig
    >>> [c.name for c in rig.cameras], rig.depth_camera.name
    (['left', 'right'], 'left')
    """

    cameras: tuple[Camera, ...]
    depth: DepthSpec | None = None
    flipped: frozenset[str] = frozenset()
    moving: bool = False  # ``rig.moving``: scenes are sequences of frames (FORMAT.md)

    def camera(self, name: str) -> Camera:
        """The camera called ``name`` (KeyError if none)."""
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise KeyError(name)

    @property
    def depth_camera(self) -> Camera | None:
        """The camera whose pixel grid the depth maps use, or None without depth."""
        return None if self.depth is None else self.camera(self.depth.camera)


@dataclass(frozen=True)
class Instance:
    """A physical copy of an object: ``marker_ids[k]`` is glued on site ``k``.

    ``sites``: where this copy's markers really are, (S, 4, 3) in the model frame (mm), in
    the order and shape of the object's ``markers.sites``, when they were measured
    (``annotator sites``: markers glued by hand land beside the layout); None: the layout.
    ``site_scenes``: per site, from how many scenes (a sequence's frames) ``annotator sites``
    measured it (0: left on the layout); None when not recorded.
    """

    name: str
    marker_ids: tuple[int, ...]
    sites: np.ndarray | None = field(default=None, compare=False, hash=False)
    site_scenes: tuple[int, ...] | None = None


@dataclass(frozen=True)
class MarkerRef:
    """Where a marker id is glued: object, instance and site index."""

    object: str
    instance: str
    site: int


@dataclass(eq=False)
class ObjectModel:
    """One object (part) of the dataset, read from ``objects/<name>/object.yaml``.

    >>> from annotator import load_dataset
    >>> part = load_dataset("sample_scenes").objects["bracket"]
    >>> part.name, part.mesh_path.name, len(part.instances)
    ('bracket', 'model.ply', 12)
    """

    name: str
    folder: Path
    mesh_path: Path
    symmetry: Symmetry
    markers: MarkerSites | None
    instances: tuple[Instance, ...]
    raw: dict[str, Any] = field(default_factory=dict)

    @cached_property
    def mesh(self) -> Mesh:
        """The part's mesh (loaded on first use; raises UserError if unreadable)."""
        return load_mesh(self.mesh_path)

    def site_corners(self, instance: str) -> np.ndarray:
        """(S, 4, 3) corners of every marker site of ``instance``: its measured sites if it
        has them, else the object's layout (KeyError for an unknown instance)."""
        sites = self.instance(instance).sites
        if sites is not None:
            return sites
        if self.markers is None:
            return np.zeros((0, 4, 3))
        return self.markers.corners

    def instance(self, name: str) -> Instance:
        """The instance called ``name`` (KeyError if none)."""
        for inst in self.instances:
            if inst.name == name:
                return inst
        raise KeyError(name)


#: The folder of a sequence's scene that holds one folder per frame (FORMAT.md, sequences).
FRAMES_DIR = "frames"


class Capture:
    """What one shot of the rig is on disk: a folder with an image per camera and an
    optional depth map (a fixed rig's scene, or one frame of a sequence)."""

    path: Path
    flipped: frozenset[str]

    def image_path(self, camera: Camera | str) -> Path:
        """Path of the intensity image of ``camera``."""
        name = camera if isinstance(camera, str) else camera.name
        return self.path / f"{name}.png"

    @property
    def depth_path(self) -> Path:
        return self.path / "depth.png"

    def read_image(self, camera: Camera) -> np.ndarray:
        """The camera's intensity image, as stored but flipped back for a mirrored camera
        (``flip: horizontal``); UserError if missing, corrupt or mis-sized."""
        from annotator.errors import UserError
        from annotator.io.images import read_image

        path = self.image_path(camera)
        img = read_image(path)
        if img.shape[1] != camera.width or img.shape[0] != camera.height:
            raise UserError(
                f"image is {img.shape[1]}x{img.shape[0]}, the rig says {camera.width}x{camera.height}",
                path=path,
            )
        return orient_image(img, camera.name in self.flipped)

    def read_depth(self, rig: Rig) -> np.ndarray | None:
        """The depth map in mm (NaN = no measurement), or None if the shot has none."""
        from annotator.errors import UserError
        from annotator.io.images import read_depth

        if rig.depth is None or not self.depth_path.exists():
            return None
        depth = read_depth(self.depth_path, rig.depth.scale)
        cam = rig.camera(rig.depth.camera)
        if depth.shape != (cam.height, cam.width):
            raise UserError(
                f"depth map is {depth.shape[1]}x{depth.shape[0]}, the rig says {cam.width}x{cam.height}",
                path=self.depth_path,
            )
        return depth


@dataclass(frozen=True)
class Frame(Capture):
    """One frame of a sequence: ``scenes/<scene>/frames/<name>/`` (FORMAT.md, sequences)."""

    scene: str
    name: str
    path: Path
    flipped: frozenset[str] = field(default=frozenset(), compare=False)

    @property
    def id(self) -> str:
        """``<scene>/<frame>``: how messages and exports name the frame."""
        return f"{self.scene}/{self.name}"


@dataclass(frozen=True)
class Scene(Capture):
    """A scene folder; the files in it are found by name (FORMAT.md layout).

    ``flipped``: the rig's mirrored cameras (:attr:`Rig.flipped`), whose images
    :meth:`read_image` flips, so that every reader of images gets them as calibrated.
    A moving rig's scene holds its images in :meth:`frames` instead.

    >>> from annotator import load_dataset
    >>> scene = load_dataset("sample_scenes").scene("000000")
    >>> scene.id, scene.annotation_path.name
    ('000000', 'annotation.json')
    """

    id: str
    path: Path
    flipped: frozenset[str] = field(default=frozenset(), compare=False)

    @property
    def gt_path(self) -> Path:
        return self.path / "gt.json"

    @property
    def annotation_path(self) -> Path:
        return self.path / "annotation.json"

    @property
    def review_path(self) -> Path:
        return self.path / "review.json"

    @property
    def unexplained_path(self) -> Path:
        return self.path / UNEXPLAINED_MASK

    @classmethod
    def relative(cls, scene_id: str) -> Scene:
        """The scene with its paths relative to the dataset's root (what a Ray task ships)."""
        return cls(scene_id, Path(SCENES_DIR) / scene_id)

    def frames(self) -> list[Frame]:
        """A sequence's frame folders (``frames/<frame>/``), in sorted order; empty for a
        fixed rig's scene."""
        folder = self.path / FRAMES_DIR
        if not folder.is_dir():
            return []
        return [
            Frame(self.id, p.name, p, self.flipped)
            for p in sorted(folder.iterdir())
            if p.is_dir() and not p.name.startswith(".")
        ]


@dataclass(eq=False)
class Dataset:
    """A dataset folder (FORMAT.md).

    >>> from annotator import load_dataset
    >>> ds = load_dataset("sample_scenes")
    >>> [s.id for s in ds.scenes()], sorted(ds.objects)
    (['000000', '000001', '000002', '000003'], ['bracket', 'brick', 'cylinder'])
    """

    root: Path
    name: str
    dictionary: str
    rig: Rig
    objects: dict[str, ObjectModel]
    raw: dict[str, Any] = field(default_factory=dict)

    def scenes(self) -> list[Scene]:
        """Every scene folder, in sorted order."""
        folder = self.root / SCENES_DIR
        if not folder.is_dir():
            return []
        return [
            Scene(p.name, p, self.rig.flipped)
            for p in sorted(folder.iterdir())
            if p.is_dir() and not p.name.startswith(".")
        ]

    def broken_scene_links(self) -> list[Path]:
        """Entries of ``scenes/`` that are symbolic links leading nowhere (dangling, or a
        loop): not scenes, but not to be passed over in silence either."""
        folder = self.root / SCENES_DIR
        if not folder.is_dir():
            return []
        return [
            p
            for p in sorted(folder.iterdir())
            if p.is_symlink() and not p.exists() and not p.name.startswith(".")
        ]

    def scene(self, scene_id: str) -> Scene:
        """The scene called ``scene_id`` (KeyError if absent)."""
        path = self.root / SCENES_DIR / scene_id
        if not path.is_dir():
            raise KeyError(scene_id)
        return Scene(scene_id, path, self.rig.flipped)

    def frame(self, unit: str) -> Frame:
        """A sequence's frame named ``<scene>/<frame>`` (as batch units and messages name
        it; the folder may be a Ray task's replica, holding only that frame's files)."""
        scene, name = unit.rsplit("/", 1)
        return Frame(
            scene, name, self.root / SCENES_DIR / scene / FRAMES_DIR / name, self.rig.flipped
        )

    @cached_property
    def background_depth(self) -> np.ndarray | None:
        """The depth (mm, NaN = none) of the empty bin or support declared as
        ``rig.depth.background``, or None; UserError if unreadable or of the wrong size."""
        from annotator.errors import UserError
        from annotator.io.images import read_depth

        spec = self.rig.depth
        if spec is None or spec.background is None:
            return None
        path = self.root / spec.background
        depth = read_depth(path, spec.scale)
        cam = self.rig.camera(spec.camera)
        if depth.shape != (cam.height, cam.width):
            raise UserError(
                f"background depth is {depth.shape[1]}x{depth.shape[0]}, the rig says "
                f"{cam.width}x{cam.height}",
                path=path,
            )
        return depth

    @cached_property
    def marker_table(self) -> dict[int, MarkerRef]:
        """Marker id -> (object, instance, site). Ids are unique across the dataset."""
        table: dict[int, MarkerRef] = {}
        for obj in self.objects.values():
            for inst in obj.instances:
                for site, mid in enumerate(inst.marker_ids):
                    table.setdefault(int(mid), MarkerRef(obj.name, inst.name, site))
        return table
