"""One page's 3D canvas: clicks on it, and the 3D view. It keeps the handles of
everything it adds and only updates them afterwards.

- **The gizmo** (viser's transform controls) sits on the selected part in the 3D view, at
  its surface centroid, turned as the part: dragging it moves the part along, and letting it
  go saves the new pose (``on_gizmo``).

- While the pictures are shown (:mod:`viewer.page.pictures`, laid over the canvas), the canvas
  draws nothing and a click on it is a click on the picture: it is passed on as a position
  in 0-1 of the canvas's size.
- **The 3D view**, shown instead of the pictures on request: the cameras, the parts at their
  proposed poses and the depth point cloud, all in the reference camera's frame (metres)
  under one frame, ``/scene3d``, at the origin. Nothing is offset: the 3D view is not beside
  the pictures but instead of them, and it is hidden while they are shown.

Each object's mesh is uploaded once per page (the first time the 3D view is shown), as one
batched mesh with one slot per physical instance (object.yaml); showing another scene only
sends the slots' poses, scales (0 hides an instance without a pose in this scene) and
colours, as viser's own examples move instances. The point cloud (downsampled when the scene
was prepared) is replaced. While the pictures are shown the 3D view is not updated at all:
it is brought up to date when it is shown.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import viser
from scipy.spatial.transform import Rotation

from annotator.dataset import Dataset
from annotator.dataset.records import InstanceAnnotation
from annotator.geometry import MM_PER_M
from annotator.geometry.camera import Camera
from annotator.geometry.transforms import invert, make_transform
from viewer.drawing.style import SELECTED_COLOUR, Look

#: A click on the canvas at (x, y), fractions of its width and height (0 to 1).
CanvasClick = Callable[[float, float], None]


def _wxyz(R: np.ndarray) -> np.ndarray:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def _matrix(wxyz, position) -> np.ndarray:
    """A gizmo's pose (viser's quaternion, metres) as a 4x4 transform in mm."""
    w, x, y, z = (float(v) for v in wxyz)
    return make_transform(
        Rotation.from_quat([x, y, z, w]).as_matrix(), np.asarray(position, float) * MM_PER_M
    )


def _rgb(bgr: tuple[int, int, int]) -> tuple[int, int, int]:
    return (bgr[2], bgr[1], bgr[0])


class Scene3D:
    """The canvas of one page (``scene`` is that client's ``client.scene``)."""

    def __init__(
        self,
        scene: viser.SceneApi,
        ds: Dataset,
        *,
        on_part: Callable[[str], None],
        on_canvas: CanvasClick,
        on_gizmo: Callable[[str, np.ndarray], None] | None = None,
    ) -> None:
        self._scene = scene
        self._ds = ds
        self._on_part = on_part
        self._on_canvas = on_canvas
        self._on_gizmo = on_gizmo
        self._gizmo: viser.TransformControlsHandle | None = None
        self._gizmo_pose: InstanceAnnotation | None = None  # the part it sits on
        self._grab: tuple[np.ndarray, np.ndarray] | None = None  # gizmo and part at the grab
        self._dragging = False
        self._arrays: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # object -> wxyzs, positions
        self._lock = threading.RLock()
        self.showing_3d = False
        self._pending_3d: (
            tuple[
                tuple[InstanceAnnotation, ...],
                Look,
                np.ndarray | None,
                object,
                Sequence[Camera] | None,
            ]
            | None
        )
        self._pending_3d = None
        self._shown_cloud: object = None
        #: The frustums drawn: (name, rig_T_cam bytes) per camera, and their handles.
        self._shown_cameras: tuple[tuple[tuple[str, bytes], ...], list[Any]] = ((), [])
        self._cloud: viser.PointCloudHandle | None = None
        self._parts: dict[str, viser.BatchedMeshHandle] = {}
        self._slots: dict[str, list[str]] = {}  # object -> instance name per slot
        self._root: viser.FrameHandle | None = None
        scene.on_click()(self._clicked)

    def _build_3d(self) -> None:
        """The 3D view's fixed content, sent the first time it is shown (a page that never
        shows it never loads the meshes)."""
        scene = self._scene
        # Lighting for the parts' shading; the pictures need none (hence not sent before).
        scene.configure_environment_map("warehouse")
        self._root = scene.add_frame("/scene3d", show_axes=False, visible=False)
        self._show_cameras(self._ds.rig.cameras)
        for name, obj in self._ds.objects.items():
            self._add_object(name, [i.name for i in obj.instances])

    def _clicked(self, event: viser.SceneClickEvent) -> None:
        if not self.showing_3d:
            x, y = event.screen_pos
            self._on_canvas(float(x), float(y))

    def show_3d(self, on: bool, camera: viser.CameraHandle) -> None:
        """Show the 3D view (looking from behind the reference camera), or hide it."""
        with self._lock:
            if on == self.showing_3d:
                return
            self.showing_3d = on
            if self._root is None:
                self._build_3d()
            if on:
                self._flush_3d()
                self._place_gizmo()
                # From above and behind the reference camera (+y is down), towards the bin.
                # Setting the position moves look_at with it: position first.
                camera.up_direction = (0.0, -1.0, 0.0)
                camera.position = (0.0, -0.25, -0.35)
                camera.look_at = (0.0, 0.0, 0.5)
            self._root.visible = on  # type: ignore[union-attr]
            if self._gizmo is not None:
                self._gizmo.visible = on and self._gizmo_pose is not None

    # ------------------------------------------------------------- 3D view
    def _add_object(self, name: str, slots: list[str]) -> None:
        obj = self._ds.objects[name]
        n = max(len(slots), 1)
        handle = self._scene.add_batched_meshes_simple(
            f"/scene3d/parts/{name}",
            obj.mesh.vertices / MM_PER_M,
            obj.mesh.faces,
            batched_wxyzs=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
            batched_positions=np.zeros((n, 3)),
            batched_scales=np.zeros(n, np.float32),
            batched_colors=np.full((n, 3), 200, np.uint8),
            lod="off",
            cast_shadow=False,
            receive_shadow=False,
        )
        handle.on_click(self._part_clicker(name))
        self._parts[name] = handle
        self._slots[name] = list(slots) or [""]

    def _part_clicker(
        self, obj: str
    ) -> Callable[[viser.SceneNodePointerEvent[viser.BatchedMeshHandle]], None]:
        """The click callback of object ``obj``'s meshes (which instance: the event's)."""

        def clicked(event: viser.SceneNodePointerEvent[viser.BatchedMeshHandle]) -> None:
            self._clicked_part(obj, event.instance_index)

        return clicked

    def _clicked_part(self, obj: str, index: int | None) -> None:
        slots = self._slots.get(obj, [])
        if index is not None and 0 <= index < len(slots) and slots[index]:
            self._on_part(f"{obj}/{slots[index]}")

    def show_3d_scene(
        self,
        poses: tuple[InstanceAnnotation, ...],
        look: Look,
        cloud: np.ndarray | None,
        cloud_key: object,
        cameras: Sequence[Camera] | None = None,
    ) -> None:
        """The parts of a scene at their poses, coloured by ``look``, and its depth points
        (reference frame, metres; None: none; sent again only when ``cloud_key`` changes);
        ``cameras``: the frustums to draw (a sequence's shown frames' cameras in the scene
        frame), None for the rig's own. Sent now if the 3D view is shown, else when it is."""
        with self._lock:
            self._pending_3d = (poses, look, cloud, cloud_key, cameras)
            if self.showing_3d:
                self._flush_3d()

    def _flush_3d(self) -> None:
        if self._pending_3d is None:
            return
        poses, look, cloud, cloud_key, cameras = self._pending_3d
        self._pending_3d = None
        self._show_parts(poses, look)
        if cloud_key != self._shown_cloud:
            self._show_cloud(cloud)
            self._shown_cloud = cloud_key
        self._show_cameras(self._ds.rig.cameras if cameras is None else cameras)

    def _show_cameras(self, cameras: Sequence[Camera]) -> None:
        """Frustums of ``cameras`` where they are, replacing those drawn for others."""
        placed = tuple((c.name, c.rig_T_cam.tobytes()) for c in cameras)
        if placed == self._shown_cameras[0]:
            return
        for handle in self._shown_cameras[1]:
            handle.remove()
        handles = []
        for cam in cameras:
            handles.append(
                self._scene.add_camera_frustum(
                    f"/scene3d/cameras/{cam.name}",
                    fov=float(2 * np.arctan(cam.height / 2 / cam.K[1, 1])),
                    aspect=cam.width / cam.height,
                    scale=0.04,
                    thickness=1.5,
                    thickness_units="screen",
                    color=(90, 90, 90),
                    wxyz=_wxyz(cam.rig_T_cam[:3, :3]),
                    position=tuple(cam.rig_T_cam[:3, 3] / MM_PER_M),
                )
            )
        self._shown_cameras = (placed, handles)

    def _show_parts(self, poses: tuple[InstanceAnnotation, ...], look: Look) -> None:
        by_object: dict[str, list[InstanceAnnotation]] = {}
        for p in poses:
            if p.object in self._parts:
                by_object.setdefault(p.object, []).append(p)
        for name, posed in by_object.items():
            unknown = [p.instance for p in posed if p.instance not in self._slots[name]]
            if unknown:  # an instance object.yaml does not list: give it a slot
                self._parts.pop(name).remove()
                self._add_object(name, [s for s in self._slots[name] if s] + unknown)
        for name, handle in self._parts.items():
            slots = self._slots[name]
            n = len(slots)
            wxyzs = np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (n, 1))
            positions = np.zeros((n, 3), np.float32)
            scales = np.zeros(n, np.float32)
            colours = np.full((n, 3), 200, np.uint8)
            for p in by_object.get(name, []):
                i = slots.index(p.instance)
                wxyzs[i] = _wxyz(p.R)
                positions[i] = p.t / MM_PER_M
                scales[i] = 1.0
                selected = p.key == look.selected
                colours[i] = _rgb(SELECTED_COLOUR if selected else look.colour(p.key))
            handle.batched_wxyzs = wxyzs
            handle.batched_positions = positions
            self._arrays[name] = (wxyzs, positions)
            handle.batched_scales = scales
            handle.batched_colors = colours

    def _show_cloud(self, points: np.ndarray | None) -> None:
        if points is None or len(points) == 0:
            if self._cloud is not None:
                self._cloud.visible = False
            return
        if self._cloud is None:
            self._cloud = self._scene.add_point_cloud(
                "/scene3d/depth",
                points,
                colors=(150, 150, 150),
                point_size=0.0015,
                precision="float16",
            )
        else:
            self._cloud.points = points
            self._cloud.visible = True

    # --------------------------------------------------------------- gizmo
    def show_gizmo(self, pose: InstanceAnnotation | None) -> None:
        """Put the gizmo on ``pose``'s part (None: take it away); shown in the 3D view only."""
        with self._lock:
            self._gizmo_pose = pose
            if self.showing_3d:
                self._place_gizmo()

    def _place_gizmo(self) -> None:
        pose = self._gizmo_pose
        if self._dragging:
            return
        if pose is None or pose.object not in self._ds.objects:
            if self._gizmo is not None:
                self._gizmo.visible = False
            return
        c = pose.R @ self._ds.objects[pose.object].mesh.moments.centroid + pose.t
        radius = self._ds.objects[pose.object].mesh.moments.radius
        if self._gizmo is None:
            self._gizmo = self._scene.add_transform_controls(
                "/scene3d/gizmo", scale=max(radius * 2.5 / MM_PER_M, 0.03), depth_test=False
            )
            self._gizmo.on_update(self._gizmo_moved)
        self._gizmo.wxyz = _wxyz(pose.R)
        self._gizmo.position = tuple(c / MM_PER_M)
        self._gizmo.visible = self.showing_3d

    def _gizmo_moved(self, event: viser.TransformControlsEvent) -> None:
        with self._lock:
            pose = self._gizmo_pose
            if pose is None:
                return
            G = _matrix(event.target.wxyz, event.target.position)
            if event.phase == "start" or self._grab is None:
                self._grab = (G, pose.T)
                self._dragging = True
            G0, T0 = self._grab
            T = G @ invert(G0) @ T0
            self._move_slot(pose, T)
            if event.phase != "end":
                return
            self._grab = None
            self._dragging = False
        if self._on_gizmo is not None:
            self._on_gizmo(pose.key, T)

    def _move_slot(self, pose: InstanceAnnotation, T: np.ndarray) -> None:
        """Show ``pose``'s part at ``T`` while the gizmo is dragged."""
        arrays = self._arrays.get(pose.object)
        slots = self._slots.get(pose.object, [])
        if arrays is None or pose.instance not in slots:
            return
        wxyzs, positions = arrays[0].copy(), arrays[1].copy()
        i = slots.index(pose.instance)
        wxyzs[i] = _wxyz(T[:3, :3])
        positions[i] = T[:3, 3] / MM_PER_M
        handle = self._parts[pose.object]
        handle.batched_wxyzs = wxyzs
        handle.batched_positions = positions
