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
from .keys import (MARKER, LAYOUT_VERSION, EXTRAS_SPEC, ANTIALIASED, SOURCE_EXTRAS, MESH_FORM, NATIVE_FORM, LANDING,
                   SPZ_POSITION_BITS, ROTATION, LOG_SCALE, OPACITY, SH_PREFIX, EXTRA_PREFIX, MAX_NAME, NATIVE_SCALE,
                   NATIVE_ROTATION, NATIVE_BASE, NATIVE_SH_PREFIX, EXACT_LOG_SCALE, EXACT_LOGIT, REST_PREFIX,
                   NATIVE_REQUIRED, FRAME_RECORD, SOURCE)
from .errors import SplatModeWarning, reported_warnings, SplatObjectError, EXPECTED_ERRORS
from .attributes import (splat_count, sh_attribute, set_attribute, BASE_TYPES, base_type, native_log_scales,
                         native_opacity_logits)
from .forms import (is_splat_mesh, is_native_splats, is_gaussian_type, splat_form, is_splat_object, sh_degree,
                    native_supported, native_by_default, is_posed_native, keep_rest_pose, show_posed, landed_raw,
                    on_spz_grid, stamp_landing, geometry_cloud, made_antialiased, mesh_to_cloud, cloud_to_mesh,
                    cloud_to_pointcloud, update_splats, built_datablock, new_splat_object, remove_geometry,
                    remove_splat_object, object_cloud, object_to_cloud)
from .transforms import probe_indices, probe_centres, remember_frame, world_matrix, snap_matrix, transform_cloud
from .scene import (POSERS, OWN_MODIFIERS, EDITS, evaluated_cloud, own_cloud, is_modified, modified_cloud,
                    carry_frames, SplatInstance, splat_instances, generated_cloud, instances_cloud, frame_range)