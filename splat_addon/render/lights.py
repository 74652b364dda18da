"""The scene's lights as the core's relighting sees them (core.lights.Light), read from the depsgraph
the engine renders: every visible point, spot, sun and area light, instances included, in the
engine's frame (world space shifted by -origin, see engine.py), with Cycles' reading of each
setting (intern/cycles/blender/light.cpp): strength = colour x temperature colour x power x
2^exposure; a light whose Normalize is off emits its power per unit of its own area; area sizes
follow the object's scale; the light points along its object's -Z, an area's width along +X; its
object's Diffuse and Glossy ray visibility say whether it lights diffuse and glossy reflection."""

import math
import warnings

import bpy
import numpy as np

from ..data import RelightWarning, instancer_of
from .scene import world_background

KINDS = {"POINT": "point", "SPOT": "spot", "SUN": "sun", "AREA": "area"}


def scene_lights(depsgraph, origin, links=None):
    """A core.lights.Light for every light object (and instance of one) the depsgraph renders, in
    world space shifted by -`origin`; lights of zero power are left out. `links`, a list if given,
    receives each one's light and shadow linking (linking_of: receivers, blockers), in the same
    order."""
    found = []
    for inst in depsgraph.object_instances:  # instance data is only valid during iteration
        obj = inst.object
        if obj.type != "LIGHT":
            continue
        light = light_from_blender(obj.data, np.array(inst.matrix_world, dtype=np.float64), origin, obj)
        if light is not None:
            found.append(light)
            if links is not None:
                links.append(tuple(linking_of(_linking_owner(inst, kind), kind) for kind in ("receiver", "blocker")))
    return found


def _linking_owner(inst, kind):
    """The object whose light linking of `kind` ("receiver" or "blocker") a light instance follows,
    as Cycles reads it: its instancer's where that one sets a collection of that kind, else its own."""
    parent = instancer_of(inst)
    if getattr(getattr(parent, "light_linking", None), f"{kind}_collection", None) is not None:
        return parent
    return inst.object.original


def linking_of(light_object, kind):
    """The light linking ("receiver") or shadow linking ("blocker") of a light object: None when it
    takes in every object, else (included, excluded) sets of object names from its collection of
    that kind (objects set there, and every object of a child collection set there), read as Blender
    reads them: only included objects when any is included, every object but the excluded ones when
    none is, included minus excluded with both."""
    linking = getattr(light_object, "light_linking", None)
    collection = getattr(linking, f"{kind}_collection", None)
    if collection is None:
        return None
    included, excluded = set(), set()
    # Each entry's state sits beside the collection's own list, in its order (the entries hold no
    # pointer to their object or child collection).
    for obj, entry in zip(collection.objects, collection.collection_objects, strict=True):
        (excluded if entry.light_linking.link_state == "EXCLUDE" else included).add(obj.name)
    for child, entry in zip(collection.children, collection.collection_children, strict=True):
        names = {obj.name for obj in child.all_objects}
        (excluded if entry.light_linking.link_state == "EXCLUDE" else included).update(names)
    return included, excluded


def blocker_collections(depsgraph):
    """[(collection name, linking_of's rule)] of every distinct blocker collection of the lights the
    depsgraph renders: where the relit splats' stand-in must be set for Cycles (relit.StandIn)."""
    found = {}
    for inst in depsgraph.object_instances:  # instance data is only valid during iteration
        if inst.object.type == "LIGHT":
            owner = _linking_owner(inst, "blocker")
            collection = getattr(getattr(owner, "light_linking", None), "blocker_collection", None)
            if collection is not None and collection.name not in found:
                found[collection.name] = linking_of(owner, "blocker")
    return list(found.items())


def takes_in(link, names):
    """Whether linking `link` (linking_of's) takes in the object known by `names` (scene.linking_names:
    its own name, and its instancer's for an instance): whether a light lights it, or it shadows the
    light. An instance is taken in where either name is included, left out where either is excluded,
    as Cycles renders a collection instance whose instancer or object is listed."""
    if link is None:
        return True
    included, excluded = link
    return (not included or not included.isdisjoint(names)) and excluded.isdisjoint(names)


