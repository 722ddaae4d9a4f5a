"""What the tests and the benchmarks share, and users never need (it is not installed with
the package): a review server in a child process (:mod:`.served`), a bare page speaking
viser's protocol (:mod:`.wire`), Debian's Chromium through Playwright (:mod:`.headless`),
waiting for another thread or process (:mod:`.polling`), a throwaway Ray cluster
(:mod:`.local_cluster`), OpenCV's own calibration pipeline run beside ours
(:mod:`.opencv_baseline`), OpenCV's ArUco detector at several settings
(:mod:`.aruco_settings`), scenes rendered with and without markers and exported
(:mod:`.marker_twins`).

The tests import it through pytest's ``pythonpath`` (pyproject.toml); the benchmarks run as
modules from the repository's root (``python -m benchmarks.bench_viewer``), where it is
importable as it is.
"""
