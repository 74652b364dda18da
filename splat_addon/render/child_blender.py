"""The child Blender of a SPLATWRIGHT render (see mesh_layer.py): renders the mesh layer of a scene
snapshot with Cycles, EEVEE or Workbench into an uncompressed multilayer EXR.

Run as a script, never imported: `blender -b --python child_blender.py` (a Blender install) or
`python child_blender.py` (the bpy module). It answers one JSON request per stdin line with one
line starting with REPLY, and ends when stdin closes:

    {"blend": snapshot.blend, "scene": name, "view_layer": name, "frame": 12, "subframe": 0.0,
     "camera": name, "engine": "CYCLES", "hide": [splat object names], "out": layer.exr,
     "autoexec": true, "environment": true, "shadow_casters": casters.npz}

With "environment", the film is transparent and the Environment pass is written too: the world
seen through each pixel, apart from the meshes. "shadow_casters" (optional) names an .npz of
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


def render(request):
    import bpy

    bpy.ops.wm.open_mainfile(filepath=request["blend"], load_ui=False, use_scripts=request.get("autoexec", False))
    scene = bpy.data.scenes[request["scene"]]
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
    image = settings.image_settings
    if hasattr(image, "media_type"):
        image.media_type = "MULTI_LAYER_IMAGE"
    image.file_format = "OPEN_EXR_MULTILAYER"
    image.color_depth = "32"
    image.exr_codec = "NONE"
    layer = scene.view_layers[request["view_layer"]]
    layer.use_pass_combined = layer.use_pass_z = True
    if request.get("environment"):
        settings.film_transparent = True
        layer.use_pass_environment = True
    bpy.ops.render.render(write_still=True, scene=scene.name, layer=layer.name)


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
