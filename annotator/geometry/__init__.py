"""Geometry shared by every stage of the pipeline.

Conventions, stated once for the whole project (they follow docs/FORMAT.md):

- Lengths are millimetres; angles radians. Libraries that want metres (MuJoCo, viser, the
  paper's files) are given ``mm / MM_PER_M``.
- A rigid transform ``a_T_b`` is a 4x4 homogeneous matrix mapping coordinates in frame ``b``
  to frame ``a``: ``x_a = a_T_b @ x_b``. Rotations are 3x3 matrices, serialised row-major.
- A pose maps model to camera, ``x_cam = R @ x_model + t`` (BOP's ``cam_R_m2c``,
  ``cam_t_m2c``), and is expressed in the *reference* camera (the rig's first camera).
- Cameras follow OpenCV: +z forward, +y down, pixel centres at integer coordinates, lens
  distortion in OpenCV's order and model.
- Marker corners follow OpenCV ArUco order: top-left, top-right, bottom-right, bottom-left
  as seen from outside the object.
- Pixel boxes come in two conventions, each with its own name: :data:`Rect` ``(x0, y0, x1,
  y1)``, end exclusive (what is cast over, unexplained-depth regions), and :data:`XYWH`
  ``(x, y, width, height)`` (what BOP writes).
"""

#: Millimetres per metre: the one conversion between our lengths and metric libraries'.
MM_PER_M = 1000.0

#: A pixel rectangle ``(x0, y0, x1, y1)``, end exclusive.
Rect = tuple[int, int, int, int]

#: A box as BOP writes it: ``(x, y, width, height)`` of the pixels it covers.
XYWH = tuple[int, int, int, int]
