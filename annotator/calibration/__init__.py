"""Rig calibration from synchronised shots of a ChArUco board (``annotator calibrate``).

One concept per module:

- :mod:`.board`: the board (``board.yaml``, OpenCV's ``CharucoBoard``, its corners);
- :mod:`.captures`: the captures folder, ``CAPTURES/<camera>/<shot>.png``, and its checks;
- :mod:`.detect`: the board's chessboard corners in one image (OpenCV's ChArUco detector);
- :mod:`.solve`: screening, per-camera ``calibrateCamera``, initial extrinsics, outliers;
- :mod:`.bundle`: the joint Levenberg-Marquardt refinement of every camera and shot;
- :mod:`.report`: RMS per camera and shot, rejections, coverage pictures, ``report.json``;
- :mod:`.rig_yaml`: the ``rig:`` block of ``dataset.yaml``, spliced in, and its diff;
- :mod:`.baseline`: OpenCV's own stereo pipelines, the reference in tests and benchmarks.

Typical use::

    from annotator.calibration.board import read_board_yaml
    from annotator.calibration.captures import find_captures
    from annotator.calibration.detect import detect_captures
    from annotator.calibration.solve import calibrate_rig

    board = read_board_yaml("captures/board.yaml")
    caps = find_captures("captures")
    found = detect_captures(caps, board)
    cal = calibrate_rig(found.views, cameras=caps.cameras, sizes=found.sizes,
                        shots=caps.shots, board=board)
    cal.rig_cameras  # Camera objects: K, dist, rig_T_cam
"""
