"""``annotation.json`` as typed records: what ``annotate`` writes and every reader (viewer,
evaluation, export, check) reads, so that a field added here reaches all of them.

The JSON layout is described in :mod:`annotator.annotation`. Each record has ``to_json`` and
``from_json``; the JSON written is exactly the layout of docs/FORMAT.md. Numbers are kept as
read (the reader has checked them), fields a record does not know are kept in its ``extra``
(``details`` for a warning) and written back after the known ones, and a flag or warning
kind this version does not know is kept as its text.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

from annotator.dataset.model import FORMAT_VERSION
from annotator.dataset.poses import InstancePose, read_pose_file, write_poses
from annotator.geometry import Rect
from annotator.geometry.transforms import make_transform


class Flag(StrEnum):
    """Reasons a reviewer should look at an instance, in the order annotation.json lists them."""

    #: A lone marker / single view whose two pose solutions fit about equally well.
    AMBIGUOUS = "ambiguous"
    #: Only one camera's markers were usable.
    SINGLE_VIEW = "single_view"
    #: Reprojection error well above the corner noise.
    HIGH_RESIDUAL = "high_residual"
    #: Some of the instance's markers disagreed with the others and were dropped.
    REJECTED_MARKERS = "rejected_markers"
    #: The depth rendered at the pose disagrees with the measured depth.
    DEPTH_DISAGREEMENT = "depth_disagreement"
    #: Estimated uncertainty above 1% of the part's diameter.
    HIGH_UNCERTAINTY = "high_uncertainty"
    #: Another copy of the part is posed in the same place (a marker on the wrong copy).
    OVERLAP = "overlap"
    #: A sequence's frames disagree about the part: it moved while the rig moved (the pose
    #: is the one most frames agree with).
    MOVED = "moved"
    #: It reaches inside another part or below the support (:attr:`PhysicsCheck.partners`).
    PENETRATES = "penetrates"
    #: Nothing is under it: its lower half is clear of the support and of every part.
    FLOATS = "floats"
    #: Left to gravity (``annotator check --physics --stability``), it moves.
    UNSTABLE = "unstable"


#: What the physics check may flag (:mod:`annotator.physics`).
PHYSICS_FLAGS = (Flag.PENETRATES, Flag.FLOATS, Flag.UNSTABLE)
#: The partner a physics figure names when it is the support, not another part.
SUPPORT = "support"


class WarningKind(StrEnum):
    """What a scene-level warning is about."""

    NO_MARKERS = "no_markers"
    UNEXPLAINED_DEPTH = "unexplained_depth"
    BLURRED = "blurred"
    UNDER_EXPOSED = "under_exposed"
    OVER_EXPOSED = "over_exposed"
    #: Plain text (files of earlier versions, or an entry that is not an object).
    NOTE = "note"


def _known(enum: type[StrEnum], text: str) -> Any:
    """``text`` as a member of ``enum`` when it is one, else the text itself."""
    try:
        return enum(text)
    except ValueError:
        return text


def sort_flags(flags: list[Flag | str]) -> list[Flag | str]:
    """Flags without repeats, in :class:`Flag`'s order (unknown ones last, as found)."""
    known = [f for f in Flag if f in flags]
    return known + [f for f in dict.fromkeys(flags) if f not in known]


def _extra(doc: dict[str, Any], known: tuple[str, ...]) -> dict[str, Any]:
    """The fields of ``doc`` a record does not know, kept to be written back."""
    return {k: v for k, v in doc.items() if k not in known}


@dataclass
class MarkerUse:
    """An instance's markers in one camera: ``used`` by the pose, ``rejected`` by the
    consensus, and those of ``used`` that were ``recovered`` (read only with the pose's help,
    through the blur model). ``extra``: fields this version does not know, kept as read."""

    used: list[int] = field(default_factory=list)
    rejected: list[int] = field(default_factory=list)
    recovered: list[int] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"used": self.used, "rejected": self.rejected}
        if self.recovered:
            out["recovered"] = self.recovered
        return {**out, **self.extra}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> MarkerUse:
        return cls(
            list(doc.get("used", [])),
            list(doc.get("rejected", [])),
            list(doc.get("recovered", [])),
            _extra(doc, ("used", "rejected", "recovered")),
        )


