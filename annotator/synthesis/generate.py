"""Generating a synthetic dataset: parts, rig, scenes, and the FORMAT.md files.

Each scene is reproducible from ``(seed, scene index)`` alone, so scenes can be made in any
order by any number of worker processes and the dataset is the same byte for byte.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import trimesh

from annotator.dataset.materials import Material
from annotator.dataset.model import FORMAT_VERSION, SCENES_DIR, Instance, Rig
from annotator.dataset.poses import InstancePose, write_poses
from annotator.dataset.write import sites_to_yaml, write_dataset_yaml
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.geometry.transforms import invert
from annotator.io.atomic import write_json
from annotator.io.images import encode_depth, write_png
from annotator.markers.glue import random_glue
from annotator.markers.layout import MarkerLayout, assign_ids, place_markers
from annotator.markers.texture import dictionary_size, marker_bits
from annotator.occlusion import scene_visibility
from annotator.parts import Part, build_part
from annotator.parts.marking import write_object_files
from annotator.rendering.raycast import Hits, PlacedMesh, Rect
from annotator.synthesis.pbr.render import (
    BIN,
    TABLE,
    PbrSettings,
    render_images,
    structured_depth,
)
from annotator.synthesis.physics import Bin, drop_parts
from annotator.synthesis.rig import RigSetup, make_rig
from annotator.synthesis.shading import (
    Surface,
    View,
    finish_image,
    render_intensity,
    render_view,
)
from annotator.synthesis.stereo import ShadowMap, dot_pattern, pattern_image, stereo_depth

DICTIONARY = "DICT_4X4_1000"


@dataclass(frozen=True)
class SynthSettings:
    """Everything that defines a synthetic dataset (with the seed, it fixes every byte).

    >>> s = SynthSettings(scenes=2, seed=7)
    >>> s.scenes, s.size
    (2, (1280, 1024))
    """

    parts: tuple[str, ...] = ("bracket", "cylinder")
    scenes: int = 10
    instances: tuple[int, int] = (8, 20)
    seed: int = 0
    size: tuple[int, int] = (1280, 1024)
    clutter: int = 0
    noise: float = 2.0
    blur: float = 0.6
    depth: bool = True
    supersample: int = 3
    #: Markers glued by hand (mm, degrees): every marker of every instance moved in its own
    #: plane by N(0, glue[0]) along both axes and turned by N(0, glue[1]) about its normal,
    #: once per instance (the same in every scene). (0, 0): exactly on their sites.
    glue: tuple[float, float] = (0.0, 0.0)
    #: False: the parts are rendered bare, as if no marker were glued on them, while
    #: object.yaml still lists the sites and ids. Every random draw is made as with markers
    #: (the noise does not depend on what is drawn), so the same seed gives the same scene,
    #: pixel for pixel, away from the markers: the twin the marker removal is measured on.
    markers: bool = True
    #: Sequences (a moving rig, ``rig.moving: true``): each scene's parts are seen in this
    #: many frames along a hand-held path (:mod:`annotator.synthesis.sequence`); 0: a fixed rig.
    frames: int = 0
    #: Sequences: the fraction of each scene's frames taken with a long exposure (motion blur).
    motion_blur: float = 0.0
    #: The rig's cameras in dataset.yaml and the scenes: 2, or 1 (the reference camera alone,
    #: as an RGB-D sensor's colour camera: its depth still comes from the simulated stereo
    #: pair, whose second camera is then rendered for the depth only).
    cameras: int = 2
    #: ``lambert``: the fast ray-cast render (diffuse, lit from the camera); ``pbr``: Cycles
    #: (:mod:`annotator.synthesis.pbr`), with ``pbr``'s materials, lights, lens and sensor.
    render: str = "lambert"
    pbr: PbrSettings = PbrSettings()

    @property
    def structured_light(self) -> bool:
        """The depth map is the structured-light model's (a pbr render's default)."""
        return self.render == "pbr" and self.pbr.depth_model == "structured_light"


#: ``SynthSettings.render``'s values.
RENDERS = ("lambert", "pbr")


@dataclass
class DatasetPlan:
    """The parts with their marker layouts and instance pools, and the rig."""

    config: SynthSettings
    parts: list[Part]
    layouts: list[MarkerLayout]
    instances: list[list[Instance]]
    setup: RigSetup
    bin: Bin = field(default_factory=Bin)
    #: Where each instance's markers really are, per part and instance: (S, 4, 3), the
    #: layout itself unless the markers are glued (``SynthSettings.glue``).
    glued: list[list[np.ndarray]] = field(default_factory=list)


@dataclass
class SceneTiming:
    physics: float = 0.0
    rendering: float = 0.0
    depth: float = 0.0
    occlusion: float = 0.0


def plan_dataset(config: SynthSettings) -> DatasetPlan:
    """Build the parts, their marker layouts and enough physical instances for any scene."""
    if config.render not in RENDERS:
        raise UserError(f"unknown render {config.render!r} (valid: {', '.join(RENDERS)})")
    if config.render == "pbr":
        config.pbr.check(config.parts)
    parts = [build_part(name) for name in config.parts]
    pool = config.instances[1]
    # Every physical instance needs its own ids: cap the sites so that all fit the dictionary.
    max_sites = dictionary_size(DICTIONARY) // (pool * len(parts))
    if max_sites < 4:
        raise UserError(
            f"{pool} instances of {len(parts)} parts need more marker ids than {DICTIONARY} has "
            "(at most 4 sites each would not be enough): use fewer instances per scene"
        )
    layouts = [
        place_markers(p.mesh, size=p.marker_size, max_sites=max_sites, seed=config.seed)
        for p in parts
    ]
    instances, next_id = [], 0
    for layout in layouts:
        ids = assign_ids(len(layout.corners), pool, start=next_id)
        next_id += len(layout.corners) * pool
        instances.append([Instance(f"{k + 1:02d}", tuple(i)) for k, i in enumerate(ids)])
    setup = make_rig(*config.size, rng=np.random.default_rng(config.seed))
    glued = [
        [_glued(layout.corners, config, p, k) for k in range(len(insts))]
        for p, (layout, insts) in enumerate(zip(layouts, instances))
    ]
    return DatasetPlan(config, parts, layouts, instances, setup, glued=glued)


def _glued(corners: np.ndarray, config: SynthSettings, part: int, instance: int) -> np.ndarray:
    """Instance ``instance`` of part ``part``'s real sites (see ``SynthSettings.glue``)."""
    sigma_mm, sigma_deg = config.glue
    if sigma_mm == 0 and sigma_deg == 0:
        return corners
    rng = np.random.default_rng([config.seed, 1 << 20, part, instance])
    return random_glue(corners, sigma_mm=sigma_mm, sigma_deg=sigma_deg, rng=rng)[0]


