"""Operators on whole splat objects that Blender's own would get wrong: Apply Splat Transform, Join
Splats (orientations, sizes and SH turn with the centres) and Convert Splat Form (mesh <-> native)."""

import bpy
import numpy as np
from bpy.props import EnumProperty

from ...core import SplatCloud
from .. import data
from ..data.display import DISPLAY_BUDGET, add_display
from ..data.errors import EXPECTED_ERRORS
from ..rig import armature as rigging


class SPLAT_OT_apply_transform(bpy.types.Operator):
    """Bake the whole object transform into the splats (centres, orientations, sizes and SH), leaving
    an identity transform; use this instead of Apply > Rotation/Scale, which moves centres only"""

    bl_idname = "splat.apply_transform"
    bl_label = "Apply Splat Transform"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT" and data.is_splat_object(context.active_object)

    def execute(self, context):
        targets = [o for o in context.selected_objects if data.is_splat_object(o)] or [context.active_object]
        shared = [o.name for o in targets if o.data.users > 1]
        if shared:
            self.report({"ERROR"}, f"splat data shared by several objects: {', '.join(shared)}")
            return {"CANCELLED"}
        try:
            baked = [data.object_to_cloud(o, np.array(o.matrix_basis, dtype=np.float64)) for o in targets]
        except EXPECTED_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for obj, cloud in zip(targets, baked):
            data.update_splats(obj, cloud)
            obj.matrix_basis.identity()
            data.remember_frame(obj)
        return {"FINISHED"}


class SPLAT_OT_join(bpy.types.Operator):
    """Join the selected splat objects into the active one, turning each one's splats (orientations,
    sizes and SH too) into the active object's space; Blender's own Join moves centres only"""

    bl_idname = "splat.join"
    bl_label = "Join Splats"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT" and data.is_splat_object(context.active_object)

    def execute(self, context):
        target = context.active_object
        others = [o for o in context.selected_objects if o is not target]
        problem = _join_problem(target, others)
        if problem:
            self.report({"ERROR"}, problem)
            return {"CANCELLED"}
        to_target = np.linalg.inv(np.array(target.matrix_world, dtype=np.float64))
        try:
            # Read everything before changing anything, so an error leaves the scene as it was; the
            # target too, or Join would fill its missing attributes with made-up defaults.
            own = data.object_cloud(target)
            moved = [data.object_to_cloud(o, to_target @ np.array(o.matrix_world, dtype=np.float64)) for o in others]
        except EXPECTED_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if all(data.splat_form(o) == data.MESH_FORM for o in (target, *others)):
            return self._join_meshes(context, target, others, moved)
        return self._join_clouds(context, target, others, [own, *moved])

    def _join_meshes(self, context, target, others, moved):
        """Blender's own Join, after each splat object is turned into the target's space: vertex
        groups and materials join as Blender joins them."""
        for obj, cloud in zip(others, moved):
            data.update_splats(obj, cloud)
            obj.matrix_world = target.matrix_world
            data.remember_frame(obj)
        with context.temp_override(
            active_object=target, selected_editable_objects=[target, *others], selected_objects=[target, *others]
        ):
            done = bpy.ops.object.join()
        if done != {"FINISHED"}:
            self.report({"ERROR"}, f"Blender's Join did not join the splat objects into '{target.name}'")
        return done

    def _join_clouds(self, context, target, others, clouds):
        """Native splats (Blender joins no point clouds): the target gets new data, in its own form,
        holding every cloud; the others are removed."""
        try:
            joined = SplatCloud.concatenate(clouds)
            made, skipped = data.new_splat_object(
                joined, target.name, context.scene.collection, form=data.splat_form(target)
            )
        except EXPECTED_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        old = target.data
        data.stamp_landing(made, data.landed_raw(target))
        target.data = made.data
        bpy.data.objects.remove(made)
        data.remove_geometry(old)
        for obj in others:
            data.remove_splat_object(obj)
        if skipped:
            self.report({"WARNING"}, f"extras not kept: {', '.join(skipped)}")
        return {"FINISHED"}


def _join_problem(target, others):
    """Why `others` cannot be joined into the splat object `target`, or None."""
    wrong = [o.name for o in others if not data.is_splat_object(o)]
    if wrong:
        return f"not splat objects: {', '.join(wrong)}"
    shared = [o.name for o in others if o.data.users > 1 or o.data is target.data]
    if shared:
        return f"splat data shared by several objects: {', '.join(shared)}"
    if not others:
        return "select the splat objects to join into the active one"
    if not any(data.splat_count(o.data) for o in others):  # Blender's Join would cancel
        return f"nothing to join: the selected splat objects hold no splats ({', '.join(o.name for o in others)})"
    antialiased = data.made_antialiased(target.data)
    other_mode = [o.name for o in others if data.made_antialiased(o.data) != antialiased]
    if other_mode:
        return (
            f"{', '.join(other_mode)}: made for {'classic' if antialiased else 'antialiased'} rendering, "
            f"'{target.name}' for {'antialiased' if antialiased else 'classic'}; one object renders one way"
        )
    matrix = np.array(target.matrix_world, dtype=np.float64)
    if not np.isfinite(matrix).all():
        return f"'{target.name}' has a transform holding NaN or Inf: splats cannot be joined into it"
    if np.linalg.det(matrix[:3, :3]) == 0:
        return f"'{target.name}' has a zero scale: splats cannot be joined into it"
    return None


