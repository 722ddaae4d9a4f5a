"""Foundation ray casting: pixel-exact silhouettes and depth with lens distortion."""

from __future__ import annotations

import numpy as np
import trimesh

from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.geometry.transforms import make_transform
from annotator.rendering.raycast import (
    NO_HIT,
    PlacedMesh,
    cast_separately,
    projected_bbox,
    render,
    render_once,
)

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


def _pile(n: int, seed: int) -> list[PlacedMesh]:
    """``n`` parts in a loose pile 300-420 mm in front of the camera, overlapping."""
    from scipy.spatial.transform import Rotation

    from annotator.parts import build_part

    rng = np.random.default_rng(seed)
    meshes = [build_part(name).mesh for name in ("bracket", "brick", "cylinder")]
    return [
        PlacedMesh(
            meshes[k % 3],
            make_transform(
                Rotation.random(random_state=rng).as_matrix(),
                [*rng.uniform(-60, 60, 2), rng.uniform(300, 420)],
            ),
        )
        for k in range(n)
    ]


def test_casting_each_mesh_alone_gives_the_scene_cast() -> None:
    cam = Camera("c", 320, 240, K / np.array([[2], [2], [1]]), np.array([-0.1, 0.05, 0, 0, 0]))
    floor = PlacedMesh(_box((600, 600, 10)), make_transform(np.eye(3), [0, 0, 460.0]))
    parts = _pile(8, seed=3)
    whole = render(cam, [floor, *parts])
    behind = render_once(cam, [floor])
    assert render_once(cam, [floor]) is behind and not behind.depth.flags.writeable
    rects = [projected_bbox(cam, pm.mesh, pm.cam_T_model) for pm in parts]
    hits, own = cast_separately(cam.pixel_rays(), parts, rects, behind=behind, first=1)
    same = hits.instance == whole.instance
    assert same.mean() > 0.999  # only exact ties between touching surfaces may differ
    assert np.array_equal(hits.triangle[same], whole.triangle[same])
    assert np.allclose(hits.depth[same], whole.depth[same], atol=1e-3)
    # float32 rays moved into the model frame: barycentrics agree to a thousandth
    assert np.allclose(hits.barycentric[same], whole.barycentric[same], atol=2e-3)
    # Each mesh's own hits are its render alone, over its rectangle.
    for pm, r, h in zip(parts, rects, own):
        alone = render(cam, [pm], region=r)
        assert np.array_equal(h.hit, alone.hit)
        assert np.allclose(h.depth[h.hit], alone.depth[h.hit], atol=1e-3)
        assert not render(cam, [pm]).hit.sum() - h.hit.sum()  # nothing outside the rectangle
    # Normals: the hit face's normal, zero on a miss.
    n = hits.normals([floor, *parts])
    assert np.allclose(np.linalg.norm(n[hits.hit], axis=1), 1.0, atol=1e-5)
    assert not n[~hits.hit].any()
    assert np.allclose(n[hits.instance == 0], [0, 0, -1], atol=1e-6)  # facing the camera


def test_every_hit_lies_in_the_hit_bbox_and_it_is_tighter() -> None:
    """Turned parts under strong distortion, one reaching out of the image, on the full grid
    and every second pixel: no hit outside the rectangle, and fewer rays than the box of
    the turned bounding box."""
    from annotator.rendering.raycast import hit_bbox

    cam = Camera("c", 640, 480, K, np.array([-0.3, 0.12, 0.002, -0.001, 0.0]))
    tighter = 0
    for pm in _pile(12, seed=4) + [
        PlacedMesh(_box((60, 40, 20)), make_transform(np.eye(3), [260.0, 0, 400]))
    ]:
        for step in (1, 2):
            hits = render(cam, [pm]).hit[::step, ::step]
            box = hit_bbox(cam, pm.mesh, pm.cam_T_model, step=step)
            if box is None:
                assert not hits.any()
                continue
            x0, y0, x1, y1 = box
            inside = np.zeros_like(hits)
            inside[y0:y1, x0:x1] = True
            assert not (hits & ~inside).any()
            loose = projected_bbox(cam, pm.mesh, pm.cam_T_model)
            if step == 1 and loose is not None:
                tighter += (x1 - x0) * (y1 - y0) < (loose[2] - loose[0]) * (loose[3] - loose[1])
    assert tighter >= 6
