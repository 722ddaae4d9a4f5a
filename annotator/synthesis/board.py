"""Synthetic calibration captures: a ChArUco board in random poses seen by the synthetic rig.

The board (:mod:`annotator.synthesis.board_render`: the textured slab and its ray-cast
picture) is posed in front of the rig of :mod:`annotator.synthesis.rig`; each image is
blurred, noised and quantised like the bin scenes
(:func:`annotator.synthesis.shading.finish_image`).

Board poses (reproducible from the seed): the board centre at a depth of 520-760 mm in the
reference camera, anywhere in its image; the board facing the rig, tilted by up to 40
degrees about a random axis in its plane and turned by up to 90 degrees in its plane; kept
only if each camera sees at least 85% of the chessboard corners (all of them for a plain
chessboard, which is only found whole), within the central ``centre`` fraction of the image
when asked (a board that covers only the middle of the image: the case where a distortion
model extrapolates).

Boards as people print and film them: ``inverted`` prints the board colour-inverted (white
markers on black, a black margin), ``printed_mirrored`` prints it mirrored left to right (a
printer's "mirror" setting, as for iron-on transfers: every camera in front reads it only
flipped, and a camera behind it sees, through the paper, the board as it should be), ``mirrored`` cameras store their images flipped left to
right (their truth carries ``flip: horizontal``), and a board of a custom dictionary gets the
dictionary file copied beside board.yaml. A board seen from behind: ``behind`` cameras are
placed on the far side of the board (turned half a turn about the vertical through the
middle of the working distance on the reference camera's axis), ``turned`` shots have the
board turned round (its back to the rig). Either makes the board thin back-lit paper, printed
on its front face: seen from behind the print shows through it mirrored, with less contrast,
lit evenly by the light behind it; seen from the front it is the ordinary print.

Webcams that are not synchronised (``timing_ms``): each camera takes its image of a shot up
to that much before or after the shot's moment, while the board, held by hand, moves at up
to ``speed`` (mm/s of its centre, degrees/s about it; each shot its own, in a random
direction): the cameras' images of one shot then show the board a little apart, by as much
as that shot's motion and their time apart make (the truth keeps each shot's moment and
each camera's offset from it). :func:`~annotator.synthesis.board_video.write_videos` turns
the shot folders into one lossless video per camera.
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from annotator.calibration.board import BOARD_FILE, BoardSpec
from annotator.dataset.model import Rig, orient_image
from annotator.dataset.write import rig_to_yaml
from annotator.errors import UserError
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import axis_angle, make_transform
from annotator.io.atomic import write_text
from annotator.io.images import write_png
from annotator.markers.dictionary import is_predefined
from annotator.synthesis.board_render import (
    BACK_BLACK,
    BACK_WHITE,
    BoardModel,
    render_board,
)
from annotator.synthesis.board_video import write_videos
from annotator.synthesis.rig import make_rig
from annotator.synthesis.shading import finish_image

#: The truth file written beside synthetic captures.
TRUTH_FILE = "truth.yaml"
#: A custom dictionary's copy beside board.yaml.
DICTIONARY_FILE = "dictionary.yml"


@dataclass(frozen=True)
class CaptureSettings:
    """What defines a set of synthetic calibration captures (with the seed, every byte).

    Attributes:
        shots: Number of board poses.
        seed: Random seed (rig perturbation, poses, noise).
        size: Image size (width, height) of every camera.
        board: The board.
        distance: Range of the board centre's depth in the reference camera, mm.
        max_tilt_deg: Largest angle between the board's normal and the direction to the rig.
        min_visible: Fraction of the chessboard corners each camera must see.
        noise: Image noise sigma, grey levels.
        blur: Image blur sigma, px.
        supersample: Sub-pixel rays per axis at texture edges.
        inverted: The board is printed colour-inverted.
        printed_mirrored: The board is printed mirrored left to right.
        mirrored: Cameras whose images are stored mirrored (left to right).
        centre: Every corner within the central fraction of each image (1: anywhere).
        behind: Cameras placed behind the board (they see it through the paper).
        turned: Shots (indices) in which the board is turned round, its back to the rig.
        through_paper: Grey of the paper and of the ink seen from behind, through the paper.
        paper_blur: Blur (sigma, px) that the paper adds to the print seen through it.
        extra_cameras: Cameras added to the rig's two (``cam2``, ``cam3``, ...: copies of the
            right camera, 120 mm above and below the reference camera in turn, aimed at the
            middle of the working distance).
        timing_ms: Each camera's image of a shot is taken up to this long before or after the
            shot's moment (0: all at once) ...
        rolling_ms: ... and camera ``k`` (rig order) this much times ``k`` later (webcams read
            one after another).
        speed: The board's largest motion during a shot: its centre's speed (mm/s) and its
            turn (degrees/s); each shot's is that times the cube of a uniform random number
            (a board held by hand is mostly still, now and then moving).

    >>> s = CaptureSettings(shots=4, size=(320, 256))
    >>> s.shots, s.board.describe()
    (4, '7x5 ChArUco, 30 mm squares, 22 mm markers, DICT_4X4_50')
    """

    shots: int = 30
    seed: int = 0
    size: tuple[int, int] = (1280, 1024)
    board: BoardSpec = BoardSpec()
    distance: tuple[float, float] = (520.0, 760.0)
    max_tilt_deg: float = 40.0
    min_visible: float = 0.85
    noise: float = 2.0
    blur: float = 0.6
    supersample: int = 4
    inverted: bool = False
    printed_mirrored: bool = False
    mirrored: tuple[str, ...] = ()
    centre: float = 1.0
    behind: tuple[str, ...] = ()
    turned: tuple[int, ...] = ()
    through_paper: tuple[float, float] = (BACK_WHITE, BACK_BLACK)
    paper_blur: float = 0.0
    extra_cameras: int = 0
    timing_ms: float = 0.0
    rolling_ms: float = 0.0
    speed: tuple[float, float] = (0.0, 0.0)

    @property
    def paper(self) -> bool:
        """The board is thin back-lit paper: some camera sees it from behind."""
        return bool(self.behind or self.turned)

    def from_behind(self, camera: str, shot: int) -> bool:
        """Whether ``camera`` sees the board's back in shot ``shot``."""
        return (camera in self.behind) != (shot in self.turned)