@dataclass
class Reprojection:
    """Reprojection error (px) of the markers used: RMS and worst corner (None where a file
    does not say), and RMS per camera."""

    rms: float | None
    max: float | None
    per_camera: dict[str, float] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"rms": self.rms, "max": self.max, "per_camera": self.per_camera, **self.extra}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> Reprojection:
        return cls(
            doc.get("rms"),
            doc.get("max"),
            dict(doc.get("per_camera") or {}),
            _extra(doc, ("rms", "max", "per_camera")),
        )


@dataclass
class DepthCheck:
    """How the measured depth agrees with the depth rendered at the pose, over the instance's
    visible pixels of the depth camera: the fraction that agree, the median absolute
    difference (mm), and the number of pixels compared (None where a file does not say)."""

    agreement: float | None
    median_abs_mm: float | None
    pixels: int | None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "agreement": self.agreement,
            "median_abs_mm": self.median_abs_mm,
            "pixels": self.pixels,
            **self.extra,
        }

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> DepthCheck:
        return cls(
            doc.get("agreement"),
            doc.get("median_abs_mm"),
            doc.get("pixels"),
            _extra(doc, ("agreement", "median_abs_mm", "pixels")),
        )


@dataclass
class PhysicsCheck:
    """Whether an instance's pose is physically possible in its pile (:mod:`annotator.physics`).

    Attributes:
        penetration_mm: Its deepest overlap with anything (0: none).
        penetrates: What it overlaps most: another instance's key, or ``"support"``.
        gap_mm: How far its lower half is from the nearest thing below; None where the
            support (and so gravity) is unknown.
        rests_on: That nearest thing: a key or ``"support"``.
        fall_mm: With the stability check, how far it moved when left to gravity.
        partners: Per physics flag the instance carries, what it names (a key or
            ``"support"``).
    """

    penetration_mm: float = 0.0
    penetrates: str | None = None
    gap_mm: float | None = None
    rests_on: str | None = None
    fall_mm: float | None = None
    partners: dict[str, str] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "penetration_mm": round(self.penetration_mm, 3),
            "penetrates": self.penetrates,
            "gap_mm": None if self.gap_mm is None else round(self.gap_mm, 3),
            "rests_on": self.rests_on,
        }
        if self.fall_mm is not None:
            out["fall_mm"] = round(self.fall_mm, 3)
        out["partners"] = dict(self.partners)
        return out

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> PhysicsCheck:
        partners = doc.get("partners")
        return cls(
            float(doc.get("penetration_mm") or 0.0),
            doc.get("penetrates"),
            doc.get("gap_mm"),
            doc.get("rests_on"),
            doc.get("fall_mm"),
            dict(partners) if isinstance(partners, dict) else {},
        )

    def describe(self, flags: list[Flag | str]) -> str:
        """What ``flags`` (an instance's) say of the physics, with whom, in words."""
        out = []
        for flag in flags:
            who = self.partners.get(str(flag), "?")
            if flag == Flag.PENETRATES:
                out.append(f"penetrates {who} by {self.penetration_mm:.1f} mm")
            elif flag == Flag.FLOATS:
                out.append(f"floats {self.gap_mm or 0.0:.1f} mm above {who}")
            elif flag == Flag.UNSTABLE:
                out.append(f"falls {self.fall_mm or 0.0:.1f} mm when left to gravity")
        return ", ".join(out)


@dataclass
class Occlusion:
    """Occlusion rate (1 - visible / full silhouette pixels) in the reference camera, with the
    depth test where it is the depth camera (None where a file does not say), and per
    camera."""

    rate: float | None
    per_camera: dict[str, float] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"rate": self.rate, "per_camera": self.per_camera, **self.extra}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> Occlusion:
        return cls(
            doc.get("rate"), dict(doc.get("per_camera") or {}), _extra(doc, ("rate", "per_camera"))
        )


def _optional(record: Any, doc: Any) -> Any:
    """``record.from_json(doc)`` for a mapping; None for None (read_pose_file has checked
    that these fields are mappings, and their numbers)."""
    return None if doc is None else record.from_json(doc)