#: Written by ``synth --glue``: the true sites of every instance (the truth the tests and
#: benchmarks measure ``annotator sites`` against).
GLUED_SITES = "glued_sites.json"


#: The empty bin's depth, as the sensor sees it (``rig.depth.background`` in dataset.yaml).
BACKGROUND_DEPTH = "background_depth.png"


def write_dataset_files(plan: DatasetPlan, root: Path) -> None:
    """dataset.yaml, objects/<part>/object.yaml and model.ply, and (with depth) the empty
    bin's depth map, simulated like the scenes' (the capture a user makes once per rig)."""
    for part, layout, insts in zip(plan.parts, plan.layouts, plan.instances):
        folder = root / "objects" / part.name
        folder.mkdir(parents=True, exist_ok=True)
        material = plan.config.pbr.material_of(part.name).name if _pbr(plan) else None
        write_object_files(folder, part, layout.sites, insts, material=material)
    if plan.config.glue != (0.0, 0.0):
        write_json(
            root / GLUED_SITES,
            {
                part.name: {i.name: sites_to_yaml(g) for i, g in zip(insts, glued)}
                for part, insts, glued in zip(plan.parts, plan.instances, plan.glued)
            },
        )
    rig = replace(written_rig(plan), moving=plan.config.frames > 0)
    # The empty bin's depth is a fixed rig's: a moving rig sees it from everywhere.
    if plan.config.depth and rig.depth is not None and not rig.moving:
        surfaces = _setting(plan)
        # Every camera of the simulated pair: a one-camera rig's depth still comes from both.
        views = [
            render_view(cam, invert(world_T_cam), surfaces, fixed=len(surfaces))
            for cam, world_T_cam in zip(plan.setup.rig.cameras, plan.setup.world_T_cams)
        ]
        rng = np.random.default_rng([plan.config.seed, 1 << 30])
        if plan.config.structured_light:
            depth = structured_depth(
                plan.setup,
                surfaces,
                _materials(plan, surfaces),
                views[0],
                rng,
                plan.config.pbr,
                fixed=len(surfaces),
            )
        else:
            depth = simulate_depth(
                plan.setup,
                surfaces,
                views,
                rng,
                pattern_seed=plan.config.seed + 7,
                fixed=len(surfaces),
            )
        write_png(root / BACKGROUND_DEPTH, encode_depth(depth, rig.depth.scale))
        rig = replace(rig, depth=replace(rig.depth, background=BACKGROUND_DEPTH))
    write_dataset_yaml(
        root,
        name=f"synthetic ({', '.join(plan.config.parts)})",
        dictionary=DICTIONARY,
        rig=rig,
        objects=[p.name for p in plan.parts],
        synth={
            k: v if not isinstance(v, tuple) else list(v)
            for k, v in plan.config.__dict__.items()
            # recorded only when used
            if not (k == "glue" and v == (0.0, 0.0))
            and not (k == "markers" and v)
            and not (k in ("frames", "motion_blur") and not plan.config.frames)
            and not (k == "cameras" and v == 2)
            and k not in ("render", "pbr")
        }
        | ({"render": "pbr", "pbr": plan.config.pbr.to_json()} if _pbr(plan) else {}),
    )


