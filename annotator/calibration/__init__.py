"""Rig calibration from synchronised shots of a ChArUco board or a plain chessboard
(``annotator calibrate``).

One concept per module:

- :mod:`.board`: the board (``board.yaml``, OpenCV's ``CharucoBoard``, its corners);
- :mod:`.captures`: the captures folder, ``CAPTURES/<camera>/<shot>.png`` or one video per
  camera, and its checks;
- :mod:`.caliscope`: a session as caliscope records it (``charuco.toml``, its videos and
  ``timestamps.csv``), read as it is;
- :mod:`.detect`: the board's chessboard corners in one image (inverted, flipped), and in
  every image of the captures;
- :mod:`.readings`: a board that reads only flipped: a mirrored camera or a board seen from
  behind, decided by the other cameras' board poses;
- :mod:`.records`: the views, the settings and the result's records;
- :mod:`.single`: one camera alone: usable views, ``calibrateCamera``;
- :mod:`.rig`: initial extrinsics, the joint refinement with outliers left out, the result;
- :mod:`.outliers`: which corners and views of the joint fit are outliers;
- :mod:`.bundle`: the joint Levenberg-Marquardt refinement of every camera and shot;
- :mod:`.heldout`: the held-out error, k-fold over shots, predicted across cameras;
- :mod:`.pairwise`: each camera pair calibrated alone as an OpenCV stereo pair, the bar a
  rig's held-out transfer error is held to;
- :mod:`.extrapolation`: where a distortion model is extrapolated, and by how much;
- :mod:`.model_choice`: the distortion model chosen by the held-out error;
- :mod:`.checks`: whether the rig holds together before anything is written;
- :mod:`.report`: RMS per camera and shot, rejections, coverage pictures, ``report.json``;
- :mod:`.rig_yaml`: the ``rig:`` block of ``dataset.yaml``, spliced in, and its diff.

OpenCV's own stereo pipelines, the reference in tests and benchmarks, live in
``tests/opencv_baseline.py``.

Typical use::

    from annotator.calibration.board import read_board_yaml
    from annotator.calibration.captures import find_captures
    from annotator.calibration.detect import detect_captures
    from annotator.calibration.model_choice import calibrate_and_assess

    board = read_board_yaml("captures/board.yaml")
    caps = find_captures("captures")
    found = detect_captures(caps, board)
    cal = calibrate_and_assess(found.views, cameras=caps.cameras, sizes=found.sizes,
                               shots=caps.shots, board=board)
    cal.rig_cameras  # Camera objects: K, dist, rig_T_cam
    cal.held_out     # the error on shots it did not fit, per camera pair
    cal.readings     # per camera: mirrored or not, the shots it saw the board from behind
    cal.problems     # why the rig must not be written (empty: it may)
"""