@dataclass
class InstanceAnnotation:
    """One posed instance and the figures that say how far to trust it.

    Attributes:
        object, instance: Which physical part.
        R, t: Its pose in the reference camera (``x_cam = R x_model + t``, mm).
        uncertainty_mm: Estimated 1-sigma pose error as RMS surface displacement.
        reprojection: Reprojection error of the markers used (``reprojection_px`` in JSON).
        markers: Per camera, the markers used, rejected and recovered.
        views: Number of cameras whose markers were used.
        depth: Agreement with the measured depth, or None (no depth, too few pixels).
        occlusion: Occlusion rates, or None.
        physics: Whether the pose is physically possible in its pile, or None (not checked).
        flags: Reasons to look (:class:`Flag`).
        extra: Fields this version does not know, kept as read.
    """

    object: str
    instance: str
    R: np.ndarray
    t: np.ndarray
    uncertainty_mm: float | None = None
    reprojection: Reprojection | None = None
    markers: dict[str, MarkerUse] = field(default_factory=dict)
    views: int = 0
    depth: DepthCheck | None = None
    occlusion: Occlusion | None = None
    physics: PhysicsCheck | None = None
    flags: list[Flag | str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def key(self) -> str:
        """``object/instance``, the key used in review.json."""
        return f"{self.object}/{self.instance}"

    @property
    def pose(self) -> InstancePose:
        return InstancePose(self.object, self.instance, self.R, self.t, self.to_json_fields())

    @property
    def T(self) -> np.ndarray:  # noqa: N802 - matrix name
        """4x4 ``cam_T_model`` in the reference camera."""
        return make_transform(self.R, self.t)

    @property
    def occlusion_rate(self) -> float | None:
        return None if self.occlusion is None else self.occlusion.rate

    @property
    def depth_agreement(self) -> float | None:
        return None if self.depth is None else self.depth.agreement

    @property
    def reprojection_rms(self) -> float | None:
        return None if self.reprojection is None else self.reprojection.rms

    def count(self, use: str) -> int:
        """Markers ``used``, ``rejected`` or ``recovered``, over every camera."""
        return sum(len(getattr(m, use)) for m in self.markers.values())

    def marker_ids(self, use: str = "used") -> set[int]:
        """Ids of the markers ``used`` (or ``rejected``, ``recovered``) in any camera."""
        return {i for m in self.markers.values() for i in getattr(m, use)}

    def to_json_fields(self) -> dict[str, Any]:
        """Everything but the pose, as JSON fields."""
        out = dict(self.extra)
        out.update(
            uncertainty_mm=self.uncertainty_mm,
            reprojection_px=None if self.reprojection is None else self.reprojection.to_json(),
            markers={c: m.to_json() for c, m in self.markers.items()},
            views=self.views,
            depth=None if self.depth is None else self.depth.to_json(),
            occlusion=None if self.occlusion is None else self.occlusion.to_json(),
            flags=[str(f) for f in self.flags],
        )
        if self.physics is not None:
            out["physics"] = self.physics.to_json()
        return out

    @classmethod
    def from_pose(cls, p: InstancePose) -> InstanceAnnotation:
        e = dict(p.extra)
        known = {k: e.pop(k) for k in _INSTANCE_KEYS if k in e}
        return cls(
            p.object,
            p.instance,
            p.R,
            p.t,
            uncertainty_mm=known.get("uncertainty_mm"),
            reprojection=_optional(Reprojection, known.get("reprojection_px")),
            markers={
                str(c): MarkerUse.from_json(m)
                for c, m in (known.get("markers") or {}).items()
                if isinstance(m, dict)
            },
            views=int(known.get("views") or 0),
            depth=_optional(DepthCheck, known.get("depth")),
            occlusion=_optional(Occlusion, known.get("occlusion")),
            physics=_optional(PhysicsCheck, known.get("physics")),
            flags=[_known(Flag, str(f)) for f in known.get("flags") or []],
            extra=e,
        )


_INSTANCE_KEYS = (
    "physics",
    "uncertainty_mm",
    "reprojection_px",
    "markers",
    "views",
    "depth",
    "occlusion",
    "flags",
)


@dataclass(frozen=True)
class DepthRegion:
    """A connected region of measured depth that no posed part explains, on the depth
    camera's full-resolution grid.

    Attributes:
        box: Its bounding :data:`~annotator.geometry.Rect` (read rounded to whole pixels).
        pixels: Its area in pixels.
        depth_mm: 5th and 95th percentiles of its measured depth.
        unread_markers: Centres (x, y) of the candidate marker squares on it that could not
            be read.
        extra: Fields this version does not know, kept as read.
    """

    box: Rect
    pixels: int | None = None
    depth_mm: tuple[float, float] | None = None
    unread_markers: tuple[tuple[float, float], ...] = ()
    extra: dict[str, Any] = field(default_factory=dict, compare=False)

    def describe(self) -> str:
        x0, y0, x1, y1 = self.box
        out = f"x {x0}-{x1}, y {y0}-{y1}"
        if self.pixels is not None:
            out += f", {self.pixels} px"
        if self.depth_mm is not None:
            out += f", depth {self.depth_mm[0]:.0f}-{self.depth_mm[1]:.0f} mm"
        return out

    def to_json(self) -> dict[str, Any]:
        return {
            "box": list(self.box),
            "pixels": self.pixels,
            "depth_mm": None if self.depth_mm is None else list(self.depth_mm),
            "unread_markers": [list(p) for p in self.unread_markers],
            **self.extra,
        }

    @classmethod
    def from_json(cls, doc: Any) -> DepthRegion | None:
        """The region, or None if ``doc`` has no usable box (the rest is read leniently: a
        field that is not what it should be is left out)."""
        if not isinstance(doc, dict):
            return None
        try:
            box = tuple(int(round(float(v))) for v in doc["box"])
        except (KeyError, TypeError, ValueError):
            return None
        if len(box) != 4:
            return None
        pixels = doc.get("pixels")
        depth_mm = _pair(doc.get("depth_mm"))
        unread = doc.get("unread_markers")
        points = [_pair(p) for p in unread] if isinstance(unread, list) else []
        return cls(
            (box[0], box[1], box[2], box[3]),
            pixels if isinstance(pixels, int) and not isinstance(pixels, bool) else None,
            depth_mm,
            tuple(p for p in points if p is not None),
            _extra(doc, ("box", "pixels", "depth_mm", "unread_markers")),
        )


def _pair(value: Any) -> tuple[float, float] | None:
    """Two numbers as read, or None for anything else (the viewer formats them)."""
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        return None
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        return None
    return (value[0], value[1])


@dataclass(frozen=True)
class SceneWarning:
    """Something about the whole scene a reviewer must know; any warning flags the scene.

    Attributes:
        kind: A :class:`WarningKind` (or the text of a kind this version does not know).
        message: What to tell the reviewer (as written; :attr:`text` is what to show).
        regions: For ``unexplained_depth``: where the depth no pose explains is.
        cameras: For the image-quality kinds: the cameras concerned.
        details: The kind's other fields, kept as read (and ``regions`` or ``cameras`` as
            read, where they were not all readable).
    """

    kind: WarningKind | str
    message: str
    regions: tuple[DepthRegion, ...] = ()
    cameras: tuple[str, ...] = ()
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def text(self) -> str:
        """The message, or the kind in words where there is none."""
        return self.message or str(self.kind).replace("_", " ")

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"kind": str(self.kind), "message": self.message}
        if self.regions:
            out["regions"] = [r.to_json() for r in self.regions]
        if self.cameras:
            out["cameras"] = list(self.cameras)
        out.update(self.details)
        return out

    @classmethod
    def from_json(cls, doc: Any) -> SceneWarning:
        """A warning from its JSON entry, never dropping one: a plain string (files of
        earlier versions) or anything else that is not an object is a ``note`` saying what
        the entry said."""
        if isinstance(doc, str):
            return cls(WarningKind.NOTE, doc)
        if not isinstance(doc, dict):
            return cls(WarningKind.NOTE, json.dumps(doc))
        d = dict(doc)
        kind = str(d.pop("kind", None) or WarningKind.NOTE)
        message = d.pop("message", None)
        regions: tuple[DepthRegion, ...] = ()
        if isinstance(d.get("regions"), list) and d["regions"]:
            read = [DepthRegion.from_json(r) for r in d["regions"]]
            regions = tuple(r for r in read if r is not None)
            if len(regions) == len(read):
                del d["regions"]
        cameras: tuple[str, ...] = ()
        if isinstance(d.get("cameras"), list) and d["cameras"]:
            if all(isinstance(c, str) for c in d["cameras"]):
                cameras = tuple(d.pop("cameras"))
        return cls(
            _known(WarningKind, kind), "" if message is None else str(message), regions, cameras, d
        )