def convert_form(context, obj, form):
    """Replace splat object `obj` by one of the other form (data.MESH_FORM or data.NATIVE_FORM) holding
    the same splats, name, transform, parent, collections and armature binding; returns the new
    object. Modifiers other than Splatwright's own are not carried over (a warning names them)."""
    cloud = data.object_cloud(obj)
    rig = rigging.rig_of(obj)
    bones = rigging.weight_names(obj)
    weights = rigging.group_weights(obj, bones)[1].T if rig is not None else None
    name, collections = obj.name, list(obj.users_collection)
    made, skipped = data.new_splat_object(cloud, name + ".converting", collections[0], form=form)
    try:
        for collection in collections[1:]:
            collection.objects.link(made)
        made.parent, made.matrix_parent_inverse = obj.parent, obj.matrix_parent_inverse.copy()
        made.matrix_world = obj.matrix_world.copy()
        data.stamp_landing(made, data.landed_raw(obj))
        data.remember_frame(made)
        if form == data.MESH_FORM:
            add_display(made, min(1.0, DISPLAY_BUDGET / max(len(cloud), 1)))
        if rig is not None:
            rigging.write_weights(made, bones, weights)
            rigging.attach(made, rig[0], rig[1])
    except BaseException:
        data.remove_splat_object(made)
        raise
    dropped = [m.name for m in obj.modifiers if m.name not in data.OWN_MODIFIERS and m.type != "ARMATURE"]
    selected, active = obj.select_get(), context.view_layer.objects.active == obj
    data.remove_splat_object(obj)
    made.name = name
    made.select_set(selected)
    if active:
        context.view_layer.objects.active = made
    return made, skipped, dropped


class SPLAT_OT_convert_form(bpy.types.Operator):
    """Turn splat objects into Blender's own Gaussian-splat point clouds (drawn by Blender 5.3's viewport,
    EEVEE and Cycles) or into Splatwright's splat meshes, keeping their splats, transform and binding"""

    bl_idname = "splat.convert_form"
    bl_label = "Convert Splat Form"
    bl_options = {"REGISTER", "UNDO"}

    form: EnumProperty(
        name="Form",
        default="NATIVE",
        items=(
            ("NATIVE", "Point Cloud (Blender's Gaussian splats)", "Blender 5.3's own splat point clouds"),
            ("MESH", "Splat Mesh", "Splatwright's mesh form, drawn by its display modifier"),
        ),
    )

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT"

    def execute(self, context):
        targets = [o for o in context.selected_objects if data.is_splat_object(o) and data.splat_form(o) != self.form]
        if not targets:
            self.report({"ERROR"}, f"no selected splat objects to convert to the {self.form.lower()} form")
            return {"CANCELLED"}
        shared = [o.name for o in targets if o.data.users > 1]
        if shared:
            self.report({"ERROR"}, f"splat data shared by several objects: {', '.join(shared)}")
            return {"CANCELLED"}
        try:
            for obj in targets:  # every object readable before any is replaced
                data.object_cloud(obj)
        except EXPECTED_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if self.form == data.NATIVE_FORM and not data.native_supported():
            self.report(
                {"ERROR"},
                f"Blender {bpy.app.version_string} cannot make point clouds from Python (Blender 4.5 and later can)",
            )
            return {"CANCELLED"}
        for obj in targets:
            try:
                made, skipped, dropped = convert_form(context, obj, self.form)
            except EXPECTED_ERRORS as exc:
                self.report({"ERROR"}, str(exc))
                return {"CANCELLED"}
            if skipped:
                self.report({"WARNING"}, f"'{made.name}': extras not kept: {', '.join(skipped)}")
            if dropped:
                self.report({"WARNING"}, f"'{made.name}': modifiers not carried over: {', '.join(dropped)}")
        return {"FINISHED"}


def menu_apply(self, context):
    self.layout.operator(SPLAT_OT_apply_transform.bl_idname)


def menu_join(self, context):
    if data.is_splat_object(context.active_object):
        self.layout.operator(SPLAT_OT_join.bl_idname)
        self.layout.operator_menu_enum(SPLAT_OT_convert_form.bl_idname, "form")


CLASSES = (SPLAT_OT_apply_transform, SPLAT_OT_join, SPLAT_OT_convert_form)
MENUS = ((bpy.types.VIEW3D_MT_object_apply, menu_apply), (bpy.types.VIEW3D_MT_object, menu_join))
