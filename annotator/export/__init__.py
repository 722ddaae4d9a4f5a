"""Exporting accepted scenes of one of our datasets: which scenes go out (:mod:`.selection`),
what is read from each (:mod:`.inputs`) and the undistortion to pinhole cameras
(:mod:`.undistort`); with ``--remove-markers``, where every marker is in every exported image
(:mod:`.markers`), how its pixels are filled in (:mod:`.fill`) and both for one scene
(:mod:`.removal`). The writers are the formats' own (:mod:`annotator.formats`)."""
