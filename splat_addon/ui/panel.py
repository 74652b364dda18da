"""The Splats panel, in Object Properties and in the 3D view's sidebar (N) under 'Splats': what a
splat object holds and costs, its display settings and the operators that work on it.

The numbers come from splat_stats(), which reads attribute names and counts only (never the
splats), so drawing stays cheap for any size; the file sizes are each writer's own layout
(io.file_sizes) for the export defaults in the preferences.
"""

import json
from typing import NamedTuple

import bpy

from ...core import material
from ...core.economy import describe_change
from ...core.memory import human_bytes
from ...core.splats import memory_bytes
from ...io import file_sizes
from .. import data
from ..data import display
from ..edit import cleanup
from ..render.lights import RELIGHT
from . import preferences

DISPLAY_INPUTS = ("Radius Scale", "Min Opacity", "Display Ratio")
# format -> (label, how the number relates to the file)
SIZE_LABELS = {
    "ply": ("PLY", ""),
    "spz": ("SPZ", "at most (before compression)"),
    "splat": (".splat", ""),
    "usd": ("OpenUSD", "arrays (crate file about 1.4 kB more)"),
}


class SplatStats(NamedTuple):
    count: int
    sh_degree: int
    memory: int  # bytes of one copy of the splats' float32 fields
    sizes: dict  # format -> bytes (see io.file_sizes)
    spz_version: int
    half: bool


def splat_stats(obj, spz_version=None, half=None, context=None):
    """What the panel shows for splat object `obj`: its own splats (modifiers aside), with file sizes
    for `spz_version` and `half` (default: the preferences')."""
    prefs = preferences.current(context)
    spz_version = int(prefs.spz_version) if spz_version is None else int(spz_version)
    half = bool(prefs.use_half) if half is None else bool(half)
    count, degree = data.splat_count(obj.data), data.sh_degree(obj)
    return SplatStats(
        count, degree, memory_bytes(count, degree), file_sizes(count, degree, spz_version, half), spz_version, half
    )


def draw_stats(box, obj, stats):
    col = box.column(align=True)
    form = "Blender point cloud" if data.splat_form(obj) == data.NATIVE_FORM else "splat mesh"
    col.label(text=f"{stats.count:,} splats, SH degree {stats.sh_degree} ({form})")
    if data.made_antialiased(obj.data):
        col.label(text="Made for antialiased rendering")
    col.label(text=f"Memory: {human_bytes(stats.memory)}")
    col.label(text="File size:")
    for fmt, size in stats.sizes.items():
        label, note = SIZE_LABELS[fmt]
        if fmt == "spz":
            label = f"SPZ v{stats.spz_version}"
        elif fmt == "usd" and stats.half:
            label = "OpenUSD (half)"
        col.label(text=f"    {label}: {human_bytes(size)}" + (f"  {note}" if note else ""))


def draw_operators(col):
    col.operator("splat.export_file", text="Export Selected", icon="EXPORT").selected_only = True
    col.operator("splat.export_animation", text="Export Animation", icon="RENDER_ANIMATION").selected_only = True
    col.operator("splat.apply_transform", icon="OBJECT_ORIGIN")
    col.operator("splat.join", icon="SELECT_EXTEND")
    col.operator_menu_enum("splat.convert_form", "form", icon="OUTLINER_OB_POINTCLOUD")
    col.operator("splat.bind_armature", icon="ARMATURE_DATA")
    col.operator("splat.bind_proxy", icon="MOD_MESHDEFORM")
    col.operator("splat.check_collisions", icon="MOD_PHYSICS")


def draw_cleanup(box, obj):
    """The clean-up and grading settings the object carries (applied on export and render), the last
    change's report, and the operators that set them."""
    col = box.column(align=True)
    settings = cleanup.settings_of(obj)
    col.label(text="Clean-up: " + (", ".join(sorted(settings)) if settings else "none"))
    report = obj.get(cleanup.REPORT)
    if report:
        col.label(text="Last: " + describe_change(json.loads(report)))
    for idname, icon in (
        ("splat.crop", "MOD_BOOLEAN"),
        ("splat.prune", "TRASH"),
        ("splat.grade", "COLOR"),
        ("splat.reduce_sh", "SPHERE"),
        ("splat.clear_cleanup", "LOOP_BACK"),
    ):
        col.operator(idname, icon=icon)


ESTIMATE_NORMALS = "splat.estimate_normals"


def material_status(obj):
    """{key: bool} of the material extras (core.material.KEYS' names: albedo, normals, roughness,
    metallic) splat object `obj` stores, read from attribute names only."""
    names = {a.name for a in obj.data.attributes}

    def stored(key):
        base = data.EXTRA_PREFIX + key
        return base in names or f"{base}.0" in names

    return {
        "albedo": stored(material.ALBEDO),
        "normals": all(stored(k) for k in material.NORMALS),
        "roughness": stored(material.ROUGHNESS),
        "metallic": stored(material.METALLIC),
    }


def draw_material(box, obj):
    """What the object carries for relighting, its Relight switch and Estimate Normals."""
    status = material_status(obj)
    col = box.column(align=True)
    col.label(text="Material")
    col.label(text=f"    Albedo: {'yes' if status['albedo'] else 'none'}")
    col.label(text=f"    Normals: {'yes' if status['normals'] else 'none'}")
    col.label(text=f"    Roughness: {'own' if status['roughness'] else f'default {material.DEFAULT_ROUGHNESS:g}'}")
    col.label(text=f"    Metallic: {'own' if status['metallic'] else f'default {material.DEFAULT_METALLIC:g}'}")
    col.prop(obj, RELIGHT, text="Relight")
    if getattr(obj, RELIGHT, False) and not (status["albedo"] and status["normals"]):
        col.label(text="No albedo and normals: renders unlit", icon="ERROR")
    col.operator(ESTIMATE_NORMALS, icon="NORMALS_FACE")


class _SplatsPanel:
    bl_label = "Splats"

    @classmethod
    def poll(cls, context):
        return data.is_splat_object(getattr(context, "object", None))

    def draw(self, context):
        layout, obj = self.layout, context.object
        try:
            stats = splat_stats(obj, context=context)
        except data.SplatObjectError as exc:
            layout.label(text=str(exc), icon="ERROR")
            return
        draw_stats(layout.box(), obj, stats)
        mod = obj.modifiers.get(display.MODIFIER_NAME) if obj.type == "MESH" else None
        if mod is not None and mod.node_group is not None:
            col = layout.column(align=True)
            col.label(text="Display")
            for name in DISPLAY_INPUTS:
                owner, prop = display.input_property(mod, name)
                col.prop(owner, prop, text=name)
        draw_cleanup(layout.box(), obj)
        draw_material(layout.box(), obj)
        draw_operators(layout.column(align=True))


class SPLAT_PT_object(_SplatsPanel, bpy.types.Panel):
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "object"


class SPLAT_PT_view3d(_SplatsPanel, bpy.types.Panel):
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "Splats"


CLASSES = (SPLAT_PT_object, SPLAT_PT_view3d)