def board_poses(rig: Rig, config: CaptureSettings, rng: np.random.Generator) -> list[np.ndarray]:
    """``config.shots`` random poses ``rig_T_board`` (see the module docstring)."""
    spec = config.board
    ref = rig.cameras[0]
    centre_board = np.array([*np.asarray(spec.size_mm) / 2, 0.0])
    # The rig's centre: the board faces it, whichever camera is the reference.
    front = [c for c in rig.cameras if c.name not in config.behind] or list(rig.cameras)
    rig_centre = np.mean([c.rig_T_cam[:3, 3] for c in front], axis=0)
    # A turned board: half a turn about its own vertical through its centre.
    turn = make_transform(axis_angle(np.array([0.0, 1.0, 0.0]), np.pi), np.zeros(3))
    turn[:3, 3] = centre_board - turn[:3, :3] @ centre_board
    poses: list[np.ndarray] = []
    for _ in range(10000 * config.shots):
        if len(poses) == config.shots:
            return poses
        z = rng.uniform(*config.distance)
        uv = rng.uniform([0.0, 0.0], [ref.width - 1.0, ref.height - 1.0])
        xy = ref.undistort_pixels(uv)
        centre = np.array([xy[0] * z, xy[1] * z, z])
        # Facing the rig: the board's z axis (into the board) points away from the rig.
        normal = centre - rig_centre
        normal /= np.linalg.norm(normal)
        facing = _frame_with_z(normal)
        spin = axis_angle(normal, rng.uniform(-np.pi / 2, np.pi / 2))
        phi = rng.uniform(0.0, 2 * np.pi)
        tilt_axis = np.cos(phi) * facing[:, 0] + np.sin(phi) * facing[:, 1]
        tilt = np.radians(config.max_tilt_deg) * np.sqrt(rng.uniform())
        R = axis_angle(tilt_axis, tilt) @ spin @ facing
        T = make_transform(R, centre - R @ centre_board)
        if len(poses) in config.turned:
            T = T @ turn
        if all(
            _visible_fraction(
                cam,
                cam.cam_T_rig @ T,
                spec.corners,
                config.centre,
                back=config.from_behind(cam.name, len(poses)),
            )
            >= config.min_visible
            for cam in rig.cameras
        ):
            poses.append(T)
    raise UserError(
        f"cannot place the {spec.describe()} board {config.distance[0]:g}-"
        f"{config.distance[1]:g} mm away in view of every camera: the images are too small"
    )


