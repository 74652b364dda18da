"""The child Blender of a SPLATWRIGHT render (see mesh_layer.py): renders the mesh layer of a scene
snapshot with Cycles, EEVEE or Workbench into an uncompressed multilayer EXR.

Run as a script, never imported: `blender -b --python child_blender.py` (a Blender install) or
`python child_blender.py` (the bpy module). It answers one JSON request per stdin line with one
line starting with REPLY, and ends when stdin closes:

    {"blend": snapshot.blend, "scene": name, "view_layer": name, "frame": 12, "subframe": 0.0,
     "camera": name, "engine": "CYCLES", "hide": [splat object names], "out": layer.exr,
     "autoexec": true, "environment": true, "shadow_casters": casters.npz}

With "environment", the film is transparent and the Environment pass is written too: the world
seen through each pixel, apart from the meshes. Without "out", no mesh layer is rendered.

"world" (optional) renders the world named "world_name" alone, with Cycles, in a scene of its own
at the request's frame (world_panorama.py reads what it writes); "blend" may hold that world alone:

    {"discs": [Sky Texture node names whose sun disc is on], "samples": 16,
     "panorama": {"size": [128, 64], "out": world.exr, "lit": lit.exr, "lit_samples": 256},
     "view": {"size": 96, "fov": radians, "rotation": 3 x 3 camera to world, "on": on.exr}}

A panorama is equirectangular as an Environment Texture lays out its image, into "out" with the
discs off and into "lit" with them on ("lit_samples" samples a pixel), each where given; a view is a
square perspective picture with the discs on. "reuse": true keeps the file the last request opened
(the world scene it made included) instead of opening it.

"shadow_casters" (optional) names an .npz of
"vertices" (V,3) and "faces" (F,3), world space, and "groups" (F,) each face's part: the relit
splats' stand-in mesh (core/shadow_casters.py), added visible to shadow rays only, so the meshes get
the splats' shadows, one object per part. "caster_links" (with it) lists [blocker collection name,
[state per part]]: each part is linked into the lights' blocker collections with that state
("INCLUDE", "EXCLUDE"; null: not linked), so shadow linking holds for it as for its splat objects.
"""

import json
import sys
import time
import traceback

REPLY = "@splatwright-mesh-layer "
CASTERS = "Splatwright Shadow Casters"


WORLD = "Splatwright World"  # the scene (and camera) the world is rendered alone in
# An equirectangular camera at the origin with this rotation (XYZ Euler) writes the world in an
# Environment Texture's layout: u = 0.5 looks along +X, 0.25 along +Y, the bottom row down.
PANORAMA_EULER = (1.5707963267948966, 0.0, -1.5707963267948966)


def render(request):
    import bpy

    if not request.get("reuse"):
        bpy.ops.wm.open_mainfile(filepath=request["blend"], load_ui=False, use_scripts=request.get("autoexec", False))
    if request.get("out"):
        render_layer(bpy, bpy.data.scenes[request["scene"]], request)
    if request.get("world"):
        world = bpy.data.worlds[request["world_name"]]
        render_world(bpy, world, request["world"], (request["frame"], request["subframe"]))


def render_layer(bpy, scene, request):
    """The mesh layer of `scene` as the request asks (see the module notes)."""
    for name in request["hide"]:
        obj = bpy.data.objects.get(name)
        if obj is not None:
            obj.hide_render = True
    scene.frame_set(request["frame"], subframe=request["subframe"])
    if request.get("shadow_casters"):
        add_shadow_casters(bpy, scene, request["shadow_casters"], request.get("caster_links", []))
    if request.get("camera"):
        scene.camera = bpy.data.objects[request["camera"]]
    settings = scene.render
    settings.engine = request["engine"]
    settings.use_border = False
    settings.use_compositing = False  # the render layer itself, not what the compositor makes of it
    settings.use_sequencer = False
    settings.filepath = request["out"]
    exr_output(settings, multilayer=True)
    layer = scene.view_layers[request["view_layer"]]
    layer.use_pass_combined = layer.use_pass_z = True
    if request.get("environment"):
        settings.film_transparent = True
        layer.use_pass_environment = True
    bpy.ops.render.render(write_still=True, scene=scene.name, layer=layer.name)


def exr_output(settings, multilayer):
    """Uncompressed 32-bit EXR output (io/exr_plain.py reads it): multilayer, or the Combined pass
    alone."""
    image = settings.image_settings
    if hasattr(image, "media_type"):
        image.media_type = "MULTI_LAYER_IMAGE" if multilayer else "IMAGE"
    image.file_format = "OPEN_EXR_MULTILAYER" if multilayer else "OPEN_EXR"
    image.color_depth = "32"
    image.exr_codec = "NONE"


