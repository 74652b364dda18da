"""Captured splats rigged through a proxy: a mesh skinned to an armature (vertex groups and an
Armature modifier) that stands where the capture's subject stands. Each splat takes the weights of
the proxy's surface point nearest to it, the proxy's vertex-group weights blended with that point's
barycentric coordinates (core.proxy), so a splat on the surface moves as that surface point does
under linear blend skinning, and then is bound like any splat object (rigging.write_plans: vertex
groups or weight attributes, an Armature modifier or property, the posing deformer), so it exports,
animates and renders as other bound splats.

Splats farther from the surface than `max_distance` (the captured floor, walls, floaters) are
reported, and by default left unbound: they stay where they are while the subject moves. Weights are
normalised per splat (as Blender's Armature modifier does), so there is no partial influence to fade
by distance: the cut at `max_distance` is hard.

The proxy is read at rest: its own mesh (modifiers not applied) in world space, as the splats are.
"""

import bpy
import numpy as np
from bpy.props import EnumProperty, FloatProperty, IntProperty, StringProperty

from ..core import proxy as core_proxy
from ..core.skinning import SkinningError
from . import data, rigging
from .cleanup import mesh_triangles
from .operators import EXPECTED_ERRORS

DEFAULT_MAX_DISTANCE = 0.1


def proxy_rig(proxy):
    """(armature object, preserve volume) of a proxy mesh: its Armature modifier, else its armature
    parent; RiggingError naming what is missing."""
    if proxy.type != "MESH" or data.is_splat_object(proxy):
        kind = "a splat object" if data.is_splat_object(proxy) else proxy.type.lower()
        raise rigging.RiggingError(f"'{proxy.name}' is {kind}, not a rigged mesh: the proxy must be a mesh "
                                   "skinned to an armature")
    if not len(proxy.data.polygons):
        raise rigging.RiggingError(f"the proxy mesh '{proxy.name}' has no faces")
    mod = next((m for m in proxy.modifiers if m.type == "ARMATURE" and m.object is not None
                and m.object.type == "ARMATURE"), None)
    if mod is not None:
        return mod.object, mod.use_deform_preserve_volume
    if proxy.parent is not None and proxy.parent.type == "ARMATURE":
        return proxy.parent, False
    raise rigging.RiggingError(f"the proxy mesh '{proxy.name}' has no armature (an Armature modifier or an "
                               "armature parent)")


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


def plan_proxy_binding(obj, proxy, arm, max_distance=DEFAULT_MAX_DISTANCE, far="STAY",
                       max_influences=rigging.DEFAULT_INFLUENCES, min_weight=rigging.DEFAULT_MIN_WEIGHT):
    """(BindPlan, far report) binding splat object `obj` through `proxy` (nothing changes)."""
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
    is_far = closest.distance > max_distance
    if far == "STAY":
        dense[is_far] = 0.0
    plan = rigging.plan_from_weights(obj, bones, dense, f"proxy '{proxy.name}'", max_influences, min_weight)
    report = {"far": int(is_far.sum()), "max_distance": max_distance, "far_kept_still": far == "STAY",
              "farthest": float(closest.distance.max()), "mean_distance": float(closest.distance.mean())}
    return plan, report


def bind_proxy(objects, proxy, max_distance=DEFAULT_MAX_DISTANCE, far="STAY",
               max_influences=rigging.DEFAULT_INFLUENCES, min_weight=rigging.DEFAULT_MIN_WEIGHT):
    """Bind the splat objects among `objects` to the armature of `proxy` through its surface; returns
    [(BindPlan, far report)]. Every binding is computed before anything changes."""
    arm, preserve_volume = proxy_rig(proxy)
    targets = [o for o in objects if o not in (proxy, arm) and data.is_splat_object(o)]
    if not targets:
        listed = ", ".join(f"'{o.name}' ({o.type.lower()})" for o in objects if o not in (proxy, arm))
        raise rigging.RiggingError("no splat objects to bind" + (f"; {listed} are not splat objects" if listed else ""))
    if max_influences < 1:
        raise rigging.RiggingError(f"max_influences must be at least 1, got {max_influences}")
    results = [plan_proxy_binding(o, proxy, arm, max_distance, far, max_influences, min_weight) for o in targets]
    rigging.write_plans([plan for plan, _ in results], arm, preserve_volume)
    return results


class SPLAT_OT_bind_proxy(bpy.types.Operator):
    """Bind the selected splat objects (a capture) to the armature of a rigged proxy mesh (the active
    object unless named): each splat takes the weights of the proxy's surface point nearest to it"""

    bl_idname = "splat.bind_proxy"
    bl_label = "Bind Splats Through Proxy"
    bl_options = {"REGISTER", "UNDO"}

    proxy: StringProperty(name="Proxy", default="",
                          description="Mesh skinned to an armature (empty: the active object)")
    max_distance: FloatProperty(name="Max Distance", default=DEFAULT_MAX_DISTANCE, min=0.0, unit="LENGTH",
                                description="Splats farther than this from the proxy's surface are reported "
                                            "(and, unless Far Splats follow, stay unbound)")
    far: EnumProperty(name="Far Splats", default="STAY", items=(
        ("STAY", "Stay", "Leave splats far from the proxy unbound: they stay still (background, floaters)"),
        ("FOLLOW", "Follow", "Bind them to their nearest surface point all the same")))
    max_influences: IntProperty(name="Max Influences", default=rigging.DEFAULT_INFLUENCES, min=1, max=32)
    min_weight: FloatProperty(name="Min Weight", default=rigging.DEFAULT_MIN_WEIGHT, min=0.0, max=0.5,
                              description="Drop bones below this share of a splat's weight")

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT"

    def execute(self, context):
        try:
            proxy = bpy.data.objects.get(self.proxy) if self.proxy else context.view_layer.objects.active
            if proxy is None:
                raise rigging.RiggingError(f"no object named '{self.proxy}'" if self.proxy else
                                           "no proxy: make the rigged mesh the active object, or name it")
            results = bind_proxy(context.selected_objects, proxy, self.max_distance, self.far,
                                 self.max_influences, self.min_weight)
        except (rigging.RiggingError, core_proxy.ProxyError, SkinningError, *EXPECTED_ERRORS) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for plan, far in results:
            r = plan.report
            still = "left unbound" if far["far_kept_still"] else "bound all the same"
            self.report({"INFO"}, f"'{plan.obj.name}': {r['splats'] - r['unbound']} of {r['splats']} splats bound "
                                  f"through '{proxy.name}', up to {r['max_influences']} bones each")
            if far["far"]:
                self.report({"WARNING"}, f"'{plan.obj.name}': {far['far']} splats are farther than "
                                         f"{far['max_distance']:g} from the proxy (farthest {far['farthest']:.3g}), "
                                         f"{still}")
        return {"FINISHED"}


CLASSES = (SPLAT_OT_bind_proxy,)
