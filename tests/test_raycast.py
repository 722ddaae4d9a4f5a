"""Foundation ray casting: pixel-exact silhouettes and depth with lens distortion."""

from __future__ import annotations

import numpy as np
import trimesh

from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.geometry.transforms import make_transform
from annotator.rendering.raycast import NO_HIT, PlacedMesh, projected_bbox, render

K = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])


def _box(size) -> Mesh:
    b = trimesh.creation.box(size)
    return Mesh(np.asarray(b.vertices), np.asarray(b.faces, dtype=np.int32))


def test_depth_and_edges_follow_opencv_pixel_convention() -> None:
    cam = Camera("c", 640, 480, K, np.array([-0.1, 0.05, 0.001, -0.001, 0.0]))
    box = _box((60, 40, 20))
    T = make_transform(np.eye(3), [7.3, -4.1, 400.0])
    hits = render(cam, [PlacedMesh(box, T)])
    assert np.allclose(hits.depth[hits.hit], 390.0, atol=1e-3)
    # Front face corners, projected by OpenCV, bound the rendered silhouette to within a pixel.
    corners = np.array([[-30, -20, -10], [30, 20, -10]], float) + T[:3, 3]
    (u0, v0), (u1, v1) = cam.project(corners)
    ys, xs = np.nonzero(hits.hit)
    assert xs.min() == np.ceil(u0) and ys.min() == np.ceil(v0)
    assert xs.max() == np.floor(u1) and ys.max() == np.floor(v1)
    bbox = projected_bbox(cam, box, T)
    assert bbox[0] <= xs.min() and bbox[1] <= ys.min() and bbox[2] > xs.max() and bbox[3] > ys.max()


def test_instances_occlude_and_regions_match_full_render() -> None:
    cam = Camera("c", 640, 480, K)
    front = PlacedMesh(_box((20, 20, 20)), make_transform(np.eye(3), [0, 0, 300.0]))
    back = PlacedMesh(_box((100, 100, 10)), make_transform(np.eye(3), [0, 0, 500.0]))
    hits = render(cam, [back, front])
    assert (
        hits.instance[240, 320] == 1
        and hits.instance[240, 400] == 0
        and hits.instance[0, 0] == NO_HIT
    )
    region = render(cam, [back, front], region=(300, 200, 360, 260))
    assert np.array_equal(region.instance, hits.instance[200:260, 300:360])
    pts = hits.model_points([back, front])
    assert np.allclose(pts[240, 320], [0 - 0, 0, -10], atol=0.2)