def _pbr(plan: DatasetPlan) -> bool:
    return plan.config.render == "pbr"


def _materials(plan: DatasetPlan, surfaces: Sequence[Surface]) -> list[Material]:
    """Each surface's material: the table's and the bin's, then each part's (by its mesh)."""
    by_mesh = {id(p.mesh): plan.config.pbr.material_of(p.name) for p in plan.parts}
    fixed = 1 + len(plan.bin.meshes())
    return [TABLE] + [
        by_mesh[id(s.mesh)] if k >= fixed else BIN for k, s in enumerate(surfaces[1:], 1)
    ]


def written_rig(plan: DatasetPlan) -> Rig:
    """The rig as dataset.yaml gives it: the simulated one's first ``config.cameras``."""
    rig = plan.setup.rig
    return replace(rig, cameras=rig.cameras[: plan.config.cameras])


def _box_mesh(size: np.ndarray) -> Mesh:
    b = trimesh.creation.box(size)
    return Mesh(np.asarray(b.vertices), np.asarray(b.faces, dtype=np.int32))


def _setting(plan: DatasetPlan) -> list[Surface]:
    """The table and the bin, without parts."""
    table = np.eye(4)
    table[2, 3] = -plan.bin.wall - 5.0
    surfaces: list[Surface] = [
        Surface(_box_mesh(np.array([2000.0, 2000.0, 10.0])), table, albedo=0.3)
    ]
    for centre, size in plan.bin.meshes():
        T = np.eye(4)
        T[:3, 3] = centre
        surfaces.append(Surface(_box_mesh(size), T, albedo=0.45))
    return surfaces


@dataclass(frozen=True)
class BinContents:
    """What lies in a scene's bin: the instances (part index, copy index) and the clutter's
    parts, the meshes dropped in that order, and each one's pose (None: fell out)."""

    chosen: list[tuple[int, int]]
    meshes: list[Mesh]
    world_T: list[np.ndarray | None]
    clutter: tuple[int, ...] = ()  # the clutter's part indices (after the instances' meshes)


def make_scene(
    plan: DatasetPlan, index: int, folder: Path, *, progress: bool = False
) -> tuple[list[InstancePose], SceneTiming]:
    """Simulate, render and write scene ``index`` into ``folder``; return its true poses
    (``progress``: a bar per pbr image)."""
    # One generator for the whole scene, drawn in a fixed order: the same seed and index
    # make the same scene.
    rng = np.random.default_rng([plan.config.seed, index])
    timing = SceneTiming()
    t0 = time.perf_counter()
    contents = fill_bin(plan, rng)
    timing.physics = time.perf_counter() - t0
    staged = stage_bin(plan, contents)
    views = write_shot(plan, staged, folder, rng, timing, index=index, progress=progress)
    staged_occlusion(plan, staged, views, timing)
    write_poses(folder / "gt.json", staged.poses, format=FORMAT_VERSION)
    return staged.poses, timing


