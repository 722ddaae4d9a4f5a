"""Writes ``bop24_results.csv`` beside this file: 6D detection results on the sample's BOP
export (``annotator export sample_scenes OUT --format bop --include-pending --poses gt
--cameras left``), made to exercise what BOP 2024's scores depend on.

Per image: copies of true poses moved by 0 to 60 % of the diameter (some turned too), false
poses, and scores with ties across images; scene 1 has 119 estimates: 110 false ones scored
above its 9 exact ones, which BOP's limit of 100 estimates per image leaves out; each image
takes its own time. Deterministic (seed 24)::

    python tests/data/make_bop24_results.py EXPORT
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def main(export: Path) -> None:
    rng = np.random.default_rng(24)
    info = json.loads((export / "models" / "models_info.json").read_text())
    lines = ["scene_id,im_id,obj_id,score,R,t,time"]

    def row(scene: int, oid: int, score: float, R: np.ndarray, t: np.ndarray) -> None:
        r = " ".join(f"{v:.9f}" for v in R.ravel())
        tt = " ".join(f"{v:.6f}" for v in t)
        lines.append(f"{scene},0,{oid},{score:.6f},{r},{tt},{1.0 + 0.25 * scene:.2f}")

    for scene in range(4):
        gts = json.loads((export / "test" / f"{scene:06d}" / "scene_gt.json").read_text())["0"]
        for g in gts:
            oid = int(g["obj_id"])
            d = float(info[str(oid)]["diameter"])
            R = np.asarray(g["cam_R_m2c"], float).reshape(3, 3)
            t = np.asarray(g["cam_t_m2c"], float)
            for j, frac in enumerate((0.0, 0.03, 0.08, 0.15, 0.3, 0.6)):
                if rng.random() < 0.35:
                    continue
                step = rng.normal(size=3)
                step *= frac * d / np.linalg.norm(step)
                turn = Rotation.from_rotvec(rng.normal(scale=0.02 * j, size=3)).as_matrix()
                score = round(float(rng.uniform(0.05, 1.0)), 2)  # ties across images
                row(scene, oid, score, turn @ R, t + step)
        for _ in range(4):  # false poses
            oid = int(rng.integers(1, 4))
            R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
            t = np.array([rng.uniform(-150, 150), rng.uniform(-150, 150), rng.uniform(350, 600)])
            row(scene, oid, round(float(rng.uniform(0.05, 1.0)), 2), R, t)
        if scene == 1:
            for _ in range(110):
                oid = int(rng.integers(1, 4))
                R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
                t = np.array([rng.uniform(-150, 150), rng.uniform(-150, 150), 800.0])
                row(scene, oid, float(rng.uniform(0.02, 0.049)), R, t)
            for g in gts:
                R = np.asarray(g["cam_R_m2c"], float).reshape(3, 3)
                row(scene, int(g["obj_id"]), 0.01, R, np.asarray(g["cam_t_m2c"], float))
    (Path(__file__).parent / "bop24_results.csv").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
