"""Generated BOP 6D pose cases of an official test set's size: a BOP folder with models (and
models_eval) of LM's size, a test split whose depth images are the instances rendered over a
table, scene_gt/scene_gt_info/scene_camera, both targets files, and a result CSV of
realistic count (found instances with errors from tight to coarse, doubles, false poses),
deterministic for a seed.

- ``lmo``: LM-O's shape: 200 images of scene 2, 640x480, LM's camera, objects 1, 5, 6, 8-12
  (10 and 11 with a half turn, as LM-O's eggbox and glue), meshes of 5k-41k vertices.
- ``tless``: a T-LESS-sized set: 30 objects of 2.5k-10k vertices (a third with a
  continuous symmetry, a third with a half turn), 20 scenes of 25 images at 720x540, 6-10
  instances an image.

The folder is named as the dataset bop_toolkit knows (``lmo``, ``tless``), so that its own
``dataset_params.py`` applies without edits.

    .venv/bin/python -m benchmarks.bop_cases OUT --case lmo
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Case:
    """The shape of a generated case."""

    name: str
    split: str  # the split folder (bop_toolkit's split + split type)
    obj_ids: tuple[int, ...]
    scenes: tuple[int, ...]
    per_scene: int
    width: int
    height: int
    K: tuple[float, ...]
    instances: tuple[int, int]  # per image (lmo: every object once)
    subdivisions: tuple[int, ...] = (5, 5, 6)  # of the icosphere: 10k or 41k vertices
    continuous: tuple[int, ...] = ()
    half_turn: tuple[int, ...] = ()
    depth_mm: tuple[float, float] = (650.0, 1050.0)


CASES = {
    "lmo": Case(
        "lmo",
        "test",
        (1, 5, 6, 8, 9, 10, 11, 12),
        (2,),
        200,
        640,
        480,
        (572.4114, 0.0, 325.2611, 0.0, 573.57043, 242.04899, 0.0, 0.0, 1.0),
        (8, 8),
        half_turn=(10, 11),
    ),
    "tless": Case(
        "tless",
        "test_primesense",
        tuple(range(1, 31)),
        tuple(range(1, 21)),
        25,
        720,
        540,
        (1075.65, 0.0, 360.0, 0.0, 1073.90, 270.0, 0.0, 0.0, 1.0),
        (6, 10),
        continuous=tuple(range(1, 11)),
        half_turn=tuple(range(11, 21)),
        subdivisions=(4, 5),
    ),
}


def _mesh(rng: np.random.Generator, oid: int, case: Case) -> tuple[np.ndarray, np.ndarray]:
    """A closed, bumpy ellipsoid of 2.5k-41k vertices and 60-220 mm across, symmetric as
    the case lists the object (about the model's z axis)."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=int(rng.choice(case.subdivisions)))
    v = np.asarray(sphere.vertices, float)
    lon, lat = np.arctan2(v[:, 1], v[:, 0]), np.arcsin(np.clip(v[:, 2], -1, 1))
    if oid in case.continuous:
        bump = 0.12 * np.sin(3 * lat + rng.uniform(0, 6))
        axes = np.r_[np.full(2, rng.uniform(30, 60)), rng.uniform(40, 110)]
    else:
        k = 2 if oid in case.half_turn else 1
        bump = 0.1 * np.cos(k * lon + (0 if k == 2 else rng.uniform(0, 6))) * np.cos(lat)
        bump += 0.06 * np.sin(2 * lat + rng.uniform(0, 6))
        if k == 1:
            bump += 0.05 * np.sin(3 * lon + 2 * lat)
        axes = rng.uniform(30, 110, 3)
    v = v * (1 + bump)[:, None] * axes
    return v - 0.5 * (v.min(0) + v.max(0)), np.asarray(sphere.faces, np.int32)


def _write_ply(path: Path, v: np.ndarray, f: np.ndarray) -> None:
    """A binary PLY as BOP's models are (vertices with normals, uchar-counted int faces)."""
    n = np.zeros_like(v)
    tri = v[f]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    verts = np.hstack([v, n]).astype("<f4")
    faces = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"], faces["i"] = 3, f
    path.write_bytes(header.encode() + verts.tobytes() + faces.tobytes())


def _info(v: np.ndarray, oid: int, case: Case) -> dict:
    from scipy.spatial import ConvexHull

    # Both tools take models_info's diameter as given: the hull's extent over a subsample
    # of its vertices is close enough, and quick.
    hull = v[ConvexHull(v).vertices][::8]
    diameter = float(np.sqrt(((hull[:, None] - hull[None]) ** 2).sum(-1)).max())
    lo, hi = v.min(0), v.max(0)
    entry = {"diameter": diameter}
    for k, axis in enumerate("xyz"):
        entry[f"min_{axis}"], entry[f"size_{axis}"] = float(lo[k]), float(hi[k] - lo[k])
    if oid in case.continuous:
        entry["symmetries_continuous"] = [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]
    elif oid in case.half_turn:
        entry["symmetries_discrete"] = [[-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]
    return entry


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _small_rotation(rng: np.random.Generator, deg: float) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(rng.normal(scale=np.radians(deg), size=3))[0]


def _pose_line(scene: int, im: int, oid: int, score: float, R: np.ndarray, t: np.ndarray) -> str:
    r = " ".join(f"{x:.9f}" for x in R.reshape(-1))
    return f"{scene},{im},{oid},{score:.6f},{r},{' '.join(f'{x:.6f}' for x in t)},0.25"


def make_case(out: Path, name: str, seed: int = 0) -> Path:
    """Writes the case ``name`` (:data:`CASES`) into ``out`` (a folder named as the case);
    returns its result CSV (``mine_<name>-test.csv``)."""
    from annotator.geometry.mesh import Mesh
    from annotator.io.images import write_png
    from annotator.rendering.raycast import render_depth

    case = CASES[name]
    rng = np.random.default_rng(seed)
    K = np.asarray(case.K, float).reshape(3, 3)
    meshes, info = {}, {}
    for folder in ("models", "models_eval"):
        (out / folder).mkdir(parents=True, exist_ok=True)
    for oid in case.obj_ids:
        v, f = _mesh(rng, oid, case)
        meshes[oid] = Mesh(v.astype(np.float32).astype(float), f)
        info[str(oid)] = _info(v, oid, case)
        for folder in ("models", "models_eval"):
            _write_ply(out / folder / f"obj_{oid:06d}.ply", v, f)
    for folder in ("models", "models_eval"):
        (out / folder / "models_info.json").write_text(json.dumps(info, indent=1))
    (out / "camera.json").write_text(
        json.dumps({"width": case.width, "height": case.height, "depth_scale": 1.0}
                   | {k: case.K[i] for k, i in (("fx", 0), ("fy", 4), ("cx", 2), ("cy", 5))})
    )  # fmt: skip
    lines = ["scene_id,im_id,obj_id,score,R,t,time"]
    targets19: list[dict[str, int]] = []
    targets24: list[dict[str, int]] = []
    ys, xs = np.mgrid[0 : case.height, 0 : case.width]
    for scene in case.scenes:
        folder = out / case.split / f"{scene:06d}"
        (folder / "depth").mkdir(parents=True, exist_ok=True)
        gt_doc, info_doc, cam_doc = {}, {}, {}
        for im in range(case.per_scene):
            n = int(rng.integers(case.instances[0], case.instances[1] + 1))
            if name == "lmo":
                oids = list(case.obj_ids)
            else:
                oids = [int(o) for o in rng.choice(case.obj_ids, size=n)]
            centre = np.array([0.0, 0.0, rng.uniform(*case.depth_mm)])
            table = centre[2] + 120.0 + 0.02 * (xs - case.width / 2)
            depth = table.astype(np.float32)
            poses, renders = [], []
            for oid in oids:
                z = centre[2] + rng.uniform(-80, 80)
                uv = rng.uniform([0.15 * case.width, 0.15 * case.height],
                                 [0.85 * case.width, 0.85 * case.height])  # fmt: skip
                t = np.array([(uv[0] - K[0, 2]) * z / K[0, 0], (uv[1] - K[1, 2]) * z / K[1, 1], z])
                R = _rotation(rng)
                T = np.eye(4)
                T[:3, :3], T[:3, 3] = R, t
                got = render_depth(meshes[oid], T, K, case.width, case.height)
                poses.append((oid, R, t))
                renders.append(got)
                if got is not None:
                    (x0, y0, x1, y1), d = got
                    crop = depth[y0:y1, x0:x1]
                    crop[(d > 0) & (d < crop)] = d[(d > 0) & (d < crop)]
            gts, infos = [], []
            for (oid, R, t), got in zip(poses, renders):
                gts.append({"cam_R_m2c": R.reshape(-1).tolist(), "cam_t_m2c": t.tolist(),
                            "obj_id": oid})  # fmt: skip
                if got is None:
                    all_px = visib_px = 0
                    box = [-1, -1, -1, -1]
                else:
                    (x0, y0, x1, y1), d = got
                    seen = d > 0
                    all_px = int(seen.sum())
                    visib_px = int((seen & (d <= depth[y0:y1, x0:x1] + 1e-3)).sum())
                    box = [x0, y0, x1 - x0, y1 - y0]
                infos.append({"bbox_obj": box, "bbox_visib": box, "px_count_all": all_px,
                              "px_count_valid": all_px, "px_count_visib": visib_px,
                              "visib_fract": visib_px / all_px if all_px else 0.0})  # fmt: skip
            noisy = depth + rng.normal(scale=1.0, size=depth.shape).astype(np.float32)
            noisy[rng.random(depth.shape) < 0.02] = 0  # holes, as a sensor's
            write_png(folder / "depth" / f"{im:06d}.png", np.round(noisy).astype(np.uint16))
            gt_doc[str(im)], info_doc[str(im)] = gts, infos
            cam_doc[str(im)] = {"cam_K": list(case.K), "depth_scale": 1.0}
            counts: dict[int, int] = {}
            for (oid, _, _), inf in zip(poses, infos):
                if inf["visib_fract"] >= 0.1:
                    counts[oid] = counts.get(oid, 0) + 1
            targets19 += [{"im_id": im, "inst_count": c, "obj_id": o, "scene_id": scene}
                          for o, c in sorted(counts.items())]  # fmt: skip
            targets24.append({"im_id": im, "scene_id": scene})
            lines += _estimates(rng, scene, im, poses, case)
        (folder / "scene_gt.json").write_text(json.dumps(gt_doc))
        (folder / "scene_gt_info.json").write_text(json.dumps(info_doc))
        (folder / "scene_camera.json").write_text(json.dumps(cam_doc))
    (out / "test_targets_bop19.json").write_text(json.dumps(targets19))
    (out / "test_targets_bop24.json").write_text(json.dumps(targets24))
    results = out / f"mine_{name}-test.csv"
    results.write_text("\n".join(lines) + "\n")
    return results


def _estimates(
    rng: np.random.Generator,
    scene: int,
    im: int,
    poses: list[tuple[int, np.ndarray, np.ndarray]],
    case: Case,
) -> list[str]:
    """An image's estimates: most instances found once (error from a fraction of a mm to
    a coarse pose), some twice, a few false poses of objects the image has or not."""
    lines = []
    for oid, R, t in poses:
        for _ in range(int(rng.choice([0, 1, 1, 1, 1, 2]))):
            deg, mm = [(1, 2), (3, 6), (8, 15), (25, 40)][int(rng.integers(4))]
            R_e = _small_rotation(rng, deg) @ R
            t_e = t + rng.normal(scale=mm, size=3)
            lines.append(_pose_line(scene, im, oid, rng.uniform(0.2, 1), R_e, t_e))
    for _ in range(int(rng.integers(1, 4))):
        oid, _, t = poses[int(rng.integers(len(poses)))]
        if rng.random() < 0.3:
            oid = int(rng.choice(case.obj_ids))
        t_e = t + rng.normal(scale=60, size=3)
        lines.append(_pose_line(scene, im, oid, rng.uniform(0, 0.6), _rotation(rng), t_e))
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path, help="parent folder; the case is written in OUT/<case>")
    ap.add_argument("--case", choices=sorted(CASES), default="lmo")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    print(make_case(args.out / args.case, args.case, seed=args.seed))


if __name__ == "__main__":
    main()
