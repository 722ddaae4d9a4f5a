"""Synthetic sequences: the parts of a scene seen by one rig moved by hand over the bin.

A sequence's scene is dropped into the bin as a fixed rig's is (:mod:`.generate`); then the
rig (its two cameras and the dot projector, mounted together like an active-stereo sensor;
with ``SynthSettings.cameras`` 1 only the first camera's images are written, as an RGB-D
sensor's) is carried along a smooth hand-held path and renders every frame, with the
sensor's blur and noise, the simulated stereo depth, and on some frames motion blur
(FORMAT.md, sequences).

Conventions of the path (all in the world, i.e. bin frame: z up, the floor's top at z = 0,
mm, radians, seconds):

- The reference camera's centre, the *eye*, lies on a cap over a *target* point near the bin
  centre: ``eye = target + distance * (sin(tilt) cos(azimuth), sin(tilt) sin(azimuth),
  cos(tilt))``; ``tilt`` is the angle of the line of sight from the vertical, ``azimuth`` is
  measured about +z from +x.
- The camera looks at the target with world -y towards the top of the image
  (:func:`annotator.synthesis.rig.look_at`), then turns by ``roll`` about its optical axis
  (positive: the camera's x axis turns towards its y axis).
- Seven quantities (:data:`PATH_FIELDS`) are given at *knots* (irregular times: the hand
  speeds up and slows down; :func:`draw_knots` draws them) and interpolated
  piecewise-cubically (monotone between knots, so that bounded quantities stay within their
  bounds, with continuous velocity); frame ``k`` is taken at ``k * FRAME_INTERVAL_S``.

Motion blur: a blurred frame is one taken with a long exposure. The blur is the true image
motion of that frame: every pixel's point (at its exact depth) is followed from the start to
the end of the exposure, the rig moving along the same path, and the rendered image is
averaged along each pixel's streak (before the sensor's blur and noise). The exposure is
chosen so that the median streak has a hand-held length (:data:`BLUR_STREAK`, a fraction of
the image width); gt.json's frame entry records ``exposure_s`` and the median streak
``motion_blur_px`` truthfully (0 for sharp frames, taken as instantaneous). The projector's
dot images (the depth) are not blurred: active-stereo sensors expose them briefly.

Jobs (:func:`annotator.runner.run_batch`, local or Ray): first one per scene drops the parts
(:class:`BinJob`, nothing written), then one per frame renders it (:class:`FrameJob`, job id
``<scene>/<frame>``); gt.json is written by the driver from their results. Every byte
depends only on the configuration, the scene's index and the frame's, never on the workers.
"""

from __future__ import annotations

import shutil
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.interpolate import PchipInterpolator

from annotator.dataset.model import FORMAT_VERSION, FRAMES_DIR, SCENES_DIR
from annotator.dataset.poses import InstancePose, write_poses
from annotator.dataset.records import FramePose, frames_to_json
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert
from annotator.runner import BatchReport, run_batch
from annotator.summary import FolderBatch
from annotator.synthesis.generate import (
    BinContents,
    DatasetPlan,
    SceneJob,
    SceneTiming,
    SynthSettings,
    cached_plan,
    fill_bin,
    stage_bin,
    staged_occlusion,
    write_shot,
)
from annotator.synthesis.rig import RigSetup, look_at
from annotator.synthesis.shading import View

__all__ = [
    "PATH_FIELDS",
    "PathKnots",
    "SequenceSummary",
    "draw_knots",
    "image_motion",
    "motion_blur",
    "moved_setup",
    "rig_path",
    "synthesize_sequences",
    "write_sequences",
]

