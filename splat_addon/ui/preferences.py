"""The extension's preferences (Edit > Preferences > Add-ons > Splatwright): export defaults that the
export dialogs, the animation export and the `blender -b --command splatwright export` verb start
from. An option given explicitly (in the dialog, to the operator from Python, on the command line)
always wins over these."""

from types import SimpleNamespace

import bpy
from bpy.props import BoolProperty, EnumProperty

from ...io import DEFAULT_EXTENSIONS

# Blender finds an extension's preferences by its package name: the package two above this one (ui, splat_addon)
# (bl_ext.<repository>.splatwright when installed as an extension, splatwright beside the bpy module).
ADDON = __package__.rsplit(".", 2)[0]

FORMAT_ITEMS = (
    ("ply", "PLY", "3DGS PLY: float32, lossless"),
    ("spz", "SPZ", "Niantic's compressed format"),
    ("splat", ".splat", "antimatter15's 32 bytes per splat, DC colour only"),
    ("usd", "OpenUSD", "ParticleField3DGaussianSplat (.usd)"),
    ("compressed_ply", "Compressed PLY", "PlayCanvas' 16 bytes per splat"),
    ("gltf", "glTF", "KHR_gaussian_splatting (.glb)"),
)
SH_DEGREE_ITEMS = (
    ("KEEP", "Keep", "Write the SH degree the splats have"),
    ("0", "0 (colour only)", "Drop every view-dependent coefficient"),
    ("1", "1", "Reduce to degree 1 (4 coefficients per channel)"),
    ("2", "2", "Reduce to degree 2 (9 coefficients per channel)"),
    ("3", "3", "Reduce to degree 3 (16 coefficients per channel)"),
)
SPZ_VERSION_ITEMS = (
    ("2", "2", "gzip, 3-byte rotations"),
    ("3", "3", "gzip, smallest-three rotations (the default of Niantic's library)"),
    ("4", "4", "zstd streams (needs the zstandard package, which Blender has)"),
)
# what the options are without the extension enabled as an add-on (the bpy module, the demo)
DEFAULTS = SimpleNamespace(export_format="ply", sh_degree="KEEP", spz_version="3", use_half=False)


def sh_degree_property(default="KEEP"):
    return EnumProperty(
        name="SH Degree",
        items=SH_DEGREE_ITEMS,
        default=default,
        description="SH degree written (only reduces: a lower degree than the splats have drops view-dependent colour)",
    )


def spz_version_property(default="3"):
    return EnumProperty(
        name="SPZ Version",
        items=SPZ_VERSION_ITEMS,
        default=default,
        description="SPZ file version written (.spz files only)",
    )


def half_property(default=False):
    return BoolProperty(
        name="Half Floats",
        default=default,
        description="OpenUSD: store orientations, scales, opacities and SH as half floats "
        "(half the size, about 5e-4 relative error)",
    )


class SplatwrightPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON

    export_format: EnumProperty(
        name="Export Format",
        items=FORMAT_ITEMS,
        default=DEFAULTS.export_format,
        description="The file format export dialogs and `--command splatwright export` start from",
    )
    sh_degree: sh_degree_property(DEFAULTS.sh_degree)
    spz_version: spz_version_property(DEFAULTS.spz_version)
    use_half: half_property(DEFAULTS.use_half)

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        col = layout.column(heading="Export Defaults")
        for name in ("export_format", "sh_degree", "spz_version", "use_half"):
            col.prop(self, name)


def current(context=None):
    """The preferences in use: the extension's own, or DEFAULTS when it is not an enabled add-on."""
    prefs = (context or bpy.context).preferences
    addon = prefs.addons.get(ADDON) if prefs is not None else None
    return addon.preferences if addon is not None and addon.preferences is not None else DEFAULTS


def default_extension(context=None):
    return DEFAULT_EXTENSIONS[current(context).export_format]


CLASSES = (SplatwrightPreferences,)