def _frame_with_z(z: np.ndarray) -> np.ndarray:
    """A rotation whose third column is ``z`` and whose x axis is as close to the rig's x as
    possible (so an unturned board is upright in the images)."""
    x = np.array([1.0, 0.0, 0.0]) - z * z[0]
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _visible_fraction(
    cam: Camera,
    cam_T_board: np.ndarray,
    points: np.ndarray,
    centre: float = 1.0,
    *,
    back: bool = False,
) -> float:
    pts = points @ cam_T_board[:3, :3].T + cam_T_board[:3, 3]
    uv = cam.project(pts)
    mx = max(8.0, 0.5 * (1 - centre) * cam.width)
    my = max(8.0, 0.5 * (1 - centre) * cam.height)
    inside = (
        np.isfinite(uv).all(axis=1)
        & (uv[:, 0] >= mx)
        & (uv[:, 1] >= my)
        & (uv[:, 0] <= cam.width - 1 - mx)
        & (uv[:, 1] <= cam.height - 1 - my)
    )
    # The board must face the camera: its normal -z points towards the camera centre (away
    # from it for a camera meant to see the back).
    facing = ((cam_T_board[:3, 2] @ cam_T_board[:3, 3]) > 0) != back
    return float(inside.mean()) if facing else 0.0


def render_shot(
    rig: Rig,
    rig_T_board: np.ndarray,
    model: BoardModel,
    config: CaptureSettings,
    rng: np.random.Generator,
    *,
    shot: int = -1,
) -> list[np.ndarray]:
    """The uint8 image of every rig camera for one board pose ``(4, 4)``, or one per camera
    ``(C, 4, 4)`` (blur and noise included; the paper's blur where a camera sees the back
    of shot ``shot``)."""
    poses = np.broadcast_to(rig_T_board, (len(rig.cameras), 4, 4))
    return [
        finish_image(
            render_board(cam, cam.cam_T_rig @ T, model, supersample=config.supersample),
            blur=float(np.hypot(config.blur, config.paper_blur))
            if config.paper and config.from_behind(cam.name, shot)
            else config.blur,
            noise=config.noise,
            rng=rng,
        )
        for cam, T in zip(rig.cameras, poses)
    ]


@dataclass
class CapturePlan:
    """The rig, the board and its poses: everything but the images.

    Attributes:
        offsets: (shots, cameras) when each camera took its image of each shot, s after the
            shot's moment (zeros: all at once).
        motion: (shots, 6) each shot's board motion: its centre's velocity (mm/s, rig frame)
            and its angular velocity about the centre (rad/s, rig frame).
    """

    config: CaptureSettings
    rig: Rig
    poses: list[np.ndarray]
    model: BoardModel
    offsets: np.ndarray | None = None
    motion: np.ndarray | None = None

    def camera_poses(self, k: int) -> np.ndarray:
        """(cameras, 4, 4) ``rig_T_board`` of shot ``k`` when each camera took its image."""
        T = self.poses[k]
        out = np.tile(T, (len(self.rig.cameras), 1, 1))
        if self.offsets is None or self.motion is None:
            return out
        centre = T[:3, :3] @ np.array([*np.asarray(self.config.board.size_mm) / 2, 0.0]) + T[:3, 3]
        v, w = self.motion[k, :3], self.motion[k, 3:]
        for c, dt in enumerate(self.offsets[k]):
            angle = float(np.linalg.norm(w)) * dt
            R = axis_angle(w / max(float(np.linalg.norm(w)), 1e-12), angle)
            out[c, :3, :3] = R @ T[:3, :3]
            out[c, :3, 3] = R @ (T[:3, 3] - centre) + centre + v * dt
        return out

    @property
    def shot_names(self) -> list[str]:
        """``000``, ``001``, ... (wider when there are more than 1000 shots)."""
        digits = max(3, len(str(self.config.shots - 1)))
        return [f"{k:0{digits}d}" for k in range(self.config.shots)]

    def render(self, k: int) -> list[np.ndarray]:
        """The images of shot ``k`` (uint8, one per camera), the same bytes every time."""
        rng = np.random.default_rng([self.config.seed, k, _NOISE_STREAM])
        return render_shot(self.rig, self.camera_poses(k), self.model, self.config, rng, shot=k)


