"""Physically based images of the synthetic scenes (``annotator synth --render pbr``).

The scenes are the same as :mod:`annotator.synthesis` builds (the physics drop, the markers
on their sites, the rig); only the images differ: Cycles renders them (:mod:`.cycles_job`,
which runs :mod:`.cycles_worker` in bpy's own interpreter) with per-part materials
(:mod:`annotator.dataset.materials`), area lights and an environment, optionally depth of field; the lens
distortion is applied afterwards (:mod:`.lens`), then the sensor's noise (:mod:`.sensor`).
The depth map comes from a structured-light model (:mod:`.structured_light`). The truth
files (gt.json, depth_ideal.png, occlusion rates) are our own ray caster's, as for every
other synthetic scene.
"""
