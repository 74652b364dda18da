"""The names splat data goes by in Blender: the point attributes of both splat forms (see forms.py)
and the custom properties Splatwright keeps on datablocks and objects, in one place so every
feature reads and writes the same keys."""

MARKER = "splatwright"
LAYOUT_VERSION = 1
EXTRAS_SPEC = "splatwright_extras"  # datablock property: JSON {name: [dtype, columns, ndim]}
ANTIALIASED = "splatwright_antialiased"  # datablock property: the splats were made for antialiased rendering
# Extras that tie splats made from a mesh to its triangles (rigging reads them): bookkeeping of this
# Blender file, not scene content, so exports leave them out.
SOURCE_EXTRAS = ("source_triangle", "barycentric", "source_vertices")

MESH_FORM, NATIVE_FORM = "MESH", "NATIVE"

# Where a splat datablock's values stand (datablock property; see landed_raw): "RAW" when they are a
# file's own axes placed as they are, as Blender's PLY importer places captures; "UPRIGHT" otherwise.
LANDING = "splatwright_landing"
SPZ_POSITION_BITS = 24  # SPZ stores centres as 24-bit signed fixed point

ROTATION = "splat_rotation"
LOG_SCALE = "splat_log_scale"
OPACITY = "splat_opacity_logit"
SH_PREFIX = "splat_sh_"
EXTRA_PREFIX = "splat_extra_"
MAX_NAME = 63  # Blender attribute names are cut at 64 bytes

NATIVE_SCALE, NATIVE_ROTATION, NATIVE_BASE = "scale", "rotation", "radiance:base"
NATIVE_SH_PREFIX = "radiance:sh_"  # radiance:sh_<j> holds SH coefficient j + 1
EXACT_LOG_SCALE, EXACT_LOGIT = ".splatwright_log_scale", ".splatwright_opacity_logit"
REST_PREFIX = ".splatwright_rest:"  # bound native splats: their rest pose, while Blender draws the posed
NATIVE_REQUIRED = ("position", NATIVE_SCALE, NATIVE_ROTATION, NATIVE_BASE)

FRAME_RECORD = "splatwright_frame"  # object property: matrix_basis and probe centres (edit/blender_apply.py)
SOURCE = "splatwright_source"  # splat mesh property: JSON, see convert/from_mesh.py source_record()