def scene_world(scene, backdrop=None):
    """The world as a uniform environment (core.lights.World) of the world's background colour
    (scene.world_color), occluded by the splats and meshes from the scene's World Occlusion
    directions (0: not). A RelightWarning where nodes drive the background (an environment map):
    the colour then stands in for them, and the render says how. backdrop: world_background(scene)
    when the caller has read it (the viewport's backdrop: an environment image read once)."""
    from ...core.lights import World

    background = world_background(scene) if backdrop is None else backdrop
    if background.note is not None:
        warnings.warn(background.note, RelightWarning, stacklevel=2)
    occlusion = int(getattr(scene, WORLD_OCCLUSION, 0))
    return World(background.color, occlusion, background.environment, background.sun)


def light_from_blender(light, matrix, origin=(0.0, 0.0, 0.0), obj=None):
    """core.lights.Light of Blender light datablock `light` placed by world `matrix` (4,4), in the frame
    shifted by -`origin` (`obj`, its object, see light_fields); None for a light that gives no light
    (zero power or colour)."""
    from ...core.lights import Light

    fields = light_fields(light, matrix, origin, obj)
    if fields is None:
        return None
    return Light(**fields)


def light_fields(light, matrix, origin=(0.0, 0.0, 0.0), obj=None):
    """The keyword arguments of core.lights.Light for `light` at `matrix` (see light_from_blender), or
    None for a light that gives no light; kept apart so tests can compare them with plain numbers.
    With the light's object `obj`, its Ray Visibility's Diffuse and Glossy too, which Cycles reads as
    the light's part in diffuse and glossy reflection (a light with Glossy off makes no highlights;
    Blender's Diffuse and Specular factors are EEVEE's alone, and Cycles leaves them out). A
    RelightWarning for shader nodes that light_nodes does not read."""
    kind = KINDS.get(light.type)
    if kind is None:
        return None
    matrix = np.asarray(matrix, dtype=np.float64)
    color = np.array(light.color[:3], dtype=np.float64)
    if getattr(light, "use_temperature", False):  # 5.0+: a blackbody tint on top of the colour
        color = color * np.array(light.temperature_color[:3], dtype=np.float64)
    factor, note = light_nodes(light)
    if note is not None:  # nodes it cannot read: the engine reports it
        warnings.warn(note, RelightWarning, stacklevel=2)
    color = color * factor
    power = float(light.energy) * 2.0 ** float(getattr(light, "exposure", 0.0))
    if power <= 0.0 or not color.any():
        return None
    axes = matrix[:3, :3]
    fields = {
        "kind": kind,
        "color": color,
        "position": matrix[:3, 3] - np.asarray(origin, dtype=np.float64),
        "direction": _unit(-axes[:, 2]),
        "cast_shadow": bool(light.use_shadow),
    }
    if obj is not None:
        fields["diffuse"] = float(getattr(obj, "visible_diffuse", True))
        fields["specular"] = float(getattr(obj, "visible_glossy", True))
    if kind == "sun":
        fields["angle"] = float(light.angle)
    elif kind == "area":
        fields.update(_area_fields(light, axes))
    else:
        fields["radius"] = float(light.shadow_soft_size)
    if kind == "spot":
        fields["spot_size"] = float(light.spot_size)
        fields["spot_blend"] = float(light.spot_blend)
    if not getattr(light, "normalize", True):
        power *= emitter_area(fields)
    fields["power"] = power
    return fields