def render_world(bpy, world, ask, frame):
    """`world` alone at `frame` (frame, subframe), as `ask` says (see the module notes)."""
    from mathutils import Matrix

    view = bpy.data.scenes.get(WORLD) or world_scene(bpy, world)
    view.frame_set(frame[0], subframe=frame[1])
    tree = view.world.node_tree
    discs = [tree.nodes[name] for name in ask.get("discs", ()) if name in tree.nodes]
    camera = view.camera
    view.cycles.samples = ask["samples"]
    if "panorama" in ask:
        pano = ask["panorama"]
        camera.data.type = "PANO"
        camera.data.panorama_type = "EQUIRECTANGULAR"
        camera.matrix_world = Matrix.Identity(4)
        camera.rotation_euler = PANORAMA_EULER
        if discs and pano.get("lit"):
            view.cycles.samples = pano["lit_samples"]
            shoot(bpy, view, pano["size"], pano["lit"], discs, True)
            view.cycles.samples = ask["samples"]
        if pano.get("out"):
            shoot(bpy, view, pano["size"], pano["out"], discs, False)
    if "view" in ask:
        close = ask["view"]
        camera.data.type = "PERSP"
        camera.data.sensor_fit = "AUTO"
        camera.data.angle = close["fov"]
        camera.data.shift_x = camera.data.shift_y = 0.0
        camera.matrix_world = Matrix(close["rotation"]).to_4x4()
        shoot(bpy, view, (close["size"], close["size"]), close["on"], discs, True)


def world_scene(bpy, world):
    """A scene holding `world` and a camera and nothing else, set to render with Cycles: the world
    seen by camera rays, each pixel the mean over its own area (a box filter) of all its samples (no
    adaptive sampling: a small sun is not passed over), no denoising, one seed."""
    view = bpy.data.scenes.new(WORLD)
    view.world = world
    visibility = getattr(world, "cycles_visibility", None)
    if visibility is not None:
        visibility.camera = True
    settings = view.render
    settings.engine = "CYCLES"
    settings.film_transparent = False
    settings.use_compositing = settings.use_sequencer = False
    settings.resolution_percentage = 100
    settings.pixel_aspect_x = settings.pixel_aspect_y = 1.0
    exr_output(settings, multilayer=False)
    view.cycles.use_denoising = False
    view.cycles.use_adaptive_sampling = False
    view.cycles.pixel_filter_type = "BOX"
    view.cycles.filter_width = 1.0
    view.cycles.seed = 0
    camera = bpy.data.objects.new(WORLD, bpy.data.cameras.new(WORLD))
    view.collection.objects.link(camera)
    view.camera = camera
    return view


def shoot(bpy, view, size, path, discs, on):
    """Render `view` at `size` (width, height) into `path` with the sun `discs` on or off."""
    for node in discs:
        node.sun_disc = on
    view.render.resolution_x, view.render.resolution_y = size
    view.render.filepath = path
    bpy.ops.render.render(write_still=True, scene=view.name)


def add_shadow_casters(bpy, scene, path, links=()):
    """The stand-in mesh in `path` as objects of `scene` (one per part) that only shadow rays see,
    each linked into the blocker collections `links` names with its state there."""
    import numpy as np

    with np.load(path) as arrays:
        vertices, faces = arrays["vertices"].astype(np.float32), arrays["faces"].astype(np.int32)
        groups = arrays["groups"] if "groups" in arrays else np.zeros(len(faces), np.int32)
    parts = [_caster_object(bpy, scene, vertices, faces[groups == g]) for g in range(int(groups.max()) + 1)]
    for name, states in links:
        collection = bpy.data.collections.get(name)
        for obj, state in zip(parts, states, strict=True):
            if collection is None or obj is None or state is None:
                continue
            collection.objects.link(obj)
            # an entry's state sits beside the collection's objects, in their order (no name lookup)
            entry = collection.collection_objects[list(collection.objects).index(obj)]
            entry.light_linking.link_state = state


def _caster_object(bpy, scene, vertices, faces):
    """One part of the stand-in: the `faces` of `vertices` as an object only shadow rays see (None
    without faces)."""
    import numpy as np

    if not len(faces):
        return None
    used, faces = np.unique(faces, return_inverse=True)
    vertices, faces = vertices[used], faces.reshape(-1, 3).astype(np.int32)
    mesh = bpy.data.meshes.new(CASTERS)
    mesh.vertices.add(len(vertices))
    mesh.vertices.foreach_set("co", vertices.ravel())
    mesh.loops.add(faces.size)
    mesh.loops.foreach_set("vertex_index", faces.ravel())
    mesh.polygons.add(len(faces))
    mesh.polygons.foreach_set("loop_start", np.arange(0, faces.size, 3, dtype=np.int32))
    mesh.update()
    obj = bpy.data.objects.new(CASTERS, mesh)
    scene.collection.objects.link(obj)
    for ray in ("camera", "diffuse", "glossy", "transmission", "volume_scatter"):
        setattr(obj, f"visible_{ray}", False)
    obj.visible_shadow = True
    return obj


def main():
    for line in sys.stdin:
        if not line.strip():
            continue
        start = time.perf_counter()
        try:
            render(json.loads(line))
            reply = {"ok": True, "seconds": time.perf_counter() - start}
        except Exception as exc:
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
        print(REPLY + json.dumps(reply), flush=True)


if __name__ == "__main__":
    main()
