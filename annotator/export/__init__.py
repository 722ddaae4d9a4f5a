"""Exporting accepted scenes of one of our datasets into another format:
:func:`~annotator.export.dataset.export_dataset` (what ``annotator export`` runs, with its
modes in :mod:`.options`); which scenes go out (:mod:`.selection`), what is read from each
(:mod:`.inputs`), the undistortion to pinhole cameras (:mod:`.undistort`), and the writers,
one per format (:mod:`.bop`, :mod:`.sileane`). With ``--remove-markers``: where every marker
is in every exported image (:mod:`.markers`), how its pixels are filled in (:mod:`.fill`)
and both for one scene (:mod:`.removal`). Reading the formats is :mod:`annotator.formats`'."""
