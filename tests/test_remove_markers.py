"""``export --remove-markers`` on scenes rendered twice, with and without markers (``synth
--no-markers``, same seed): the markers are found before and not after, the filled regions
are close to the bare render, every other pixel is untouched, depth is as measured; and
the marker regions themselves on hand-built scenes (occlusion, far side)."""

from __future__ import annotations

import json
import tarfile

import cv2
import numpy as np
import pytest
import trimesh
import yaml
from pycocotools import mask as coco_mask

from annotator.cli import main
from annotator.dataset import load_dataset
from annotator.dataset.model import Rig
from annotator.export.fill import fill_markers
from annotator.export.markers import MarkedInstance, scene_markers
from annotator.geometry.camera import Camera
from annotator.geometry.mesh import Mesh
from annotator.geometry.transforms import make_transform
from devkit.marker_twins import export_twins, render_twins

pytestmark = pytest.mark.slow  # scenes rendered and exported first

SYNTH = ["--parts", "bracket,brick,cylinder", "--scenes", "2", "--instances", "6-8"]
SYNTH += ["--seed", "5", "--size", "640x512", "--workers", "1", "--quiet"]


@pytest.fixture(scope="module")
def twins(tmp_path_factory):
    """The same two scenes with markers and bare."""
    return render_twins(tmp_path_factory.mktemp("twins"), SYNTH)


@pytest.fixture(scope="module")
def exports(twins):
    """BOP exports (gt poses) of both twins, and of the marked one with --remove-markers."""
    return export_twins(twins)


def _detector() -> cv2.aruco.ArucoDetector:
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_1000)
    return cv2.aruco.ArucoDetector(d, cv2.aruco.DetectorParameters(), cv2.aruco.RefineParameters())


def _found(det: cv2.aruco.ArucoDetector, img: np.ndarray) -> set[int]:
    _, ids, _ = det.detectMarkers(img)
    return set() if ids is None else set(np.asarray(ids).reshape(-1).tolist())


def _read(path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(float) - b.astype(float)) ** 2))
    return 10 * np.log10(255.0**2 / mse)


def test_bare_twin_differs_only_at_the_markers(twins) -> None:
    """Independent of the export: every pixel that differs lies within a few pixels of a
    marker square projected with OpenCV from gt.json and object.yaml."""
    ds = load_dataset(twins / "marked")
    synth = [
        yaml.safe_load((twins / k / "dataset.yaml").read_text())["synth"]
        for k in ("marked", "bare")
    ]
    assert "markers" not in synth[0] and synth[1].pop("markers") is False and synth[0] == synth[1]
    assert (twins / "marked" / "objects").is_dir()
    for name in ds.objects:  # the bare twin's parts still list their markers
        a, b = (
            (twins / k / "objects" / name / "object.yaml").read_bytes() for k in ("marked", "bare")
        )
        assert a == b
    for scene in ds.scenes():
        gt = json.loads(scene.gt_path.read_text())
        bare = twins / "bare" / "scenes" / scene.id
        assert json.loads((bare / "gt.json").read_text()) == gt
        for cam in ds.rig.cameras:
            a, b = _read(scene.path / f"{cam.name}.png"), _read(bare / f"{cam.name}.png")
            near = np.zeros(a.shape, np.uint8)
            for inst in gt["instances"]:
                obj = ds.objects[inst["object"]]
                T = np.eye(4)
                T[:3, :3] = np.reshape(inst["cam_R_m2c"], (3, 3))
                T[:3, 3] = inst["cam_t_m2c"]
                M = cam.cam_T_rig @ T
                for X in obj.markers.corners[: len(obj.instance(inst["instance"]).marker_ids)]:
                    uv, _ = cv2.projectPoints(
                        X @ M[:3, :3].T + M[:3, 3], np.zeros(3), np.zeros(3), cam.K, cam.dist
                    )
                    cv2.fillConvexPoly(near, np.round(uv.reshape(4, 2)).astype(np.int32), 1)
            near = cv2.dilate(near, np.ones((11, 11), np.uint8)) > 0
            assert (a != b).sum() > 1000  # the markers are there in one and not the other
            assert not ((a != b) & ~near).any()


