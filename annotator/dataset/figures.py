"""The figures annotation.json keeps beside each pose and scene, as typed records: which
markers were used (:class:`MarkerUse`), how well they reproject (:class:`Reprojection`),
how the depth agrees (:class:`DepthCheck`), whether the pile is possible
(:class:`PhysicsCheck`), how hidden a part is (:class:`Occlusion`), and the scene's
warnings (:class:`SceneWarning`, :class:`DepthRegion`) and image figures
(:class:`ImageQuality`).

Each record has ``to_json`` and ``from_json``; the JSON written is exactly the layout of
docs/FORMAT.md. Numbers are kept as read (the reader has checked them), fields a record does
not know are kept in its ``extra`` (``details`` for a warning) and written back after the
known ones.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from annotator.dataset.flags import Flag, WarningKind, known_member
from annotator.geometry import Rect

__all__ = [
    "SUPPORT",
    "DepthCheck",
    "DepthRegion",
    "ImageQuality",
    "MarkerUse",
    "Occlusion",
    "PhysicsCheck",
    "Reprojection",
    "SceneWarning",
    "depth_regions",
    "image_qualities",
]

#: The partner a physics figure names when it is the support, not another part.
SUPPORT = "support"


def _extra(doc: dict[str, Any], known: tuple[str, ...]) -> dict[str, Any]:
    """The fields of ``doc`` a record does not know, kept to be written back."""
    return {k: v for k, v in doc.items() if k not in known}


@dataclass
class MarkerUse:
    """An instance's markers in one camera: ``used`` by the pose, ``rejected`` by the
    consensus, and those of ``used`` that were ``recovered`` (read only with the pose's help,
    through the blur model). ``extra``: fields this version does not know, kept as read.

    >>> MarkerUse(used=[18, 9], rejected=[2]).to_json()
    {'used': [18, 9], 'rejected': [2]}
    """

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
    does not say), and RMS per camera.

    >>> Reprojection.from_json({"rms": 0.17, "max": 0.36, "per_camera": {"left": 0.19}}).per_camera
    {'left': 0.19}
    """

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
    difference (mm), and the number of pixels compared (None where a file does not say).

    >>> DepthCheck.from_json({"agreement": 0.97, "median_abs_mm": 0.24, "pixels": 48076})
    DepthCheck(agreement=0.97, median_abs_mm=0.24, pixels=48076, extra={})
    """

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

    >>> PhysicsCheck(penetration_mm=1.5, penetrates="brick/01").to_json()["penetrates"]
    'brick/01'
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
    camera.

    >>> Occlusion(rate=0.25).to_json()
    {'rate': 0.25, 'per_camera': {}}
    """

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

    >>> r = DepthRegion((10, 20, 50, 60), pixels=900)
    >>> DepthRegion.from_json(r.to_json()) == r
    True
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

    >>> from annotator.dataset.flags import WarningKind
    >>> w = SceneWarning(WarningKind.NOTE, "a part moved between frames")
    >>> w.text
    'a part moved between frames'
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
            known_member(WarningKind, kind),
            "" if message is None else str(message),
            regions,
            cameras,
            d,
        )


def depth_regions(
    warnings: list[SceneWarning] | tuple[SceneWarning, ...],
) -> tuple[DepthRegion, ...]:
    """Every unexplained-depth region of the warnings."""
    return tuple(r for w in warnings if w.kind == WarningKind.UNEXPLAINED_DEPTH for r in w.regions)


@dataclass
class ImageQuality:
    """One camera's image figures: the edge blur (px, None where no marker edge was
    measured), the median grey level and the fraction of saturated pixels, and the grey
    levels of the detected markers' printed white and black (None where no marker was read
    or a file does not say); ``extra``: fields this version does not know."""

    edge_blur_px: float | None
    median: float | None
    saturated: float | None
    extra: dict[str, Any] = field(default_factory=dict)
    marker_white: float | None = None
    marker_black: float | None = None

    def to_json(self) -> dict[str, Any]:
        out = {
            "edge_blur_px": self.edge_blur_px,
            "median": self.median,
            "saturated": self.saturated,
        }
        if self.marker_white is not None or self.marker_black is not None:
            out["marker_white"] = self.marker_white
            out["marker_black"] = self.marker_black
        return {**out, **self.extra}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> ImageQuality:
        return cls(
            doc.get("edge_blur_px"),
            doc.get("median"),
            doc.get("saturated"),
            _extra(doc, _QUALITY_FIELDS),
            marker_white=doc.get("marker_white"),
            marker_black=doc.get("marker_black"),
        )


_QUALITY_FIELDS = ("edge_blur_px", "median", "saturated", "marker_white", "marker_black")


def image_qualities(doc: Any) -> dict[str, ImageQuality]:
    """Per camera, its :class:`ImageQuality` (entries that are not mappings are left out:
    the figures are annotate's own, rewritten on the next run)."""
    if not isinstance(doc, dict):
        return {}
    return {str(c): ImageQuality.from_json(q) for c, q in doc.items() if isinstance(q, dict)}
