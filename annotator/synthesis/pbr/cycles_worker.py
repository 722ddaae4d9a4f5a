"""The Blender side of ``synth --render pbr``: build a described scene in Cycles and render it.

Run by the interpreter that holds ``bpy`` (``python cycles_worker.py JOB.json``), never
imported by the rest of the project: it needs nothing but ``bpy``, numpy (1.x or 2.x) and the
standard library, so that bpy's own environment (Python 3.11, numpy < 2) can run it. The job
(:func:`annotator.synthesis.pbr.cycles_job.write_job`) gives metres, Blender's frames (a camera
looks along its -z, +y up; an area light shines along its -z) and, per camera, where to save
the linear RGB image as a float32 ``.npy``. Progress goes to stdout as ``PROGRESS <camera>
<sample> <samples>`` lines, the end of a camera as ``DONE <camera>``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any


def _mesh(bpy: Any, np: Any, name: str, verts: Any, faces: Any, uv: Any = None) -> Any:
    """A Blender mesh from (V, 3) vertices and (F, 3|4) faces; ``uv``: per face corner."""
    mesh = bpy.data.meshes.new(name)
    n_corner = faces.shape[1]
    mesh.vertices.add(len(verts))
    mesh.vertices.foreach_set("co", np.ascontiguousarray(verts, np.float32).ravel())
    mesh.loops.add(faces.size)
    mesh.loops.foreach_set("vertex_index", np.ascontiguousarray(faces, np.int32).ravel())
    mesh.polygons.add(len(faces))
    mesh.polygons.foreach_set("loop_start", np.arange(0, faces.size, n_corner, dtype=np.int32))
    if uv is not None:
        layer = mesh.uv_layers.new(name="UVMap")
        layer.data.foreach_set("uv", np.ascontiguousarray(uv, np.float32).ravel())
    mesh.update(calc_edges=True)
    mesh.validate()
    return mesh


def _material(bpy: Any, spec: dict[str, Any], atlas: Any = None) -> Any:
    """A Principled BSDF material: metal, painted plastic or printed paper (``atlas``)."""
    mat = bpy.data.materials.new(spec["name"])
    mat.use_nodes = True
    nodes = mat.node_tree.nodes
    bsdf = nodes.get("Principled BSDF")
    colour = [*spec["color"], 1.0]
    bsdf.inputs["Base Color"].default_value = colour
    bsdf.inputs["Metallic"].default_value = float(spec["metallic"])
    bsdf.inputs["Roughness"].default_value = float(spec["roughness"])
    bsdf.inputs["Specular IOR Level"].default_value = float(spec.get("specular", 0.5))
    if atlas is not None:
        tex = nodes.new("ShaderNodeTexImage")
        tex.image = atlas
        # The printed cells have sharp edges: no filtering across them.
        tex.interpolation = "Closest"
        mat.node_tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def _atlas(bpy: Any, path: Path) -> Any:
    """The markers' printed squares, one grey PNG (0 black, 255 white)."""
    img = bpy.data.images.load(str(path))
    img.colorspace_settings.name = "Non-Color"
    return img


def _device(bpy: Any, wanted: str) -> str:
    """'GPU' when asked for or when ``auto`` finds one Cycles can use, else 'CPU'."""
    if wanted == "cpu":
        return "CPU"
    prefs = bpy.context.preferences.addons["cycles"].preferences
    for kind in ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL"):
        try:
            prefs.compute_device_type = kind
        except TypeError:
            continue
        prefs.get_devices()
        gpus = [d for d in prefs.devices if d.type != "CPU"]
        if gpus:
            for d in prefs.devices:
                d.use = d.type != "CPU"
            return "GPU"
    if wanted == "gpu":
        raise RuntimeError("no GPU that Cycles can use")
    return "CPU"


