"""Synthetic twins of annotated scenes (the paper's section 5): the same rig, the annotated
poses, the markers, and the depth sensor simulated as ``annotator synth`` does, so that real
and simulated data can be compared scene by scene.

The *setting* (what is not a part) comes from the dataset's background depth
(``rig.depth.background``, the empty bin) turned into a surface: every 4th pixel of the depth
camera back-projected, neighbours joined into triangles except across depth steps of more
than 8 mm (a bin's rim seen from above is a step, not a slope). Without a background depth, it
is the support plane fitted to the scene's own measured depth
(:func:`annotator.annotation.completeness.fit_support_plane`), as a 2 m square.

The projector of the simulated sensor sits midway between the first two cameras, looking
along the reference camera's axis (as in ``synth``). Images get the renderer's default blur
and noise. A twin dataset is a dataset: the same objects and rig, and per scene the two
images, ``depth.png`` (simulated), ``depth_ideal.png`` (exact) and ``gt.json`` holding the
annotated poses, so that the twin's ground truth *is* the annotation.

A moving rig's sequence (FORMAT.md, sequences) has a twin frame for every posed frame a
reviewer did not reject: the instance poses (scene frame) taken through the frame's
``scene_T_rig`` and rendered as above into ``frames/<frame>/``, the setting the support plane
fitted to that frame's own measured depth (a background depth is a fixed rig's). The twin's
gt.json holds the poses in the scene frame and ``frames`` with each twin frame's
``scene_T_rig`` and the instances in its view (``instances``: occlusion per camera), each
instance's ``occlusion`` the least any frame saw, as ``synth --frames`` writes it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset import Dataset, InstancePose, Scene
from annotator.dataset.frames import poses_in_frame
from annotator.dataset.model import FORMAT_VERSION, FRAMES_DIR, SCENES_DIR, Capture, orient_image
from annotator.dataset.records import FramePose, frames_to_json
from annotator.geometry.mesh import Mesh
from annotator.io.images import encode_depth, write_png
from annotator.markers.dictionary import is_predefined
from annotator.markers.texture import marker_bits
from annotator.synthesis.rig import RigSetup, look_at
from annotator.synthesis.shading import Surface, finish_image, render_intensity, render_view

BACKGROUND_ALBEDO = 0.45
PART_ALBEDO = 0.8
MESH_STEP = 4
#: A one-camera rig's simulated stereo partner: this far to its right (mm), as synth's rig.
STEREO_BASELINE_MM = 100.0
STEP_MM = 8.0


def twin_setup(ds: Dataset) -> RigSetup:
    """The dataset's rig in a world frame that is the reference camera's, with a projector
    midway between the first two cameras. A rig of one camera with depth (an RGB-D sensor's
    colour camera) gets the simulated stereo pair's second camera, :data:`STEREO_BASELINE_MM`
    to its right, rendered for the depth only (as ``synth --cameras 1`` does)."""
    rig = ds.rig
    if len(rig.cameras) == 1 and rig.depth is not None:
        ref = rig.cameras[0]
        shift = np.eye(4)
        shift[0, 3] = STEREO_BASELINE_MM
        partner = replace(ref, name=f"{ref.name}.stereo", rig_T_cam=ref.rig_T_cam @ shift)
        rig = replace(rig, cameras=(ref, partner))
    cams = rig.cameras
    world_T_cams = tuple(c.rig_T_cam for c in cams)
    centre = 0.5 * (world_T_cams[0][:3, 3] + world_T_cams[min(1, len(cams) - 1)][:3, 3])
    T = look_at(centre, centre + np.array([0.0, 0.0, 500.0]))
    w, h = cams[0].width, cams[0].height
    fp = w * 0.9
    K = np.array([[fp, 0, (w - 1) / 2], [0, fp, (h - 1) / 2], [0, 0, 1.0]])
    return RigSetup(rig, world_T_cams, T, K, (w, h))


def background_mesh(ds: Dataset, scene: Capture) -> Mesh | None:
    """The setting of ``scene`` (a fixed rig's scene, or one frame of a sequence) as a mesh
    in the reference camera's frame (see the module docstring): the dataset's background,
    the same for every scene (made once), or the plane fitted to the shot's own measured
    depth (always, for a moving rig's frame)."""
    from annotator.annotation.completeness import fit_support_plane

    cam = ds.rig.depth_camera
    if cam is None:  # no depth: neither a background depth nor the scene's
        return None
    depth = None if ds.rig.moving else ds.background_depth
    if depth is not None:
        hit = _BACKGROUND.get(id(depth))
        if hit is None or hit[0] is not depth:
            rays = cam.pixel_rays(MESH_STEP)
            z = depth[::MESH_STEP, ::MESH_STEP]
            pts = rays * z[..., None]
            pts = pts @ cam.rig_T_cam[:3, :3].T + cam.rig_T_cam[:3, 3]
            _BACKGROUND.clear()
            hit = _BACKGROUND[id(depth)] = (depth, _grid_mesh(pts, z))
        return hit[1]
    measured = scene.read_depth(ds.rig)
    if measured is None:
        return None
    plane = fit_support_plane(cam.pixel_rays(2) * measured[::2, ::2, None])
    if plane is None:
        return None
    n, d = plane
    n = cam.rig_T_cam[:3, :3] @ n
    d = d + float(n @ cam.rig_T_cam[:3, 3])
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    c = n * d
    corners = np.array(
        [c + a * u + b * v for a, b in ((-1e3, -1e3), (1e3, -1e3), (1e3, 1e3), (-1e3, 1e3))]
    )
    # Wound so that the faces look back at the camera (n points away from it).
    return Mesh(corners, np.array([[0, 2, 1], [0, 3, 2]], np.int32))


_BACKGROUND: dict[int, tuple[np.ndarray, Mesh]] = {}


def _grid_mesh(pts: np.ndarray, z: np.ndarray) -> Mesh:
    """Triangles between neighbouring grid points, none across depth steps or holes."""
    h, w = z.shape
    ok = np.isfinite(z)
    idx = np.arange(h * w).reshape(h, w)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    za, zb, zc, zd = z[:-1, :-1], z[:-1, 1:], z[1:, :-1], z[1:, 1:]
    oka, okb, okc, okd = ok[:-1, :-1], ok[:-1, 1:], ok[1:, :-1], ok[1:, 1:]
    faces = []
    for (i, j, k), (zi, zj, zk), good in (
        ((a, c, b), (za, zc, zb), oka & okc & okb),
        ((b, c, d), (zb, zc, zd), okb & okc & okd),
    ):
        with np.errstate(invalid="ignore"):
            spread = np.maximum(np.maximum(zi, zj), zk) - np.minimum(np.minimum(zi, zj), zk)
        keep = good & (spread < STEP_MM)
        faces.append(np.stack([i[keep], j[keep], k[keep]], axis=1))
    vertices = np.nan_to_num(pts.reshape(-1, 3))
    return Mesh(vertices, np.concatenate(faces).astype(np.int32))


@dataclass(frozen=True)
class TwinSettings:
    blur: float = 0.6
    noise: float = 2.0
    supersample: int = 3
    seed: int = 0


def make_twin_scene(
    ds: Dataset,
    scene: Scene,
    poses: list[InstancePose],
    out: Path,
    *,
    settings: TwinSettings = TwinSettings(),
) -> None:
    """Render the twin of ``scene`` with ``poses`` into the scene folder ``out``."""
    from annotator.dataset.poses import write_poses

    rng = np.random.default_rng([settings.seed, int.from_bytes(scene.id.encode()[:8], "little")])
    truth = _render_shot(ds, scene, poses, out, settings=settings, rng=rng)
    write_poses(Scene("", out).gt_path, truth, format=FORMAT_VERSION)


def _render_shot(
    ds: Dataset,
    shot: Capture,
    poses: list[InstancePose],
    out: Path,
    *,
    settings: TwinSettings,
    rng: np.random.Generator,
) -> list[InstancePose]:
    """Render one shot of the rig (``poses`` in its reference camera) into the folder
    ``out``: an image per camera and the simulated and exact depth; the poses rendered,
    each with its true ``occlusion`` in the shot."""
    from annotator.synthesis.generate import add_true_occlusion, simulate_depth

    setup = twin_setup(ds)
    surfaces: list[Surface] = []
    bg = background_mesh(ds, shot)
    if bg is not None:
        surfaces.append(Surface(bg, np.eye(4), BACKGROUND_ALBEDO))
    fixed = len(surfaces)  # the background, rendered once per camera while it stays the same
    for p in poses:
        obj = ds.objects[p.object]
        ids = obj.instance(p.instance).marker_ids
        sites = obj.site_corners(p.instance)[: len(ids)] if obj.markers is not None else None
        bits = np.stack([marker_bits(ds.dictionary, m) for m in ids]) if ids else None
        surfaces.append(Surface(obj.mesh, p.T, PART_ALBEDO, sites, bits))
    views = []
    for k, (cam, world_T_cam) in enumerate(zip(setup.rig.cameras, setup.world_T_cams)):
        if k >= len(ds.rig.cameras):  # the stereo partner of a one-camera rig: depth only
            views.append(render_view(cam, np.linalg.inv(world_T_cam), surfaces, fixed=fixed))
            continue
        img, view = render_intensity(
            cam,
            np.linalg.inv(world_T_cam),
            surfaces,
            supersample=settings.supersample,
            fixed=fixed,
        )
        # Stored as the camera stores its images (mirrored for a flip: horizontal camera).
        write_png(
            out / f"{cam.name}.png",
            orient_image(
                finish_image(img, blur=settings.blur, noise=settings.noise, rng=rng),
                cam.name in ds.rig.flipped,
            ),
        )
        views.append(view)
    if ds.rig.depth is not None:
        depth = simulate_depth(
            setup, surfaces, views, rng, pattern_seed=settings.seed + 7, fixed=fixed
        )
        ref = [c.name for c in ds.rig.cameras].index(ds.rig.depth.camera)
        if ref != 0:
            raise ValueError("twins simulate depth on the reference camera's grid only")
        write_png(Scene("", out).depth_path, encode_depth(depth, ds.rig.depth.scale))
        write_png(out / "depth_ideal.png", encode_depth(views[0].hits.depth, ds.rig.depth.scale))
    truth = [InstancePose(p.object, p.instance, p.R, p.t) for p in poses]
    meshes = [ds.objects[p.object].mesh for p in truth]
    casts = {cam.name: view.own for cam, view in zip(ds.rig.cameras, views)}
    add_true_occlusion(ds.rig, truth, meshes, views[0].hits.depth, casts=casts)
    return truth


def make_twin_sequence(
    ds: Dataset,
    scene: Scene,
    poses: list[InstancePose],
    frames: Mapping[str, np.ndarray],
    out: Path,
    *,
    settings: TwinSettings = TwinSettings(),
) -> None:
    """Render the twin of a moving rig's ``scene`` into the scene folder ``out``: every
    frame of ``frames`` (frame -> ``scene_T_rig``) into ``out/frames/<frame>/`` with
    ``poses`` (scene frame) as that frame's rig sees them, and gt.json with the poses in the
    scene frame and ``frames`` (see the module docstring).

    Raises:
        KeyError: a frame of ``frames`` that the scene has no folder for.
    """
    from annotator.dataset.poses import write_poses

    folders = {f.name: f for f in scene.frames()}
    entries: dict[str, FramePose] = {}
    seen: dict[str, list[dict[str, Any]]] = {p.key: [] for p in poses}
    sid = int.from_bytes(scene.id.encode()[:8], "little")
    for name in sorted(frames):
        T = np.asarray(frames[name], dtype=np.float64).reshape(4, 4)
        fid = int.from_bytes(name.encode()[:8], "little")
        rng = np.random.default_rng([settings.seed, sid, fid])
        folder = out / FRAMES_DIR / name
        folder.mkdir(parents=True, exist_ok=True)
        truth = _render_shot(
            ds, folders[name], poses_in_frame(poses, T), folder, settings=settings, rng=rng
        )
        in_view = {}
        for p in truth:
            occ = p.extra["occlusion"]
            seen[p.key].append(occ)
            if occ["rate"] < 1.0:
                in_view[p.key] = {"occlusion": occ["per_camera"]}
        entries[name] = FramePose(name, T, instances=in_view)
    truth = [InstancePose(p.object, p.instance, p.R, p.t) for p in poses]
    for p in truth:
        occs = seen[p.key]
        if occs:
            p.extra["occlusion"] = {
                "rate": min(o["rate"] for o in occs),
                "per_camera": {
                    c: min(o["per_camera"][c] for o in occs) for c in occs[0]["per_camera"]
                },
            }
    write_poses(
        Scene("", out).gt_path, truth, format=FORMAT_VERSION, frames=frames_to_json(entries)
    )


@dataclass(frozen=True)
class TwinJob:
    """Render the twin of one scene of ``root`` into ``out`` (picklable, for workers).

    ``poses`` holds, per scene id, the poses to render (the accepted annotation; a
    sequence's in the scene frame); ``frames``, per sequence, the frames to render, each with
    its ``scene_T_rig`` (16 floats, row-major)."""

    root: str
    out: str
    poses: dict[str, list[tuple[str, str, list[float], list[float]]]]
    settings: TwinSettings = TwinSettings()
    frames: dict[str, dict[str, list[float]]] = field(default_factory=dict)

    def prepare(self) -> None:
        """Load the dataset and tabulate the cameras' rays once, before workers fork."""
        from annotator.dataset import cached_dataset

        ds = cached_dataset(self.root)
        for cam in ds.rig.cameras:
            cam.pixel_rays()
            cam.pixel_rays(MESH_STEP)

    # What a scene's work reads (relative to ``root``) and writes (relative to ``out``), for
    # --ray: the poses travel with the job.

    def shared_files(self) -> list[str]:
        """The dataset description (dataset.yaml, objects, background depth)."""
        from annotator.dataset import cached_dataset
        from annotator.runner.files import description_files

        return description_files(cached_dataset(self.root))

    def scene_files(self, scene_id: str) -> list[str]:
        """The scene's measured depth (the support plane is fitted to it when the dataset
        has no background depth); a sequence's, every rendered frame's."""
        if scene_id in self.frames:
            return [f"scenes/{scene_id}/{FRAMES_DIR}/{f}/depth.png" for f in self.frames[scene_id]]
        return [f"scenes/{scene_id}/depth.png"]

    def output_files(self, scene_id: str) -> list[str]:
        """Every file of the twin scene's folder."""
        return [f"scenes/{scene_id}/"]

    def __call__(self, scene_id: str) -> dict:
        from annotator.dataset import cached_dataset

        ds = cached_dataset(self.root)
        poses = [
            InstancePose(o, i, np.asarray(R, float).reshape(3, 3), np.asarray(t, float))
            for o, i, R, t in self.poses[scene_id]
        ]
        folder = Path(self.out) / SCENES_DIR / scene_id
        folder.mkdir(parents=True, exist_ok=True)
        if scene_id in self.frames:
            frames = {
                f: np.asarray(T, float).reshape(4, 4) for f, T in self.frames[scene_id].items()
            }
            make_twin_sequence(
                ds, ds.scene(scene_id), poses, frames, folder, settings=self.settings
            )
            return {"instances": len(poses), "frames": len(frames)}
        make_twin_scene(ds, ds.scene(scene_id), poses, folder, settings=self.settings)
        return {"instances": len(poses)}


def write_twin_description(ds: Dataset, out: Path) -> None:
    """The twin dataset's dataset.yaml, objects and background: the original's, unchanged."""
    import shutil

    shutil.copy2(ds.root / "dataset.yaml", out / "dataset.yaml")
    shutil.copytree(ds.root / "objects", out / "objects")
    # A custom dictionary file named relative to dataset.yaml travels with it.
    named = Path(str(ds.raw.get("markers", {}).get("dictionary", "")))
    if not is_predefined(str(named)) and not named.is_absolute() and (ds.root / named).is_file():
        (out / named).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ds.root / named, out / named)
    if ds.rig.depth is not None and ds.rig.depth.background is not None:
        target = out / ds.rig.depth.background
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ds.root / ds.rig.depth.background, target)