#: The quantities a path gives at its knots, in the columns of :attr:`PathKnots.values`.
PATH_FIELDS = ("azimuth", "tilt", "distance", "target_x", "target_y", "target_z", "roll")
#: Time between two frames (s).
FRAME_INTERVAL_S = 0.25
#: Range of the time between two knots (s): the hand changes course about every second.
KNOT_INTERVAL_S = (0.5, 1.2)
#: Ranges of the eye's distance to the target (mm) and of its tilt from the vertical (rad),
#: and their random steps from knot to knot.
DISTANCE_MM = (430.0, 640.0)
TILT = (np.radians(4.0), np.radians(32.0))
DISTANCE_STEP_MM = 50.0
TILT_STEP = np.radians(7.0)
#: The rig orbits the bin at a steady rate drawn in this range (rad/s, either way round)...
ORBIT = (np.radians(20.0), np.radians(45.0))
#: ... and per knot, the azimuth's random step about that orbit (rad), the target's jitter
#: about the bin centre (mm, horizontal and vertical) and the roll (rad).
AZIMUTH_STEP = np.radians(10.0)
TARGET_JITTER_MM = (40.0, 10.0)
ROLL = np.radians(6.0)
#: The point the rig aims at on average (mm): the bin centre, a little above the floor.
TARGET = np.array([0.0, 0.0, 30.0])
#: A blurred frame's median streak, as a fraction of the image width (range).
BLUR_STREAK = (0.004, 0.012)
#: Bounds of a blurred frame's exposure (s).
EXPOSURE_S = (1.0 / 1000.0, 1.0 / 10.0)

# The random streams of a sequence beside the scene's own ([seed, index]: the drop).
_PATH_STREAM = 1 << 24
_FRAME_STREAM = 1 << 25


@dataclass(frozen=True)
class PathKnots:
    """A hand-held path's knots: ``times`` (K,) increasing, s; ``values`` (K, 7), the
    :data:`PATH_FIELDS` at each knot (rad, mm)."""

    times: np.ndarray
    values: np.ndarray


def draw_knots(n_frames: int, rng: np.random.Generator) -> PathKnots:
    """A random hand-held path covering frames ``0 .. n_frames - 1`` (and a knot beyond each
    end, so that the path does not start or stop at rest): the rig orbits the bin (a steady
    turn plus a random walk), the distance and tilt wander within their ranges (bounded random
    walks), the target and roll are drawn afresh at every knot."""
    duration = max(n_frames - 1, 0) * FRAME_INTERVAL_S
    times = [-rng.uniform(*KNOT_INTERVAL_S)]
    while times[-1] <= duration:
        times.append(times[-1] + rng.uniform(*KNOT_INTERVAL_S))
    k = len(times)
    turn = rng.choice([-1.0, 1.0]) * rng.uniform(*ORBIT)
    azimuth = (
        rng.uniform(0.0, 2 * np.pi)
        + turn * np.asarray(times)
        + np.cumsum(rng.normal(0.0, AZIMUTH_STEP, k))
    )
    values = np.column_stack(
        [
            azimuth,
            _bounded_walk(rng, k, TILT, TILT_STEP),
            _bounded_walk(rng, k, DISTANCE_MM, DISTANCE_STEP_MM),
            TARGET[0] + rng.normal(0.0, TARGET_JITTER_MM[0], k),
            TARGET[1] + rng.normal(0.0, TARGET_JITTER_MM[0], k),
            TARGET[2] + rng.normal(0.0, TARGET_JITTER_MM[1], k),
            rng.normal(0.0, ROLL, k),
        ]
    )
    return PathKnots(np.asarray(times), values)


def _bounded_walk(
    rng: np.random.Generator, n: int, bounds: tuple[float, float], step: float
) -> np.ndarray:
    """``n`` values of a random walk of Gaussian ``step``s, started anywhere within
    ``bounds`` and reflected at them."""
    lo, hi = bounds
    out = np.empty(n)
    x = rng.uniform(lo, hi)
    for i, d in enumerate(rng.normal(0.0, step, n)):
        x = x + d
        x = 2 * lo - x if x < lo else 2 * hi - x if x > hi else x
        out[i] = float(np.clip(x, lo, hi))
    return out


def rig_path(knots: PathKnots, times: np.ndarray) -> np.ndarray:
    """``world_T_rig`` (N, 4, 4) of the reference camera at ``times`` (N,) along the path
    (conventions in the module docstring); a pure function of its arguments.

    >>> knots = PathKnots(np.array([0.0, 1.0]), np.array([[0, 0, 500, 0, 0, 0, 0]] * 2, float))
    >>> T = rig_path(knots, np.array([0.5]))[0]
    >>> T[:3, 3].round(6).tolist(), T[:3, 2].round(6).tolist()  # above the target, looking down
    ([0.0, 0.0, 500.0], [0.0, 0.0, -1.0])
    """
    q = PchipInterpolator(knots.times, knots.values, axis=0)(np.asarray(times, float))
    az, tilt, dist = q[:, 0], q[:, 1], q[:, 2]
    target = q[:, 3:6]
    sight = np.column_stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    out = np.empty((len(q), 4, 4))
    for i in range(len(q)):
        T = look_at(target[i] + dist[i] * sight[i], target[i])
        c, s = np.cos(q[i, 6]), np.sin(q[i, 6])
        roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        T[:3, :3] = T[:3, :3] @ roll
        out[i] = T
    return out