def build(bpy: Any, np: Any, job: dict[str, Any], arrays: Any, folder: Path) -> Any:
    """The scene of ``job`` (its files in ``folder``) in Blender; returns the scene."""
    # The start-up file's cube, light and camera go; its add-ons (Cycles) stay.
    for ob in list(bpy.data.objects):
        bpy.data.objects.remove(ob)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    q = job["quality"]
    cyc = scene.cycles
    cyc.device = _device(bpy, job["device"])
    cyc.samples = int(q["samples"])
    cyc.use_adaptive_sampling = True
    cyc.adaptive_threshold = float(q["adaptive_threshold"])
    cyc.use_denoising = bool(q["denoise"])
    if q["denoise"]:
        cyc.denoiser = "OPENIMAGEDENOISE"
        cyc.denoising_input_passes = "RGB_ALBEDO_NORMAL"
    cyc.max_bounces = int(q["bounces"])
    cyc.caustics_reflective = False
    cyc.caustics_refractive = False
    cyc.seed = int(job["seed"])
    if job["threads"]:
        scene.render.threads_mode = "FIXED"
        scene.render.threads = int(job["threads"])
    scene.render.film_transparent = False
    scene.view_settings.view_transform = "Standard"

    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    bg = world.node_tree.nodes.get("Background")
    bg.inputs["Color"].default_value = [*job["environment"]["color"], 1.0]
    bg.inputs["Strength"].default_value = float(job["environment"]["strength"])
    scene.world = world

    atlas = _atlas(bpy, folder / job["atlas"]) if job.get("atlas") else None
    materials = [_material(bpy, m) for m in job["materials"]]
    paper = _material(bpy, job["paper"], atlas) if atlas is not None else None
    meshes = [
        _mesh(bpy, np, f"mesh{k}", arrays[f"v{k}"], arrays[f"f{k}"]) for k in range(job["meshes"])
    ]
    for mesh in meshes:
        # One slot on the shared mesh; each object fills it with its own material.
        mesh.materials.append(materials[0])
    for k, obj in enumerate(job["objects"]):
        ob = bpy.data.objects.new(f"obj{k}", meshes[obj["mesh"]])
        ob.matrix_world = _matrix(obj["world_T"])
        ob.material_slots[0].link = "OBJECT"
        ob.material_slots[0].material = materials[obj["material"]]
        scene.collection.objects.link(ob)
    if atlas is not None and paper is not None:
        quads = arrays["marker_quads"]  # (M, 4, 3) world, TL TR BR BL seen from the front
        n = len(quads)
        faces = np.arange(4 * n, dtype=np.int32).reshape(n, 4)
        # Blender's polygons wind counter-clockwise seen from their front: TL BL BR TR.
        faces = faces[:, [0, 3, 2, 1]]
        mesh = _mesh(bpy, np, "markers", quads.reshape(-1, 3), faces, arrays["marker_uv"])
        ob = bpy.data.objects.new("markers", mesh)
        ob.data.materials.append(paper)
        scene.collection.objects.link(ob)
    for k, light in enumerate(job["lights"]):
        data = bpy.data.lights.new(f"light{k}", type="AREA")
        data.shape = "RECTANGLE"
        data.size, data.size_y = light["size"]
        data.energy = float(light["power"])
        ob = bpy.data.objects.new(f"light{k}", data)
        ob.matrix_world = _matrix(light["world_T"])
        scene.collection.objects.link(ob)
    return scene


def _matrix(rows: list[float]) -> Any:
    from mathutils import Matrix  # bpy's own module, there only once bpy is imported

    return Matrix([rows[0:4], rows[4:8], rows[8:12], rows[12:16]])


def render_camera(bpy: Any, np: Any, scene: Any, cam: dict[str, Any], out_dir: Path) -> None:
    """Render one camera of the job into ``cam['out']`` (float32 (H, W, 3) linear RGB)."""
    data = bpy.data.cameras.new(cam["name"])
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = cam["width"] * cam["pixel_pitch_mm"]
    data.lens = cam["f"] * cam["pixel_pitch_mm"]
    data.clip_start, data.clip_end = 0.01, 20.0
    if cam.get("dof"):
        data.dof.use_dof = True
        data.dof.focus_distance = float(cam["dof"]["focus"])
        data.dof.aperture_fstop = float(cam["dof"]["fstop"])
    ob = bpy.data.objects.new(cam["name"], data)
    ob.matrix_world = _matrix(cam["world_T"])
    scene.collection.objects.link(ob)
    scene.camera = ob
    scene.render.resolution_x, scene.render.resolution_y = cam["width"], cam["height"]
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    exr = out_dir / f".{cam['name']}.exr"
    scene.render.filepath = str(exr)

    def stats(text: Any, *_: Any) -> None:
        # Cycles' status line ends "... | Sample 5/16" while it samples.
        tail = str(text).rsplit("Sample ", 1)
        if len(tail) == 2 and "/" in tail[1]:
            done, _sep, total = tail[1].split()[0].partition("/")
            print(f"PROGRESS {cam['name']} {done} {total}", flush=True)

    bpy.app.handlers.render_stats.append(stats)
    try:
        bpy.ops.render.render(write_still=True)
    finally:
        bpy.app.handlers.render_stats.remove(stats)
    img = bpy.data.images.load(str(exr))
    px = np.empty(img.size[0] * img.size[1] * img.channels, np.float32)
    img.pixels.foreach_get(px)
    rgb = px.reshape(img.size[1], img.size[0], img.channels)[::-1, :, :3]
    np.save(out_dir / cam["out"], np.ascontiguousarray(rgb))
    bpy.data.images.remove(img)
    exr.unlink()
    print(f"DONE {cam['name']}", flush=True)


def main(argv: list[str]) -> int:
    # The script's folder is first on sys.path; Blender's add-ons must not find the
    # project's modules there.
    here = str(Path(__file__).resolve().parent)
    sys.path[:] = [p for p in sys.path if str(Path(p or ".").resolve()) != here]
    job_path = Path(argv[1])
    job = json.loads(job_path.read_text())
    import bpy
    import numpy as np

    arrays = dict(np.load(job_path.with_suffix(".npz")))
    scene = build(bpy, np, job, arrays, job_path.parent)
    for cam in job["cameras"]:
        render_camera(bpy, np, scene, cam, job_path.parent)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
