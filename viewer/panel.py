"""One page's control panel: title and progress, what went wrong, the scene's warnings, the
buttons and hotkeys, and the instance table with one "Zoom on" button per instance. It shows a :class:`PanelView` and calls a
:class:`PanelActions` (the page's session); it decides nothing itself.

Hotkeys (none on W A S D Q E or the arrows, which move the 3D camera):

=====  ==========================================================================
Y      accept the scene and go to the next
N      reject the scene and go to the next
J / K  next / previous scene (of the filter)
F      next flagged scene
I      select the next instance and zoom on it
T      toggle the selected instance (accepted <-> rejected)
Z      open / close the zoom
O      outline / fill in the zoom
B      blink the rendered part over the zoom (on / off)
M      "a part has no pose here": the next click on a picture marks it
V      3D view (parts, depth points, cameras) / back to the pictures
=====  ==========================================================================
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import viser

from annotator.dataset.review import ReviewStatus
from viewer.state import FILTERS, SceneInfo

PANEL_WIDTH = 480  # CSS pixels

HOTKEYS: tuple[tuple[str, str, str], ...] = (
    # (key, command label, action name)
    ("Y", "Accept scene", "accept"),
    ("N", "Reject scene", "reject"),
    ("J", "Next scene", "next"),
    ("K", "Previous scene", "previous"),
    ("F", "Next flagged scene", "next_flagged"),
    ("I", "Select next instance", "select_next"),
    ("T", "Toggle selected instance", "toggle_instance"),
    ("Z", "Open / close the zoom", "toggle_zoom"),
    ("O", "Outline / fill in the zoom", "toggle_fill"),
    ("B", "Blink the rendered part", "toggle_blink"),
    ("M", "A part has no pose here (then click it)", "arm_missing"),
    ("V", "3D view / pictures", "toggle_3d"),
)


class PanelActions(Protocol):
    """What the panel's buttons and hotkeys do (implemented by the page's session)."""

    def accept(self) -> None: ...
    def reject(self) -> None: ...
    def next(self) -> None: ...
    def previous(self) -> None: ...
    def next_flagged(self) -> None: ...
    def select_next(self) -> None: ...
    def toggle_instance(self) -> None: ...
    def toggle_zoom(self) -> None: ...
    def toggle_fill(self) -> None: ...
    def toggle_blink(self) -> None: ...
    def arm_missing(self) -> None: ...
    def toggle_3d(self) -> None: ...
    def set_filter(self, flt: str) -> None: ...
    def select(self, key: str) -> None: ...
    def set_instance(self, status: ReviewStatus) -> None: ...


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


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def instance_table(info: SceneInfo, selected: str | None) -> str:
    """The instances of a scene with what there is to trust or distrust, as markdown."""
    rows = [
        "| | instance | state | flags | mk | px | mm | occl | depth |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for p in info.poses:
        mark = "▶" if p.key == selected else ""
        flags = ", ".join(f.replace("_", " ") for f in p.flags) or "-"
        rows.append(
            f"| {mark} | {p.key} | {info.instance_status(p.key)} | {flags} | "
            f"{p.count('used')}/{p.count('rejected')} | {_fmt(p.reprojection_rms, '.2f')} | "
            f"{_fmt(p.uncertainty_mm, '.2f')} | {_fmt(p.occlusion_rate, '.2f')} | "
            f"{_fmt(p.depth_agreement, '.2f')} |"
        )
    rows.append(
        "\nmk: markers used/rejected · px: reprojection RMS · mm: estimated uncertainty · "
        "occl: occlusion rate · depth: depth agreement"
    )
    return "\n".join(rows)


def warnings_text(info: SceneInfo) -> str:
    """The scene's annotation warnings, unexplained-depth regions listed (markdown)."""
    lines = []
    for w in info.warnings:
        lines.append(f"- **{w.kind.replace('_', ' ')}**: {w.message}")
        for r in w.regions:
            lines.append(f"    - <span style='color:#e00'>■</span> {r.describe()}")
    for m in info.review.missing:
        lines.append(f"- no pose here: {m.camera} ({m.pixel[0]:.0f}, {m.pixel[1]:.0f})")
    return "\n".join(lines)


class Panel:
    """The GUI of one page (``gui`` is that client's ``client.gui``)."""

    def __init__(self, gui: viser.GuiApi, actions: PanelActions) -> None:
        self._gui = gui
        gui.configure_theme(control_width="large", show_share_button=False)
        # Docked, the panel takes its width from the canvas instead of covering the mosaic.
        gui.main_panel.dock_right()
        gui.main_panel.set_width(PANEL_WIDTH)
        self.title = gui.add_markdown("")
        self.alert = gui.add_markdown("", visible=False)
        self.notice = gui.add_markdown("", visible=False)
        self.progress = gui.add_progress_bar(0.0)
        self.progress_text = gui.add_markdown("")
        self.warnings = gui.add_markdown("", visible=False)
        with gui.add_folder("Scene"):
            self.filter = gui.add_dropdown("Filter", FILTERS, initial_value="all")
            self._button("Accept scene (Y)", actions.accept, color="green")
            self._button("Reject scene (N)", actions.reject, color="red")
            self._button("Previous (K)", actions.previous)
            self._button("Next (J)", actions.next)
            self._button("Next flagged (F)", actions.next_flagged)
            self._button("No pose here… (M, then click)", actions.arm_missing)
        with gui.add_folder("Instances"):
            # viser's tables are markdown, whose rows cannot be clicked: one button per row.
            self.instances = gui.add_button_group("Zoom on", ["-"])
            self.table = gui.add_markdown("")
            self._button("Accept instance", lambda: actions.set_instance(ReviewStatus.ACCEPTED))
            self._button("Reject instance", lambda: actions.set_instance(ReviewStatus.REJECTED))
            self._button("Toggle instance (T)", actions.toggle_instance)
        with gui.add_folder("Zoom and view"):
            self._button("Open / close zoom (Z)", actions.toggle_zoom)
            self._button("Outline / fill (O)", actions.toggle_fill)
            self._button("Blink rendered part (B)", actions.toggle_blink)
            self._button("3D view / pictures (V)", actions.toggle_3d)
        self.filter.on_update(lambda _: actions.set_filter(self.filter.value))
        self.instances.on_click(lambda event: actions.select(event.target.value))
        for key, text, name in HOTKEYS:
            cmd = gui.add_command(text, hotkey=key, modifier=None)  # type: ignore[arg-type]
            action = getattr(actions, name)
            cmd.on_trigger(lambda _, fn=action: fn())

    def _button(self, text: str, fn: Callable[[], None], color: str | None = None) -> None:
        button = self._gui.add_button(text, color=color)  # type: ignore[arg-type]
        button.on_click(lambda _: fn())

    def show(self, view: PanelView, keys: list[str]) -> None:
        """Update every element (viser sends only what changed); ``keys`` are the scene's
        instances, one "Zoom on" button each."""
        self.title.content = view.title
        self.alert.content = view.alert
        self.alert.visible = bool(view.alert)
        self.notice.content = view.notice
        self.notice.visible = bool(view.notice)
        self.progress.value = view.progress
        self.progress_text.content = view.progress_text
        self.table.content = view.table
        options = tuple(keys) or ("-",)  # viser wants at least one button
        if tuple(self.instances.options) != options:
            self.instances.options = options
        self.instances.visible = bool(keys)
        self.warnings.content = view.warnings
        self.warnings.visible = bool(view.warnings)
