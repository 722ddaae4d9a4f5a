"""``annotator check``: every problem of a dataset in one run, one line each naming its file.

On top of what :func:`annotator.dataset.read_dataset` finds in the YAML files, it checks the
meshes (readable), the marker sites (squares of the stated size whose corners and centre lie
on the mesh surface within ``SITE_TOLERANCE_MM``; ids inside the dictionary) and every scene
(an image per rig camera, readable, of the rig's size; depth maps only with a depth scale,
uint16 of the depth camera's size; gt.json, annotation.json and review.json well-formed).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from annotator.dataset.frames import frames_left_out, frames_line, scene_shots
from annotator.dataset.load import Problem, read_dataset, site_shape_problem
from annotator.dataset.model import Capture, Dataset, ObjectModel
from annotator.dataset.records import frames_from_json
from annotator.errors import UserError
from annotator.geometry.mesh import Mesh
from annotator.io.atomic import is_abandoned_folder, remove_abandoned_files

SITE_TOLERANCE_MM = 0.5
BROKEN_LINK = "a symbolic link that leads nowhere (dangling or a loop): not a scene"


@dataclass(frozen=True)
class CheckReport:
    """What ``annotator check`` found: every problem (one per file and fault; warnings
    among them) and how many scenes were looked at.

    >>> from annotator import check_dataset
    >>> report = check_dataset("sample_scenes")
    >>> report.scenes, report.errors
    (4, [])
    """

    problems: list[Problem]
    scenes: int

    @property
    def errors(self) -> list[Problem]:
        """The problems that make the dataset unusable (not warnings)."""
        return [p for p in self.problems if not p.warning]


def check_dataset(root: str | Path, *, annotations: bool = False) -> CheckReport:
    """All problems of the dataset at ``root`` and the number of scenes looked at; with
    ``annotations``, the warnings of every annotation.json too (as warning problems).

    >>> report = check_dataset("sample_scenes")
    >>> report.scenes, report.errors
    (4, [])
    """
    ds, problems = read_dataset(root)
    if ds is None:
        return CheckReport(problems, 0)
    problems += _check_objects(ds) + _no_objects_yet(ds) + _leftovers(ds)
    try:
        ds.background_depth  # noqa: B018  (cached property: reads and checks the file)
    except UserError as exc:
        problems.append(Problem(exc.path or ds.root / "dataset.yaml", exc.message))
    for link in ds.broken_scene_links():
        problems.append(Problem(link, BROKEN_LINK))
    n = 0
    for scene in ds.scenes():
        n += 1
        problems += _check_scene(ds, scene)
        if annotations and scene.annotation_path.exists():
            problems += _annotation_warnings(scene.annotation_path)
    return CheckReport(problems, n)


def _annotation_warnings(path: Path) -> list[Problem]:
    from annotator.dataset.records import SceneAnnotation

    try:
        ann = SceneAnnotation.read(path)
    except UserError:
        return []  # reported by _check_scene
    return [Problem(path, f"{w.kind}: {w.message}", warning=True) for w in ann.warnings]


def _check_objects(ds: Dataset) -> list[Problem]:
    out: list[Problem] = []
    for obj in ds.objects.values():
        if not obj.mesh_path.is_file():
            continue  # already reported by read_dataset
        try:
            mesh = obj.mesh
        except UserError as exc:
            out.append(Problem(obj.mesh_path, exc.message))
            continue
        out += _check_mesh(obj.mesh_path, mesh)
        if obj.markers is not None:
            out += _check_sites(obj, mesh)
    return out


def _check_mesh(path: Path, mesh: Mesh) -> list[Problem]:
    """The mesh is a solid (else a warning), closed (else a warning) and its faces turn
    outwards."""
    if mesh.is_flat:
        return [
            Problem(
                path,
                "mesh has no volume (its vertices lie on a plane or a line): occlusion rates "
                "hold, but `check --physics` and the physics of synthetic drops need a solid",
                warning=True,
            )
        ]
    if not mesh.is_watertight:
        return [
            Problem(
                path,
                "mesh is not watertight (open edges): occlusion rates and surface moments "
                "assume a closed surface",
                warning=True,
            )
        ]
    if mesh.signed_volume < 0:
        return [
            Problem(
                path,
                f"mesh is inside out (signed volume {mesh.signed_volume:.0f} mm^3): its "
                "faces must be counter-clockwise seen from outside; flip them",
            )
        ]
    return []


def _check_sites(obj: ObjectModel, mesh: Mesh) -> list[Problem]:
    """Every marker site, the layout's and the instances' own, lies on the mesh surface (a
    site that is not a square of the markers' size is reported by the dataset's reader)."""
    assert obj.markers is not None
    yaml_path = obj.folder / "object.yaml"
    size = obj.markers.size
    sites = [(f"markers.sites[{k}]", c) for k, c in enumerate(obj.markers.corners)]
    for inst in obj.instances:
        if inst.sites is not None:
            sites += [(f"instance {inst.name!r}: sites[{k}]", c) for k, c in enumerate(inst.sites)]
    out = []
    for where, c in sites:
        if site_shape_problem(c, size) is not None:
            continue  # reported by the dataset's reader
        dist = mesh.distance_to_surface(np.concatenate([c, c.mean(axis=0, keepdims=True)]))
        if dist.max() > SITE_TOLERANCE_MM:
            out.append(
                Problem(
                    yaml_path,
                    f"{where} is {dist.max():.2f} mm off the mesh surface (tolerance {SITE_TOLERANCE_MM} mm)",
                )
            )
    return out


def _check_capture(ds: Dataset, capture: Capture) -> list[Problem]:
    """A scene's (or a frame's) images and depth map: there, readable, of the rig's sizes."""
    out: list[Problem] = []
    for cam in ds.rig.cameras:
        try:
            capture.read_image(cam)
        except UserError as exc:
            out.append(Problem(exc.path or capture.image_path(cam), exc.message))
    declared = isinstance(ds.raw.get("rig"), dict) and ds.raw["rig"].get("depth") is not None
    if capture.depth_path.exists():
        if ds.rig.depth is None and declared:
            pass  # rig.depth is there but unusable: reported once, for dataset.yaml
        elif ds.rig.depth is None:
            out.append(
                Problem(
                    capture.depth_path,
                    "depth map present but dataset.yaml has no rig.depth (camera and scale)",
                )
            )
        else:
            try:
                capture.read_depth(ds.rig)
            except UserError as exc:
                out.append(Problem(exc.path or capture.depth_path, exc.message))
    return out


