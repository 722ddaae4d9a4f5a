"""Scene switching in the review viewer: two 1280x1024 cameras, 20 instances per scene.
Target: the new overlays shown in under 300 ms (the next scene is prepared in advance).

    .venv/bin/python benchmarks/bench_viewer.py
"""

from __future__ import annotations

import shutil
import socket
import tempfile
import time
from pathlib import Path

from annotator.synthesis.generate import SynthConfig, make_scene, plan_dataset, write_dataset_files
from viewer.app import ReviewApp
from viewer.overlays import prepare


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "ds"
        plan = plan_dataset(SynthConfig(parts=("bracket", "cylinder"), instances=(20, 20), seed=3))
        write_dataset_files(plan, root)
        for k in range(4):
            folder = root / "scenes" / f"{k:06d}"
            folder.mkdir(parents=True)
            make_scene(plan, k, folder)
            shutil.copy(folder / "gt.json", folder / "annotation.json")  # poses to review
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        app = ReviewApp(root, port=port)
        try:
            ds = app.state.ds
            t0 = time.perf_counter()
            prepare(ds, ds.scene("000003"), list(app.state.info("000003").poses))
            cold = time.perf_counter() - t0
            times = []
            for _ in range(3):
                time.sleep(1.5)  # a person looks at the scene; the next one is being prepared
                t0 = time.perf_counter()
                app.step(+1)
                times.append(time.perf_counter() - t0)
        finally:
            app.stop()
    print(
        f"viewer, 2 x 1280x1024 cameras, 20 instances: preparing a scene cold {1000 * cold:.0f} ms"
    )
    worst = max(times)
    print(
        f"  switching to the prefetched next scene: {', '.join(f'{1000 * t:.0f}' for t in times)} ms "
        f"(target 300 ms: ratio {worst / 0.3:.2f})"
    )


if __name__ == "__main__":
    main()