#: ``smear(k, camera, image, view)``: what happens to camera ``k``'s rendered image (float32,
#: 0..1) before the sensor's blur and noise (a sequence's motion blur).
Smear = Callable[[int, Camera, np.ndarray, View], np.ndarray]


def write_shot(
    plan: DatasetPlan,
    staged: _Staged,
    folder: Path,
    rng: np.random.Generator,
    timing: SceneTiming,
    *,
    smear: Smear | None = None,
    index: int = 0,
    progress: bool = False,
) -> list[View]:
    """Render what ``plan``'s rig sees of ``staged`` into ``folder`` (each camera's image,
    and with depth the simulated and exact depth maps), timed into ``timing``; the views.
    ``index``: the scene's (Cycles' seed); ``progress``: a bar per pbr image."""
    t0 = time.perf_counter()
    if _pbr(plan):
        if smear is not None:
            raise UserError("--render pbr makes fixed-rig scenes only (no sequences)")
        views = _write_pbr_images(plan, staged, folder, rng, index=index, progress=progress)
    else:
        views = _write_images(plan, staged, folder, rng, smear=smear)
    timing.rendering = time.perf_counter() - t0
    if plan.config.depth:
        t0 = time.perf_counter()
        _write_depth(plan, staged, views, folder, rng)
        timing.depth = time.perf_counter() - t0
    return views


def staged_occlusion(
    plan: DatasetPlan, staged: _Staged, views: list[View], timing: SceneTiming
) -> None:
    """Set the true occlusion rates of ``staged.poses`` (:func:`add_true_occlusion`) as the
    rig of ``plan`` saw them in ``views``, timed into ``timing``."""
    t0 = time.perf_counter()
    poses = staged.poses
    meshes = [plan.parts[plan.config.parts.index(p.object)].mesh for p in poses]
    # The posed parts follow the fixed surfaces: their casts serve the occlusion rates.
    rig = written_rig(plan)
    casts = {cam.name: view.own[: len(poses)] for cam, view in zip(rig.cameras, views)}
    add_true_occlusion(rig, poses, meshes, views[0].hits.depth, casts=casts)
    timing.occlusion = time.perf_counter() - t0


def fill_bin(plan: DatasetPlan, rng: np.random.Generator) -> BinContents:
    """Which physical instances are in the bin (a random part per instance, distinct
    copies) and the clutter, dropped into it."""
    cfg = plan.config
    n = int(rng.integers(cfg.instances[0], cfg.instances[1] + 1))
    chosen: list[tuple[int, int]] = []
    counts = [0] * len(plan.parts)
    for p in rng.integers(0, len(plan.parts), size=n):
        chosen.append((int(p), counts[p]))
        counts[p] += 1
    clutter = [int(p) for p in rng.integers(0, len(plan.parts), size=cfg.clutter)]
    meshes = [plan.parts[p].mesh for p, _ in chosen] + [plan.parts[p].mesh for p in clutter]
    world_T = drop_parts(meshes, bin=plan.bin, rng=rng)
    return BinContents(chosen, meshes, world_T, tuple(clutter))


@dataclass(frozen=True)
class _Staged:
    """A scene ready to render: its surfaces (the first ``fixed`` of them the setting, then
    the instances with their markers, then the clutter) and the instances' true poses in
    the reference camera."""

    surfaces: list[Surface]
    fixed: int
    poses: list[InstancePose]