def depth_regions(
    warnings: list[SceneWarning] | tuple[SceneWarning, ...],
) -> tuple[DepthRegion, ...]:
    """Every unexplained-depth region of the warnings."""
    return tuple(r for w in warnings if w.kind == WarningKind.UNEXPLAINED_DEPTH for r in w.regions)


@dataclass
class ImageQuality:
    """One camera's image figures: the edge blur (px, None where no marker edge was
    measured), the median grey level and the fraction of saturated pixels (None where a file
    does not say); ``extra``: fields this version does not know."""

    edge_blur_px: float | None
    median: float | None
    saturated: float | None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "edge_blur_px": self.edge_blur_px,
            "median": self.median,
            "saturated": self.saturated,
            **self.extra,
        }

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> ImageQuality:
        return cls(
            doc.get("edge_blur_px"),
            doc.get("median"),
            doc.get("saturated"),
            _extra(doc, ("edge_blur_px", "median", "saturated")),
        )


@dataclass
class SceneAnnotation:
    """A scene's annotation.json.

    Attributes:
        instances: The posed instances.
        warnings: Scene-level warnings (completeness and image quality).
        image_quality: Per camera, its :class:`ImageQuality`.
        unknown_markers: ``{camera: [ids]}`` read but belonging to no instance.
        unconfirmed_markers: ``{camera: [ids]}`` of poses left out because the measured depth
            contradicted them and nothing else supported them.
        duplicates: ``{camera: [ids]}`` seen twice in one image.
        unexplained_mask: File name of the unexplained-depth mask beside annotation.json
            (uint8 PNG on the depth camera's grid, 255 = unexplained), or None.
        created_at, description_digest, errors: Provenance.
        extra: Top-level fields this version does not know.
    """

    instances: list[InstanceAnnotation] = field(default_factory=list)
    warnings: list[SceneWarning] = field(default_factory=list)
    image_quality: dict[str, ImageQuality] = field(default_factory=dict)
    unknown_markers: dict[str, list[int]] = field(default_factory=dict)
    unconfirmed_markers: dict[str, list[int]] = field(default_factory=dict)
    duplicates: dict[str, list[int]] = field(default_factory=dict)
    unexplained_mask: str | None = None
    created_at: str | None = None
    description_digest: str | None = None
    errors: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def flagged(self) -> bool:
        """True if a reviewer should look: a warning or a flagged instance."""
        return bool(self.warnings) or any(i.flags for i in self.instances)

    def write(self, path: str | Path) -> None:
        """Write annotation.json atomically."""
        top = dict(self.extra)
        top.update(
            format=FORMAT_VERSION,
            created_at=self.created_at,
            description_digest=self.description_digest,
            unknown_markers=self.unknown_markers,
            unconfirmed_markers=self.unconfirmed_markers,
            duplicates=self.duplicates,
            image_quality={c: q.to_json() for c, q in self.image_quality.items()},
            unexplained_mask=self.unexplained_mask,
            warnings=[w.to_json() for w in self.warnings],
            errors=self.errors,
        )
        write_poses(path, [i.pose for i in self.instances], **top)

    @classmethod
    def read(cls, path: str | Path) -> SceneAnnotation:
        """Read annotation.json (UserError naming the file if it is malformed)."""
        poses, top = read_pose_file(path)
        top = dict(top)
        top.pop("format", None)
        return cls(
            instances=[InstanceAnnotation.from_pose(p) for p in poses],
            warnings=[SceneWarning.from_json(w) for w in top.pop("warnings", None) or []],
            image_quality=_qualities(top.pop("image_quality", None)),
            unknown_markers=top.pop("unknown_markers", None) or {},
            unconfirmed_markers=top.pop("unconfirmed_markers", None) or {},
            duplicates=top.pop("duplicates", None) or {},
            unexplained_mask=top.pop("unexplained_mask", None),
            created_at=top.pop("created_at", None),
            description_digest=top.pop("description_digest", None),
            errors=list(top.pop("errors", None) or []),
            extra=top,
        )


def _qualities(doc: Any) -> dict[str, ImageQuality]:
    """Per camera, its :class:`ImageQuality` (entries that are not mappings are left out:
    the figures are annotate's own, rewritten on the next run)."""
    if not isinstance(doc, dict):
        return {}
    return {str(c): ImageQuality.from_json(q) for c, q in doc.items() if isinstance(q, dict)}
