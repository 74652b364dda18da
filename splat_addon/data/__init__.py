"""The add-on's bottom floor: splat clouds as Blender data, in two forms, and the one way every
feature reads them. Nothing here imports another part of the add-on; the features above register
their own hooks here (rig/armature.py its poser in POSERS, edit/cleanup.py its settings in EDITS).

    keys.py          attribute names and custom-property keys
    errors.py        SplatObjectError, EXPECTED_ERRORS, Blender reports of Python warnings
    attributes.py    typed attribute reads and writes, SH by coefficient, extras
    forms.py         the mesh form and the native form: detecting, reading, writing, new objects
    transforms.py    world matrices, affine maps of clouds, an object's frame record
    scene.py         the evaluated scene: evaluated_cloud, the POSERS and EDITS hooks, instances
    display.py       the mesh form's viewport display (a geometry-nodes modifier)
    camera.py        a Blender camera as the core Camera
    progress.py      the window's progress bar, where there is a window
    modal_jobs.py    long operators as modal jobs (a step per timer tick, Esc cancels)
    bundled_pxr.py   Blender's own bundled `pxr` made importable

The names of the first six are gathered here: `data.evaluated_cloud`, `data.SplatObjectError`, ...
"""

# ruff: noqa: F401
from .attributes import (
    BASE_TYPES,
    base_type,
    native_log_scales,
    native_opacity_logits,
    set_attribute,
    sh_attribute,
    splat_count,
)
from .errors import EXPECTED_ERRORS, RelightWarning, SplatModeWarning, SplatObjectError, reported_warnings
from .forms import (
    built_datablock,
    cloud_to_mesh,
    cloud_to_pointcloud,
    geometry_cloud,
    is_gaussian_type,
    is_native_splats,
    is_posed_native,
    is_splat_mesh,
    is_splat_object,
    keep_rest_pose,
    landed_raw,
    made_antialiased,
    mesh_to_cloud,
    native_by_default,
    native_supported,
    new_splat_object,
    object_cloud,
    object_to_cloud,
    on_spz_grid,
    remove_geometry,
    remove_splat_object,
    set_extras,
    sh_degree,
    show_posed,
    splat_form,
    stamp_landing,
    stamp_unrecorded,
    update_splats,
)
from .handlers import add_handlers, remove_handlers
from .keys import (
    ANTIALIASED,
    EXACT_LOG_SCALE,
    EXACT_LOGIT,
    EXTRA_PREFIX,
    EXTRAS_SPEC,
    FRAME_RECORD,
    LANDING,
    LAYOUT_VERSION,
    LOG_SCALE,
    MARKER,
    MAX_NAME,
    MESH_FORM,
    NATIVE_BASE,
    NATIVE_FORM,
    NATIVE_REQUIRED,
    NATIVE_ROTATION,
    NATIVE_SCALE,
    NATIVE_SH_PREFIX,
    OPACITY,
    REST_PREFIX,
    ROTATION,
    SH_PREFIX,
    SOURCE,
    SOURCE_EXTRAS,
    SPZ_POSITION_BITS,
)
from .scene import (
    EDITS,
    OWN_MODIFIERS,
    POSERS,
    SplatInstance,
    carry_frames,
    evaluated_cloud,
    frame_range,
    generated_cloud,
    instancer_of,
    instances_cloud,
    is_modified,
    modified_cloud,
    own_cloud,
    splat_instances,
)
from .transforms import probe_centres, probe_indices, remember_frame, snap_matrix, transform_cloud, world_matrix
