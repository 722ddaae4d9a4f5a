"""A sequence's solve as records (:class:`SequenceSolution`): every frame's ``scene_T_rig``
with its figures and flags, every instance's pose with its uncertainty and flags
(:func:`records`)."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from annotator.annotation.consistency import FrameAgreement, frame_agreement
from annotator.annotation.misreads import rays_meet, worth_a_look
from annotator.annotation.sequence.noise import (
    MOTION_BLUR_PX,
    FrameBlur,
    frame_site_covariance,
    glue_spread,
)
from annotator.annotation.sequence.placing import Placed
from annotator.annotation.settings import AnnotateSettings
from annotator.dataset import Dataset
from annotator.dataset.figures import (
    MarkerUse,
    Reprojection,
    SceneWarning,
)
from annotator.dataset.flags import Flag, FrameFlag, WarningKind, sort_flags
from annotator.dataset.records import (
    FramePose,
    InstanceAnnotation,
)
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import SurfaceMoments
from annotator.geometry.transforms import invert
from annotator.noise import NOISE
from annotator.pnp.bundle import BundleObservations, BundleResult
from annotator.pnp.uncertainty import relative_rms_uncertainty, site_covariance


@dataclass
class SequenceSolution:
    """The solved sequence: instance poses in the scene frame, every frame's pose and
    figures, and the instances' records (markers, reprojection, uncertainty, flags)."""

    reference: str | None
    instances: list[InstanceAnnotation]
    frames: dict[str, FramePose]
    warnings: list[SceneWarning] = field(default_factory=list)
    unknown_markers: dict[str, list[int]] = field(default_factory=dict)
    duplicates: dict[str, list[int]] = field(default_factory=dict)
    #: Per posed frame, how many of each instance's marker observations the solve kept.
    markers_used: dict[str, dict[str, int]] = field(default_factory=dict)
    #: The scale the measured depth gave the sites (1: not measured, or no depth).
    site_scale: float = 1.0


def _uncertainty(
    moments: SurfaceMoments,
    result: BundleResult,
    instance: int,
    frames: np.ndarray,
    sites: np.ndarray,
    site_mm: float,
    site_floor_mm: float,
) -> float:
    """An instance's uncertainty as the frames that see it do (what a frame's export holds):
    the median over them of the RMS surface displacement of its pose relative to the frame's,
    from the joint covariance (a part's pose and the frames' are known together), plus what
    its markers' own errors on the part give (:func:`~annotator.pnp.uncertainty.site_covariance`: the same in every
    frame, so more frames do not average them out); infinite where a direction nothing fixes
    is involved. ``sites``: the corners (model frame) of the markers it was posed on, each
    off by ``site_mm`` on the part (at least ``site_floor_mm``)."""
    T = result.scene_T_model[instance]
    on_part = site_covariance(T[:3, :3], sites, max(site_mm, site_floor_mm))
    values = []
    for f in frames.tolist():
        cov = result.joint_covariance(instance, f)
        cov[:6, :6] += on_part
        if not np.isfinite(cov).all():
            values.append(np.inf)
            continue
        values.append(relative_rms_uncertainty(moments, T, result.scene_T_rig[f], cov))
    return float(np.median(values)) if values else float("inf")


def _kept_sites(
    obs: BundleObservations, ids: np.ndarray, keep: np.ndarray, result: BundleResult
) -> np.ndarray:
    """(M, 4, 3) every site whose marker the solve kept, of every instance, in the scene
    frame."""
    pairs = np.unique(np.c_[obs.instance[keep], ids[keep]], axis=0, return_index=True)[1]
    rows = np.flatnonzero(keep)[pairs]
    T = result.scene_T_model[obs.instance[rows]]  # (M, 4, 4)
    return np.einsum("mij,mkj->mki", T[:, :3, :3], obs.model_corners[rows]) + T[:, None, :3, 3]


