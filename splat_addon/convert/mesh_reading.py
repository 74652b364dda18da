"""Blender mesh objects read for conversion: triangles, UVs, colours, each face's material and its
Base Color (a value, an image texture or a colour attribute), and the rest pose of armature-deformed
meshes. What from_mesh.py hands to the core converter (see its notes for the rules)."""

import contextlib

import bpy
import numpy as np

from ...core.material import DEFAULT_METALLIC, DEFAULT_ROUGHNESS
from ...core.mesh import Material


class MeshConversionError(ValueError):
    """A selection or mesh that cannot be converted; the message names the object and the problem."""


# reading Blender data ------------------------------------------------------------------------------


def _foreach(collection, prop, width, dtype):
    out = np.empty(len(collection) * width, dtype=dtype)
    collection.foreach_get(prop, out)
    return out.reshape(len(collection), width) if width > 1 else out


def _linked_node(socket):
    """The node feeding `socket`, looking through reroutes; None when unlinked."""
    while socket.is_linked:
        node = socket.links[0].from_node
        if node.bl_idname != "NodeReroute":
            return node
        socket = node.inputs[0]
    return None


def _base_color_socket(tree):
    """The colour input of the shader feeding the active Material Output (Base Color or Color), or
    the first Principled BSDF's Base Color; None if there is neither."""
    outputs = [n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial"]
    output = next((n for n in outputs if n.is_active_output), outputs[0] if outputs else None)
    shader = _linked_node(output.inputs["Surface"]) if output is not None else None
    for node in ([shader] if shader is not None else []) + [
        n for n in tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled"
    ]:
        socket = node.inputs.get("Base Color") or node.inputs.get("Color")
        if socket is not None and socket.type == "RGBA":
            return socket
    return None


def _node_tree(mat):
    if bpy.app.version < (5, 0, 0) and not mat.use_nodes:
        return None
    return mat.node_tree


class Appearance:
    """One material slot as the core sees it: a core Material, the UV map its texture reads ("" for
    the active render map) and the colour attribute it multiplies by (None for none, "" for the
    render colour attribute)."""

    def __init__(self, material, uv_map=None, color_attribute=None):
        self.material, self.uv_map, self.color_attribute = material, uv_map, color_attribute


def material_appearance(mat, warn):
    """Appearance of a Blender material (None: the default grey surface), with the Principled
    BSDF's roughness and metallic for relighting (_principled_values)."""
    appearance = _colour_appearance(mat, warn)
    tree = _node_tree(mat) if mat is not None else None
    appearance.material.roughness, appearance.material.metallic = _principled_values(tree)
    return appearance


def _principled_values(tree):
    """(roughness, metallic) of the Principled BSDF feeding the active Material Output (else the
    first one in the tree): each socket's own value where nothing is linked into it, Blender's
    defaults where something is (a texture's values are not read) or there is no such node."""
    if tree is None:
        return DEFAULT_ROUGHNESS, DEFAULT_METALLIC
    outputs = [n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial"]
    output = next((n for n in outputs if n.is_active_output), outputs[0] if outputs else None)
    shader = _linked_node(output.inputs["Surface"]) if output is not None else None
    principled = [n for n in tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled"]
    node = shader if shader is not None and shader.bl_idname == "ShaderNodeBsdfPrincipled" else None
    node = node or (principled[0] if principled else None)
    if node is None:
        return DEFAULT_ROUGHNESS, DEFAULT_METALLIC

    def unlinked(name, default):
        socket = node.inputs.get(name)
        if socket is None or socket.is_linked:
            return default
        return float(min(max(socket.default_value, 0.0), 1.0))

    return unlinked("Roughness", DEFAULT_ROUGHNESS), unlinked("Metallic", DEFAULT_METALLIC)


def _colour_appearance(mat, warn):
    if mat is None:
        return Appearance(Material())
    tree = _node_tree(mat)
    socket = _base_color_socket(tree) if tree is not None else None
    if socket is None:
        return Appearance(Material(base_color=tuple(mat.diffuse_color[:3]), name=mat.name))
    base = tuple(socket.default_value[:3])
    node = _linked_node(socket)
    if node is None:
        return Appearance(Material(base_color=base, name=mat.name))
    if node.bl_idname == "ShaderNodeTexImage":
        appearance = _texture_appearance(mat, node, base, warn)
        appearance.material.alpha_mode, appearance.material.alpha_cutoff = alpha_mode(mat, socket.node, node)
        return appearance
    if node.bl_idname == "ShaderNodeVertexColor":
        return Appearance(Material(base_color=(1.0, 1.0, 1.0), name=mat.name), color_attribute=node.layer_name)
    if node.bl_idname == "ShaderNodeAttribute" and node.attribute_type == "GEOMETRY":
        return Appearance(Material(base_color=(1.0, 1.0, 1.0), name=mat.name), color_attribute=node.attribute_name)
    warn(
        f"material '{mat.name}': Base Color comes from a {node.bl_label} node, which is not converted; "
        f"using the socket's own colour"
    )
    return Appearance(Material(base_color=base, name=mat.name))


def _texture_appearance(mat, node, base, warn):
    image = node.image
    texels = image_texels(image, warn) if image is not None else None
    if texels is None:
        warn(f"material '{mat.name}': image texture '{node.name}' has no pixels; using the base colour")
        return Appearance(Material(base_color=base, name=mat.name))
    pixels, srgb = texels
    return Appearance(
        Material(base_color=base, texture=pixels, texture_srgb=srgb, name=mat.name),
        uv_map=_texture_uv_map(mat, node, warn),
    )


def alpha_mode(mat, shader, image_node):
    """(alpha_mode, alpha_cutoff) of core.mesh.Material for a shader whose colour is `image_node`'s:
    "MASK" where its Alpha input takes the image's Alpha through an alpha clip (as Blender's glTF
    importer builds one and its exporter reads them: Round, 1 - (alpha < c), 1 - (c > alpha),
    alpha > c, c < alpha), or directly on a material whose blend_method (Blender before 4.2's EEVEE)
    is CLIP; "BLEND" where it takes the Alpha directly (Cycles mixes the surface with transparency);
    else "OPAQUE"."""
    socket = shader.inputs.get("Alpha")
    if socket is None or not socket.is_linked:
        return "OPAQUE", 0.5
    node, output = socket.links[0].from_node, socket.links[0].from_socket
    if node == image_node:
        if output.name != "Alpha":
            return "OPAQUE", 0.5
        if getattr(mat, "blend_method", "") == "CLIP":
            return "MASK", float(mat.alpha_threshold)
        return "BLEND", 0.5
    cutoff = _alpha_clip(node, image_node)
    return ("MASK", cutoff) if cutoff is not None else ("OPAQUE", 0.5)


def _alpha_clip(node, image_node):
    """The cutoff of an alpha clip built of Math nodes from `image_node`'s Alpha, or None."""
    if node.bl_idname != "ShaderNodeMath":
        return None
    a, b = node.inputs[0], node.inputs[1]

    def is_alpha(socket):
        return (
            socket.is_linked and socket.links[0].from_node == image_node and socket.links[0].from_socket.name == "Alpha"
        )

    if node.operation == "ROUND" and is_alpha(a):
        return 0.5
    if node.operation == "SUBTRACT" and not a.is_linked and a.default_value == 1.0 and b.is_linked:
        inner = b.links[0].from_node
        if inner.bl_idname == "ShaderNodeMath":
            x, y = inner.inputs[0], inner.inputs[1]
            if inner.operation == "LESS_THAN" and is_alpha(x) and not y.is_linked:
                return float(y.default_value)  # 1 - (alpha < c): alpha >= c
            if inner.operation == "GREATER_THAN" and is_alpha(y) and not x.is_linked:
                return float(x.default_value)  # 1 - (c > alpha)
        return None
    if node.operation == "GREATER_THAN" and is_alpha(a) and not b.is_linked:
        return float(b.default_value)  # alpha > c
    if node.operation == "LESS_THAN" and is_alpha(b) and not a.is_linked:
        return float(a.default_value)  # c < alpha
    return None


def _texture_uv_map(mat, node, warn):
    source = _linked_node(node.inputs["Vector"])
    if source is None or (
        source.bl_idname == "ShaderNodeTexCoord" and node.inputs["Vector"].links[0].from_socket.name == "UV"
    ):
        return ""
    if source.bl_idname == "ShaderNodeUVMap":
        return source.uv_map
    warn(
        f"material '{mat.name}': texture coordinates from a {source.bl_label} node are not converted; "
        f"using the active UV map"
    )
    return ""


def image_texels(image, warn):
    """(pixels (H,W,C) float32 with row 0 at the top, sRGB-encoded?) or None for an image without
    pixels. Byte buffers hold the file's encoding, float buffers scene-linear values."""
    width, height = image.size
    if width == 0 or height == 0 or image.channels == 0:
        return None
    pixels = np.empty(width * height * image.channels, np.float32)
    image.pixels.foreach_get(pixels)
    pixels = pixels.reshape(height, width, image.channels)[::-1]  # Blender's row 0 is the bottom
    space = image.colorspace_settings
    if image.is_float or space.is_data or "linear" in space.name.lower():
        return pixels, False
    if space.name != "sRGB":
        warn(f"image '{image.name}': colour space '{space.name}' is read as sRGB")
    return pixels, True


class Triangles:
    """An evaluated mesh as loop triangles: float64 vertices (V,3), vertex indices (F,3), loop
    indices (F,3), polygon indices (F,) and material indices (F,)."""

    def __init__(self, mesh):
        mesh.calc_loop_triangles()
        tris = mesh.loop_triangles
        self.vertices = _foreach(mesh.vertices, "co", 3, np.float32).astype(np.float64)
        self.faces = _foreach(tris, "vertices", 3, np.int32)
        self.loops = _foreach(tris, "loops", 3, np.int32)
        self.polygons = _foreach(tris, "polygon_index", 1, np.int32)
        self.materials = _foreach(tris, "material_index", 1, np.int32)


def _uv_layer(mesh, name):
    if name:
        return mesh.uv_layers.get(name)
    return next((u for u in mesh.uv_layers if u.active_render), mesh.uv_layers.active)


def _drop_textures_without_uvs(mesh, looks, owner, warn):
    """A texture whose UV map is missing cannot be sampled: its material falls back to its base colour."""
    for look in looks:
        if look.uv_map is not None and _uv_layer(mesh, look.uv_map) is None:
            which = f"UV map '{look.uv_map}'" if look.uv_map else "a UV map"
            warn(
                f"'{owner}': material '{look.material.name}' has a texture but the mesh has no {which}; "
                f"using its base colour"
            )
            look.material.texture, look.uv_map = None, None


def _corner_uvs(mesh, triangles, name):
    uv = _foreach(_uv_layer(mesh, name).uv, "vector", 2, np.float32)
    return uv[triangles.loops].astype(np.float64)


def _corner_colors(mesh, triangles, name, owner):
    """(F,3,3) scene-linear colour of each triangle corner from a colour attribute."""
    attrs = mesh.color_attributes
    if name:
        attr = attrs.get(name)
    else:
        index = attrs.render_color_index
        attr = attrs[index] if 0 <= index < len(attrs) else None
    if attr is None:
        raise MeshConversionError(f"'{owner}' has no colour attribute" + (f" named '{name}'" if name else ""))
    values = _foreach(attr.data, "color", 4, np.float32)[:, :3].astype(np.float64)  # .color is linear
    index = {
        "POINT": triangles.faces,
        "CORNER": triangles.loops,
        "FACE": np.repeat(triangles.polygons[:, None], 3, axis=1),
    }.get(attr.domain)
    if index is None:
        raise MeshConversionError(f"'{owner}': colour attribute '{attr.name}' is on the {attr.domain} domain")
    return values[index]


def mesh_inputs(obj, mesh, warn):
    """(Triangles, keyword arguments of mesh_to_splats) for an evaluated mesh of `obj`."""
    triangles = Triangles(mesh)
    looks = [material_appearance(slot.material, warn) for slot in obj.material_slots] or [Appearance(Material())]
    if not obj.material_slots and len(mesh.color_attributes):
        looks = [Appearance(Material(base_color=(1.0, 1.0, 1.0)), color_attribute="")]
    _drop_textures_without_uvs(mesh, looks, obj.name, warn)
    face_looks = np.clip(triangles.materials, 0, len(looks) - 1)
    corner_uvs = _per_face(
        triangles, face_looks, looks, lambda a: a.uv_map, lambda name: _corner_uvs(mesh, triangles, name), np.zeros(2)
    )
    corner_colors = _per_face(
        triangles,
        face_looks,
        looks,
        lambda a: a.color_attribute,
        lambda name: _corner_colors(mesh, triangles, name, obj.name),
        np.ones(3),
    )
    return triangles, dict(
        corner_uvs=corner_uvs,
        face_materials=face_looks,
        materials=[a.material for a in looks],
        corner_colors=corner_colors,
        corner_normals=_corner_normals(mesh, triangles),
    )


def _corner_normals(mesh, triangles):
    """(F,3,3) the normals Blender shades each triangle's corners with (smooth or flat faces, sharp
    edges and custom normals resolved): what the material's normals interpolate."""
    normals = _foreach(mesh.corner_normals, "vector", 3, np.float32).astype(np.float64)
    return normals[triangles.loops]


def _per_face(triangles, face_looks, looks, key, read, fill):
    """(F,3,k) corner data where each face's appearance names a source (key), `fill` elsewhere;
    None when no appearance uses any. Each named source is read once."""
    names = {key(a) for a in looks if key(a) is not None}
    if not names:
        return None
    out = np.broadcast_to(fill, (len(triangles.faces), 3, len(fill))).copy()
    for name in names:
        faces = np.isin(face_looks, [i for i, a in enumerate(looks) if key(a) == name])
        out[faces] = read(name)[faces]
    return out


# converting --------------------------------------------------------------------------------------


@contextlib.contextmanager
def rest_pose(objects):
    """Put the armatures deforming `objects` in their rest position for the duration."""
    armatures = {
        mod.object.data
        for obj in objects
        for mod in obj.modifiers
        if mod.type == "ARMATURE" and mod.object is not None and mod.object.type == "ARMATURE"
    }
    posed = [arm for arm in armatures if arm.pose_position != "REST"]
    for arm in posed:
        arm.pose_position = "REST"
    try:
        yield
    finally:
        for arm in posed:
            arm.pose_position = "POSE"


def source_record(obj, evaluated_vertices, rest):
    """What the splat mesh remembers of its source: the mesh object and whether "source_vertices"
    index the original mesh's vertices (true when the evaluated mesh kept its vertex count, i.e.
    only deforming modifiers ran)."""
    return {
        "object": obj.name,
        "mesh": obj.data.name,
        "vertices": int(evaluated_vertices),
        "original_vertices": len(obj.data.vertices),
        "rest_pose": bool(rest),
    }


def read_object(obj, depsgraph, warn=print, rest=False):
    """(Triangles, mesh_to_splats appearance keywords, source record) of one mesh object as
    `depsgraph` evaluates it: NumPy copies, so nothing of Blender's is held afterwards."""
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        if len(mesh.polygons) == 0:
            raise MeshConversionError(f"'{obj.name}' has no faces to convert ({len(mesh.vertices)} vertices)")
        triangles, appearance = mesh_inputs(evaluated, mesh, warn)
        return triangles, appearance, source_record(obj, len(triangles.vertices), rest)
    finally:
        evaluated.to_mesh_clear()