def test_removed_markers_against_the_bare_render(exports) -> None:
    det = _detector()
    ds = load_dataset(exports / "marked")
    ids = {m for o in ds.objects.values() for i in o.instances for m in i.marker_ids}
    before = after = 0
    err_marked = err_filled = 0.0
    pixels = 0
    files = sorted((exports / "plain" / "test").glob("*/gray_*/000000.png"))
    assert len(files) == 4  # two scenes, two cameras
    for f in files:
        rel = f.relative_to(exports / "plain")
        marked, bare = _read(f), _read(exports / "bare_bop" / rel)
        filled = _read(exports / "removed" / rel)
        cam = rel.parent.name[len("gray") :]
        mask_png = _read(exports / "removed" / rel.parents[1] / f"mask_markers{cam}" / "000000.png")
        assert mask_png.dtype == np.uint8 and set(np.unique(mask_png)) <= {0, 255}
        mask = mask_png > 0
        found = _found(det, marked)
        assert len(found & ids) >= 10  # (a false detection of an id of no instance is rare)
        before += len(found)
        after += len(_found(det, filled))
        # outside the regions: byte for byte the plain export, and the bare render
        assert np.array_equal(filled[~mask], marked[~mask])
        assert np.array_equal(filled[~mask], bare[~mask])
        err_marked += float(np.sum((marked[mask].astype(float) - bare[mask]) ** 2))
        err_filled += float(np.sum((filled[mask].astype(float) - bare[mask]) ** 2))
        pixels += int(mask.sum())
    assert after == 0, after
    psnr_marked = 10 * np.log10(255.0**2 * pixels / err_marked)
    psnr_filled = 10 * np.log10(255.0**2 * pixels / err_filled)
    print(
        f"markers found {before} -> {after}; PSNR in regions {psnr_marked:.1f} -> {psnr_filled:.1f}"
    )
    assert psnr_filled > psnr_marked + 10.0
    assert psnr_filled > 25.0


def test_depth_masks_and_coco(exports) -> None:
    """Depth and the instances' files are the plain export's; COCO has a marker category
    whose annotations are the markers of the scene's instances."""
    plain, removed = exports / "plain" / "test", exports / "removed" / "test"
    for f in sorted(plain.rglob("*")):
        rel = f.relative_to(plain)
        if f.is_file() and not rel.as_posix().split("/")[-2:][0].startswith("gray"):
            if rel.name.startswith("scene_gt_coco"):
                a, b = (json.loads(p.read_text())["annotations"] for p in (f, removed / rel))
                assert b[: len(a)] == a  # the instances' annotations, then the markers'
            else:
                assert f.read_bytes() == (removed / rel).read_bytes(), rel
    ds = load_dataset(exports / "marked")
    info = json.loads((exports / "removed" / "models" / "models_info.json").read_text())
    for scene in sorted(p for p in removed.iterdir() if p.is_dir()):
        gts = json.loads((scene / "scene_gt_left.json").read_text())["0"]
        coco = json.loads((scene / "scene_gt_coco_left.json").read_text())
        cats = {c["name"]: c["id"] for c in coco["categories"]}
        assert cats["marker"] == len(info) + 1
        marks = [a for a in coco["annotations"] if a["category_id"] == cats["marker"]]
        objs = [a for a in coco["annotations"] if a["category_id"] != cats["marker"]]
        assert objs and len(marks) >= 10
        mask = _read(scene / "mask_markers_left" / "000000.png") > 0
        filled_rle = coco_mask.encode(np.asfortranarray(mask.astype(np.uint8)))
        names = list(ds.objects)
        sid = json.loads((removed / "scene_ids.json").read_text())[scene.name]
        gt_src = json.loads((exports / "marked" / "scenes" / sid / "gt.json").read_text())
        for a in marks:
            inst = gt_src["instances"][a["gt_index"]]
            assert a["obj_id"] == gts[a["gt_index"]]["obj_id"] == names.index(inst["object"]) + 1
            assert (
                a["marker_id"] in ds.objects[inst["object"]].instance(inst["instance"]).marker_ids
            )
            seg = {
                "counts": a["segmentation"]["counts"].encode(),
                "size": a["segmentation"]["size"],
            }
            assert int(coco_mask.area(seg)) == a["area"] > 0
            # every marker's pixels are filled: inside mask_markers
            inside = coco_mask.merge([seg, filled_rle], intersect=True)
            assert int(coco_mask.area(inside)) == a["area"]