def _rejected_markers(
    obs: BundleObservations,
    ids: np.ndarray,
    mine: np.ndarray,
    keep: np.ndarray,
    on_part: Callable[[int], bool],
    ray: Callable[[int], tuple[np.ndarray, np.ndarray]],
) -> bool:
    """True if a marker of the instance was never kept, and read in two frames or more
    where it may be a sticker: each reading ``on_part`` (of the observation's index:
    :func:`~annotator.annotation.misreads.worth_a_look`), and the lines of sight (``ray``,
    origin and direction in the scene frame) of two of them meet
    (:func:`~annotator.annotation.misreads.rays_meet`)."""
    used = set(ids[mine & keep].tolist())
    readings: dict[int, dict[int, int]] = defaultdict(dict)  # id -> frame -> observation
    for k in np.flatnonzero(mine & ~keep):
        if int(ids[k]) not in used and on_part(int(k)):
            readings[int(ids[k])].setdefault(int(obs.frame[k]), int(k))
    for per_frame in readings.values():
        if len(per_frame) < 2:
            continue
        origins, directions = zip(*(ray(k) for k in per_frame.values()))
        if rays_meet(np.array(origins), np.array(directions)):
            return True
    return False


@dataclass
class SolvedSequence:
    """What the sequence's last bundle adjustment leaves for :func:`records`.

    Attributes:
        keys: Every instance, ``(object, instance)``, by its index in the solve.
        names: Every frame folder's name; ``live``: the indices (into ``names``) of the
            frames the solve posed, by their index in the solve.
        obs: Every marker observation; ``ids``: their marker ids; ``keep``: those the solve
            kept; ``err``: their reprojection errors (px) at the solve's poses.
        result: The solve (poses, covariances, corner noise).
        placed: How the frames were first placed (the scene frame, the reasons of those
            left out).
        moved: The instances that moved during the sequence.
        blur: Each posed frame's motion streak.
        agree_px: (N,) each observation's error within which it agrees with the solve.
        site_mm: (I,) each instance's markers' spread off their sites (mm).
        scale: Each observation's marker depth (mm) and the scene scale's 1-sigma (a
            fraction).
    """

    keys: list[tuple[str, str]]
    names: list[str]
    live: list[int]
    obs: BundleObservations
    ids: np.ndarray
    keep: np.ndarray
    result: BundleResult
    err: np.ndarray
    placed: Placed
    moved: set[int]
    blur: FrameBlur
    agree_px: np.ndarray
    site_mm: np.ndarray
    scale: tuple[np.ndarray, float]


def records(ds: Dataset, sv: SolvedSequence, s: AnnotateSettings, out: SequenceSolution) -> None:
    """annotation.json's records from the solve ``sv``, into ``out``: per instance, per
    frame, and the scene's notes."""
    out.reference = sv.names[sv.placed.reference]
    glued = np.array([glue_spread(ds.objects[o], inst) for o, inst in sv.keys])
    agree = np.zeros((len(sv.live), len(sv.keys)), dtype=bool)
    agree[sv.obs.frame[sv.keep], sv.obs.instance[sv.keep]] = True
    kept_sites = _kept_sites(sv.obs, sv.ids, sv.keep, sv.result)
    for i in range(len(sv.keys)):
        r = _instance_record(ds, sv, s, i, max(sv.site_mm[i], glued[i]), agree, kept_sites)
        if r is not None:
            out.instances.append(r)
    out.warnings.extend(_instance_notes(out.instances, s))
    agreement = frame_agreement(
        sv.obs.frame,
        sv.obs.instance,
        sv.ids,
        sv.err < sv.agree_px,
        len(sv.live),
        posed=set(sv.obs.instance[sv.keep].tolist()),
    )
    sites_off = np.maximum(np.maximum(sv.site_mm, s.sequence.site_sigma_mm), glued)
    by_live = {f: n for n, f in enumerate(sv.live)}
    for f, name in enumerate(sv.names):
        n = by_live.get(f)
        out.frames[name] = _frame_record(
            ds, sv, s, f, n, None if n is None else agreement[n], sites_off
        )
        if out.frames[name].scene_T_rig is not None and n is not None:
            mine = (sv.obs.frame == n) & sv.keep
            counts = np.bincount(sv.obs.instance[mine], minlength=len(sv.keys))
            out.markers_used[name] = {
                "/".join(sv.keys[i]): int(c) for i, c in enumerate(counts) if c
            }
    changed = [
        n
        for n in sv.names
        if out.frames[n].has(FrameFlag.INCONSISTENT)
        or "differently from the rest" in (out.frames[n].reason or "")
    ]
    if changed:
        parts = sorted(
            {
                "/".join(sv.keys[i])
                for f in sv.live
                if sv.names[f] in changed
                for i in agreement[by_live[f]].disagreeing
            }
        )
        out.warnings.append(
            SceneWarning(
                WarningKind.NOTE,
                f"frames {', '.join(changed)} place parts ({', '.join(parts)}) differently from "
                "the rest of the sequence: parts moved, or frames of another arrangement (each "
                "frame's reason says which)",
            )
        )