def moved_setup(setup: RigSetup, world_T_rig: np.ndarray) -> RigSetup:
    """``setup``'s rig (cameras and projector, rigidly together) with its reference camera at
    ``world_T_rig``."""
    rig_T_world = invert(setup.world_T_cams[0])
    return replace(
        setup,
        world_T_cams=tuple(world_T_rig @ rig_T_world @ T for T in setup.world_T_cams),
        world_T_projector=world_T_rig @ rig_T_world @ setup.world_T_projector,
    )


def image_motion(
    camera: Camera,
    depth: np.ndarray,
    world_T_cam: np.ndarray,
    world_T_start: np.ndarray,
    world_T_end: np.ndarray,
) -> np.ndarray:
    """Each pixel's image motion (H, W, 2), px, from ``world_T_start`` to ``world_T_end``
    (the camera's poses at the ends of the exposure) of the point it sees at ``depth``
    (z-depth, mm, from the camera at ``world_T_cam``; pixels that see nothing are taken at
    the median depth)."""
    z = np.where(np.isfinite(depth), depth, np.nan).astype(np.float64)
    fill = float(np.nanmedian(z)) if np.isfinite(z).any() else 1000.0
    z = np.nan_to_num(z, nan=fill)
    pts = camera.pixel_rays().astype(np.float64) * z[..., None]
    uv = []
    for world_T_at in (world_T_start, world_T_end):
        at_T_cam = invert(world_T_at) @ world_T_cam
        uv.append(camera.project(pts @ at_T_cam[:3, :3].T + at_T_cam[:3, 3]))
    flow = uv[1] - uv[0]
    return np.nan_to_num(flow, nan=0.0).astype(np.float32)


