"""Viewport display: a geometry-nodes modifier adds to a splat mesh points, one per splat, sized by
its largest standard deviation and coloured by its DC colour through a shared material.

Loose vertices are invisible in object mode, so without this a splat object would show nothing.
Points draw as spheres in Solid mode and take the DC colour in Material Preview; the node group
is built once per file and shared, and evaluating it for 1M points is one multithreaded pass.
The modifier is viewport-only: the render engine and the exporter read the splat data directly.
"""

import bpy

from ...core import sh as shmod
from .attributes import sh_attribute
from .forms import built_datablock
from .keys import LOG_SCALE, OPACITY

GROUP_NAME = "Splatwright Display"
MATERIAL_NAME = "Splatwright Splat"
MODIFIER_NAME = "Splatwright Display"
TAG = "splatwright_display"  # custom property on the node group and material: build version
VERSION = 3  # 3: the mesh passes through; gamma by a Gamma node (POWER is 4.3+)
SRGB_GAMMA = 2.2  # display-only approximation of the sRGB -> linear curve
DISPLAY_BUDGET = 1_000_000  # splats drawn per object before the display thins itself out


def display_material():
    """The shared material: emission coloured max(0, 0.5 + C0 * DC) ^ 2.2 (display sRGB -> linear)."""
    mat = built_datablock(bpy.data.materials, MATERIAL_NAME, TAG, VERSION)
    if mat is not None:
        return mat
    mat = bpy.data.materials.new(MATERIAL_NAME)
    mat[TAG] = VERSION
    mat.diffuse_color = (0.55, 0.62, 0.75, 1.0)  # Solid mode's material colour
    tree = _material_tree(mat)
    nodes, links = tree.nodes, tree.links
    nodes.clear()
    attr = nodes.new("ShaderNodeAttribute")
    attr.attribute_type, attr.attribute_name = "GEOMETRY", sh_attribute(0)
    dc_to_rgb = _vector_math(nodes, "MULTIPLY_ADD", None, (shmod.C0,) * 3, (0.5,) * 3)
    clamp = _vector_math(nodes, "MAXIMUM", None, (0.0,) * 3)
    to_linear = nodes.new("ShaderNodeGamma")  # Vector Math has POWER only from Blender 4.3
    to_linear.inputs["Gamma"].default_value = SRGB_GAMMA
    emission = nodes.new("ShaderNodeEmission")
    out = nodes.new("ShaderNodeOutputMaterial")
    links.new(attr.outputs["Vector"], dc_to_rgb.inputs[0])
    links.new(dc_to_rgb.outputs[0], clamp.inputs[0])
    links.new(clamp.outputs[0], to_linear.inputs[0])
    links.new(to_linear.outputs[0], emission.inputs["Color"])
    links.new(emission.outputs[0], out.inputs["Surface"])
    for i, node in enumerate((attr, dc_to_rgb, clamp, to_linear, emission, out)):
        node.location = (200 * i, 0)
    return mat


def _material_tree(mat):
    if bpy.app.version < (5, 0, 0):
        mat.use_nodes = True
    return mat.node_tree


def _vector_math(nodes, operation, *values):
    node = nodes.new("ShaderNodeVectorMath")
    node.operation = operation
    for socket, value in zip(node.inputs, values):
        if value is not None:
            socket.default_value = value
    return node


def _math(nodes, links, operation, a, b=None):
    """A float Math node on sockets or constants a, b; returns its output socket."""
    node = nodes.new("ShaderNodeMath")
    node.operation = operation
    for socket, value in zip(node.inputs, (a, b)):
        if isinstance(value, bpy.types.NodeSocket):
            links.new(value, socket)
        elif value is not None:
            socket.default_value = value
    return node.outputs[0]


def _named(nodes, data_type, name):
    node = nodes.new("GeometryNodeInputNamedAttribute")
    node.data_type = data_type
    node.inputs["Name"].default_value = name
    return node.outputs["Attribute"]


def _socket(tree, name, in_out, socket_type, default=None, minimum=None, maximum=None, description=""):
    sock = tree.interface.new_socket(name, in_out=in_out, socket_type=socket_type, description=description)
    for attr, value in (("default_value", default), ("min_value", minimum), ("max_value", maximum)):
        if value is not None:
            setattr(sock, attr, value)
    return sock