def _marker_uses(
    cams: Sequence[Camera], sv: SolvedSequence, mine: np.ndarray
) -> tuple[dict[str, MarkerUse], dict[str, float]]:
    """Per camera, the markers of the observations ``mine`` the solve kept and those it
    left out, and the kept ones' RMS residual (px)."""
    obs, ids, keep = sv.obs, sv.ids, sv.keep
    markers: dict[str, MarkerUse] = {}
    per_cam: dict[str, float] = {}
    for j, cam in enumerate(cams):
        u = mine & keep & (obs.camera == j)
        r = mine & ~keep & (obs.camera == j)
        if u.any() or r.any():
            good = {int(x) for x in ids[u]}
            markers[cam.name] = MarkerUse(sorted(good), sorted({int(x) for x in ids[r]} - good))
        if u.any():
            per_cam[cam.name] = round(float(np.sqrt(np.mean(sv.err[u] ** 2))), 4)
    return markers, per_cam


def _instance_record(
    ds: Dataset,
    sv: SolvedSequence,
    s: AnnotateSettings,
    i: int,
    site_off_mm: float,
    agree: np.ndarray,
    kept_sites: np.ndarray,
) -> InstanceAnnotation | None:
    """Instance ``i``'s record (None: the solve kept none of its markers); ``site_off_mm``:
    how far its markers sit off their sites; ``agree``: (frames, instances) whether the
    frame's kept markers pose it; ``kept_sites``: see :func:`_kept_sites`."""
    obs, ids, keep, err, result = sv.obs, sv.ids, sv.keep, sv.err, sv.result
    cams = ds.rig.cameras
    obj, inst = sv.keys[i]
    mine = obs.instance == i
    used = mine & keep
    if not used.any():
        return None
    T = result.scene_T_model[i]
    model = ds.objects[obj]
    _, first = np.unique(ids[used], return_index=True)
    corners = obs.model_corners[np.flatnonzero(used)[first]].reshape(-1, 3)
    unc = _uncertainty(
        model.mesh.moments,
        result,
        i,
        np.unique(obs.frame[used]),
        corners,
        site_off_mm,
        s.sequence.site_sigma_mm,
    )
    # The scene's scale, as well as it is known, moves the part along its line of sight.
    unc = float(np.hypot(unc, sv.scale[1] * float(np.median(sv.scale[0][used]))))
    markers, per_cam = _marker_uses(cams, sv, mine)
    rms = float(np.sqrt(np.mean(err[used] ** 2)))
    flags: list[Flag | str] = []
    if i in sv.moved:
        flags.append(Flag.MOVED)
    if rms > s.high_residual_px:
        flags.append(Flag.HIGH_RESIDUAL)

    # A marker left out in a blurred frame is noise; one that two frames or more read
    # and none agrees with is not (glued elsewhere, or another copy's).
    def on_part(k: int) -> bool:
        cam = cams[int(obs.camera[k])]
        cam_T_scene = cam.cam_T_rig @ invert(result.scene_T_rig[int(obs.frame[k])])
        return worth_a_look(cam, cam_T_scene, kept_sites, obs.image_corners[k])

    def ray(k: int) -> tuple[np.ndarray, np.ndarray]:
        cam = cams[int(obs.camera[k])]
        scene_T_cam = result.scene_T_rig[int(obs.frame[k])] @ cam.rig_T_cam
        xy = cam.undistort_pixels(obs.image_corners[k].mean(axis=0))
        return scene_T_cam[:3, 3], scene_T_cam[:3, :3] @ np.array([xy[0], xy[1], 1.0])

    if _rejected_markers(obs, ids, mine, keep, on_part, ray):
        flags.append(Flag.REJECTED_MARKERS)
    if not unc < s.high_uncertainty_fraction * model.mesh.moments.diameter:
        flags.append(Flag.HIGH_UNCERTAINTY)
    if int(agree[:, i].sum()) == 1 and len(per_cam) == 1:
        flags.append(Flag.SINGLE_VIEW)
    return InstanceAnnotation(
        obj,
        inst,
        T[:3, :3].copy(),
        T[:3, 3].copy(),
        uncertainty_mm=round(unc, 4) if np.isfinite(unc) else None,
        reprojection=Reprojection(round(rms, 4), round(float(err[used].max()), 4), per_cam),
        markers=markers,
        views=len(per_cam),
        flags=sort_flags(flags),
        frames_seen=int(agree[:, i].sum()),
    )


