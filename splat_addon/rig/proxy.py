"""Captured splats rigged through a proxy: a mesh skinned to an armature (vertex groups and an
Armature modifier) that stands where the capture's subject stands. Each splat takes the weights of
the proxy's surface point nearest to it, the proxy's vertex-group weights blended with that point's
barycentric coordinates (core.proxy), so a splat on the surface moves as that surface point does
under linear blend skinning, and then is bound like any splat object (rigging.write_plans: vertex
groups or weight attributes, an Armature modifier or property, the posing deformer), so it exports,
animates and renders as other bound splats.

The binding fades with the distance d to the proxy's surface, so the captured floor, walls and
floaters stay where they are while the subject moves: each splat gets a binding strength, 1 up to
`falloff_start`, 0 beyond `max_distance`, a smoothstep between (core.proxy.falloff_strength). The
strength is the Armature modifier's vertex-group mask (rigging.MASK_GROUP), which Blender's viewport
and our posing both read: a splat moves to (1 - strength) rest + strength posed. Far Splats "Stay"
cuts hard at `max_distance` (strength 1 or 0), "Follow" binds every splat fully (no mask). Splats
beyond `max_distance` are reported. Every splat keeps the weights of its nearest surface point, so
painting the mask later brings it along.

The proxy is read at rest: its own mesh (modifiers not applied) in world space, as the splats are.
"""

import bpy
import numpy as np
from bpy.props import EnumProperty, FloatProperty, IntProperty, StringProperty

from ...core import proxy as core_proxy
from ...core.skinning import SkinningError
from .. import data
from ..data.errors import EXPECTED_ERRORS
from ..data.meshes import mesh_triangles
from . import armature as rigging

DEFAULT_MAX_DISTANCE = 0.1
DEFAULT_FALLOFF_START = 0.05
FAR_MODES = ("FADE", "STAY", "FOLLOW")


def proxy_rig(proxy):
    """(armature object, preserve volume) of a proxy mesh: its Armature modifier, else its armature
    parent; RiggingError naming what is missing."""
    if proxy.type != "MESH" or data.is_splat_object(proxy):
        kind = "a splat object" if data.is_splat_object(proxy) else proxy.type.lower()
        raise rigging.RiggingError(
            f"'{proxy.name}' is {kind}, not a rigged mesh: the proxy must be a mesh skinned to an armature"
        )
    if not len(proxy.data.polygons):
        raise rigging.RiggingError(f"the proxy mesh '{proxy.name}' has no faces")
    mod = next(
        (m for m in proxy.modifiers if m.type == "ARMATURE" and m.object is not None and m.object.type == "ARMATURE"),
        None,
    )
    if mod is not None:
        return mod.object, mod.use_deform_preserve_volume
    if proxy.parent is not None and proxy.parent.type == "ARMATURE":
        return proxy.parent, False
    raise rigging.RiggingError(
        f"the proxy mesh '{proxy.name}' has no armature (an Armature modifier or an armature parent)"
    )


def proxy_surface(proxy, bones):
    """World-space (V,3) vertices, (F,3) triangles and (V, B) vertex weights over `bones` of a proxy."""
    vertices, triangles = mesh_triangles(proxy.data)
    matrix = data.world_matrix(proxy)
    names, columns = rigging.group_weights(proxy, bones)
    if not names:
        raise rigging.RiggingError(f"no vertex group of the proxy '{proxy.name}' is named like a deforming bone")
    weights = np.zeros((len(vertices), len(bones)))
    for name, column in zip(names, columns):
        weights[:, bones.index(name)] = column
    return vertices @ matrix[:3, :3].T + matrix[:3, 3], triangles, weights


def falloff_range(far, falloff_start, max_distance):
    """Where the binding strength starts to fall (it reaches 0 at `max_distance`), or None when every
    splat binds fully (Far Splats: Follow); Stay, or a start at or beyond the end, cut hard there."""
    if far not in FAR_MODES:
        raise rigging.RiggingError(f"Far Splats must be one of {', '.join(FAR_MODES)}, got '{far}'")
    if falloff_start < 0.0:
        raise rigging.RiggingError(f"Falloff Start must not be negative, got {falloff_start:g}")
    if far == "FOLLOW":
        return None
    return max_distance if far == "STAY" else min(falloff_start, max_distance)


def plan_proxy_binding(
    obj,
    proxy,
    arm,
    max_distance=DEFAULT_MAX_DISTANCE,
    far="FADE",
    max_influences=rigging.DEFAULT_INFLUENCES,
    min_weight=rigging.DEFAULT_MIN_WEIGHT,
    falloff_start=DEFAULT_FALLOFF_START,
):
    """(BindPlan, far report) binding splat object `obj` through `proxy` (nothing changes)."""
    start = falloff_range(far, falloff_start, max_distance)
    bones = rigging.deform_bones(arm)
    if not bones:
        raise rigging.RiggingError(f"armature '{arm.name}' has no deforming bones")
    if data.splat_count(obj.data) == 0:
        raise rigging.RiggingError(f"'{obj.name}' has no splats to bind")
    vertices, triangles, vertex_weights = proxy_surface(proxy, bones)
    matrix = data.world_matrix(obj)
    centres = data.object_cloud(obj).positions.astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
    if not np.isfinite(centres).all():
        raise rigging.RiggingError(f"'{obj.name}': splat centres are NaN or infinite in world space")
    closest = core_proxy.closest_points(centres, vertices, triangles)
    dense = core_proxy.surface_weights(closest, triangles, vertex_weights)
    strength = None if start is None else core_proxy.falloff_strength(closest.distance, start, max_distance)
    plan = rigging.plan_from_weights(obj, bones, dense, f"proxy '{proxy.name}'", max_influences, min_weight)
    plan.strength = strength
    partial = 0 if strength is None else int(((strength > 0) & (strength < 1)).sum())
    report = {
        "far": int((closest.distance > max_distance).sum()),
        "max_distance": max_distance,
        "falloff_start": start,
        "partial": partial,
        "far_kept_still": start is not None,
        "farthest": float(closest.distance.max()),
        "mean_distance": float(closest.distance.mean()),
    }
    return plan, report


