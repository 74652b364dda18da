"""Shadow maps (core.shadows) against closed forms and the float64 ray reference of
tests/shadow_reference.py: a sphere of splats over a plane of splats, a mesh over the plane, and
self-shadowing of lit surfaces."""

import math

import numpy as np
import pytest
from shadow_reference import plane_cloud, reference_visibility, sphere_cloud

from splatwright.core import material, shadow_cameras, shadows
from splatwright.core.camera import Camera
from splatwright.core.lights import Light
from splatwright.core.mesh import Surface
from splatwright.core.render import Shapes, render
from splatwright.core.splats import SplatCloud

CENTRE, RADIUS = np.array([0.0, 0.0, 0.8]), 0.3


@pytest.fixture(scope="module")
def scene():
    plane = plane_cloud(1.5, 60)
    return SplatCloud.concatenate([plane, sphere_cloud(CENTRE, RADIUS, 1500)]), len(plane)


def _facing(cloud, light, idx):
    """Of splats idx, those whose normal faces the light (the only ones shading lights)."""
    p = cloud.positions[idx].astype(np.float64)
    to_light = -light.direction[None] if light.kind == "sun" else light.position - p
    cos = np.einsum("ni,ni->n", material.normals(cloud)[idx], to_light)
    return idx[cos > 0]


@pytest.mark.parametrize("kind", ["point", "sun"])
def test_sphere_shadow_disc_matches_closed_form(scene, kind):
    cloud, n = scene
    resolution = 1024
    if kind == "point":
        height = 3.0
        light = Light("point", position=(0, 0, height), radius=0.0)
        # The cone from the light tangent to the sphere meets the plane in a disc.
        edge = height * RADIUS / math.sqrt((height - CENTRE[2]) ** 2 - RADIUS**2)
        texel = (height - CENTRE[2]) / (resolution / 2) * height / (height - CENTRE[2])  # on the plane
    else:
        light, edge = Light("sun", direction=(0, 0, -1)), RADIUS
        texel = 3.0 / resolution
    vis = shadows.visibility(cloud, light, resolution=resolution)
    rho = np.hypot(*cloud.positions[:n, :2].T)
    spacing = 3.0 / 60
    assert vis[:n][rho < edge - spacing].max() < 0.02
    assert vis[:n][rho > edge + spacing].min() > 0.98
    # The shadowed area is the disc's and a ring of a few texels: the map sees occluders dilated
    # by the renderer's 0.3 px^2 low-pass, which widens the edge-on splats of the silhouette
    # (measured at 1024: a ring of 1.4 texels by the point light, 3.1 by the sun; the float64
    # reference's shadow is the disc's to 0.6%).
    shadowed = (1 - vis[:n]).sum() * spacing**2
    assert 0 <= shadowed - math.pi * edge**2 < 2 * math.pi * edge * 3.5 * texel


EYE = Camera.look_at((2.0, -2.5, 1.5), (0, 0, 0.4), up=(0, 0, 1), fov_deg=50, width=96, height=64)
LIGHTS = {
    "soft point": Light("point", position=(0.5, 0.3, 3.0), radius=0.3),
    "spot": Light("spot", position=(0.3, -0.2, 2.5), direction=(0, 0, -1), radius=0.2, spot_size=math.radians(90)),
    "tilted sun": Light("sun", direction=(0.3, 0.2, -1), angle=math.radians(5)),
    "area": Light("area", position=(0, 0.2, 2.5), direction=(0, 0, -1), size_x=0.8),
}


@pytest.mark.parametrize("name", LIGHTS)
def test_soft_shadows_match_the_ray_reference(scene, name):
    cloud, n = scene
    light = LIGHTS[name]
    idx = _facing(cloud, light, np.random.default_rng(0).choice(len(cloud), 500, replace=False))
    ref = reference_visibility(cloud, light, idx, samples=64)
    err = np.abs(shadows.visibility(cloud, light, resolution=512)[idx] - ref)
    # Measured at 512 texels: mean 0.001-0.006, largest 0.12-0.19 (in penumbrae).
    assert err.mean() < 0.01
    assert err.max() < 0.25


# A 2 m softbox 1.4 m over the sphere with a grid (Spread) of 30, 60 and 90 degrees -> the mean
# |visibility - float64 ray reference| (weighted by the spread, 144 samples over the light) measured
# with the spread's model (a sun along the light's axis where the plane sees a disc of the light
# smaller than it, its panel past twice that, a blend between) and with the panel's cube alone.
SPREAD_SHADOWS = {30: (0.0067, 0.0469), 60: (0.0184, 0.035), 90: (0.0329, 0.032)}