def stage_bin(plan: DatasetPlan, contents: BinContents) -> _Staged:
    """The surfaces of the setting and of everything that stayed in the bin."""
    surfaces = _setting(plan)
    fixed = len(surfaces)
    poses: list[InstancePose] = []
    for k, (p, copy) in enumerate(contents.chosen):
        T = contents.world_T[k]
        if T is None:
            continue
        inst = plan.instances[p][copy]
        if plan.config.markers:
            bits = np.stack([marker_bits(DICTIONARY, m) for m in inst.marker_ids])
            corners = plan.glued[p][copy][: len(inst.marker_ids)]
            surfaces.append(Surface(plan.parts[p].mesh, T, 0.8, corners, bits))
        else:
            surfaces.append(Surface(plan.parts[p].mesh, T, 0.8))
        cam_T = plan.setup.ref_T_world @ T
        poses.append(InstancePose(plan.parts[p].name, inst.name, cam_T[:3, :3], cam_T[:3, 3]))
    for k in range(len(contents.chosen), len(contents.meshes)):
        T = contents.world_T[k]
        if T is not None:
            surfaces.append(Surface(contents.meshes[k], T, 0.7))
    return _Staged(surfaces, fixed, poses)


def _write_images(
    plan: DatasetPlan,
    staged: _Staged,
    folder: Path,
    rng: np.random.Generator,
    *,
    smear: Smear | None = None,
) -> list[View]:
    """Each camera's image, blurred and noisy, into ``folder``; the views rendered (those of
    the cameras not written too, for the depth)."""
    cfg = plan.config
    views = []
    for k, (cam, world_T_cam) in enumerate(zip(plan.setup.rig.cameras, plan.setup.world_T_cams)):
        if k >= cfg.cameras:
            views.append(render_view(cam, invert(world_T_cam), staged.surfaces, fixed=staged.fixed))
            continue
        img, view = render_intensity(
            cam,
            invert(world_T_cam),
            staged.surfaces,
            supersample=cfg.supersample,
            fixed=staged.fixed,
        )
        if smear is not None:
            img = smear(k, cam, img, view)
        write_png(
            folder / f"{cam.name}.png", finish_image(img, blur=cfg.blur, noise=cfg.noise, rng=rng)
        )
        views.append(view)
    return views


def _write_pbr_images(
    plan: DatasetPlan,
    staged: _Staged,
    folder: Path,
    rng: np.random.Generator,
    *,
    index: int,
    progress: bool,
) -> list[View]:
    """Each written camera's Cycles image into ``folder``; every camera's centre-ray view
    (the truth, the depth and the occlusion rates are our ray caster's, as in the default
    render)."""
    cfg = plan.config
    views = [
        render_view(cam, invert(world_T_cam), staged.surfaces, fixed=staged.fixed)
        for cam, world_T_cam in zip(plan.setup.rig.cameras, plan.setup.world_T_cams)
    ]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=100, desc=f"pbr {index:06d}", leave=False, unit="%")

    def step(fraction: float) -> None:
        if bar is not None:
            bar.n = round(100 * fraction)
            bar.refresh()

    try:
        images = render_images(
            plan.setup,
            plan.setup.rig.cameras[: cfg.cameras],
            staged.surfaces,
            _materials(plan, staged.surfaces),
            cfg.pbr,
            seed=(cfg.seed * 100003 + index) % (1 << 31),
            rng=rng,
            progress=step,
            markers=cfg.markers,
        )
    finally:
        if bar is not None:
            bar.close()
    for name, img in images.items():
        write_png(folder / f"{name}.png", img)
    return views


def _write_depth(
    plan: DatasetPlan, staged: _Staged, views: list[View], folder: Path, rng: np.random.Generator
) -> None:
    """The simulated sensor's depth map, and the exact one."""
    depth_spec = plan.setup.rig.depth
    assert depth_spec is not None  # make_rig always gives the rig a depth camera
    if plan.config.structured_light:
        depth = structured_depth(
            plan.setup,
            staged.surfaces,
            _materials(plan, staged.surfaces),
            views[0],
            rng,
            plan.config.pbr,
            fixed=staged.fixed,
        )
    else:
        depth = simulate_depth(
            plan.setup,
            staged.surfaces,
            views,
            rng,
            pattern_seed=plan.config.seed + 7,
            fixed=staged.fixed,
        )
    write_png(folder / "depth.png", encode_depth(depth, depth_spec.scale))
    # The exact depth of everything (parts, bin, clutter), for comparison with the sensor's.
    write_png(folder / "depth_ideal.png", encode_depth(views[0].hits.depth, depth_spec.scale))