def _check_scene(ds: Dataset, scene) -> list[Problem]:
    from annotator.dataset.poses import InstancePose, read_pose_file
    from annotator.dataset.review import read_review
    from annotator.dataset.validity import pose_problem, same_place

    out: list[Problem] = []
    if ds.rig.moving:
        frames = scene.frames()
        if not frames:
            out.append(
                Problem(
                    scene.path,
                    "a moving rig's scene holds its images in frames/<frame>/: none found",
                )
            )
        for frame in frames:
            out += _check_capture(ds, frame)
    else:
        out += _check_capture(ds, scene)
    for path in (scene.gt_path, scene.annotation_path):
        if path.exists():
            try:
                poses, top = read_pose_file(path)
                frames = frames_from_json(top.get("frames"), path)  # every reader checks them
                if ds.rig.moving:
                    scene_shots(ds, scene, frames)
            except UserError as exc:
                out.append(Problem(path, exc.message))
                continue
            left = frames_left_out(frames)
            if left and path == scene.annotation_path:  # no export or evaluation takes them
                out.append(Problem(path, frames_line(left, len(frames)), warning=True))
            for p in poses:
                problem = pose_problem(ds, p)
                if problem is not None:
                    out.append(Problem(path, problem))
            out += [Problem(path, problem) for problem in same_place(ds, poses)]
    try:
        review = read_review(scene.review_path)
    except UserError as exc:
        out.append(Problem(scene.review_path, exc.message))
        review = None
    for key, edit in sorted((review.poses if review else {}).items()):
        obj, _, inst = key.partition("/")
        problem = pose_problem(ds, InstancePose(obj, inst, edit.R, edit.t))
        if problem is not None:
            out.append(Problem(scene.review_path, f"poses[{key!r}]: {problem}"))
    return out


def _leftovers(ds: Dataset) -> list[Problem]:
    """The partial files and folders that a command killed while writing left in the
    dataset (hidden; each write replaces a file whole, so nothing else is damaged)."""
    folders = [ds.root, ds.root / "scenes", ds.root / "objects"]
    for top in folders[1:]:
        if top.is_dir():
            folders += [p for p in top.iterdir() if p.is_dir() and not p.is_symlink()]
    for scene in list(folders):
        frames = scene / "frames"
        if frames.is_dir():
            folders += [p for p in frames.iterdir() if p.is_dir() and not p.is_symlink()]
    out = []
    for folder in folders:
        for p in remove_abandoned_files(folder, older_than_s=0, remove=False):
            out.append(
                Problem(
                    p,
                    "a partial file left by a command killed while writing it (the file it "
                    "was to replace is intact): delete it; the next write here removes it too",
                    warning=True,
                )
            )
        if folder.name.startswith(".") and is_abandoned_folder(folder):
            out.append(
                Problem(
                    folder,
                    "a partial folder left by a command killed while building it: delete it; "
                    "the next run of that command removes it too",
                    warning=True,
                )
            )
    return out


def _no_objects_yet(ds: Dataset) -> list[Problem]:
    """A warning for a dataset without objects (as ``ingest --rig-from-source`` makes one):
    usable, with nothing to annotate yet."""
    if ds.objects:
        return []
    return [
        Problem(
            ds.root / "dataset.yaml",
            "no objects yet: add objects/<name>/object.yaml (with its mesh and marker sites, "
            "`annotator markers`) and list each under objects",
            warning=True,
        )
    ]