def light_nodes(light):
    """((3,) factor, note or None): what a light's shader nodes multiply its colour by, as Cycles
    reads them (measured: an Emission Strength of 2 doubles the light, its Color tints it): the
    Emission node feeding the Light Output, Color x Strength. Nodes that drive those inputs (an IES
    texture, say) or another shader are not read: the factor is then 1, and the note names them.
    Blender before 5.0 reads the nodes only with Use Nodes on."""
    tree = light.node_tree
    if tree is None or (bpy.app.version < (5, 0, 0) and not light.use_nodes):  # 5.0+: always read (deprecated)
        return np.ones(3), None
    output = next((n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputLight" and n.is_active_output), None)
    if output is None or not output.inputs["Surface"].is_linked:
        return np.ones(3), None
    shader = output.inputs["Surface"].links[0].from_node
    inputs = [shader.inputs[name] for name in ("Color", "Strength")] if shader.bl_idname == "ShaderNodeEmission" else []
    driven = [socket.links[0].from_node.name for socket in inputs if socket.is_linked]
    if not inputs or driven:
        return np.ones(3), (
            f"light '{light.name}': its node '{driven[0] if driven else shader.name}' is not read by relighting, "
            "which lights the splats by the light's own colour and power"
        )
    return np.array(inputs[0].default_value[:3], dtype=np.float64) * float(inputs[1].default_value), None


def _area_fields(light, axes):
    """An area light's shape, its sizes in the world (the object's scale applied, as Cycles does) and
    its Spread (at least core.lights.MIN_SPREAD, as Cycles takes it)."""
    from ...core.lights import MIN_SPREAD

    shape = light.shape
    size_x = float(light.size) * float(np.linalg.norm(axes[:, 0]))
    size_y = float(light.size_y if shape in ("RECTANGLE", "ELLIPSE") else light.size) * float(
        np.linalg.norm(axes[:, 1])
    )
    spread = min(max(float(getattr(light, "spread", math.pi)), MIN_SPREAD), math.pi)
    return {"shape": shape, "size_x": size_x, "size_y": size_y, "x_axis": _unit(axes[:, 0]), "spread": spread}


def emitter_area(fields):
    """The area an unnormalised light's power is per (Cycles' `area` of each kind): the rectangle
    or ellipse of an area light, the disk of a point or spot light's radius, the disk a sun's angle
    spans at unit distance; 1 where that is zero (a point light of radius 0 emits its power)."""
    kind = fields["kind"]
    if kind == "area":
        area = fields["size_x"] * fields["size_y"] * (math.pi / 4.0 if fields["shape"] in ("DISK", "ELLIPSE") else 1.0)
    elif kind == "sun":
        area = math.pi * math.tan(fields["angle"] / 2.0) ** 2
    else:
        area = math.pi * fields["radius"] ** 2
    return area if area > 0.0 else 1.0


def _unit(v):
    norm = float(np.linalg.norm(v))
    return v / norm if norm > 0.0 else np.array([0.0, 0.0, -1.0])


# the per-object switch ----------------------------------------------------------------------------

RELIGHT = "splatwright_relight"  # Object property: shade the object with the scene's lights
WORLD_OCCLUSION = "splatwright_world_occlusion"  # Scene property: directions of the world's occlusion


def is_relit(obj):
    """Whether splat object `obj` (original) asks to be shaded with the scene's lights."""
    return bool(getattr(obj, RELIGHT, False))


def register():
    setattr(
        bpy.types.Object,
        RELIGHT,
        bpy.props.BoolProperty(
            name="Relight",
            default=False,
            description="Shade the splats with the scene's lights and world (needs a material: albedo and "
            "normals); off keeps the baked or captured look",
        ),
    )
    setattr(
        bpy.types.Scene,
        WORLD_OCCLUSION,
        bpy.props.IntProperty(
            name="World Occlusion",
            default=0,
            min=0,
            soft_max=64,
            max=256,
            description="Directions from which relit splats test what of the world the splats and meshes "
            "hide (ambient occlusion; 24 give a sphere's closed-form share within 0.011 on average). Each "
            "costs about one sun shadow map per frame; 0 lights every relit splat with the whole world",
        ),
    )


def unregister():
    delattr(bpy.types.Scene, WORLD_OCCLUSION)
    delattr(bpy.types.Object, RELIGHT)
