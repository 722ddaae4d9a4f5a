"""One page's control panel: title and progress, what went wrong, the scene's warnings, the
buttons and hotkeys, the instance table with one "Zoom on" button per instance, and the
repair folder (what the last repair did, "Add here" after M and a click, the nudge buttons).
It shows a :class:`PanelView` and calls a :class:`PanelActions` (the page's session); it
decides nothing itself.

Hotkeys (none on W S D Q E or the arrows, which move viser's 3D camera; A, which it takes
too, and any review key typed at a camera key's place on another keyboard layout, is kept
from it while the pictures are shown, see :mod:`viewer.page.keyguard`):

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
M      "a part has no pose here": the next click on a picture marks it (and offers
       the instances without a pose, to add there)
V      3D view (parts, depth points, cameras) / back to the pictures
R      refine the selected instance (depth ICP with its markers)
A / C  the selected instance's next candidate pose (from its markers)
1-6    nudge the selected instance: -x +x -y +y -z +z of the reference camera
G      nudges move / turn (about the part's centre)
L      small (1 mm, 1 degree) / large (10 mm, 10 degrees) nudges
U      undo the last pose edit of this scene (Shift+U: redo)
X      reset the selected instance to the auto-annotation
P      a sequence: show the next frames side by side (Shift+P: the previous ones)
H      a sequence: reject the first frame shown on its own (again: take it back);
       Y accepts the scene as a whole, its rejected frames left out of the export
=====  ==========================================================================
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import viser

from annotator.dataset.review import ReviewStatus
from annotator.review import FILTERS
from viewer.page.keyguard import guard_html
from viewer.page.panel_text import PanelView

PANEL_WIDTH = 480  # CSS pixels
_GUARD_ORDER = -1e9  # first: an empty element, it takes no room

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
    ("R", "Refine the selected instance", "refine"),
    # viser's 3D camera takes A too (its W A S D): viewer.keyguard keeps it from the camera
    # while the pictures are shown. C is the same command on a key the camera never takes.
    ("A", "Next candidate pose", "alternative"),
    ("C", "Next candidate pose (as A)", "alternative"),
    ("G", "Nudges move / turn", "toggle_nudge_kind"),
    ("L", "Small / large nudges", "toggle_nudge_size"),
    ("U", "Undo a pose edit", "undo"),
    ("X", "Reset the instance to the auto-annotation", "reset_pose"),
    # A sequence's scene: which frames are shown, and one frame rejected on its own.
    ("P", "Show the next frames of the sequence", "next_frames"),
    ("H", "Reject / restore the first frame shown", "toggle_frame"),
)
#: Nudge keys: (key, camera axis, sign).
NUDGE_KEYS: tuple[tuple[str, int, int], ...] = (
    ("1", 0, -1),
    ("2", 0, +1),
    ("3", 1, -1),
    ("4", 1, +1),
    ("5", 2, -1),
    ("6", 2, +1),
)


class PanelActions(Protocol):
    """What the panel's buttons and hotkeys do (implemented by the page's session)."""

    def pressed(self) -> None:
        """A key or button came, before what it does: work the page would do meanwhile
        (drawing the canvas's copy of the picture) waits, so as not to slow the answer."""

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
    def refine(self) -> None: ...
    def alternative(self) -> None: ...
    def toggle_nudge_kind(self) -> None: ...
    def toggle_nudge_size(self) -> None: ...
    def undo(self) -> None: ...
    def redo(self) -> None: ...
    def reset_pose(self) -> None: ...
    def nudge(self, axis: int, sign: int) -> None: ...
    def add_missing(self, key: str) -> None: ...
    def next_frames(self) -> None: ...
    def previous_frames(self) -> None: ...
    def toggle_frame(self) -> None: ...


class Panel:
    """The GUI of one page (``gui`` is that client's ``client.gui``)."""

    def __init__(self, gui: viser.GuiApi, actions: PanelActions) -> None:
        self._gui = gui
        self._actions = actions
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
        self._scene_folder(actions)
        self._instances_folder(actions)
        self._repair_folder(actions)
        with gui.add_folder("Zoom and view"):
            self._button("Open / close zoom (Z)", actions.toggle_zoom)
            self._button("Outline / fill (O)", actions.toggle_fill)
            self._button("Blink rendered part (B)", actions.toggle_blink)
            self._button("3D view / pictures (V)", actions.toggle_3d)
        self._hotkeys(actions)

    def _scene_folder(self, actions: PanelActions) -> None:
        with self._gui.add_folder("Scene"):
            self.filter = self._gui.add_dropdown("Filter", FILTERS, initial_value="all")
            self._button("Accept scene (Y)", actions.accept, color="green")
            self._button("Reject scene (N)", actions.reject, color="red")
            self._button("Previous (K)", actions.previous)
            self._button("Next (J)", actions.next)
            self._button("Next flagged (F)", actions.next_flagged)
            self._button("No pose here… (M, then click)", actions.arm_missing)
            self._button("Next frames of a sequence (P)", actions.next_frames)
            self._button("Reject / restore the first frame shown (H)", actions.toggle_frame)
        self.filter.on_update(self._callback(lambda: actions.set_filter(self.filter.value)))

    def _instances_folder(self, actions: PanelActions) -> None:
        with self._gui.add_folder("Instances"):
            # viser's tables are markdown, whose rows cannot be clicked: one button per row.
            self.instances = self._gui.add_button_group("Zoom on", ["-"])
            self.table = self._gui.add_markdown("")
            self._button("Accept instance", lambda: actions.set_instance(ReviewStatus.ACCEPTED))
            self._button("Reject instance", lambda: actions.set_instance(ReviewStatus.REJECTED))
            self._button("Toggle instance (T)", actions.toggle_instance)

        def select(event: viser.GuiEvent[viser.GuiButtonGroupHandle]) -> None:
            actions.pressed()
            actions.select(event.target.value)

        self.instances.on_click(select)

    def _repair_folder(self, actions: PanelActions) -> None:
        with self._gui.add_folder("Repair the pose"):
            self.repair = self._gui.add_markdown("")
            self.offer = self._gui.add_button_group("Add here", ["-"], visible=False)
            self._button("Refine (R)", actions.refine)
            self._button("Next candidate pose (A)", actions.alternative)
            self.nudges = self._gui.add_markdown("")
            for key, axis, sign in NUDGE_KEYS:
                self._button(f"{'-+'[sign > 0]}{'xyz'[axis]} ({key})", _nudge(actions, axis, sign))
            self._button("Move / turn (G)", actions.toggle_nudge_kind)
            self._button("Small / large steps (L)", actions.toggle_nudge_size)
            self._button("Undo (U)", actions.undo)
            self._button("Redo (Shift+U)", actions.redo)
            self._button("Reset to the auto-annotation (X)", actions.reset_pose)

        def add(event: viser.GuiEvent[viser.GuiButtonGroupHandle]) -> None:
            actions.pressed()
            actions.add_missing(event.target.value)

        self.offer.on_click(add)

    def _hotkeys(self, actions: PanelActions) -> None:
        gui = self._gui
        # Over the pictures, review keys typed where the camera's are (A) are not the camera's.
        keys = [key for key, _, _ in HOTKEYS] + [key for key, _, _ in NUDGE_KEYS]
        gui.add_html(guard_html(keys), order=_GUARD_ORDER)
        for key, text, name in HOTKEYS:
            cmd = gui.add_command(text, hotkey=key, modifier=None)  # type: ignore[arg-type]
            cmd.on_trigger(self._callback(getattr(actions, name)))
        redo = gui.add_command("Redo a pose edit", hotkey="U", modifier="shift")
        redo.on_trigger(self._callback(actions.redo))
        back = gui.add_command(
            "Show the previous frames of the sequence", hotkey="P", modifier="shift"
        )
        back.on_trigger(self._callback(actions.previous_frames))
        for key, axis, sign in NUDGE_KEYS:
            cmd = gui.add_command(
                f"Nudge {'-+'[sign > 0]}{'xyz'[axis]}",
                hotkey=key,  # type: ignore[arg-type]
                modifier=None,
            )
            cmd.on_trigger(self._callback(_nudge(actions, axis, sign)))

    def _button(self, text: str, fn: Callable[[], None], color: str | None = None) -> None:
        button = self._gui.add_button(text, color=color)  # type: ignore[arg-type]
        button.on_click(self._callback(fn))

    def _callback(self, fn: Callable[[], None]) -> Callable[[object], None]:
        """A viser callback for a key or button: the page hears that one came (see
        :meth:`PanelActions.pressed`), then ``fn`` runs (the event says nothing it needs)."""

        def callback(_event: object) -> None:
            self._actions.pressed()
            fn()

        return callback

    def show(self, view: PanelView, keys: list[str]) -> None:
        """Update every element (viser sends only what changed); ``keys`` are the scene's
        instances, one "Zoom on" button each."""
        self.title.content = view.title
        self.alert.content = view.alert
        self.alert.visible = bool(view.alert)
        self.notice.content = view.notice
        self.notice.visible = bool(view.notice)
        # viser 1.1.1's handle declares the setter on a generic base mypy cannot see through.
        self.progress.value = view.progress  # type: ignore[misc]
        self.progress_text.content = view.progress_text
        self.table.content = view.table
        options = tuple(keys) or ("-",)  # viser wants at least one button
        if tuple(self.instances.options) != options:
            self.instances.options = options
        self.instances.visible = bool(keys)
        self.warnings.content = view.warnings
        self.warnings.visible = bool(view.warnings)
        self.repair.content = view.repair
        offer = view.offer or ("-",)
        if tuple(self.offer.options) != offer:
            self.offer.options = offer
        self.offer.visible = bool(view.offer)

    def show_repair(self, text: str, nudges: str) -> None:
        """Only the repair's text (while a refinement runs) and the nudge settings."""
        self.repair.content = text
        self.nudges.content = nudges


def _nudge(actions: PanelActions, axis: int, sign: int) -> Callable[[], None]:
    """The nudge of one button or key (bound now: a loop's variables change)."""

    def nudge() -> None:
        actions.nudge(axis, sign)

    return nudge