@pytest.mark.parametrize("spread", SPREAD_SHADOWS)
def test_a_spread_area_light_shadows_along_its_axis_close_by(scene, monkeypatch, spread):
    """Under a narrow Spread each point sees the light from within the spread around its axis, from
    the part of the panel above it: a shadow falls along the axis, not away from the panel's centre
    (the cube alone put the sphere's shadow 0.3 m off: errors up to 0.79)."""
    cloud, _ = scene
    light = Light("area", position=(0.1, 0.2, 2.2), direction=(0, 0, -1), size_x=2.0, spread=math.radians(spread))
    idx = _facing(cloud, light, np.random.default_rng(0).choice(len(cloud), 500, replace=False))
    ref = reference_visibility(cloud, light, idx, samples=144)
    ours = np.abs(shadows.visibility(cloud, light, resolution=512)[idx] - ref).mean()
    monkeypatch.setattr(shadows, "_along_axis", lambda light, height: np.zeros_like(height))  # the panel alone
    panel = np.abs(shadows.visibility(cloud, light, resolution=512)[idx] - ref).mean()
    want_ours, want_panel = SPREAD_SHADOWS[spread]
    assert ours == pytest.approx(want_ours, rel=0.1) and panel == pytest.approx(want_panel, rel=0.1)
    assert ours < 0.2 * panel if spread == 30 else ours < 1.05 * panel


def test_meshes_behind_a_spread_lights_plane_cast_no_shadow():
    """A narrow Spread shadows close by as a sun along its axis: of a mesh there only what lies ahead
    of the panel may block (a quad over it shades nothing; one through its plane, its lower half).
    Receivers under the panel, against the ray reference."""
    plane = plane_cloud(1.5, 60)
    light = Light("area", position=(0.0, 0.0, 1.0), direction=(0, 0, -1), size_x=1.0, spread=math.radians(30))
    quad = np.array([[0, 1, 2], [0, 2, 3]])
    over = Surface(np.array([[-0.6, -0.6, 1.3], [0.6, -0.6, 1.3], [0.6, 0.6, 1.3], [-0.6, 0.6, 1.3]]), quad)
    np.testing.assert_array_equal(shadows.visibility(plane, light, occluders=[over], resolution=256), 1.0)
    # from 0.3 m ahead of the panel's plane to 0.3 m behind it
    through = Surface(np.array([[-0.3, -0.1, 0.7], [0.2, -0.1, 1.3], [0.2, 0.3, 1.3], [-0.3, 0.3, 0.7]]), quad)
    idx = np.arange(0, len(plane), 3)
    idx = idx[(np.abs(plane.positions[idx, :2]) < 0.45).all(axis=1)]  # where the light reaches
    ref = reference_visibility(plane, light, idx, samples=144, meshes=[through])
    err = np.abs(shadows.visibility(plane, light, occluders=[through], resolution=512)[idx] - ref)
    assert 0.08 < 1 - ref.mean() < 0.15  # the lower half shades the plane
    assert err.mean() < 0.05  # measured 0.041 (0.114 with the whole quad blocking)


@pytest.mark.parametrize("elevation", [45, 10, 5])
@pytest.mark.parametrize("kind", ["sun", "point"])
def test_lit_surfaces_do_not_shadow_themselves(kind, elevation):
    e = math.radians(elevation)
    if kind == "sun":
        light = Light("sun", direction=(math.cos(e), 0.3 * math.cos(e), -math.sin(e)), angle=math.radians(3))
    else:
        light = Light("point", position=(-3 * math.cos(e), 0, 3 * math.sin(e)), radius=0.05)
    for cloud in (plane_cloud(1.5, 60), sphere_cloud(CENTRE, RADIUS, 1500)):
        for resolution in (512, 1024):
            vis = shadows.visibility(cloud, light, resolution=resolution)
            idx = _facing(cloud, light, np.arange(len(cloud)))
            # Measured: 0 everywhere but at 1024 the sphere by the sun (0.0007-0.0008, near its
            # terminator: MAX_SLOPE) and the plane by the point light at 5 degrees (0.0001).
            assert (1 - vis[idx]).mean() < 0.005, (resolution, len(cloud))