def bind_proxy(
    objects,
    proxy,
    max_distance=DEFAULT_MAX_DISTANCE,
    far="FADE",
    max_influences=rigging.DEFAULT_INFLUENCES,
    min_weight=rigging.DEFAULT_MIN_WEIGHT,
    falloff_start=DEFAULT_FALLOFF_START,
):
    """Bind the splat objects among `objects` to the armature of `proxy` through its surface; returns
    [(BindPlan, far report)]. Every binding is computed before anything changes."""
    arm, preserve_volume = proxy_rig(proxy)
    targets = [o for o in objects if o not in (proxy, arm) and data.is_splat_object(o)]
    if not targets:
        listed = ", ".join(f"'{o.name}' ({o.type.lower()})" for o in objects if o not in (proxy, arm))
        raise rigging.RiggingError("no splat objects to bind" + (f"; {listed} are not splat objects" if listed else ""))
    if max_influences < 1:
        raise rigging.RiggingError(f"max_influences must be at least 1, got {max_influences}")
    results = [
        plan_proxy_binding(o, proxy, arm, max_distance, far, max_influences, min_weight, falloff_start) for o in targets
    ]
    rigging.write_plans([plan for plan, _ in results], arm, preserve_volume)
    return results


class SPLAT_OT_bind_proxy(bpy.types.Operator):
    """Bind the selected splat objects (a capture) to the armature of a rigged proxy mesh (the active
    object unless named): each splat takes the weights of the proxy's surface point nearest to it"""

    bl_idname = "splat.bind_proxy"
    bl_label = "Bind Splats Through Proxy"
    bl_options = {"REGISTER", "UNDO"}

    proxy: StringProperty(
        name="Proxy", default="", description="Mesh skinned to an armature (empty: the active object)"
    )
    falloff_start: FloatProperty(
        name="Falloff Start",
        default=DEFAULT_FALLOFF_START,
        min=0.0,
        unit="LENGTH",
        description="Splats nearer than this to the proxy's surface follow it fully; "
        "farther ones fade (smoothstep) until Max Distance (at or beyond "
        "it: a hard cut there)",
    )
    max_distance: FloatProperty(
        name="Max Distance",
        default=DEFAULT_MAX_DISTANCE,
        min=0.0,
        unit="LENGTH",
        description="Splats farther than this from the proxy's surface are reported "
        "and, unless Far Splats follow, stay still",
    )
    far: EnumProperty(
        name="Far Splats",
        default="FADE",
        items=(
            (
                "FADE",
                "Fade",
                "Binding strength fades from 1 at Falloff Start to 0 at Max Distance: the "
                "Armature modifier's mask group " + rigging.MASK_GROUP,
            ),
            ("STAY", "Stay", "Splats beyond Max Distance stay still, nearer ones follow fully (a hard cut)"),
            ("FOLLOW", "Follow", "Every splat follows its nearest surface point fully, however far"),
        ),
    )
    max_influences: IntProperty(name="Max Influences", default=rigging.DEFAULT_INFLUENCES, min=1, max=32)
    min_weight: FloatProperty(
        name="Min Weight",
        default=rigging.DEFAULT_MIN_WEIGHT,
        min=0.0,
        max=0.5,
        description="Drop bones below this share of a splat's weight",
    )

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT"

    def execute(self, context):
        try:
            proxy = bpy.data.objects.get(self.proxy) if self.proxy else context.view_layer.objects.active
            if proxy is None:
                raise rigging.RiggingError(
                    f"no object named '{self.proxy}'"
                    if self.proxy
                    else "no proxy: make the rigged mesh the active object, or name it"
                )
            results = bind_proxy(
                context.selected_objects,
                proxy,
                self.max_distance,
                self.far,
                self.max_influences,
                self.min_weight,
                self.falloff_start,
            )
        except (rigging.RiggingError, core_proxy.ProxyError, SkinningError, *EXPECTED_ERRORS) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for plan, far in results:
            r = plan.report
            still = "kept still" if far["far_kept_still"] else "bound all the same"
            fading = f", {far['partial']} of them partly (fading with distance)" if far["partial"] else ""
            self.report(
                {"INFO"},
                f"'{plan.obj.name}': {r['splats'] - r['unbound']} of {r['splats']} splats bound "
                f"through '{proxy.name}', up to {r['max_influences']} bones each{fading}",
            )
            if far["far"]:
                self.report(
                    {"WARNING"},
                    f"'{plan.obj.name}': {far['far']} splats are farther than "
                    f"{far['max_distance']:g} from the proxy (farthest {far['farthest']:.3g}), "
                    f"{still}",
                )
        return {"FINISHED"}


CLASSES = (SPLAT_OT_bind_proxy,)
