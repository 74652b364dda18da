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
    return missing