def test_a_wide_sun_finds_no_blocker_in_the_receivers_own_plane():
    """A sun 40 degrees wide, 15 degrees over a plane with a sphere on it: the blocker search's disc
    of taps reaches parts of the plane nearer the sun than the receiver by more than its bias, and
    they shade it (a fifth of the light, upwind of the sphere where nothing blocks it); tested
    against each receiver's own tangent plane the plane there is lit, and the sphere's shadow
    stays (measured: 0.21 against 0; the shadow's darkest 0.75)."""
    light = Light(
        "sun", direction=(math.cos(math.radians(15)), 0.0, -math.sin(math.radians(15))), angle=math.radians(40)
    )
    plane = plane_cloud(1.5, 60)
    cloud = SplatCloud.concatenate([plane, sphere_cloud(CENTRE, RADIUS, 1500)])
    upwind = np.flatnonzero(plane.positions[:, 0] < -0.5)
    own = shadows.visibility(cloud, light, resolution=256)[: len(plane)]
    tangent = shadows.visibility(cloud, light, resolution=256, receiver_plane=True)[: len(plane)]
    assert (1 - own[upwind]).mean() > 0.1
    assert (1 - tangent[upwind]).mean() < 0.01
    assert tangent.min() < 0.8


def test_mesh_occluder_over_a_splat_plane():
    plane = plane_cloud(1.5, 60)
    vertices = np.array(
        [
            [-0.5, -0.4, 0.7],
            [0.4, -0.3, 0.9],
            [0.0, 0.5, 0.6],
            [0.6, 0.3, 0.4],
            [1.0, 0.3, 0.4],
            [1.0, 0.7, 0.4],
            [0.6, 0.7, 0.4],
        ]
    )
    mesh = Surface(vertices, np.array([[0, 1, 2], [3, 4, 5], [3, 5, 6]]))
    idx = np.arange(0, len(plane), 2)
    for light, samples in ((Light("point", position=(0.2, 0, 3.0), radius=0.0), 1), (LIGHTS["tilted sun"], 32)):
        ref = reference_visibility(plane, light, idx, samples=samples, meshes=[mesh])
        vis = shadows.visibility(plane, light, occluders=[mesh], resolution=512)
        err = np.abs(vis[idx] - ref)
        assert 0.05 < 1 - ref.mean() < 0.12  # the mesh does shade the plane
        # Measured: hard, 0.6% of these splats (on the triangles' edges) wrong, mean 0.006; soft,
        # mean 0.0013.
        assert (err > 0.5).mean() < 0.015
        assert err.mean() < 0.01


def test_lights_that_cast_no_shadow_and_empty_clouds(scene):
    cloud, _ = scene
    light = Light("point", position=(0, 0, 3.0), cast_shadow=False)
    assert np.array_equal(shadows.visibility(cloud, light), np.ones(len(cloud), np.float32))
    assert shadows.visibility(cloud[:0], LIGHTS["spot"]).shape == (0,)


def test_point_light_cube_keeps_only_faces_with_splats(scene):
    """Everything lies below the light: the downward face sees it; faces no splat can reach (the
    upward one) are left out, and every splat keeps the face it has in the whole cube."""
    cloud, n = scene
    light = Light("point", position=(0, 0, 3.0), radius=0.2)
    views = shadows.shadow_views(cloud, light, resolution=64)
    forward = np.array([v.camera.forward for v in views])
    assert 1 <= len(views) < 6 and not (forward[:, 2] > 0.9).any()
    down = np.flatnonzero(forward[:, 2] < -0.9)
    assert len(down) == 1 and (views[down[0]].alpha > 0).any()
    cube = [shadow_cameras._cube_face(light.position, d, views[0].camera.near, 64) for d in (*np.eye(3), *-np.eye(3))]
    own = set(shadow_cameras.face_of(cube, cloud.positions.astype(np.float64)).tolist())  # each splat's face
    kept = {k for k, c in enumerate(cube) if any(np.allclose(c.forward, f) for f in forward)}
    assert own <= kept  # every splat is tested on the face it would have had in the whole cube


def test_maps_drawn_side_by_side_are_the_maps_drawn_in_turn(scene, monkeypatch):
    """A point light beside the sphere sees it on several cube faces: drawn side by side, one core
    each, they are the very maps drawn one after another on every core, in the cube's order."""
    cloud, _ = scene
    light = Light("point", position=(0.45, 0.0, 0.8), radius=0.05)  # beside the sphere, over the plane
    monkeypatch.setattr(shadows, "_side_by_side", lambda sizes, threads: False)
    in_turn = shadows.shadow_views(cloud, light, resolution=96, threads=2)
    monkeypatch.setattr(shadows, "_side_by_side", lambda sizes, threads: True)
    side = shadows.shadow_views(cloud, light, resolution=96, threads=2)
    assert len(in_turn) >= 3 and sum(np.isfinite(v.depth).any() for v in in_turn) >= 3
    for a, b in zip(in_turn, side, strict=True):
        np.testing.assert_array_equal(a.camera.forward, b.camera.forward)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.alpha, b.alpha)


