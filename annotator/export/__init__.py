"""Exporting accepted scenes of one of our datasets: which scenes go out (:mod:`.selection`),
what is read from each (:mod:`.inputs`) and the undistortion to pinhole cameras
(:mod:`.undistort`). The writers are the formats' own (:mod:`annotator.formats`)."""
