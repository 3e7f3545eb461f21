"""Blender side of ``scripts/render_person.py``: Cycles renders of a posed OBJ model.

Run by the driver, not by hand::

    blender -b --factory-startup -P scripts/blender_person.py -- JOB.json

JOB.json (written by the driver) holds::

    obj            path of the (cleaned) OBJ model, with its .mtl and textures beside it
    model_to_world 4x4 row-major matrix: OBJ coordinates -> world (+z up, metres)
    cameras        list of 4x4 OpenGL camera-to-world matrices (x right, y up, looking down -z),
                   which is also Blender's camera convention
    fov_deg, size  horizontal = vertical field of view and image size of the square views
    samples        Cycles samples per pixel (denoised with OpenImageDenoise when built in)
    lights         list of {"location", "size", "power"}: square area lights aimed at "target"
    target         where the lights point
    world          strength of the uniform grey environment (soft ambient fill)
    out            folder: rgba/frame_NNNNN.png (8-bit straight RGBA, transparent backdrop)
                   and depth/frame_NNNNN.exr (camera-space distance along -z, float),
                   render_info.json (Blender version, samples, denoiser)

Only ``bpy``, ``mathutils`` and the standard library: Blender's Python has no numpy.
"""

import json
import math
import os
import sys

import bpy
from mathutils import Matrix, Vector


def _job() -> dict:
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    if len(argv) != 1:
        raise SystemExit("usage: blender -b -P blender_person.py -- JOB.json")
    with open(argv[0], encoding="utf-8") as f:
        return json.load(f)


def _import_model(path: str, model_to_world: Matrix) -> None:
    # forward Y / up Z: no axis conversion, the driver's matrix does all of it.
    bpy.ops.wm.obj_import(filepath=path, forward_axis="Y", up_axis="Z")
    for obj in bpy.context.selected_objects:
        obj.matrix_world = model_to_world @ obj.matrix_world
        for slot in obj.material_slots:
            _soften(slot.material)


def _soften(material) -> None:
    """The MTL's Ks/Ns map to a glossy plastic; skin, cloth and hair read better rough."""
    if material is None or not material.use_nodes:
        return
    for node in material.node_tree.nodes:
        if node.type == "BSDF_PRINCIPLED":
            node.inputs["Roughness"].default_value = 0.65
            node.inputs["Specular"].default_value = 0.25


def _lights(job: dict) -> None:
    target = Vector(job["target"])
    for i, spec in enumerate(job["lights"]):
        data = bpy.data.lights.new(f"area_{i}", type="AREA")
        data.shape = "SQUARE"
        data.size = spec["size"]
        data.energy = spec["power"]
        light = bpy.data.objects.new(f"area_{i}", data)
        light.location = Vector(spec["location"])
        # Area lights emit along their local -z: aim it at the target.
        light.rotation_euler = (target - light.location).to_track_quat("-Z", "Y").to_euler()
        bpy.context.scene.collection.objects.link(light)
    world = bpy.data.worlds.new("studio")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.8, 0.8, 0.8, 1.0)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = job["world"]
    bpy.context.scene.world = world


def _settings(job: dict) -> dict:
    """Render settings; returns what the dataset's credits should say about the renderer."""
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = job["samples"]
    scene.cycles.use_adaptive_sampling = True
    denoise = "OPENIMAGEDENOISE" in {i.identifier for i in
                                     scene.cycles.bl_rna.properties["denoiser"].enum_items}
    scene.cycles.use_denoising = denoise
    if denoise:
        scene.cycles.denoiser = "OPENIMAGEDENOISE"
    print(f"blender_person: denoising {'on (OpenImageDenoise)' if denoise else 'unavailable'}")
    scene.render.resolution_x = scene.render.resolution_y = job["size"]
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    scene.render.film_transparent = True  # the backdrop is the loader's background colour
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    scene.render.image_settings.color_depth = "8"
    # "Standard": textures keep their photographed colours (Filmic would flatten them).
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.render.threads_mode = "FIXED"
    scene.render.threads = max(1, int(os.environ.get("BLENDER_THREADS", "2")))
    scene.view_layers[0].use_pass_z = True
    return {"renderer": f"Blender {bpy.app.version_string} Cycles (CPU)",
            "samples": job["samples"], "denoiser": "OpenImageDenoise" if denoise else None}


def _depth_output(out: str) -> None:
    """Compositor: the Depth pass to depth/frame_NNNNN.exr, the image to the composite."""
    scene = bpy.context.scene
    scene.use_nodes = True
    tree = scene.node_tree
    tree.nodes.clear()
    layers = tree.nodes.new("CompositorNodeRLayers")
    composite = tree.nodes.new("CompositorNodeComposite")
    composite.use_alpha = True
    tree.links.new(layers.outputs["Image"], composite.inputs["Image"])
    tree.links.new(layers.outputs["Alpha"], composite.inputs["Alpha"])
    depth = tree.nodes.new("CompositorNodeOutputFile")
    depth.base_path = os.path.join(out, "depth")
    depth.format.file_format = "OPEN_EXR"
    depth.format.color_depth = "32"
    depth.file_slots[0].path = "frame_#####"
    tree.links.new(layers.outputs["Depth"], depth.inputs[0])


def _camera(fov_deg: float):
    data = bpy.data.cameras.new("camera")
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = 36.0
    data.lens = 0.5 * data.sensor_width / math.tan(math.radians(fov_deg) / 2.0)
    data.clip_start, data.clip_end = 0.05, 100.0
    cam = bpy.data.objects.new("camera", data)
    bpy.context.scene.collection.objects.link(cam)
    bpy.context.scene.camera = cam
    return cam


def main() -> None:
    job = _job()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    info = _settings(job)
    os.makedirs(job["out"], exist_ok=True)
    with open(os.path.join(job["out"], "render_info.json"), "w", encoding="utf-8") as f:
        json.dump(info, f)
    _import_model(job["obj"], Matrix(job["model_to_world"]))
    _lights(job)
    _depth_output(job["out"])
    cam = _camera(job["fov_deg"])
    scene = bpy.context.scene
    for i, c2w in enumerate(job["cameras"]):
        cam.matrix_world = Matrix(c2w)
        scene.frame_set(i)  # numbers the depth file
        scene.render.filepath = os.path.join(job["out"], "rgba", f"frame_{i:05d}.png")
        bpy.ops.render.render(write_still=True)
        print(f"blender_person: view {i + 1}/{len(job['cameras'])}", flush=True)


if __name__ == "__main__":
    main()