@pytest.mark.parametrize(
    ("sizes", "threads", "expected"),
    [
        ((114, 43, 20), 2, True),  # greedy loads 114 / 63: sooner than 177 / 1.4 = 126 in turn
        ((131, 46, 4), 2, False),  # 131 / 50 against 181 / 1.4 = 129: one map dominates
        ((50, 50, 50, 50, 50, 50), 4, True),  # 100 against 300 / 2.8 = 107
        ((160,), 2, False),  # one map has every core
        ((114, 43, 20), 1, False),
    ],
)
def test_maps_go_side_by_side_where_they_split_evenly_over_the_cores(sizes, threads, expected):
    assert shadows._side_by_side(np.array(sizes), threads) is expected


@pytest.mark.parametrize("name", LIGHTS)
def test_compiled_filter_matches_the_numpy_path(scene, monkeypatch, name):
    cloud, _ = scene
    light = LIGHTS[name]
    if shadows.jit.compiled(shadows.__name__, shadows.FILTER_KERNEL) is None:
        pytest.skip("compiled kernels are not available here")
    compiled = shadows.visibility(cloud, light, resolution=256)
    hard = shadows.visibility(cloud, light, resolution=256, soft=False)
    plane = shadows.visibility(cloud, light, resolution=256, receiver_plane=True)
    # One picture's: a third of the splats not wanted, and those whose seen side faces away untested.
    picture = dict(receiving=np.arange(len(cloud)) % 3 != 0, eye=EYE)
    seen = shadows.visibility(cloud, light, resolution=256, **picture)
    tested = picture["receiving"] & shadows._facing(cloud, light, EYE)
    assert tested.sum() < picture["receiving"].sum() - 200  # the sphere's far side
    assert np.array_equal(seen[tested], compiled[tested]) and (seen[~tested] == 1.0).all()
    assert (compiled[~tested] < 0.5).sum() > 100  # in shadow, yet not wanted or reflecting none of it
    monkeypatch.setattr(shadows.jit, "compiled", lambda *args: None)
    assert np.abs(shadows.visibility(cloud, light, resolution=256) - compiled).max() < 1e-5
    assert np.abs(shadows.visibility(cloud, light, resolution=256, soft=False) - hard).max() < 1e-5
    assert np.abs(shadows.visibility(cloud, light, resolution=256, receiver_plane=True) - plane).max() < 1e-5
    assert np.abs(shadows.visibility(cloud, light, resolution=256, **picture) - seen).max() < 1e-5


@pytest.mark.parametrize("name", ["soft point", "tilted sun"])
def test_shadow_linking_leaves_out_the_splats_that_do_not_block(scene, name):
    """With the sphere left out of the blockers the plane under it is lit everywhere (nothing else
    stands over it) and the sphere's lit side is lit as before; all splats blocking is the default,
    to the bit."""
    from splatwright.core import relight

    cloud, n_plane = scene
    light = LIGHTS[name]
    plane = np.arange(len(cloud)) < n_plane
    default = shadows.visibility(cloud, light)
    assert (default[plane] < 0.5).sum() > 50  # the sphere's shadow on the plane
    np.testing.assert_array_equal(shadows.visibility(cloud, light, blocking=np.ones(len(cloud), bool)), default)
    unblocked = shadows.visibility(cloud, light, blocking=plane)
    assert unblocked[plane].min() > 0.99
    lit_side = _facing(cloud, light, np.flatnonzero(~plane))
    np.testing.assert_allclose(unblocked[lit_side], default[lit_side], atol=1e-6)  # the lit side as before
    visible = relight.visibilities(cloud, [light], blockers={0: plane})
    np.testing.assert_array_equal(visible[0], unblocked)
    with pytest.raises(ValueError, match="blocking must be"):
        shadows.visibility(cloud, light, blocking=plane[:-1])