def plan_captures(config: CaptureSettings) -> CapturePlan:
    """The synthetic rig of ``annotator synth --seed`` (the same rig as its scenes) and the
    board poses, all from the seed."""
    rig = _with_extra_cameras(
        make_rig(*config.size, rng=np.random.default_rng(config.seed)).rig, config
    )
    unknown = [c for c in config.mirrored if c not in [cam.name for cam in rig.cameras]]
    if unknown:
        raise UserError(
            f"no camera {unknown[0]!r} to mirror: the rig's cameras are "
            + ", ".join(c.name for c in rig.cameras)
        )
    unknown = [c for c in config.behind if c not in [cam.name for cam in rig.cameras]]
    if unknown or len(config.behind) >= len(rig.cameras):
        raise UserError(
            f"cannot put camera {unknown[0]!r} behind the board: the rig's cameras are "
            + ", ".join(c.name for c in rig.cameras)
            if unknown
            else "at least one camera must stay in front of the board"
        )
    cameras = tuple(
        dataclasses.replace(cam, rig_T_cam=_behind(config) @ cam.rig_T_cam)
        if cam.name in config.behind
        else cam
        for cam in rig.cameras
    )
    rig = Rig(cameras, rig.depth, frozenset(config.mirrored))
    poses = board_poses(rig, config, np.random.default_rng([config.seed, _POSE_STREAM]))
    model = BoardModel(
        config.board,
        inverted=config.inverted,
        printed_mirrored=config.printed_mirrored,
        paper=config.paper,
        through_paper=config.through_paper,
    )
    offsets, motion = _timing(config, len(rig.cameras))
    return CapturePlan(config, rig, poses, model, offsets, motion)


def _timing(config: CaptureSettings, n_cameras: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Each camera's time offset in each shot and each shot's board motion (see
    :class:`CaptureSettings`), from their own random stream; None when the cameras are in step."""
    if not (config.timing_ms > 0 or config.rolling_ms > 0) or not any(config.speed):
        return None, None
    rng = np.random.default_rng([config.seed, _TIMING_STREAM])
    offsets = rng.uniform(-1.0, 1.0, (config.shots, n_cameras)) * config.timing_ms / 1000.0
    offsets += np.arange(n_cameras) * config.rolling_ms / 1000.0
    directions = rng.normal(size=(config.shots, 2, 3))
    directions /= np.linalg.norm(directions, axis=2, keepdims=True)
    # Mostly still, now and then moving: the cube of a uniform number.
    amounts = rng.uniform(0.0, 1.0, (config.shots, 1)) ** 3 * [
        config.speed[0],
        np.radians(config.speed[1]),
    ]
    motion = (directions * amounts[:, :, None]).reshape(config.shots, 6)
    return offsets, motion


def _with_extra_cameras(rig: Rig, config: CaptureSettings) -> Rig:
    """``rig`` with ``config.extra_cameras`` more cameras (see :class:`CaptureSettings`)."""
    from annotator.synthesis.rig import look_at

    middle = np.array([0.0, 0.0, float(np.mean(config.distance))])
    extra = []
    for k in range(config.extra_cameras):
        eye = np.array([0.0, 120.0 * (k // 2 + 1) * (1 if k % 2 else -1), 0.0])
        extra.append(
            dataclasses.replace(
                rig.cameras[-1], name=f"cam{len(rig.cameras) + k}", rig_T_cam=look_at(eye, middle)
            )
        )
    return Rig(tuple(rig.cameras) + tuple(extra), rig.depth, rig.flipped)


def _behind(config: CaptureSettings) -> np.ndarray:
    """Half a turn about the vertical through the middle of the working distance on the
    reference camera's axis: a camera moved so turns to face the rig from the far side."""
    T = make_transform(axis_angle(np.array([0.0, 1.0, 0.0]), np.pi), np.zeros(3))
    middle = np.array([0.0, 0.0, float(np.mean(config.distance))])
    T[:3, 3] = middle - T[:3, :3] @ middle
    return T


def write_truth(plan: CapturePlan, root: Path) -> None:
    """``board.yaml`` (the board, read by ``annotator calibrate``) and ``truth.yaml`` (the rig
    in dataset.yaml's ``rig:`` format, each shot's ``rig_T_board`` and the settings)."""
    cfg = plan.config
    board = dataclasses.replace(cfg.board, inverted=cfg.inverted or None)
    doc = board.to_yaml()
    if board.has_markers and not is_predefined(board.dictionary):
        # The dictionary travels with the captures, named relative to board.yaml.
        shutil.copyfile(board.dictionary, root / DICTIONARY_FILE)
        doc["dictionary"] = DICTIONARY_FILE
    write_text(root / BOARD_FILE, yaml.safe_dump(doc, sort_keys=False))
    doc = {
        "rig": rig_to_yaml(plan.rig),
        "board_poses": {
            name: [round(float(v), 9) for v in T.ravel()]
            for name, T in zip(plan.shot_names, plan.poses)
        },
        "synth": {
            "shots": cfg.shots,
            "seed": cfg.seed,
            "size": list(cfg.size),
            "distance_mm": list(cfg.distance),
            "max_tilt_deg": cfg.max_tilt_deg,
            "min_visible": cfg.min_visible,
            "noise": cfg.noise,
            "blur": cfg.blur,
            "supersample": cfg.supersample,
            "inverted": cfg.inverted,
            "mirrored": list(cfg.mirrored),
            "centre": cfg.centre,
            "behind": list(cfg.behind),
            "turned": list(cfg.turned),
            "through_paper": list(cfg.through_paper),
            "extra_cameras": cfg.extra_cameras,
        },
    }
    if cfg.printed_mirrored or cfg.paper_blur:
        doc["synth"].update(printed_mirrored=cfg.printed_mirrored, paper_blur=cfg.paper_blur)
    if plan.offsets is not None:
        # Only when the cameras are not in step: the truth of captures that are stays as it was.
        doc["synth"].update(
            timing_ms=cfg.timing_ms, rolling_ms=cfg.rolling_ms, speed=list(cfg.speed)
        )
        doc["camera_offsets_s"] = {
            name: {cam.name: round(float(dt), 6) for cam, dt in zip(plan.rig.cameras, row)}
            for name, row in zip(plan.shot_names, plan.offsets)
        }
    header = (
        "# The truth behind these synthetic captures (annotator synth --calibration):\n"
        "# rig: the rig that rendered them, in dataset.yaml's format; board_poses: rig_T_board\n"
        "# of every shot (16 floats, row-major, mm).\n"
    )
    write_text(
        root / TRUTH_FILE,
        header + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=200),
    )


