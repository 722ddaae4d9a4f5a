"""A synthetic scene's physically based images and structured-light depth.

:func:`render_images` hands the scene's surfaces (each with its :class:`Material`), its
printed markers, two area lights and the environment to Cycles, one distortion-free wide
camera per rig camera, then distorts (:mod:`.lens`) and exposes (:mod:`.sensor`) each image.
:func:`structured_depth` is the depth sensor's map (:mod:`.structured_light`), computed on
the exact geometry our own ray caster gives.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from annotator.dataset.materials import DEFAULT_MATERIAL, Material, material_named
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert
from annotator.rendering.raycast import PlacedMesh
from annotator.synthesis.pbr.cycles_job import (
    AreaLight,
    CyclesCamera,
    CyclesScene,
    Quality,
    render,
)
from annotator.synthesis.pbr.lens import wide_pinhole
from annotator.synthesis.pbr.sensor import SensorSettings, expose, exposure_scale, grey
from annotator.synthesis.pbr.structured_light import (
    Reflectance,
    StructuredLightSettings,
    structured_light_depth,
)
from annotator.synthesis.rig import RigSetup
from annotator.synthesis.shading import Surface, View
from annotator.synthesis.stereo import ShadowMap

#: The table under the bin and the bin itself (a dark grey plastic tote, as in most cells).
TABLE = Material("table", (0.3, 0.3, 0.3), roughness=0.6)
BIN = Material("bin", (0.07, 0.07, 0.075), roughness=0.5)

#: ``synth --depth-model``: the depth sensor simulated.
DEPTH_MODELS = ("structured_light", "stereo")


@dataclass(frozen=True)
class PbrSettings:
    """What ``synth --render pbr`` adds to a scene's settings.

    Attributes:
        quality: Cycles' sampling (samples, denoising).
        materials: ``(part, preset)`` pairs; a part not named is :data:`DEFAULT_MATERIAL`.
        lights: How many area lights above the bin (0, 1 or 2).
        light_power: Each light's power (W).
        environment: The uniform environment's strength (grey).
        dof: ``(focus distance mm, f-number)``, or None for a pinhole's infinite depth of field.
        sensor: Exposure and noise.
        depth_model: ``structured_light`` or ``stereo`` (the default render's active stereo).
        device: ``auto`` (a GPU when Cycles finds one), ``cpu`` or ``gpu``.
        threads: Cycles' threads (0: every core).
        pixel_pitch_mm: The sensor's pixel pitch: with the focal length in pixels it gives
            the lens' focal length, which sets the depth of field.
    """

    quality: Quality = Quality()
    materials: tuple[tuple[str, str], ...] = ()
    lights: int = 2
    light_power: float = 40.0
    environment: float = 0.25
    dof: tuple[float, float] | None = None
    sensor: SensorSettings = SensorSettings()
    depth_model: str = "structured_light"
    device: str = "auto"
    threads: int = 0
    pixel_pitch_mm: float = 0.0048
    structured_light: StructuredLightSettings = field(default_factory=StructuredLightSettings)

    def material_of(self, part: str) -> Material:
        """The preset of ``part`` (:data:`DEFAULT_MATERIAL` unless ``materials`` names one)."""
        name = dict(self.materials).get(part, DEFAULT_MATERIAL)
        return material_named(name, where=f"--material {part}")

    def check(self, parts: Sequence[str]) -> None:
        """Raise UserError for a material of an unknown part or preset, or a bad option."""
        for part, _ in self.materials:
            if part not in parts:
                raise UserError(
                    f"--material {part}: no such part in this synth (parts: {', '.join(parts)})"
                )
            self.material_of(part)
        if self.depth_model not in DEPTH_MODELS:
            raise UserError(
                f"unknown depth model {self.depth_model!r} (valid: {', '.join(DEPTH_MODELS)})"
            )
        if self.dof is not None and min(self.dof) <= 0:
            raise UserError(f"--dof needs a focus distance and an f-number above 0, not {self.dof}")
        if self.device not in ("auto", "cpu", "gpu"):
            raise UserError(f"unknown device {self.device!r} (valid: auto, cpu, gpu)")

    def to_json(self) -> dict:
        return {
            "samples": self.quality.samples,
            "denoise": self.quality.denoise,
            "materials": dict(self.materials),
            "lights": self.lights,
            "dof": None if self.dof is None else list(self.dof),
            "sensor_noise": self.sensor.noise,
            "depth_model": self.depth_model,
        }


#: A printed marker's white margin around its black border, in cells.
PAPER_MARGIN = 1.0
#: How far the paper floats above its site's plane (mm): enough for Cycles to tell the two
#: surfaces apart, small against what a pose is judged by (the sites are where the printed
#: corners are; a sheet 0.05 mm up moved the corners of an oblique marker by 0.1 px).
PAPER_LIFT = 0.002
#: The printed black and the paper's white (linear reflectance).
INK, PAPER_WHITE = 0.04, 0.85


def marker_quads(surface: Surface) -> tuple[np.ndarray, np.ndarray]:
    """The printed squares of ``surface``'s markers in the world (M, 4, 3), with their paper
    margin, lifted off the part just enough to lie on it where it curves; and their tiles
    (M, c+2, c+2) of printed grey."""
    if surface.sites is None or surface.bits is None or not len(surface.sites):
        return np.zeros((0, 4, 3)), np.zeros((0, 1, 1))
    sites = np.asarray(surface.sites, float)
    cells = surface.bits.shape[1]
    tl = sites[:, 0]
    ex, ey = sites[:, 1] - tl, sites[:, 3] - tl
    normal = np.cross(ey, ex)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    # A flat sheet on a curved part: lift it by the part's deepest reach above the site's
    # plane under the square, so the sheet is never inside the part.
    v = surface.mesh.vertices
    lift = np.zeros(len(sites))
    for k in range(len(sites)):
        rel = v - tl[k]
        s = rel @ ex[k] / (ex[k] @ ex[k])
        t = rel @ ey[k] / (ey[k] @ ey[k])
        d = rel @ normal[k]
        under = (s > -0.2) & (s < 1.2) & (t > -0.2) & (t < 1.2) & (np.abs(d) < 3.0)
        lift[k] = max(float(d[under].max(initial=0.0)), 0.0)
    m = PAPER_MARGIN / cells
    grow = np.array([[-m, -m], [1 + m, -m], [1 + m, 1 + m], [-m, 1 + m]])
    quads = (
        tl[:, None]
        + grow[None, :, :1] * ex[:, None]
        + grow[None, :, 1:] * ey[:, None]
        + (lift + PAPER_LIFT)[:, None, None] * normal[:, None]
    )
    world = quads @ surface.world_T_model[:3, :3].T + surface.world_T_model[:3, 3]
    tiles = np.full((len(sites), cells + 2, cells + 2), PAPER_WHITE, np.float32)
    tiles[:, 1:-1, 1:-1] = np.where(surface.bits > 0, PAPER_WHITE, INK)
    return world, tiles


def lights(setup: RigSetup, settings: PbrSettings) -> list[AreaLight]:
    """Up to two area lights above the bin, to either side of the rig, aimed at its centre."""
    height = float(setup.world_T_cams[0][2, 3]) + 150.0
    spots = [(-320.0, 180.0), (300.0, -200.0)][: settings.lights]
    return [
        AreaLight((x, y, height), (0.0, 0.0, 30.0), (250.0, 250.0), settings.light_power)
        for x, y in spots
    ]


def cycles_scene(
    surfaces: Sequence[Surface],
    materials: Sequence[Material],
    setup: RigSetup,
    settings: PbrSettings,
    *,
    markers: bool = True,
) -> CyclesScene:
    """Cycles' scene of ``surfaces``, each of ``materials``, with their printed markers."""
    scene = CyclesScene(lights=lights(setup, settings), environment=(1.0, settings.environment))
    quads, tiles = [], []
    for s, m in zip(surfaces, materials):
        scene.add(s.mesh, s.world_T_model, m)
        if markers:
            q, t = marker_quads(s)
            if len(q):
                quads.append(q)
                tiles.append(t)
    if quads:
        scene.marker_quads = np.concatenate(quads)
        scene.marker_tiles = np.concatenate(tiles)
    return scene


#: ``progress(fraction)`` of one scene's images.
Progress = Callable[[float], None]


def render_images(
    setup: RigSetup,
    cameras: Sequence[Camera],
    surfaces: Sequence[Surface],
    materials: Sequence[Material],
    settings: PbrSettings,
    *,
    seed: int,
    rng: np.random.Generator,
    progress: Progress | None = None,
    markers: bool = True,
) -> dict[str, np.ndarray]:
    """Each of ``cameras`` (the rig's first ones, in order) as the sensor reads it (uint8);
    ``markers`` False: the parts bare."""
    scene = cycles_scene(surfaces, materials, setup, settings, markers=markers)
    wides = [wide_pinhole(cam) for cam in cameras]
    dof = settings.dof
    jobs = [
        CyclesCamera(
            cam.name,
            setup.world_T_cams[k],
            w.f,
            (w.width, w.height),
            pixel_pitch_mm=settings.pixel_pitch_mm,
            focus_mm=None if dof is None else dof[0],
            fstop=None if dof is None else dof[1],
        )
        for k, (cam, w) in enumerate(zip(cameras, wides))
    ]
    names = [c.name for c in cameras]

    def step(camera: str, fraction: float) -> None:
        if progress is not None:
            k = names.index(camera) if camera in names else 0
            progress((k + fraction) / len(names))

    linear = render(
        scene,
        jobs,
        quality=settings.quality,
        seed=seed,
        device=settings.device,
        threads=settings.threads,
        progress=step,
    )
    out = {}
    scale = None
    for cam, w in zip(cameras, wides):
        radiance = w.remap(grey(linear[cam.name]))
        # One exposure for the rig (the reference camera's), as a triggered rig is set.
        scale = exposure_scale(radiance, settings.sensor) if scale is None else scale
        out[cam.name] = expose(radiance, settings.sensor, scale=scale, rng=rng)
    return out


def reflectance(view: View, materials: Sequence[Material]) -> Reflectance:
    """Per pixel of ``view`` its surface's reflectance; markers are paper."""
    inst = view.hits.instance
    table = np.array(
        [(m.diffuse, m.mirror, m.roughness) for m in materials] + [(0.0, 0.0, 1.0)], np.float32
    )
    per = table[inst]  # a miss (-1) picks the trailing row
    diffuse, mirror, rough = per[..., 0], per[..., 1], per[..., 2]
    on = view.on_marker
    diffuse = np.where(on, view.albedo, diffuse)
    mirror = np.where(on, np.float32(0.03), mirror)
    rough = np.where(on, np.float32(0.9), rough)
    return Reflectance(diffuse, mirror, rough)


def structured_depth(
    setup: RigSetup,
    surfaces: Sequence[Surface],
    materials: Sequence[Material],
    view: View,
    rng: np.random.Generator,
    settings: PbrSettings,
    *,
    fixed: int = 0,
) -> np.ndarray:
    """The structured-light sensor's depth (mm, NaN = none) on the reference camera's grid,
    its projector the rig's (``fixed``: see :func:`~annotator.synthesis.shading.render_view`)."""
    camera = setup.rig.cameras[0]
    rays = camera.pixel_rays()
    hit = view.hits.hit
    z = np.where(hit, view.hits.depth, np.float32(1.0))
    points = rays * z[..., None]
    cam_T_proj = invert(setup.world_T_cams[0]) @ setup.world_T_projector
    projector = cam_T_proj[:3, 3]
    proj_T_world = invert(setup.world_T_projector)
    w, h = setup.projector_size
    shadows = ShadowMap.render(
        Camera("projector", w, h, setup.projector_K),
        [PlacedMesh(s.mesh, proj_T_world @ s.world_T_model) for s in surfaces],
        fixed=fixed,
    )
    proj_T_cam = invert(cam_T_proj)
    q = points @ proj_T_cam[:3, :3].T + proj_T_cam[:3, 3]
    K = setup.projector_K
    qz = np.maximum(q[..., 2], 1e-6)
    u = K[0, 0] * q[..., 0] / qz + K[0, 2]
    v = K[1, 1] * q[..., 1] / qz + K[1, 2]
    inside = (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5) & (q[..., 2] > 0)
    lit = inside & shadows.lit(u, v, q[..., 2].astype(np.float32))
    return structured_light_depth(
        points,
        view.normals_cam.astype(np.float64),
        hit,
        lit,
        reflectance(view, materials),
        projector=projector,
        focal_px=float(camera.K[0, 0]),
        rng=rng,
        settings=settings.structured_light,
    )