def display_group():
    """The shared node group: Mesh to Points with radius exp(max log scale) * Radius Scale, keeping
    splats at least Min Opacity opaque and a random Display Ratio of them."""
    group = built_datablock(bpy.data.node_groups, GROUP_NAME, TAG, VERSION)
    if group is not None:
        return group
    group = bpy.data.node_groups.new(GROUP_NAME, "GeometryNodeTree")
    group[TAG] = VERSION
    _socket(group, "Geometry", "INPUT", "NodeSocketGeometry")
    _socket(
        group,
        "Radius Scale",
        "INPUT",
        "NodeSocketFloat",
        1.0,
        0.0,
        None,
        "Point radius in standard deviations of each splat's longest axis",
    )
    _socket(group, "Min Opacity", "INPUT", "NodeSocketFloat", 0.05, 0.0, 1.0, "Hide splats fainter than this")
    _socket(
        group,
        "Display Ratio",
        "INPUT",
        "NodeSocketFloat",
        1.0,
        0.0,
        1.0,
        "Fraction of splats drawn (lower it for very large clouds)",
    )
    _socket(group, "Geometry", "OUTPUT", "NodeSocketGeometry")
    nodes, links = group.nodes, group.links
    gin, gout = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")
    to_points = nodes.new("GeometryNodeMeshToPoints")
    links.new(gin.outputs["Geometry"], to_points.inputs["Mesh"])
    links.new(_kept(nodes, links, gin), to_points.inputs["Selection"])
    links.new(_radius(nodes, links, gin), to_points.inputs["Radius"])
    set_mat = nodes.new("GeometryNodeSetMaterial")
    set_mat.inputs["Material"].default_value = display_material()
    links.new(to_points.outputs["Points"], set_mat.inputs["Geometry"])
    # The splat mesh passes through beside the points (its loose vertices draw nothing in Object Mode):
    # the evaluated mesh is what export and rendering read, modifiers and edit-mode changes included.
    join = nodes.new("GeometryNodeJoinGeometry")
    links.new(set_mat.outputs["Geometry"], join.inputs["Geometry"])
    links.new(gin.outputs["Geometry"], join.inputs["Geometry"])
    links.new(join.outputs["Geometry"], gout.inputs["Geometry"])
    for node, x in ((gin, -400), (to_points, 400), (set_mat, 600), (join, 800), (gout, 1000)):
        node.location = (x, 0)
    return group


def _radius(nodes, links, gin):
    """exp(max(log_scale)) * Radius Scale."""
    split = nodes.new("ShaderNodeSeparateXYZ")
    links.new(_named(nodes, "FLOAT_VECTOR", LOG_SCALE), split.inputs[0])
    largest = _math(
        nodes, links, "MAXIMUM", _math(nodes, links, "MAXIMUM", split.outputs[0], split.outputs[1]), split.outputs[2]
    )
    return _math(nodes, links, "MULTIPLY", _math(nodes, links, "EXPONENT", largest), gin.outputs["Radius Scale"])


def _kept(nodes, links, gin):
    """sigmoid(opacity logit) > Min Opacity, and a random draw below Display Ratio."""
    negated = _math(nodes, links, "MULTIPLY", _named(nodes, "FLOAT", OPACITY), -1.0)
    denominator = _math(nodes, links, "ADD", _math(nodes, links, "EXPONENT", negated), 1.0)
    opacity = _math(nodes, links, "DIVIDE", 1.0, denominator)
    opaque = _math(nodes, links, "GREATER_THAN", opacity, gin.outputs["Min Opacity"])
    rand = nodes.new("FunctionNodeRandomValue")
    rand.data_type = "BOOLEAN"
    links.new(gin.outputs["Display Ratio"], rand.inputs["Probability"])
    keep = nodes.new("FunctionNodeBooleanMath")
    keep.operation = "AND"
    links.new(opaque, keep.inputs[0])
    links.new(next(o for o in rand.outputs if o.type == "BOOLEAN"), keep.inputs[1])
    return keep.outputs[0]


def add_display(obj, display_ratio=1.0):
    """Give a splat mesh the display modifier (once); returns the modifier. Native splat point clouds
    need none (Blender draws them): None."""
    if obj.type != "MESH":
        return None
    mod = obj.modifiers.get(MODIFIER_NAME)
    if mod is None:
        mod = obj.modifiers.new(MODIFIER_NAME, "NODES")
    mod.node_group = display_group()
    mod.show_render = False
    set_input(mod, "Display Ratio", float(display_ratio))
    return mod


def input_property(mod, name):
    """(owner, property name) of the display modifier's input `name`, for layout.prop(): a struct's
    `value` from Blender 5.2, the modifier's ID property before (see set_input)."""
    identifier = next(
        item.identifier
        for item in mod.node_group.interface.items_tree
        if getattr(item, "name", None) == name and item.in_out == "INPUT"
    )
    if "properties" in mod.bl_rna.properties:
        return getattr(mod.properties.inputs, identifier), "value"
    return mod, f'["{identifier}"]'


def set_input(mod, name, value):
    """Set one of the display modifier's inputs by its name. Up to Blender 5.1 the values are ID
    properties of the modifier; from 5.2 each is a struct under `properties.inputs` with a `value`."""
    identifier = next(
        item.identifier
        for item in mod.node_group.interface.items_tree
        if getattr(item, "name", None) == name and item.in_out == "INPUT"
    )
    if "properties" in mod.bl_rna.properties:
        getattr(mod.properties.inputs, identifier).value = value
    else:
        mod[identifier] = value
    mod.id_data.update_tag()
