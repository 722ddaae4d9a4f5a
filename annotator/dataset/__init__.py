"""The dataset contract (docs/FORMAT.md): its records, its reader and its JSON files.

Typical use::

    from annotator.dataset import load_dataset
    ds = load_dataset("sample_scenes")
    for scene in ds.scenes():
        img = scene.read_image(ds.rig.cameras[0])
"""

from annotator.dataset.load import (
    Problem,
    as_dataset,
    cached_dataset,
    load_dataset,
    read_dataset,
    require_meshes,
)
from annotator.dataset.model import (
    Dataset,
    DepthSpec,
    Instance,
    MarkerRef,
    MarkerSites,
    ObjectModel,
    Rig,
    Scene,
    Symmetry,
)
from annotator.dataset.poses import InstancePose, read_poses, write_poses

__all__ = [
    "Dataset",
    "DepthSpec",
    "Instance",
    "InstancePose",
    "MarkerRef",
    "MarkerSites",
    "ObjectModel",
    "Problem",
    "Rig",
    "Scene",
    "Symmetry",
    "as_dataset",
    "cached_dataset",
    "load_dataset",
    "read_dataset",
    "read_poses",
    "require_meshes",
    "write_poses",
]
