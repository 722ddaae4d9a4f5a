"""A baseline pose estimator on depth maps: point pair features (Drost et al. 2010), with the
symmetry-aware mode finding and duplicate removal of Brégier et al. 2017, section 4.2.

Why a native implementation and not OpenCV's ``cv2.ppf_match_3d.PPF3DDetector``: the paper's
variant *replaces the clustering of the votes*, and OpenCV's detector hides it: it returns
poses already clustered in SE(3), its clustering (``setSearchParams``) is not exposed to
Python, and the votes themselves are never returned. It also subsamples the scene relative to
the scene's own bounding box (the same part is sampled differently in a bigger bin), returns
non-unit quaternions from clustering in 4.x, trains all model pairs on one thread and has no
upstream tests. Here every step is numpy/scipy, seeded and tested, and the votes are there
to cluster either way.

Modules, one concept each:

- :mod:`.cloud`: the depth map as oriented points, the setting (bin, support) removed;
- :mod:`.features`: point pair features and local frames;
- :mod:`.model`: the trained part (samples and the pair table), cached per part;
- :mod:`.voting`: one pose vote per scene reference point;
- :mod:`.estimator`: votes to hypotheses (mean shift in SE(3) or in the part's pose space,
  duplicates, the optional post-processing) and the variants' settings;
- :mod:`.icp`, :mod:`.scoring`: the post-processing's refinement and depth score;
- :mod:`.results`: BOP's results CSV; :mod:`.job`: a scene as a batch job.
"""

from annotator.estimation.estimator import (
    Hypothesis,
    PPFSettings,
    SceneEstimate,
    estimate_scene,
    variants,
)

__all__ = ["Hypothesis", "PPFSettings", "SceneEstimate", "estimate_scene", "variants"]