def _instance_notes(instances: list[InstanceAnnotation], s: AnnotateSettings) -> list[SceneWarning]:
    """The scene's notes about its instances: markers off their layout, parts that moved."""
    notes = []
    several = [r for r in instances if (r.frames_seen or 0) >= 2]
    off = [r for r in several if Flag.HIGH_RESIDUAL in r.flags]
    if several and len(off) >= s.sequence.glued_share * len(several):
        notes.append(SceneWarning(WarningKind.NOTE, _sites_hint(len(off), len(several))))
    which = [r.key for r in instances if Flag.MOVED in r.flags]
    if which:
        notes.append(
            SceneWarning(
                WarningKind.NOTE,
                f"parts moved during the sequence: {', '.join(which)} (their markers disagree "
                "with their pose in part of the frames; the pose is the one most frames agree with)",
            )
        )
    return notes


def _frame_record(
    ds: Dataset,
    sv: SolvedSequence,
    s: AnnotateSettings,
    f: int,
    n: int | None,
    a: FrameAgreement | None,
    sites_off: np.ndarray,
) -> FramePose:
    """Frame ``f``'s record (``n``: its index in the solve, None if it was left out before;
    ``a``: its agreement with the rest); ``sites_off``: (I,) how far each instance's markers
    sit off their sites (mm)."""
    name = sv.names[f]
    if n is None or a is None:
        reason = sv.placed.reasons[f]
        why_not = None
        if reason == FrameFlag.OUTLIER:
            why_not = "its markers agree with no placed instance's pose"
        return FramePose(name, None, flags=[] if reason is None else [reason], reason=why_not)
    mine = (sv.obs.frame == n) & sv.keep
    if not mine.any():
        return FramePose(
            name, None, flags=[FrameFlag.OUTLIER], reason="none of its markers agree with the solve"
        )
    (unc_mm, unc_deg), (weak_mm, weak_deg) = _frame_uncertainties(ds, sv, s, f, n, mine, sites_off)
    others = ", ".join("/".join(sv.keys[i]) for i in a.disagreeing)
    why = None
    if a.refused:
        why = (
            f"its markers place {len(a.disagreeing)} parts ({others}) differently from the "
            f"rest of the sequence and only {len(a.agreeing)} as it does: another "
            "arrangement, or parts moved"
        )
    elif len(set(sv.ids[mine].tolist())) < 2:
        # One square's two mirror poses fit it about equally well: not evidence enough.
        why = f"it is posed on one marker only ({int(mine.sum())} observations)"
    elif not (
        unc_mm <= s.sequence.frame_max_uncertainty_mm
        and unc_deg <= s.sequence.frame_max_uncertainty_deg
    ):
        why = (
            f"its {int(mine.sum())} marker observations leave its pose uncertain "
            f"(1-sigma {unc_mm:.3g} mm, {unc_deg:.3g} degrees)"
        )
    if why is not None:
        return FramePose(name, None, flags=[FrameFlag.OUTLIER], reason=why)
    rms_f = float(np.sqrt(np.mean(sv.err[mine] ** 2)))
    flags, reasons = _frame_flags(sv, s, n, mine, a, others, rms_f, weak_mm, weak_deg)
    return FramePose(
        name,
        sv.result.scene_T_rig[n],
        reprojection_px=round(rms_f, 4),
        markers_used=int(mine.sum()),
        uncertainty_mm=round(weak_mm, 4),
        uncertainty_deg=round(weak_deg, 4),
        instances={},
        flags=flags,
        reason="; ".join(reasons) if reasons else None,
    )


