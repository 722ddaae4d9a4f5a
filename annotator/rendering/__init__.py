"""CPU ray casting of posed meshes into calibrated cameras (open3d, no GL)."""
