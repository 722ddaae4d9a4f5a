"""Synthetic bin-picking scenes with exact ground truth (paper section 3.2).

Parts are dropped into a bin by MuJoCo (:mod:`.physics`), seen by a two-camera rig with a
pseudo-random dot projector (:mod:`.rig`), rendered with their markers (:mod:`.shading`), and
the depth map is reconstructed by simulated active stereo (:mod:`.stereo`);
:mod:`.generate` writes the dataset (FORMAT.md).

World frame: the bin frame, z up, the bin floor's top surface at z = 0, mm.
"""