def test_mesh_shadow_linking_gives_each_light_its_own_meshes():
    """Two lights over a splat plane and a mesh between: with the mesh left out of the first light's
    mesh blockers the plane is lit everywhere under it (to the bit, as with no meshes), the second
    keeps the mesh's shadow (to the bit, as without linking); a light index past the lights is
    refused."""
    from splatwright.core import relight

    plane = plane_cloud(1.5, 40)
    mesh = Surface(np.array([[-0.5, -0.5, 0.6], [0.5, -0.5, 0.6], [0.0, 0.5, 0.6]]), np.array([[0, 1, 2]]))
    lights = [Light("point", position=(0.2, 0.0, 3.0), radius=0.1), LIGHTS["tilted sun"]]
    linked = relight.visibilities(plane, lights, meshes=[mesh], mesh_blockers={0: []})
    unlinked = relight.visibilities(plane, lights, meshes=[mesh])
    assert (unlinked[0] < 0.5).sum() > 50 and (unlinked[1] < 0.5).sum() > 50  # the mesh shadows both
    np.testing.assert_array_equal(linked[0], relight.visibilities(plane, lights[:1])[0])
    np.testing.assert_array_equal(linked[1], unlinked[1])
    with pytest.raises(ValueError, match="mesh_blockers names light 2, but there are 2 lights"):
        relight.visibilities(plane, lights, meshes=[mesh], mesh_blockers={2: []})


def test_spot_lights_see_what_a_point_light_there_sees(scene):
    cloud, n = scene
    point = Light("point", position=(0.3, -0.2, 2.5), radius=0.2)
    wide = Light("spot", position=point.position, radius=0.2, spot_size=math.radians(150))
    narrow = Light("spot", position=point.position, radius=0.2, spot_size=math.radians(90))
    faces = shadows.shadow_views(cloud, wide, resolution=32)  # past 120 degrees: the cube's faces with splats
    assert len(faces) > 1 and all(v.camera.fx < 32 / 2 for v in faces)  # each a little over 90 degrees
    assert np.array_equal(shadows.visibility(cloud, wide), shadows.visibility(cloud, point))
    # Inside the narrow cone, one 1024 map against the 512 cube faces: the same shadows.
    p = cloud.positions.astype(np.float64) - point.position
    inside = np.flatnonzero(p[:, 2] < -np.linalg.norm(p, axis=1) * math.cos(math.radians(40)))
    inside = _facing(cloud, point, inside)
    one = shadows.visibility(cloud, narrow, resolution=1024)[inside]
    cube = shadows.visibility(cloud, point, resolution=512)[inside]
    # Measured: 0.0024 (each is within about 0.004 of the ray reference on average).
    assert len(inside) > 1000 and np.abs(one - cube).mean() < 0.006