def motion_blur(img: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """``img`` (float32, H x W) averaged along each pixel's streak ``flow`` (H, W, 2, px):
    samples at ``pixel + s * flow`` for ``s`` evenly spread over [-1/2, 1/2], one per pixel
    of the longest streak (bilinear, the border repeated)."""
    longest = float(np.sqrt((flow**2).sum(axis=2)).max(initial=0.0))
    n = int(np.clip(np.ceil(longest) + 1, 2, 96))
    h, w = img.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    acc = np.zeros(img.shape, np.float64)
    for s in (np.arange(n) + 0.5) / n - 0.5:
        acc += cv2.remap(
            img,
            u + np.float32(s) * flow[..., 0],
            v + np.float32(s) * flow[..., 1],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
    return (acc / n).astype(np.float32)


@dataclass(frozen=True)
class _ScenePath:
    """One scene's path: the knots, each frame's time and ``world_T_rig``, which frames are
    blurred and the median streak each of those has (px)."""

    knots: PathKnots
    times: np.ndarray
    world_T_rig: np.ndarray
    streak_px: dict[int, float] = field(default_factory=dict)


@lru_cache(maxsize=8)
def _scene_path(config: SynthSettings, index: int) -> _ScenePath:
    """Scene ``index``'s path, drawn from its own stream (the same in every process)."""
    rng = np.random.default_rng([config.seed, index, _PATH_STREAM])
    n = config.frames
    knots = draw_knots(n, rng)
    times = np.arange(n) * FRAME_INTERVAL_S
    blurred = sorted(
        int(k) for k in rng.choice(n, size=int(round(config.motion_blur * n)), replace=False)
    )
    streaks = rng.uniform(*BLUR_STREAK, len(blurred)) * config.size[0]
    return _ScenePath(knots, times, rig_path(knots, times), dict(zip(blurred, streaks.tolist())))


def _contents_to_result(contents: BinContents) -> dict[str, Any]:
    return {
        "chosen": [list(c) for c in contents.chosen],
        "clutter": list(contents.clutter),
        "world_T": [None if T is None else np.asarray(T).tolist() for T in contents.world_T],
    }


def _contents_from_result(plan: DatasetPlan, doc: Mapping[str, Any]) -> BinContents:
    chosen = [(int(p), int(c)) for p, c in doc["chosen"]]
    clutter = tuple(int(p) for p in doc["clutter"])
    meshes = [plan.parts[p].mesh for p, _ in chosen] + [plan.parts[p].mesh for p in clutter]
    world_T = [None if T is None else np.asarray(T, float) for T in doc["world_T"]]
    return BinContents(chosen, meshes, world_T, clutter)


@dataclass(frozen=True)
class BinJob(SceneJob):
    """Drop scene ``scene_id``'s parts into the bin (the same draws as a fixed rig's scene of
    that index); writes nothing, returns the settled contents (a batch job)."""

    def output_files(self, scene_id: str) -> list[str]:
        """None: the drop is returned, the frames are written by :class:`FrameJob`."""
        return []

    def __call__(self, scene_id: str) -> dict:
        plan = cached_plan(self.config)
        rng = np.random.default_rng([self.config.seed, int(scene_id)])
        return _contents_to_result(fill_bin(plan, rng))


@dataclass(frozen=True)
class FrameJob(SceneJob):
    """Render one frame (job id ``<scene>/<frame>``) into ``scenes/<scene>/frames/<frame>/``
    from the scene's drop (``bins``: :class:`BinJob`'s results by scene); returns the frame's
    motion blur and each instance's occlusion rates in it."""

    bins: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    def output_files(self, scene_id: str) -> list[str]:
        """Every file of the frame's folder."""
        scene, frame = scene_id.split("/")
        return [f"{SCENES_DIR}/{scene}/{FRAMES_DIR}/{frame}/"]

    def __call__(self, scene_id: str) -> dict:
        scene, frame = scene_id.split("/")
        index, k = int(scene), int(frame)
        plan = cached_plan(self.config)
        path = _scene_path(self.config, index)
        contents = _contents_from_result(plan, self.bins[scene])
        at = replace(plan, setup=moved_setup(plan.setup, path.world_T_rig[k]))
        staged = stage_bin(at, contents)
        folder = Path(self.root) / SCENES_DIR / scene / FRAMES_DIR / frame
        folder.mkdir(parents=True, exist_ok=True)
        rng = np.random.default_rng([self.config.seed, index, _FRAME_STREAM, k])
        timing = SceneTiming()
        blur: dict[str, float] = {"motion_blur_px": 0.0}
        smear = None
        if k in path.streak_px:
            smear = _Exposure(at, path, k, path.streak_px[k], blur)
        views = write_shot(at, staged, folder, rng, timing, smear=smear)
        staged_occlusion(at, staged, views, timing)
        occlusion = {p.key: p.extra["occlusion"] for p in staged.poses}
        return {**blur, **timing.__dict__, "instances": occlusion}


@dataclass
class _Exposure:
    """A blurred frame's smear (:data:`annotator.synthesis.generate.Smear`): the exposure is
    fixed on the reference camera's image (its median streak ``streak_px`` long), then every
    camera's image is blurred along its own motion over that exposure; ``record`` receives
    ``exposure_s`` and the reference camera's median streak ``motion_blur_px``."""

    plan: DatasetPlan
    path: _ScenePath
    frame: int
    streak_px: float
    record: dict[str, float]
    exposure_s: float | None = None

    def _ends(self, exposure: float) -> tuple[np.ndarray, np.ndarray]:
        t = self.path.times[self.frame]
        T = rig_path(self.path.knots, np.array([t - exposure / 2, t + exposure / 2]))
        return T[0], T[1]

    def _flow(self, k: int, cam: Camera, view: View, exposure: float) -> np.ndarray:
        start, end = self._ends(exposure)
        return image_motion(
            cam,
            view.hits.depth,
            self.plan.setup.world_T_cams[k],
            start @ cam.rig_T_cam,
            end @ cam.rig_T_cam,
        )

    def __call__(self, k: int, cam: Camera, img: np.ndarray, view: View) -> np.ndarray:
        if self.exposure_s is None:
            probe = 0.01
            speed = float(np.median(_lengths(self._flow(k, cam, view, probe)))) / probe
            exposure = self.streak_px / max(speed, 1e-6)
            self.exposure_s = float(np.clip(exposure, *EXPOSURE_S))
        flow = self._flow(k, cam, view, self.exposure_s)
        if k == 0:
            self.record["exposure_s"] = round(self.exposure_s, 6)
            self.record["motion_blur_px"] = round(float(np.median(_lengths(flow))), 3)
        return motion_blur(img, flow)


def _lengths(flow: np.ndarray) -> np.ndarray:
    return np.sqrt((flow.astype(np.float64) ** 2).sum(axis=2))


def frame_name(k: int) -> str:
    """The folder name of frame ``k``: ``000000``, ``000001``..."""
    return f"{k:06d}"


def write_sequences(
    config: SynthSettings,
    root: Path,
    scene_ids: Sequence[str],
    **batch: Any,
) -> tuple[BatchReport, dict[str, float]]:
    """Make the sequences ``scene_ids`` (``000000``...: their index) of ``config`` under
    ``root`` (its dataset files already written): the drops, then every frame, then each
    scene's gt.json (instances in the scene frame, ``frames`` with each ``scene_T_rig``).

    ``batch``: the options of :func:`annotator.runner.run_batch` (``workers``, ``quiet``,
    ``ray_address``...). Returns the per-scene report (a scene fails when its drop or any of
    its frames does; its folder is then removed; a scene's result holds ``instances``,
    ``frames`` and ``physics``) and the mean seconds per frame of each stage of the frames.
    """
    desc = batch.pop("desc", "synth")
    drops = run_batch(BinJob(config, str(root)), list(scene_ids), desc=f"{desc} (drops)", **batch)
    frame_ids = [
        f"{sid}/{frame_name(k)}" for sid in sorted(drops.done) for k in range(config.frames)
    ]
    job = FrameJob(config, str(root), bins=dict(drops.done))
    frames = run_batch(job, frame_ids, desc=f"{desc} (frames)", **batch)
    report = BatchReport(failed=dict(drops.failed))
    plan = cached_plan(config)
    for sid in sorted(drops.done):
        names = [frame_name(k) for k in range(config.frames)]
        errors = [
            f"frame {n}: {frames.failed[f'{sid}/{n}']}"
            for n in names
            if f"{sid}/{n}" in frames.failed
        ]
        folder = root / SCENES_DIR / sid
        if errors:
            report.failed[sid] = "; ".join(errors)
            shutil.rmtree(folder, ignore_errors=True)
            continue
        results = [frames.done[f"{sid}/{n}"] for n in names]
        poses = _scene_gt(plan, sid, drops.done[sid], names, results, folder)
        report.done[sid] = {"instances": len(poses), "frames": len(names)}
    done = list(frames.done.values())
    per_frame = {
        k: round(sum(r[k] for r in done) / max(len(done), 1), 3)
        for k in ("rendering", "depth", "occlusion")
    }
    return report, per_frame


def _scene_gt(
    plan: DatasetPlan,
    sid: str,
    drop: Mapping[str, Any],
    names: list[str],
    results: list[dict[str, Any]],
    folder: Path,
) -> list[InstancePose]:
    """Write the sequence's gt.json; its poses (scene frame). An instance's ``occlusion``
    is the least any frame saw (rate and per camera, each the minimum over frames); each
    frame's entry lists, under ``instances``, the instances in its view with their rates
    per camera (as annotation.json's frames do)."""
    path = _scene_path(plan.config, int(sid))
    first = replace(plan, setup=moved_setup(plan.setup, path.world_T_rig[0]))
    poses = stage_bin(first, _contents_from_result(plan, drop)).poses
    scene_T_world = invert(path.world_T_rig[0])
    frames: dict[str, FramePose] = {}
    for k, (name, res) in enumerate(zip(names, results)):
        scene_T_rig = np.eye(4) if k == 0 else scene_T_world @ path.world_T_rig[k]
        in_view = {
            key: {"occlusion": occ["per_camera"]}
            for key, occ in res["instances"].items()
            if occ["rate"] < 1.0
        }
        frames[name] = FramePose(
            name,
            scene_T_rig,
            time_s=round(float(path.times[k]), 6),
            motion_blur_px=res.get("motion_blur_px"),
            exposure_s=res.get("exposure_s"),
            instances=in_view,
        )
    for p in poses:
        seen = [res["instances"][p.key] for res in results]
        cams = seen[0]["per_camera"]
        p.extra["occlusion"] = {
            "rate": min(s["rate"] for s in seen),
            "per_camera": {c: min(s["per_camera"][c] for s in seen) for c in cams},
        }
    write_poses(folder / "gt.json", poses, format=FORMAT_VERSION, frames=frames_to_json(frames))
    return poses


@dataclass(frozen=True)
class SequenceSummary(FolderBatch):
    """What :func:`synthesize_sequences` wrote (``synth --frames --json`` prints
    :meth:`to_json`).

    Attributes:
        out: The dataset folder.
        report: The per-scene outcomes (a scene fails when its drop or a frame does).
        frames: Frames per sequence.
        seconds_per_frame: Mean seconds per frame of ``rendering``, ``depth``, ``occlusion``.

    >>> from pathlib import Path
    >>> from annotator.runner import BatchReport
    >>> per_frame = {"rendering": 0.1, "depth": 0.02, "occlusion": 0.01}
    >>> report = BatchReport({"000000": {"frames": 5, "instances": 9}})
    >>> s = SequenceSummary(Path("seq"), report, 5, per_frame)
    >>> s.counts()
    {'scenes': 1, 'frames': 5, 'failed': 0, 'instances': 9}
    """

    out: Path
    report: BatchReport
    frames: int
    seconds_per_frame: dict[str, float]

    def counts(self) -> dict[str, int]:
        done = self.report.done.values()
        return {
            "scenes": len(self.report.done),
            "frames": sum(r["frames"] for r in done),
            "failed": len(self.report.failed),
            "instances": sum(r["instances"] for r in done),
        }

    def to_json(self) -> dict[str, Any]:
        return {
            "out": str(self.out),
            **self.counts(),
            "seconds_per_frame": self.seconds_per_frame,
            "failures": dict(sorted(self.report.failed.items())),
        }

    def text(self) -> str:
        j, t = self.counts(), self.seconds_per_frame
        return (
            f"synth: {j['scenes']} sequences of {self.frames} frames ({j['instances']} "
            f"instances) written to {self.out}, {j['failed']} failed; per frame: rendering "
            f"{t['rendering']} s, depth {t['depth']} s, occlusion rates {t['occlusion']} s"
        )


def synthesize_sequences(
    out: str | Path, config: SynthSettings, *, overwrite: bool = False, **batch: Any
) -> SequenceSummary:
    """``annotator synth --frames N OUT``: a moving rig's dataset of ``config.scenes``
    sequences of ``config.frames`` frames in the new folder ``out`` (built aside, put in
    place whole; ``overwrite`` replaces an earlier synth's).

    ``batch``: the options of :func:`annotator.runner.run_batch` (``workers``, ``quiet``,
    ``ray_address``, ``ray_wait``).

    >>> import tempfile
    >>> from pathlib import Path
    >>> out = Path(tempfile.mkdtemp()) / "seq"
    >>> settings = SynthSettings(parts=("brick",), scenes=1, instances=(2, 2), size=(160, 128), frames=2)
    >>> _ = synthesize_sequences(out, settings)
    >>> sorted(p.name for p in (out / "scenes" / "000000" / "frames").iterdir())
    ['000000', '000001']
    """
    from annotator.io.atomic import atomic_folder
    from annotator.io.output_folder import check_output_folder, write_manifest
    from annotator.synthesis.generate import write_dataset_files

    if config.frames < 1:
        raise ValueError("a sequence needs config.frames >= 1")
    out = Path(out)
    check_output_folder(out, command="synth", overwrite=overwrite)
    with atomic_folder(out) as tmp:
        write_manifest(tmp, command="synth")
        write_dataset_files(cached_plan(config), tmp)
        ids = [f"{k:06d}" for k in range(config.scenes)]
        report, per_frame = write_sequences(config, tmp, ids, **batch)
    return SequenceSummary(out, report, config.frames, per_frame)