def test_every_layout_and_the_sileane_format(exports, tmp_path) -> None:
    src = exports / "marked"
    common = ["--poses", "gt", "--include-pending", "--quiet", "--remove-markers"]
    assert (
        main(
            [
                "export",
                str(src),
                str(tmp_path / "iw"),
                "--format",
                "bop",
                "--layout",
                "imagewise",
                *common,
            ]
        )
        == 0
    )
    iw = tmp_path / "iw" / "test_imagewise"
    key = "000000_000000"
    scenewise = exports / "removed" / "test" / "000000"
    assert (iw / f"{key}.mask_markers.png").read_bytes() == (
        scenewise / "mask_markers_left" / "000000.png"
    ).read_bytes()
    tiff = cv2.imread(str(iw / f"{key}.gray.tiff"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(tiff, _read(scenewise / "gray_left" / "000000.png"))

    assert (
        main(
            [
                "export",
                str(src),
                str(tmp_path / "wds"),
                "--format",
                "bop",
                "--layout",
                "webdataset",
                *common,
            ]
        )
        == 0
    )
    with tarfile.open(tmp_path / "wds" / "test_webdataset" / "shard-000000.tar") as tar:
        names = tar.getnames()
        member = tar.extractfile(f"{key}.mask_markers.png")
        assert member is not None
        data = member.read()
    assert f"{key}.gray.tiff" in names
    assert data == (iw / f"{key}.mask_markers.png").read_bytes()

    assert main(["export", str(src), str(tmp_path / "sil"), "--format", "sileane", *common]) == 0
    assert (
        main(["export", str(src), str(tmp_path / "sil0"), "--format", "sileane", *common[:-1]]) == 0
    )
    det = _detector()
    for obj in ("bracket", "cylinder"):
        filled = _read(tmp_path / "sil" / obj / "rgb" / "000000.PNG")
        plain = _read(tmp_path / "sil0" / obj / "rgb" / "000000.PNG")
        mask = _read(tmp_path / "sil" / obj / "mask_markers" / "000000.PNG") > 0
        assert _found(det, plain) and not _found(det, filled)
        assert np.array_equal(filled[~mask], plain[~mask])
        depth = tmp_path / "sil" / obj / "depth" / "000000.PNG"
        assert depth.read_bytes() == (tmp_path / "sil0" / obj / "depth" / "000000.PNG").read_bytes()


def test_bad_options_say_so(twins, tmp_path, capsys) -> None:
    out = tmp_path / "x"
    args = ["export", str(twins / "marked"), str(out), "--format", "bop", "--poses", "gt"]
    assert main([*args, "--include-pending", "--marker-fill", "telea"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--marker-fill is for --remove-markers" in err
    assert not out.exists()
    assert main([*args, "--include-pending", "--remove-markers", "--marker-fill", "blur"]) == 2
    assert "invalid choice" in capsys.readouterr().err
    assert not out.exists()
    assert main(["synth", str(out), "--calibration", "--no-markers"]) == 2
    assert "--no-markers does not apply to --calibration" in capsys.readouterr().err
    assert not out.exists()


# ------------------------------------------------------------------ hand-built scenes

K = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])


def _box(size) -> Mesh:
    b = trimesh.creation.box(size)
    return Mesh(np.asarray(b.vertices), np.asarray(b.faces, dtype=np.int32))


def _site(z: float, half: float, flip: bool = False) -> np.ndarray:
    """A square on the plane z (model frame), ArUco order, facing -z (the camera) or +z."""
    tl, tr, br, bl = [-half, -half], [half, -half], [half, half], [-half, half]
    pts = [tl, tr, br, bl] if not flip else [tr, tl, bl, br]
    return np.array([[x, y, z] for x, y in pts])


def _one_camera() -> Rig:
    return Rig(cameras=(Camera("cam", 640, 480, K),))


def test_marker_behind_another_part_is_not_erased() -> None:
    """A marker on a box's face turned to the camera, the right half of it behind a second
    box: its visible pixels are the left half, none of them the occluder's; the mask grows
    by the margin only from those. A marker on the far face shows nowhere."""
    box = _box([60.0, 60.0, 20.0])
    near_face = _site(-10.0, 10.0)  # outward normal -z: towards the camera
    far_face = _site(10.0, 10.0, flip=True)  # outward normal +z: away from it
    # the square's edge normal check: (BL - TL) x (TR - TL) points out of the part
    for s, sign in ((near_face, -1), (far_face, 1)):
        n = np.cross(s[3] - s[0], s[1] - s[0])
        assert np.sign(n[2]) == sign
    back = MarkedInstance(
        "box",
        "01",
        box,
        make_transform(np.eye(3), [0, 0, 600.0]),
        np.stack([near_face, far_face]),
        (3, 4),
    )
    # a thin box in front, covering x > 0 of the marker
    front = MarkedInstance(
        "plate",
        "01",
        _box([40.0, 80.0, 2.0]),
        make_transform(np.eye(3), [20.0, 0, 500.0]),
        np.zeros((0, 4, 3)),
        (),
    )
    vis, images = scene_markers(_one_camera(), [back, front], cameras=["cam"], margin_px=3)
    im = images["cam"]
    near_r, far_r = im.regions
    assert near_r.facing and not far_r.facing
    assert far_r.px_surface == far_r.px_visib == 0 and len(far_r.pixels) == 0
    # the marker with its white border (1 cell of 6: 20 mm * 8/6 wide) at 600 mm, f = 800
    side = 20.0 * 8 / 6 * 800 / 600
    assert abs(near_r.px_surface - side * side) < 0.1 * side * side
    assert abs(near_r.px_visib - near_r.px_surface / 2) < 0.1 * near_r.px_surface
    rows, cols = near_r.pixels[:, 0], near_r.pixels[:, 1]
    assert (im.labels[rows, cols] == 0).all()  # never a pixel of the plate
    assert cols.max() <= 320  # the plate's edge, x = 0, is at column 319.5
    # the mask: the visible pixels grown by 3 px, a few columns into the plate, no more
    plate = im.labels == 1
    assert im.mask[rows, cols].all()
    assert 0 < (im.mask & plate).sum() <= 3 * (rows.max() - rows.min() + 7)
    ys, xs = np.nonzero(im.mask)
    assert xs.max() <= cols.max() + 3
    # the scene's visibility is what scene_visibility gives on its own
    from annotator.occlusion import scene_visibility

    ref = scene_visibility(
        _one_camera(), [back.mesh, front.mesh], [back.rig_T_model, front.rig_T_model], masks=True
    )
    for a, b in zip(vis, ref):
        assert np.array_equal(a.cameras[0].mask_visib, b.cameras[0].mask_visib)
        assert a.occlusion == b.occlusion


def test_fill_keeps_each_surface_its_own() -> None:
    """Two surfaces meet inside a masked square: the surface fill gives each its own grey
    and touches nothing outside the mask; OpenCV's inpainting blends them."""
    h, w = 60, 80
    yy, xx = np.mgrid[0:h, 0:w]
    labels = np.where(xx < 40, 0, 1).astype(np.int32)
    truth = np.where(labels == 0, 90, 220).astype(np.uint8)
    truth = truth + (np.random.default_rng(0).normal(0, 1, (h, w)) > 0)  # a little texture
    img = truth.copy()
    mask = np.zeros((h, w), bool)
    mask[20:40, 25:55] = True
    img[mask] = 0  # the marker
    out = fill_markers(img, mask, labels, method="surface", noise=False)
    assert np.array_equal(out[~mask], img[~mask])
    assert np.abs(out[mask].astype(int) - truth[mask]).max() <= 1
    telea = fill_markers(img, mask, labels, method="telea")
    assert np.array_equal(telea[~mask], img[~mask])
    assert np.abs(telea[mask].astype(int) - truth[mask]).max() > 30
    colour = fill_markers(np.dstack([img] * 3), mask, labels, noise=False)
    assert np.array_equal(colour[..., 1], out)
    wide = fill_markers(img.astype(np.uint16) * 200, mask, labels, noise=False)
    assert np.abs(wide[mask].astype(int) - truth[mask].astype(int) * 200).max() <= 200
    assert np.array_equal(fill_markers(img, np.zeros_like(mask), labels), img)


def test_fill_carries_shading_across_a_marker() -> None:
    """A curved surface lit from the camera (grey = 40 + 180 cos, the cosine turning fast
    across the marker): the shading model puts back what lies under the marker, which no
    interpolation of the border's greys does."""
    h, w = 50, 120
    yy, xx = np.mgrid[0:h, 0:w]
    theta = np.radians(85.0) * xx / (w - 1)  # the normal turns from facing to edge-on
    normals = np.dstack([np.sin(theta), np.zeros_like(theta), -np.cos(theta)]).astype(np.float32)
    rays = np.dstack([np.zeros((h, w)), np.zeros((h, w)), np.ones((h, w))]).astype(np.float32)
    truth = np.round(40 + 180 * np.cos(theta)).astype(np.uint8)
    labels = np.zeros((h, w), np.int32)
    mask = np.zeros((h, w), bool)
    mask[10:40, 40:90] = True
    img = truth.copy()
    img[mask] = 5
    model = fill_markers(img, mask, labels, normals=normals, rays=rays, noise=False)
    plain = fill_markers(img, mask, labels, noise=False)
    err_model = np.abs(model[mask].astype(int) - truth[mask]).max()
    err_plain = np.abs(plain[mask].astype(int) - truth[mask]).max()
    assert err_model <= 1 < 10 < err_plain


def test_fill_has_the_noise_of_its_surroundings() -> None:
    """A flat grey with sensor noise: the filled square has that noise (not a smooth patch),
    the same on every run."""
    rng = np.random.default_rng(3)
    img = np.clip(np.round(120 + rng.normal(0, 3.0, (120, 160))), 0, 255).astype(np.uint8)
    mask = np.zeros(img.shape, bool)
    mask[40:80, 50:110] = True
    marked = img.copy()
    marked[mask] = 0
    a = fill_markers(marked, mask)
    assert np.array_equal(a, fill_markers(marked, mask))
    assert np.array_equal(a[~mask], marked[~mask])
    inner = a[45:75, 55:105].astype(float)
    assert 2.4 < inner.std() < 3.6 and abs(inner.mean() - 120) < 1.0
    smooth = fill_markers(marked, mask, noise=False)[45:75, 55:105].astype(float)
    assert smooth.std() < 0.5


def test_the_instances_own_measured_sites_are_used(tmp_path, capsys) -> None:
    """Markers glued beside their layout (``synth --glue``): the layout's sites leave ink
    that only the search for markers the poses did not place finds; the instances' own sites
    (object.yaml ``instances[].sites``, as ``annotator sites`` writes them, here the true
    ones) leave none to find. Neither leaves ink outside the masks."""
    opts = ["--parts", "bracket,brick", "--scenes", "1", "--instances", "6-6", "--seed", "4"]
    opts += ["--size", "640x512", "--glue", "2.0,6", "--workers", "1", "--quiet"]
    assert main(["synth", str(tmp_path / "marked"), *opts]) == 0
    assert main(["synth", str(tmp_path / "bare"), *opts, "--no-markers"]) == 0
    common = ["--format", "bop", "--poses", "gt", "--include-pending", "--quiet"]

    def ink_outside(out: str) -> tuple[int, int]:
        """Ink outside the masks, and markers found where no pose put them."""
        args = ["export", str(tmp_path / "marked"), str(tmp_path / out), *common]
        capsys.readouterr()
        assert main([*args, "--remove-markers", "--json"]) == 0
        elsewhere = json.loads(capsys.readouterr().out)["markers_found_beyond"]
        n = 0
        for f in (tmp_path / out / "test").glob("*/gray_*/000000.png"):
            cam = f.parent.name[len("gray") :]
            mask = _read(f.parents[1] / f"mask_markers{cam}" / "000000.png") > 0
            bare = _read(tmp_path / "bare_bop" / f.relative_to(tmp_path / out))
            n += int((_read(f) != bare)[~mask].sum())
        return n, elsewhere

    assert main(["export", str(tmp_path / "bare"), str(tmp_path / "bare_bop"), *common]) == 0
    ink, elsewhere = ink_outside("layout")
    assert elsewhere >= 2 and ink < 20
    glued = json.loads((tmp_path / "marked" / "glued_sites.json").read_text())
    for obj, sites in glued.items():
        path = tmp_path / "marked" / "objects" / obj / "object.yaml"
        doc = yaml.safe_load(path.read_text())
        for inst in doc["instances"]:
            inst["sites"] = sites[inst["name"]]
        path.write_text(yaml.safe_dump(doc))
    assert ink_outside("measured") == (0, 0)


def test_the_summary_counts_the_markers_filled(exports, tmp_path, capsys) -> None:
    """``annotator export --json`` says how many markers were filled in: the COCO files'
    marker annotations; a plain export says null."""
    args = ["export", str(exports / "marked"), str(tmp_path / "a"), "--format", "bop"]
    args += ["--poses", "gt", "--include-pending", "--quiet", "--json"]
    assert main([*args, "--remove-markers"]) == 0
    summary = json.loads(capsys.readouterr().out)
    count = 0
    for f in (exports / "removed" / "test").glob("*/scene_gt_coco_*.json"):
        coco = json.loads(f.read_text())
        marker = next(c["id"] for c in coco["categories"] if c["name"] == "marker")
        count += sum(a["category_id"] == marker for a in coco["annotations"])
    assert summary["markers_filled"] == count > 40
    args[2] = str(tmp_path / "b")
    assert main(args) == 0
    assert json.loads(capsys.readouterr().out)["markers_filled"] is None


def test_marker_turned_a_little_away_on_a_curved_part() -> None:
    """A square tangent to a cylinder beyond its outline (its plane turned 10 degrees away
    from the camera): the curved surface under its near edge still faces the camera and
    carries ink up to the outline, where the part's outline pixels (either side, no pixel
    centre on the sliver) are taken too, as for a facing square seen edge-on."""
    c = trimesh.creation.cylinder(radius=15.0, height=80.0, sections=256)
    rx = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # the axis along y
    cyl = Mesh(np.asarray(c.vertices) @ rx.T, np.asarray(c.faces, dtype=np.int32))
    phi, h = np.radians(100.0), 10.0
    n0 = np.array([np.sin(phi), 0, -np.cos(phi)])  # outward, 10 degrees past edge-on
    a, b = np.array([np.cos(phi), 0, np.sin(phi)]), np.array([0, 1.0, 0])
    centre = 15.0 * n0
    site = np.array([centre - h * a - h * b, centre + h * a - h * b])
    site = np.vstack([site, [centre + h * a + h * b, centre - h * a + h * b]])
    inst = MarkedInstance(
        "cyl", "01", cyl, make_transform(np.eye(3), [0, 0, 300.0]), site[None], (7,)
    )
    _, images = scene_markers(_one_camera(), [inst], cameras=["cam"], margin_px=0)
    im = images["cam"]
    (r,) = im.regions
    assert not r.facing and r.px_visib > 0
    rows, cols = r.pixels[:, 0], r.pixels[:, 1]
    outside = im.labels[rows, cols] == -1
    assert outside.any()  # the outline's far side: only the outline rule takes it
    # ... and only along the outline (x = 15 mm at 300 mm, f = 800: column 359.5)
    assert np.abs(cols[outside] - 359.5).max() <= 3


def test_each_frame_of_a_sequence_has_its_own_blur(sequence) -> None:
    """A sequence's annotation.json keeps the blur ``annotate`` measured per frame (a frame
    taken while the rig moved is blurred more): the masks of a frame grow by its own."""
    from annotator.export.removal import scene_blur
    from annotator.io.documents import read_json

    (scene,) = load_dataset(sequence).scenes()
    frames = read_json(scene.annotation_path)["frames"]
    assert scene_blur(scene) == {}  # the scene's own entry is empty for a sequence
    for name, doc in frames.items():
        quality = doc["image_quality"].items()
        want = {c: q["edge_blur_px"] for c, q in quality if q["edge_blur_px"] is not None}
        assert scene_blur(scene, name) == want and want  # (a camera may measure none)
