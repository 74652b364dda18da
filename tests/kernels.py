"""Which compiled kernels fail to load in this interpreter: shared by the layout test (the project's
own numba) and the packaging test (the numba a platform zip bundles, in an environment of its own).
Imports only the product and NumPy, so it runs in such an environment without the test suite."""


def missing_kernels():
    """[name: why] for every compiled kernel that does not load here; [] when all do."""
    from splatwright.core import geometry, jit, kinematics, mesh_render, mesh_sampling, render, render_grad
    from splatwright.core.collision import contacts, distance
    from splatwright.io import ply

    missing = [
        name
        for name, kernel in (
            ("polar", geometry._polar_kernel()),
            ("fk", kinematics._fk_kernel()),
            ("contacts", contacts._contact_kernel()),
            ("distance bounds", distance._bounds_kernel()),
            ("bisection", mesh_sampling._bisect_kernel()),
        )
        if kernel is None
    ]
    for name, module in (
        ("render", render),
        ("mesh render", mesh_render),
        ("backward pass", render_grad),
        ("ply", ply),
    ):
        if jit.load(module.KERNELS, check=module._check_kernels) is None:
            missing.append(f"{name}: {jit.status(module.KERNELS)}")
    return missing + _relighting_missing()


def _relighting_missing():
    """The relighting kernels (shadow maps' masks, extents and filter, shading, lit colours) compile
    on first use: a small lit frame compiles them all; [why] where one fails or does not load."""
    import numpy as np

    from splatwright.core import jit, material, relight, scenes, shading, shadow_cameras, shadows
    from splatwright.core.camera import Camera
    from splatwright.core.lights import Light

    cloud = scenes.seed_cube(points_per_edge=6, sigma=0.06, opacity=0.6)
    normals = np.tile([0.0, 0.0, 1.0], (len(cloud), 1))
    cloud = material.with_material(cloud, albedo=np.full((len(cloud), 3), 0.5), normals=normals)
    camera = Camera.look_at((1.2, 0.8, 0.5), (0.0, 0.0, 3.0), width=32, height=24)
    lights = [Light("point", position=(0.0, 0.0, 0.0), radius=0.1), Light("sun", direction=(0.0, 0.0, 1.0))]
    try:
        frame = relight.render_lit(cloud, camera, lights)
    except Exception as exc:  # a kernel that does not compile with this numba
        return [f"relighting: {type(exc).__name__}: {exc}"]
    kernels = {
        "shadow filter": (shadows.__name__, shadows.FILTER_KERNEL),
        "shadow masks": (shadow_cameras.__name__, ("_near_loop",)),
        "shadow casters": (shadows.__name__, shadows.CASTERS_KERNEL),
        "shadow cells": (shadows.__name__, shadows.BOXES_KERNEL),
        "shadow reach": (shadow_cameras.__name__, ("_reach_loop",)),
        "sun framing": (shadow_cameras.__name__, ("_bounds_loop",)),
        "shadow extents": (shadows.__name__, shadows.EXTENT_KERNEL),
        "shading": (shading.__name__, shading.SHADE_KERNEL),
        "lit colours": (relight.__name__, ("_display_dc_loop",)),
    }
    missing = [name for name, (module, names) in kernels.items() if jit.compiled(module, names) is None]
    if not np.isfinite(frame.color).all():
        missing.append("relighting: the lit frame is not finite")
    return missing
