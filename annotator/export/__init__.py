"""Exporting accepted scenes: to the BOP format (:mod:`.bop`) and to the paper's own dataset
format (:mod:`.sileane`); which scenes go out is decided by :mod:`.selection`."""