@dataclass(frozen=True)
class ShotJob:
    """Render and write one shot (a job of :func:`annotator.runner.run_batch`, picklable)."""

    config: CaptureSettings
    root: str

    def prepare(self) -> None:
        """Plan the captures and tabulate the cameras' rays once, before workers fork."""
        for cam in _plan(self.config).rig.cameras:
            cam.pixel_rays()

    def __call__(self, shot: str) -> dict:
        plan = _plan(self.config)
        images = plan.render(plan.shot_names.index(shot))
        for cam, img in zip(plan.rig.cameras, images):
            stored = orient_image(img, cam.name in plan.rig.flipped)
            write_png(Path(self.root) / cam.name / f"{shot}.png", stored)
        return {}


_POSE_STREAM, _NOISE_STREAM, _TIMING_STREAM = 7919, 104729, 15485863
_PLANS: dict[CaptureSettings, CapturePlan] = {}


def _plan(config: CaptureSettings) -> CapturePlan:
    if config not in _PLANS:
        _PLANS[config] = plan_captures(config)
    return _PLANS[config]


def write_captures(
    config: CaptureSettings,
    out: Path,
    *,
    workers: int = 1,
    quiet: bool = True,
    video: bool = False,
) -> CapturePlan:
    """Render every shot of ``config`` into the new folder ``out`` (``<camera>/<shot>.png``,
    board.yaml, truth.yaml; with ``video``, one video per camera instead of its images),
    written whole or not at all; returns the plan (the rig and the shots).

    Raises:
        UserError: a shot failed to render (nothing is written).
    """
    from annotator.io.atomic import atomic_folder
    from annotator.io.output_folder import write_manifest
    from annotator.runner import run_batch

    with atomic_folder(out) as tmp:
        write_manifest(tmp, command="synth")
        plan = plan_captures(config)
        write_truth(plan, tmp)
        report = run_batch(
            ShotJob(config, str(tmp)),
            plan.shot_names,
            workers=workers,
            desc="synth --calibration",
            quiet=quiet,
        )
        if report.failed:
            report.print_failures()
            raise UserError(f"{len(report.failed)} shots failed to render; nothing written")
        if video:
            write_videos(tmp, [c.name for c in plan.rig.cameras])
    return plan
