"""Symmetry-aware evaluation of pose estimation in scenes of many instances (paper section 5)."""
