"""What the review panel says, as text: the scene's title, status and progress, red alerts
(a decision not saved, another reviewer's decision over ours), notices (problems with the
scene's files, the armed "no pose here" click, the parts offered to add), the instance table
and the annotation's warnings. Pure functions of the scene's state and the page's; the
widgets that show them are :mod:`viewer.page.panel`'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from annotator.dataset.records import InstanceAnnotation
from annotator.review import SceneInfo
from viewer.page.editor import Offer


@dataclass
class PanelView:
    """Everything the panel shows, as text."""

    title: str
    alert: str = ""  # red: a decision not saved, another reviewer's overriding decision
    notice: str = ""  # problems with the scene's files, the armed "no pose here" click
    progress: float = 0.0  # percent
    progress_text: str = ""
    table: str = ""
    warnings: str = ""
    repair: str = ""  # what the last repair did (residuals), or what it is doing
    offer: tuple[str, ...] = ()  # instances without a pose, to add where M was clicked


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def instance_table(info: SceneInfo, selected: str | None) -> str:
    """The instances of a scene with what there is to trust or distrust, as markdown."""
    rows = [
        "| | instance | state | flags | mk | px | mm | occl | depth | phys |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for p in info.poses:
        mark = "▶" if p.key == selected else ""
        state = str(info.instance_status(p.key))
        if p.key in info.edited:
            state += " · ✎ edited"
        elif p.key in info.stale_edits:
            state += " · ✎ edit stale"
        flags = ", ".join(_flag_text(p, f) for f in p.flags) or "-"
        phys = p.physics
        physics = (
            "-"
            if phys is None
            else f"{phys.penetration_mm:.1f}/{'-' if phys.gap_mm is None else f'{phys.gap_mm:.1f}'}"
        )
        rows.append(
            f"| {mark} | {p.key} | {state} | {flags} | "
            f"{p.count('used')}/{p.count('rejected')} | {_fmt(p.reprojection_rms, '.2f')} | "
            f"{_fmt(p.uncertainty_mm, '.2f')} | {_fmt(p.occlusion_rate, '.2f')} | "
            f"{_fmt(p.depth_agreement, '.2f')} | {physics} |"
        )
    rows.append(
        "\nmk: markers used/rejected · px: reprojection RMS · mm: estimated uncertainty · "
        "occl: occlusion rate · depth: depth agreement · phys: deepest penetration / gap "
        "below, mm · ✎: pose repaired in review.json "
        "(export and evaluate use it)"
    )
    return "\n".join(rows)


def _flag_text(p: InstanceAnnotation, flag: str) -> str:
    """A flag in words; a physics flag with the part (or support) it concerns."""
    partner = p.physics.partners.get(str(flag)) if p.physics is not None else None
    return str(flag).replace("_", " ") + (f" {partner}" if partner else "")


def warnings_text(info: SceneInfo) -> str:
    """The scene's annotation warnings, unexplained-depth regions listed (markdown)."""
    lines = []
    for w in info.warnings:
        lines.append(f"- **{str(w.kind).replace('_', ' ')}**: {w.text}")
        for r in w.regions:
            lines.append(f"    - <span style='color:#e00'>■</span> {r.describe()}")
    for m in info.review.missing:
        lines.append(f"- no pose here: {m.camera} ({m.pixel[0]:.0f}, {m.pixel[1]:.0f})")
    return "\n".join(lines)


def panel_view(
    info: SceneInfo,
    *,
    position: tuple[int, int],
    filter: str,
    selected: str | None,
    messages: Sequence[str] = (),
    unsaved: str | None = None,
    alerts: Sequence[str] = (),
    armed: bool = False,
    offer: Offer | None = None,
    progress: tuple[int, int] = (0, 0),
    pace: float = 0.0,
    repair: str = "",
) -> PanelView:
    """The panel for scene ``info``, ``position`` (k, n) its place among the n scenes.

    Args:
        messages: Problems with the scene's files (the prepared overlays' messages).
        unsaved: Why this page's decision about the scene is not saved, if it is not.
        alerts: Other reviewers' decisions over this page's, still to repeat.
        armed: The next click on a picture marks a part without a pose.
        offer: The parts offered to add where the reviewer clicked (for this scene only).
        progress: (scenes with a current decision, scenes); pace: decisions per minute.
        repair: What the last repair did.

    >>> from annotator.review import SceneInfo
    >>> from annotator.dataset.review import Review
    >>> info = SceneInfo("000003", True, (), Review(), False, False, None)
    >>> panel_view(info, position=(4, 10), filter="all", selected=None).title
    '## Scene 000003\\n**pending** · 4 of 10 · filter: all'
    """
    sid = info.id
    status = "**gone**" if info.gone else f"**{info.status}**"
    status += " (stale: the annotation changed since)" if info.stale else ""
    if info.review.reason:
        status += f" — {info.review.reason}"
    title = f"## Scene {sid}\n{status} · {position[0]} of {position[1]} · filter: {filter}"
    if info.shown:
        title += "\n\n" + frames_text(info)
    red = ([f"⛔ {unsaved}"] if unsaved else []) + [f"⚠ {a}" for a in alerts]
    messages = list(messages)
    if not info.annotated and not info.gone:
        messages.append(f"scene {sid} has no annotation.json: run `annotator annotate` first")
    if info.error and not info.gone:  # a gone scene's is the page's alert
        messages.append(info.error)
    notice = "\n\n".join(f"⚠ {m}" for m in messages)
    if armed:
        notice = "**Click on a picture where a part without a pose lies** (M again to cancel)" + (
            f"\n\n{notice}" if notice else ""
        )
    if offer is not None and offer.scene == sid:
        x, y = offer.pixel
        notice = (
            f"**Add a part at {offer.camera} ({x:.0f}, {y:.0f})**: pick "
            "the instance below (then R to refine it)" + (f"\n\n{notice}" if notice else "")
        )
    else:
        offer = None
    done, total = progress
    eta = f", about {(total - done) / pace:.0f} min left" if pace > 0 else ""
    return PanelView(
        title=title,
        alert="\n\n".join(f"<span style='color:#d00'>{a}</span>" for a in red),
        notice=notice,
        progress=100.0 * done / max(total, 1),
        progress_text=f"reviewed {done} / {total} · {pace:.1f} scenes/min{eta}",
        table=instance_table(info, selected),
        warnings=warnings_text(info),
        repair=repair,
        offer=offer.instances if offer is not None else (),
    )


def frames_text(info: SceneInfo) -> str:
    """A sequence's line: the frames shown (each ``<frame>:<camera>`` in the pictures), the
    first one's own decision, and how many frames are posed and rejected.

    >>> from annotator.review import SceneInfo
    >>> from annotator.dataset.review import Review
    >>> info = SceneInfo("s", True, (), Review(frames={"000004": "rejected"}), False, False, None,
    ...                  frames={"000000": None, "000004": None}, shown=("000004", "000000"))
    >>> frames_text(info)
    'frames shown: **000004 (rejected)**, 000000 · 2 frames, 1 rejected · P: next frames, H: reject / restore 000004'
    """
    rejected = info.rejected_frames
    shown = [f"{f} (rejected)" if f in rejected else f for f in info.shown]
    shown[0] = f"**{shown[0]}**"
    return (
        f"frames shown: {', '.join(shown)} · {len(info.frames)} frames, {len(rejected)} "
        f"rejected · P: next frames, H: reject / restore {info.shown[0]}"
    )