def _frame_uncertainties(
    ds: Dataset,
    sv: SolvedSequence,
    s: AnnotateSettings,
    f: int,
    n: int,
    mine: np.ndarray,
    sites_off: np.ndarray,
) -> tuple[tuple[float, float], tuple[float, float]]:
    """A posed frame's 1-sigma position (mm) and turn (degrees), as its corners' residuals
    say and as the detector's noise says where it rests on few corners (``mine``: its kept
    observations)."""
    result = sv.result
    T = result.scene_T_rig[n]
    cov = result.frame_covariance[n]
    blur_mm, blur_deg = sv.blur.uncertainty(n, float(ds.rig.cameras[0].K[0, 0]))
    scale_mm = sv.scale[1] * float(np.linalg.norm(T[:3, 3]))  # its distance to the origin
    if f == sv.placed.reference:  # the scene frame: its pose is the gauge, exact
        blur_mm = blur_deg = 0.0
    else:  # the sites it was posed on are off on their parts the same in every frame
        cov = cov + frame_site_covariance(sv.obs, mine, result, T, sites_off)
    unc = _frame_uncertainty(cov, blur_mm, blur_deg, scale_mm)
    # A frame posed on few corners is worth what the detector's noise says of them, not
    # the sequence's median residual (which many sharp frames set): its shift traded
    # against a turn is that much looser than the sequence's corners say.
    weak = int(mine.sum()) < s.sequence.weak_markers and result.sigma_px < NOISE.corner_px
    if weak and f != sv.placed.reference:
        floored = cov + result.frame_covariance[n] * ((NOISE.corner_px / result.sigma_px) ** 2 - 1)
        return unc, _frame_uncertainty(floored, blur_mm, blur_deg, scale_mm)
    return unc, unc


def _frame_flags(
    sv: SolvedSequence,
    s: AnnotateSettings,
    n: int,
    mine: np.ndarray,
    a: FrameAgreement,
    others: str,
    rms_f: float,
    weak_mm: float,
    weak_deg: float,
) -> tuple[list[str], list[str]]:
    """A posed frame's flags and the reasons that explain them."""
    flags: list[str] = []
    reasons: list[str] = []
    if not (
        weak_mm <= s.sequence.frame_max_uncertainty_mm
        and weak_deg <= s.sequence.frame_max_uncertainty_deg
    ):
        flags.append(FrameFlag.WEAK_GEOMETRY)
        n_parts = len(set(sv.obs.instance[mine].tolist()))
        reasons.append(
            f"weak geometry: posed on {int(mine.sum())} marker observations of {n_parts} parts, "
            f"at the detector's {NOISE.corner_px:g} px a corner (not the sequence's "
            f"{sv.result.sigma_px:.2g} px) its pose is uncertain {weak_mm:.3g} mm, "
            f"{weak_deg:.3g} degrees (1-sigma)"
        )
    if rms_f > s.sequence.high_reprojection_px:
        flags.append(FrameFlag.HIGH_REPROJECTION)
    if int(mine.sum()) < s.sequence.few_markers:
        flags.append(FrameFlag.FEW_MARKERS)
    if sv.blur.streak_px[n] >= MOTION_BLUR_PX:
        flags.append(FrameFlag.MOTION_BLUR)
        reasons.append(
            f"motion blur: its markers are smeared {sv.blur.streak_px[n]:.3g} px, and which "
            "instant of the exposure its pose stands for is not known"
        )
    if a.inconsistent:
        flags.append(FrameFlag.INCONSISTENT)
        reasons.append(
            f"its markers place {len(a.disagreeing)} parts ({others}) differently from the "
            "rest of the sequence: parts moved, or another arrangement"
        )
    if a.single_part and len(sv.keys) > 1:
        flags.append(FrameFlag.SINGLE_PART)
        reasons.append(
            f"posed on the markers of one part only ({'/'.join(sv.keys[a.agreeing[0]])}): "
            "nothing in it checks that part against the rest"
        )
    return flags, reasons


def _frame_uncertainty(
    cov: np.ndarray, blur_mm: float, blur_deg: float, scale_mm: float
) -> tuple[float, float]:
    """A frame's 1-sigma position (mm) and turn (degrees) from its ``(w, v)`` covariance, its
    streak's spread and the scene's scale."""
    mm = float(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0) + blur_mm**2 + scale_mm**2))
    deg = float(np.sqrt(np.degrees(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))) ** 2 + blur_deg**2))
    return mm, deg


def _sites_hint(off: int, parts: int) -> str:
    """The one line that says the markers are not where the layout puts them."""
    return (
        f"the markers of {off} of {parts} parts sit off their layout in every frame (glued by "
        "hand?): their spread is in the uncertainties; `annotator sites` measures where they "
        "are, and annotating again then tightens the poses"
    )