def add_true_occlusion(
    rig: Rig,
    poses: list[InstancePose],
    meshes: list[Mesh],
    ideal_depth: np.ndarray,
    *,
    casts: Mapping[str, Sequence[tuple[Rect, Hits] | None]] | None = None,
) -> None:
    """Set each pose's true ``occlusion`` (``{"rate", "per_camera"}``): the posed instances
    occlude each other, and the exact depth of everything else (bin walls, clutter) hides
    what lies behind it. ``casts``: the instances' own casts per camera, when the renderer
    made them (see :func:`scene_visibility`)."""
    vis = scene_visibility(rig, meshes, [p.T for p in poses], depth=ideal_depth, casts=casts)
    for p, v in zip(poses, vis):
        p.extra["occlusion"] = {
            "rate": round(v.occlusion, 4),
            "per_camera": {c.camera: round(c.occlusion, 4) for c in v.cameras},
        }


def simulate_depth(
    setup: RigSetup,
    surfaces: list[Surface],
    views: list,
    rng: np.random.Generator,
    *,
    pattern_seed: int,
    fixed: int = 0,
) -> np.ndarray:
    """Active-stereo depth on the reference camera's pixel grid (mm, NaN = hole). ``fixed``:
    the leading surfaces that are the same in every scene (see :func:`render_view`)."""
    w, h = setup.projector_size
    pattern = dot_pattern(w, h, seed=pattern_seed)
    projector_T_world = invert(setup.world_T_projector)
    shadows = ShadowMap.render(
        Camera("projector", w, h, setup.projector_K),
        [PlacedMesh(s.mesh, projector_T_world @ s.world_T_model) for s in surfaces],
        fixed=fixed,
    )
    imgs = []
    for cam, world_T_cam, view in zip(setup.rig.cameras, setup.world_T_cams, views):
        img = pattern_image(
            view,
            cam,
            world_T_cam,
            projector_T_world=projector_T_world,
            projector_K=setup.projector_K,
            pattern=pattern,
            shadows=shadows,
        )
        imgs.append(finish_image(img, blur=0.5, noise=1.5, rng=rng))
    ideal = views[0].hits.depth
    finite = ideal[np.isfinite(ideal)]
    z_range = (float(finite.min()) - 20.0, float(finite.max()) + 20.0)
    return stereo_depth(
        imgs[0], imgs[1], setup.rig.cameras[0], setup.rig.cameras[1], z_range=z_range
    )


@dataclass(frozen=True)
class SceneJob:
    """Make one scene of a dataset being written in ``root`` (picklable for worker processes)."""

    config: SynthSettings
    root: str
    #: A progress bar per pbr image.
    progress: bool = False

    def prepare(self) -> None:
        """Plan the dataset (parts, rig, ray tables) once, before workers are forked."""
        plan = cached_plan(self.config)
        for cam in plan.setup.rig.cameras:
            cam.pixel_rays()

    # What a scene's work reads and writes, relative to ``root`` (for --ray): a scene is made
    # from the configuration alone, and everything in its folder is its output.

    def shared_files(self) -> list[str]:
        """None: the parts and the rig are planned from the configuration."""
        return []

    def scene_files(self, scene_id: str) -> list[str]:
        """None: the scene is made from the configuration and its index."""
        return []

    def output_files(self, scene_id: str) -> list[str]:
        """Every file of the scene's folder."""
        return [f"scenes/{scene_id}/"]

    def __call__(self, scene_id: str) -> dict:
        plan = cached_plan(self.config)
        folder = Path(self.root) / SCENES_DIR / scene_id
        folder.mkdir(parents=True, exist_ok=True)
        poses, timing = make_scene(plan, int(scene_id), folder, progress=self.progress)
        return {"instances": len(poses), **timing.__dict__}


_PLANS: dict[SynthSettings, DatasetPlan] = {}


def cached_plan(config: SynthSettings) -> DatasetPlan:
    """:func:`plan_dataset` of ``config``, planned once per process (the jobs of every
    scene, and the driver writing the dataset files, share it)."""
    if config not in _PLANS:
        _PLANS[config] = plan_dataset(config)
    return _PLANS[config]
