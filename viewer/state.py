"""Review decisions of a dataset, read from and written to each scene's review.json.

Every action writes review.json atomically at once (killing the server loses nothing), and
every read goes back to the files (cached by modification time), so two browsers, or two
servers, on the same dataset see the same decisions.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

from annotator.dataset import InstancePose, load_dataset
from annotator.dataset.poses import read_poses
from annotator.dataset.review import Review, now_iso, poses_fingerprint, read_review, write_review
from annotator.errors import UserError

FILTERS = ("all", "pending", "flagged", "rejected", "stale")


@dataclass(frozen=True)
class SceneInfo:
    id: str
    annotated: bool
    poses: tuple[InstancePose, ...]
    review: Review
    stale: bool
    flagged: bool
    error: str | None  # a problem to show (unreadable annotation, corrupt review.json)

    @property
    def status(self) -> str:
        return self.review.status

    def instance_status(self, key: str) -> str:
        """``accepted``, ``rejected`` or ``pending`` (no decision yet)."""
        return self.review.instances.get(
            key, "accepted" if self.review.status == "accepted" else "pending"
        )


class ReviewState:
    """The review state of one dataset."""

    def __init__(self, root: str | Path) -> None:
        self.ds = load_dataset(root)
        self.ids = [s.id for s in self.ds.scenes()]
        self._lock = threading.Lock()
        self._cache: dict[str, tuple[tuple[float, float], SceneInfo]] = {}
        self.started = time.time()
        self.decided = 0  # decisions made through this server

    def _mtimes(self, sid: str) -> tuple[float, float]:
        sc = self.ds.scene(sid)
        a = sc.annotation_path.stat().st_mtime if sc.annotation_path.exists() else 0.0
        r = sc.review_path.stat().st_mtime_ns if sc.review_path.exists() else 0.0
        return (a, r)

    def info(self, sid: str) -> SceneInfo:
        key = self._mtimes(sid)
        hit = self._cache.get(sid)
        if hit and hit[0] == key:
            return hit[1]
        sc = self.ds.scene(sid)
        error = None
        poses: list[InstancePose] = []
        annotated = sc.annotation_path.exists()
        if annotated:
            try:
                poses = read_poses(sc.annotation_path)
            except UserError as exc:
                error = str(exc)
        try:
            review = read_review(sc.review_path) or Review()
        except UserError as exc:
            review, error = Review(), f"{exc} (it will be replaced by the next decision)"
        fp = poses_fingerprint(poses)
        info = SceneInfo(
            id=sid,
            annotated=annotated,
            poses=tuple(poses),
            review=review,
            stale=review.is_stale(fp),
            flagged=any(p.extra.get("flags") for p in poses),
            error=error,
        )
        self._cache[sid] = (key, info)
        return info

    def _write(self, sid: str, review: Review) -> None:
        info = self.info(sid)
        review.annotation_fingerprint = poses_fingerprint(list(info.poses))
        review.decided_at = now_iso()
        write_review(self.ds.scene(sid).review_path, review)
        self.decided += 1

    def set_scene(self, sid: str, status: str) -> None:
        """Accept or reject a whole scene (per-instance rejections are kept)."""
        with self._lock:
            info = self.info(sid)
            instances = {k: v for k, v in info.review.instances.items() if v == "rejected"}
            self._write(
                sid, Review(status=status, instances=instances, extra=dict(info.review.extra))
            )

    def toggle_instance(self, sid: str, key: str) -> str:
        """Flip one instance between accepted and rejected; return its new status."""
        with self._lock:
            info = self.info(sid)
            new = "accepted" if info.instance_status(key) == "rejected" else "rejected"
            instances = dict(info.review.instances)
            instances[key] = new
            self._write(
                sid,
                Review(
                    status=info.review.status, instances=instances, extra=dict(info.review.extra)
                ),
            )
            return new

    def matches(self, sid: str, flt: str) -> bool:
        info = self.info(sid)
        return {
            "all": True,
            "pending": info.status == "pending" or info.stale,
            "flagged": info.flagged,
            "rejected": info.status == "rejected",
            "stale": info.stale,
        }[flt]

    def progress(self) -> tuple[int, int]:
        """(scenes with a current decision, total)."""
        done = 0
        for sid in self.ids:
            info = self.info(sid)
            done += info.status != "pending" and not info.stale
        return done, len(self.ids)

    def pace(self) -> float:
        """Decisions per minute made through this server."""
        minutes = max((time.time() - self.started) / 60.0, 1e-6)
        return self.decided / minutes
