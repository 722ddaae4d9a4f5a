"""The viser review page: overlays, a 3D view, the instance panel, actions and hotkeys.

Hotkeys (none on W A S D Q E or the arrows, which move the 3D camera):
Y accept scene (and go to the next), N reject scene (and next), J next, K previous,
F next flagged, T toggle the selected instance, I select the next instance.
"""

from __future__ import annotations

import threading
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import viser
from scipy.spatial.transform import Rotation

from viewer.overlays import Prepared, compose, mosaic, prepare
from viewer.state import FILTERS, ReviewState

SCENE3D = "/scene3d"  # the 3D view sits beside the overlays (x + 2.5 m)
STATE_RGB = {"pending": (255, 220, 0), "accepted": (60, 220, 60), "rejected": (255, 40, 40)}


class ReviewApp:
    """A review server for one dataset. ``stop()`` ends it."""

    def __init__(self, root: str | Path, *, host: str = "127.0.0.1", port: int = 8080) -> None:
        self.state = ReviewState(root)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.port = self.server.get_port()
        self._lock = threading.RLock()
        self._pool = ThreadPoolExecutor(max_workers=1)
        self._prepared: dict[str, Future[Prepared]] = {}
        self.filter = "all"
        self.current = self.state.ids[0] if self.state.ids else None
        self.selected: str | None = None
        self._parts_shown: set[str] = set()
        self._build_gui()
        self.show()

    # ----------------------------------------------------------------- GUI
    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large")
        self.title = gui.add_markdown("")
        self.notice = gui.add_markdown("", visible=False)
        self.progress = gui.add_progress_bar(0.0)
        self.progress_text = gui.add_markdown("")
        with gui.add_folder("Actions"):
            self.flt = gui.add_dropdown("Filter", FILTERS, initial_value="all")
            accept = gui.add_button("Accept scene (Y)", color="green")
            reject = gui.add_button("Reject scene (N)", color="red")
            prev = gui.add_button("Previous (K)")
            nxt = gui.add_button("Next (J)")
            nflag = gui.add_button("Next flagged (F)")
            self.inst = gui.add_dropdown("Instance", ["-"], initial_value="-")
            toggle = gui.add_button("Toggle instance (T)")
        self.table = gui.add_markdown("")
        self._overlay: viser.ImageHandle | None = None
        self.server.on_client_connect(self._frame_overlays)

        accept.on_click(lambda _: self.decide("accepted"))
        reject.on_click(lambda _: self.decide("rejected"))
        prev.on_click(lambda _: self.step(-1))
        nxt.on_click(lambda _: self.step(+1))
        nflag.on_click(lambda _: self.next_flagged())
        toggle.on_click(lambda _: self.toggle())
        self.flt.on_update(lambda _: self.set_filter(self.flt.value))
        self.inst.on_update(
            lambda _: self.select(None if self.inst.value == "-" else self.inst.value)
        )
        for label, key, fn in (
            ("Accept scene", "Y", lambda: self.decide("accepted")),
            ("Reject scene", "N", lambda: self.decide("rejected")),
            ("Next scene", "J", lambda: self.step(+1)),
            ("Previous scene", "K", lambda: self.step(-1)),
            ("Next flagged scene", "F", self.next_flagged),
            ("Toggle selected instance", "T", self.toggle),
            ("Select next instance", "I", self.select_next),
        ):
            cmd = gui.add_command(label, hotkey=key, modifier=None)
            cmd.on_trigger(lambda _, fn=fn: fn())

    # ------------------------------------------------------------- actions
    def visible_ids(self) -> list[str]:
        return [sid for sid in self.state.ids if self.state.matches(sid, self.filter)]

    def set_filter(self, flt: str) -> None:
        with self._lock:
            self.filter = flt
            ids = self.visible_ids()
            if ids and self.current not in ids:
                self.current = ids[0]
            self.show()

    def step(self, delta: int) -> None:
        with self._lock:
            ids = self.visible_ids() or self.state.ids
            if not ids:
                return
            k = ids.index(self.current) if self.current in ids else -1
            self.current = ids[max(0, min(len(ids) - 1, k + delta))]
            self.selected = None
            self.show()

    def next_flagged(self) -> None:
        with self._lock:
            ids = self.state.ids
            k = ids.index(self.current) if self.current in ids else -1
            for sid in ids[k + 1 :] + ids[: k + 1]:
                if self.state.info(sid).flagged:
                    self.current, self.selected = sid, None
                    break
            self.show()

    def decide(self, status: str) -> None:
        with self._lock:
            if self.current is None:
                return
            self.state.set_scene(self.current, status)
            ids = self.visible_ids() or self.state.ids
            if self.current in ids and ids.index(self.current) + 1 < len(ids):
                self.current = ids[ids.index(self.current) + 1]
                self.selected = None
            self.show()

    def select(self, key: str | None) -> None:
        with self._lock:
            self.selected = key
            self.show(prefetch=False)

    def select_next(self) -> None:
        with self._lock:
            keys = [p.key for p in self.state.info(self.current).poses] if self.current else []
            if keys:
                k = keys.index(self.selected) if self.selected in keys else -1
                self.selected = keys[(k + 1) % len(keys)]
            self.show(prefetch=False)

    def toggle(self) -> None:
        with self._lock:
            if self.current is not None and self.selected is not None:
                self.state.toggle_instance(self.current, self.selected)
            self.show(prefetch=False)

    # ------------------------------------------------------------ display
    def _prepared_for(self, sid: str) -> Future[Prepared]:
        fut = self._prepared.get(sid)
        if fut is None:
            info = self.state.info(sid)
            ds = self.state.ds
            fut = self._pool.submit(prepare, ds, ds.scene(sid), list(info.poses))
            self._prepared[sid] = fut
            if len(self._prepared) > 8:
                for old in list(self._prepared)[:-8]:
                    if old != sid:
                        self._prepared.pop(old, None)
        return fut

    def show(self, *, prefetch: bool = True) -> None:
        """Display the current scene (and prepare the next one in the background)."""
        if self.current is None:
            self.title.content = "## No scene in this dataset"
            return
        info = self.state.info(self.current)
        prep = self._prepared_for(self.current).result()
        if [p.key for p in info.poses] != prep.keys:  # annotation changed on disk: re-render
            self._prepared.pop(self.current, None)
            prep = self._prepared_for(self.current).result()
        states = {p.key: info.instance_status(p.key) for p in info.poses}
        flagged = {p.key for p in info.poses if p.extra.get("flags")}
        panels = compose(prep, states, flagged, self.selected)
        self._show_mosaic(mosaic(panels))
        status = info.status + (" (stale: the annotation changed since)" if info.stale else "")
        idx = self.state.ids.index(self.current)
        self.title.content = f"## Scene {self.current}\n**{status}** · {idx + 1} of {len(self.state.ids)} · filter: {self.filter}"
        messages = list(prep.messages)
        if not info.annotated:
            messages.append(
                f"scene {self.current} has no annotation.json: run `annotator annotate` first"
            )
        if info.error:
            messages.append(info.error)
        self.notice.content = "\n".join(f"⚠ {m}" for m in messages)
        self.notice.visible = bool(messages)
        done, total = self.state.progress()
        self.progress.value = 100.0 * done / max(total, 1)
        pace = self.state.pace()
        eta = f", about {(total - done) / pace:.0f} min left" if pace > 0 else ""
        self.progress_text.content = f"reviewed {done} / {total} · {pace:.1f} scenes/min{eta}"
        self.table.content = self._table(info)
        keys = ["-"] + [p.key for p in info.poses]
        if tuple(self.inst.options) != tuple(keys):
            self.inst.options = keys
        self.inst.value = self.selected or "-"
        self._scene3d(info, prep)
        if prefetch:
            ids = self.visible_ids() or self.state.ids
            if self.current in ids and ids.index(self.current) + 1 < len(ids):
                self._prepared_for(ids[ids.index(self.current) + 1])

    def _show_mosaic(self, img: np.ndarray) -> None:
        """The overlays as one picture filling the initial 3D view (1 unit = 1000 px)."""
        h, w = img.shape[:2]
        if self._overlay is None or self._overlay_size != (w, h):
            self._overlay = self.server.scene.add_image(
                "/overlays",
                img,
                render_width=w / 1000,
                render_height=h / 1000,
                format="jpeg",
                jpeg_quality=85,
            )
            self._overlay_size = (w, h)
        else:
            self._overlay.image = img

    def _frame_overlays(self, client: viser.ClientHandle) -> None:
        w, h = getattr(self, "_overlay_size", (1920, 1536))
        # Images follow the camera convention (rows down +y): look along +z with -y up.
        client.camera.up_direction = (0.0, -1.0, 0.0)
        client.camera.position = (0.0, 0.0, -1.05 * h / 1000)
        client.camera.look_at = (0.0, 0.0, 0.0)

    def _table(self, info) -> str:
        rows = [
            "| instance | state | flags | markers used/rej. | reproj. px | unc. mm | occl. | depth agr. |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for p in info.poses:
            e = p.extra
            used = sum(len(v.get("used", [])) for v in (e.get("markers") or {}).values())
            rej = sum(len(v.get("rejected", [])) for v in (e.get("markers") or {}).values())
            rp = (e.get("reprojection_px") or {}).get("rms")
            occ = (e.get("occlusion") or {}).get("rate")
            dep = (e.get("depth") or {}).get("agreement")
            fmt = lambda x, f: "-" if x is None else format(x, f)  # noqa: E731
            mark = "▶ " if p.key == self.selected else ""
            rows.append(
                f"| {mark}{p.key} | {info.instance_status(p.key)} | {', '.join(e.get('flags', [])) or '-'} | {used}/{rej} | "
                f"{fmt(rp, '.2f')} | {fmt(e.get('uncertainty_mm'), '.2f')} | {fmt(occ, '.2f')} | {fmt(dep, '.2f')} |"
            )
        return "\n".join(rows)

    def _scene3d(self, info, prep: Prepared) -> None:
        ds = self.state.ds
        scene = self.server.scene
        root = SCENE3D
        off = np.array([2.5, 0.0, 0.0])  # beside the overlays
        for cam in ds.rig.cameras:
            R = cam.rig_T_cam[:3, :3]
            q = Rotation.from_matrix(R).as_quat()
            fov = 2 * np.arctan(cam.height / 2 / cam.K[1, 1])
            scene.add_camera_frustum(
                f"{root}/cameras/{cam.name}",
                fov=float(fov),
                aspect=cam.width / cam.height,
                scale=0.05,
                wxyz=(q[3], q[0], q[1], q[2]),
                position=tuple(cam.rig_T_cam[:3, 3] / 1000.0),
            )
        depth = None
        try:
            depth = ds.scene(info.id).read_depth(ds.rig)
        except Exception:  # reported in the page already
            depth = None
        if depth is not None:
            cam = ds.rig.depth_camera
            rays = cam.pixel_rays()[::4, ::4]
            d = depth[::4, ::4]
            ok = np.isfinite(d)
            pts = rays[ok] * d[ok][:, None] / 1000.0
            pts = pts @ cam.rig_T_cam[:3, :3].T + cam.rig_T_cam[:3, 3] / 1000.0 + off
            scene.add_point_cloud(
                "/depth", pts.astype(np.float32), colors=(150, 150, 150), point_size=0.0015
            )
        for p in info.poses:
            obj = ds.objects.get(p.object)
            if obj is None:
                continue
            q = Rotation.from_matrix(p.R).as_quat()
            colour = (
                (255, 255, 255)
                if p.key == self.selected
                else STATE_RGB[info.instance_status(p.key)]
            )
            handle = scene.add_mesh_simple(
                f"{root}/parts/{p.object}_{p.instance}",
                obj.mesh.vertices / 1000.0,
                obj.mesh.faces,
                color=colour,
                wxyz=(q[3], q[0], q[1], q[2]),
                position=tuple(p.t / 1000.0),
            )
            handle.on_click(lambda _, key=p.key: self.select(key))
        shown = {f"{root}/parts/{p.object}_{p.instance}" for p in info.poses}
        for name in self._parts_shown - shown:
            scene.remove_by_name(name) if hasattr(scene, "remove_by_name") else None
        self._parts_shown = shown

    def stop(self) -> None:
        self.server.stop()
        self._pool.shutdown(wait=False, cancel_futures=True)
