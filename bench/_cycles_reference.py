"""The benches' independent reference: Blender Cycles (headless bpy, CPU) rendering a core Mesh from
core Cameras in a subprocess, as core.mesh shades it: emission materials (unlit: the 'Standard' view
transform gives sRGB-encoded emission) or lit ones, image textures, colours per corner (a Color
Attribute multiplying the material's colour) and alpha cut-outs (MASK, BLEND), over a black world.
bench/mesh2splats.py, bench/bake.py and bench/relight_accuracy.py (with its own lit scene) use it.

    python bench/_cycles_reference.py --cycles SPEC.npz   (what cycles_render runs)
"""

import math
import subprocess
import sys
import time

import numpy as np

from splatwright.core.camera import opengl_camera_to_world
from splatwright.core.mesh import Material

CYCLES_SAMPLES = 64


def cycles_render(mesh, cameras, folder, samples=CYCLES_SAMPLES, lit=False, script=None, **extra):
    """Render the mesh with Blender Cycles from every camera in one subprocess; returns ([display
    sRGB images], seconds). Unlit (emission) unless `lit`: then see _lit_scene (`lit="diffuse"`:
    Diffuse BSDF materials, no specular, in the same lights). `script`: another bench's file run as
    the subprocess instead (it calls _cycles_main with its own lit scene), `extra` saved in the spec
    for it."""
    from PIL import Image

    spec = folder / "cycles_spec.npz"
    textures, materials = [], mesh.materials or [Material()]
    for k, material in enumerate(materials):
        path = ""
        if material.texture is not None:
            path = str(folder / f"cycles_tex_{k}.png")
            texture = material.texture
            if texture.dtype != np.uint8:
                texture = (np.clip(texture, 0, 1) * 255 + 0.5).astype(np.uint8)
            keep_alpha = material.alpha_mode != "OPAQUE" and texture.ndim == 3 and texture.shape[2] == 4
            Image.fromarray(texture if keep_alpha or texture.ndim == 2 else texture[..., :3]).save(path)
        textures.append(path)
    uvs = mesh.corner_uvs if mesh.corner_uvs is not None else np.zeros((len(mesh.faces), 3, 2))
    fm = mesh.face_materials if mesh.face_materials is not None else np.zeros(len(mesh.faces), int)
    corners = mesh.corner_colors
    if corners is not None and corners.ndim == 2:  # per vertex: every corner takes its vertex's
        corners = corners[mesh.faces]
    np.savez(
        spec,
        vertices=mesh.vertices,
        faces=mesh.faces,
        uvs=uvs,
        face_materials=fm,
        corner_colors=np.zeros((0, 3, 3)) if corners is None else corners,
        base_colors=np.array([m.base_color[:3] for m in materials]),
        alpha_modes=np.array([m.alpha_mode for m in materials]),
        alpha_cutoffs=np.array([m.alpha_cutoff for m in materials]),
        textures=np.array(textures),
        camera_to_world=np.array([opengl_camera_to_world(c.world_to_camera) for c in cameras]),
        fov=np.array([c.fov_x_deg for c in cameras]),
        width=cameras[0].width,
        height=cameras[0].height,
        samples=samples,
        lit=lit,
        out=str(folder / "cycles_"),
        **extra,
    )
    start = time.perf_counter()
    subprocess.run(
        [sys.executable, script or __file__, "--cycles", str(spec)],
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    seconds = time.perf_counter() - start
    images = []
    for i in range(len(cameras)):
        rgba = np.asarray(Image.open(folder / f"cycles_{i}.png").convert("RGBA"), np.float64) / 255.0
        images.append(rgba[..., :3] * rgba[..., 3:])  # over black (unlit: alpha is 1)
    return images, seconds


def _cycles_main(spec_path, lit_scene=None):
    """Runs inside the subprocess: build the scene in bpy and render it from every camera; a lit
    scene is set up by `lit_scene(scene, obj, world)` (default _lit_scene)."""
    import bpy
    import mathutils

    d = np.load(spec_path)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    mesh = bpy.data.meshes.new("mesh")
    mesh.from_pydata(d["vertices"].tolist(), [], d["faces"].tolist())
    mesh.uv_layers.new(name="UVMap").data.foreach_set("uv", d["uvs"].reshape(-1).astype(np.float32))
    mesh.polygons.foreach_set("material_index", d["face_materials"].astype(np.int32))
    corners = d["corner_colors"] if "corner_colors" in d else np.zeros((0, 3, 3))
    if len(corners):  # colours per corner multiply the material's, as core.mesh shades them
        rgba = np.concatenate([corners, np.ones(corners.shape[:2] + (1,))], axis=2)
        layer = mesh.color_attributes.new("Col", "FLOAT_COLOR", "CORNER")
        layer.data.foreach_set("color", rgba.reshape(-1).astype(np.float32))
    modes = d["alpha_modes"] if "alpha_modes" in d else ["OPAQUE"] * len(d["textures"])
    cutoffs = d["alpha_cutoffs"] if "alpha_cutoffs" in d else [0.5] * len(d["textures"])
    for base, texture, mode, cutoff in zip(d["base_colors"], d["textures"], modes, cutoffs):
        material = bpy.data.materials.new("m")
        material.use_nodes = True
        nodes, links = material.node_tree.nodes, material.node_tree.links
        nodes.clear()
        if str(d["lit"]) == "diffuse":
            shader = nodes.new("ShaderNodeBsdfDiffuse")
            colour_input = shader.inputs["Color"]
        elif d["lit"]:
            shader = nodes.new("ShaderNodeBsdfPrincipled")
            colour_input = shader.inputs["Base Color"]
        else:
            shader = nodes.new("ShaderNodeEmission")
            shader.inputs["Strength"].default_value = 1.0
            colour_input = shader.inputs["Color"]
        colour_input.default_value = (*base, 1.0)  # scene-linear, as Kd
        if str(texture):
            image = nodes.new("ShaderNodeTexImage")
            image.image = bpy.data.images.load(str(texture))
            image.image.colorspace_settings.name = "sRGB"
            image.interpolation = "Linear"
            links.new(image.outputs["Color"], colour_input)
        if len(corners):
            _multiply_by_corner_colours(nodes, links, colour_input)
        surface = shader.outputs[0]
        if str(texture) and str(mode) != "OPAQUE":
            image.image.alpha_mode = "CHANNEL_PACKED"  # colours as stored, alpha beside them
            surface = _cut_out(nodes, links, image.outputs["Alpha"], surface, str(mode), float(cutoff))
        links.new(surface, nodes.new("ShaderNodeOutputMaterial").inputs["Surface"])
        mesh.materials.append(material)
    obj = bpy.data.objects.new("mesh", mesh)
    scene.collection.objects.link(obj)
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0, 0, 0, 1)
    scene.world = world
    cam_data = bpy.data.cameras.new("camera")
    cam_data.sensor_fit = "HORIZONTAL"
    cam = bpy.data.objects.new("camera", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    render_settings = scene.render
    render_settings.engine = "CYCLES"
    render_settings.resolution_x, render_settings.resolution_y = int(d["width"]), int(d["height"])
    render_settings.resolution_percentage = 100
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(d["samples"])
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 0
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.display_settings.display_device = "sRGB"
    render_settings.image_settings.file_format = "PNG"
    render_settings.image_settings.color_mode = "RGB"
    render_settings.image_settings.color_depth = "8"
    if d["lit"]:
        (lit_scene or _lit_scene)(scene, obj, world)
    for i, (matrix, fov) in enumerate(zip(d["camera_to_world"], d["fov"])):
        cam_data.angle = math.radians(float(fov))
        distance = float(np.linalg.norm(matrix[:3, 3] - np.asarray(obj.location)))
        cam_data.clip_start = max(1e-4, 1e-3 * distance)
        cam_data.clip_end = 1e4 * distance
        cam.matrix_world = mathutils.Matrix(matrix.tolist())
        render_settings.filepath = f"{d['out']}{i}.png"
        bpy.ops.render.render(write_still=True)


def _cut_out(nodes, links, alpha, surface, mode, cutoff):
    """`surface` mixed with a Transparent BSDF by the texture's `alpha`: by alpha >= cutoff for MASK
    (glTF's rule, as core.mesh cuts), by alpha itself for BLEND."""
    if mode == "MASK":
        compare = nodes.new("ShaderNodeMath")
        compare.operation = "GREATER_THAN"
        compare.inputs[1].default_value = cutoff - 1e-6
        links.new(alpha, compare.inputs[0])
        alpha = compare.outputs[0]
    mix = nodes.new("ShaderNodeMixShader")
    links.new(alpha, mix.inputs[0])
    links.new(nodes.new("ShaderNodeBsdfTransparent").outputs[0], mix.inputs[1])
    links.new(surface, mix.inputs[2])
    return mix.outputs[0]


def _multiply_by_corner_colours(nodes, links, colour_input):
    """Feed `colour_input` what fed it (a texture, else its own value) times the "Col" attribute."""
    mix = nodes.new("ShaderNodeMix")
    mix.data_type, mix.blend_type = "RGBA", "MULTIPLY"
    mix.inputs["Factor"].default_value = 1.0
    if colour_input.is_linked:
        links.new(colour_input.links[0].from_socket, mix.inputs[6])
    else:
        mix.inputs[6].default_value = colour_input.default_value
    attribute = nodes.new("ShaderNodeAttribute")
    attribute.attribute_name = "Col"
    links.new(attribute.outputs["Color"], mix.inputs[7])
    links.new(mix.outputs[2], colour_input)


def _lit_scene(scene, obj, world):
    """The lit variant: Principled BSDF materials (Blender's defaults: speculars), a sun and a large
    area light beside the mesh, a dim grey world for ambient light and two diffuse/glossy bounces,
    the world transparent to the camera (so images come over black, as splats render), denoised."""
    import bpy
    import mathutils

    co = np.array([v.co[:] for v in obj.data.vertices])
    centre = (co.min(axis=0) + co.max(axis=0)) / 2
    size = max(float(np.abs(co - centre).max()), 1e-3)
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.08, 0.08, 0.1, 1)
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 2.5
    sun.rotation_euler = (math.radians(40), math.radians(-25), math.radians(30))
    area = bpy.data.objects.new("area", bpy.data.lights.new("area", "AREA"))
    area.data.energy = 60.0 * size * size
    area.data.size = 1.5 * size
    area.location = tuple(centre + size * np.array([3, -2.5, 2]))
    area.rotation_euler = mathutils.Vector((-3, 2.5, -2)).to_track_quat("-Z", "Y").to_euler()
    for light in (sun, area):
        scene.collection.objects.link(light)
    scene.cycles.max_bounces = 2
    scene.cycles.use_denoising = True
    scene.render.film_transparent = True
    scene.render.image_settings.color_mode = "RGBA"


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--cycles":
        _cycles_main(sys.argv[2])