@pytest.mark.parametrize("kind", ["soft point", "tilted sun", "area"])
def test_compiled_light_rays_and_masks_match_the_numpy_path(scene, monkeypatch, kind):
    cloud, _ = scene
    light = LIGHTS[kind]
    if shadows.jit.compiled(shadows.__name__, shadows.EXTENT_KERNEL) is None:
        pytest.skip("compiled kernels are not available here")
    source = None if light.kind == "sun" else light.position
    compiled = shadows._extent_and_slope(cloud, light)
    reach, gap = shadow_cameras.reach_and_gap(cloud, source)
    shapes = Shapes(cloud)  # their widest scales, made with the projection's shapes: the same reach
    np.testing.assert_array_equal(shadow_cameras.reach_and_gap(cloud, source, shapes)[0], reach)
    frame = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]  # any rotation
    bounds = shadow_cameras.bounds_in(frame, cloud.positions, reach)
    views = shadows.shadow_views(cloud, light, resolution=128)
    # A map draws its rows of the cloud: it is the map of a copy of the casters near it.
    cameras = [v.camera for v in views]
    masks = shadow_cameras.near_masks(cameras, cloud.positions, reach)
    casters = shadows._casters(cloud, light, cameras, masks, reach)
    assert casters.mean() < 0.8  # the sphere; the plane has nothing under it
    bare = SplatCloud(cloud.positions, cloud.rotations.copy(), cloud.log_scales.copy(), cloud.opacity_logits, cloud.sh)
    bare.rotations[::7] *= -3.0  # any norm and sign: the same axes
    bare.log_scales[::5, 2] = bare.log_scales[::5, 0]  # two equal smallest scales: too round
    bare_casters = shadows._casters(bare, light, cameras, masks, reach)  # shortest axes for normals
    copied = [_map_of(cloud[near & casters], view.camera) for view, near in zip(views, masks, strict=True)]
    monkeypatch.setattr(shadows.jit, "compiled", lambda *args: None)
    reference = shadows._extent_and_slope(cloud, light)
    for got, want in zip(compiled, reference, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12)
    want_reach, want_gap = shadow_cameras.reach_and_gap(cloud, source)
    np.testing.assert_allclose(reach, want_reach, rtol=1e-12)
    local = cloud.positions.astype(np.float64) @ frame.T  # the sun's framing: float64 brute force
    np.testing.assert_allclose(bounds[0], (local - reach[:, None]).min(axis=0), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(bounds[1], (local + reach[:, None]).max(axis=0), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(shadow_cameras.bounds_in(frame, cloud.positions, reach), bounds, rtol=1e-12, atol=1e-12)
    assert (gap is None) == (source is None)
    if gap is not None:
        np.testing.assert_allclose(gap, want_gap, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(shadow_cameras.reach_and_gap(cloud, source, shapes)[1], gap, rtol=1e-15)
    want_masks = shadow_cameras.near_masks(cameras, cloud.positions, want_reach)
    assert np.array_equal(masks, want_masks)
    assert np.array_equal(casters, shadows._casters(cloud, light, cameras, want_masks, want_reach))
    assert np.array_equal(bare_casters, shadows._casters(bare, light, cameras, want_masks, want_reach))
    for got, want, copy in zip(views, shadows.shadow_views(cloud, light, resolution=128), copied, strict=True):
        assert np.array_equal(got.depth, want.depth) and np.array_equal(got.alpha, want.alpha)
        assert np.array_equal(copy.depth, want.depth) and np.array_equal(copy.alpha, want.alpha)


def _map_of(cloud, camera):
    """A shadow map's depth and alpha drawn from `cloud` alone."""
    result = render(cloud, camera, background=None, tile_size=shadows.MAP_TILE)
    depth = np.where(result.alpha > 0, result.depth, np.float32(np.inf)).astype(np.float32)
    return shadows.ShadowView(camera, depth, result.alpha)


@pytest.mark.parametrize("kind", list(LIGHTS))
def test_maps_leave_out_splats_with_nothing_behind_them(scene, kind):
    """A floor shadows nothing unless something lies under it: the maps draw the sphere, the floor
    only over a lower floor (a table top over the ground), and all of it where a grazing sun's disc
    straddles its plane."""
    cloud, n_plane = scene
    light = LIGHTS[kind]
    below = plane_cloud(0.3, 12, z=-0.4)  # under the floor's middle
    layered = SplatCloud.concatenate([cloud, below])
    for c, expect_floor_over_below in ((cloud, False), (layered, True)):
        views = shadows.shadow_views(c, light, resolution=512)
        cameras = [v.camera for v in views]
        reach = shadow_cameras.reach_and_gap(c, None)[0]
        near = shadow_cameras.near_masks(cameras, c.positions, reach)
        casters = shadows._casters(c, light, cameras, near, reach)
        floor = casters[:n_plane]
        assert casters[n_plane : len(cloud)][near[:, n_plane : len(cloud)].any(axis=0)].all()  # the sphere
        xy = np.abs(c.positions[:n_plane, :2]).max(axis=1)
        if expect_floor_over_below:
            assert floor[xy < 0.3].all()  # over the lower floor: kept
            assert not floor[xy > 1.2].any()  # far from it: left out
        else:
            assert not floor.any()
    grazing = Light("sun", direction=(1.0, 0.0, -0.01), angle=math.radians(5))
    views = shadows.shadow_views(cloud, grazing, resolution=128)
    cameras = [v.camera for v in views]
    reach = shadow_cameras.reach_and_gap(cloud, None)[0]
    near = shadow_cameras.near_masks(cameras, cloud.positions, reach)
    assert shadows._casters(cloud, grazing, cameras, near, reach)[:n_plane].all()
    # Without material normals (captured splats), a flat splat's shortest axis stands for its normal;
    # splats too round to have one are all drawn.
    bare = SplatCloud(cloud.positions, cloud.rotations, cloud.log_scales, cloud.opacity_logits, cloud.sh)
    with_normals = shadows._casters(cloud, light, cameras, near, reach)
    assert np.array_equal(shadows._casters(bare, light, cameras, near, reach), with_normals)
    round_ = bare.replace(log_scales=bare.log_scales[:, [0, 0, 0]])
    assert shadows._casters(round_, light, cameras, near, reach)[near.any(axis=0)].all()
