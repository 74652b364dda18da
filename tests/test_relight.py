"""The lit render (core.relight.render_lit) against the float64 brute-force renderer of the same
splats coloured plainly per splat by their shading, and its passes and material-less splats."""

import copy
import dataclasses
import math

import numpy as np
import pytest
from helpers import needs_numba
from reference_render import reference_render
from shadow_reference import plane_cloud, sphere_cloud

from splatwright.core import material, relight, shadows
from splatwright.core.camera import Camera
from splatwright.core.lights import Light, World
from splatwright.core.mesh import Material, Surface
from splatwright.core.render import render
from splatwright.core.shading import shade
from splatwright.core.splats import SplatCloud

CAMERA = Camera.look_at((2.2, -2.6, 2.4), (0, 0, 0.3), up=(0, 0, 1), fov_deg=45, width=64, height=48)
LIGHTS = [
    Light("point", power=400.0, position=(0.6, -0.4, 2.5), radius=0.2),
    Light("sun", color=(1.0, 0.8, 0.6), power=2.0, direction=(0.4, 0.3, -1), angle=math.radians(4)),
]


def _srgb(linear):
    """IEC 61966-2-1, written out."""
    x = np.maximum(linear, 0.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


@pytest.fixture(scope="module")
def scene():
    cloud = SplatCloud.concatenate([plane_cloud(1.2, 24), sphere_cloud((0, 0, 0.6), 0.3, 400)])
    rng = np.random.default_rng(0)
    albedo = rng.uniform(0.2, 0.9, (len(cloud), 3))
    return material.with_material(cloud, albedo=albedo, roughness=rng.uniform(0.3, 0.9, len(cloud)))


def test_lit_render_is_the_cloud_coloured_by_its_shading(scene):
    world = World((0.05, 0.06, 0.08))
    got = relight.render_lit(scene, CAMERA, LIGHTS, world, background=(0.1, 0.1, 0.1))
    visibility = {k: shadows.visibility(scene, light, resolution=relight.SHADOW_RESOLUTION[light.kind])
                  for k, light in enumerate(LIGHTS)}  # fmt: skip
    radiance = shade(scene, CAMERA, LIGHTS, world, visibility).radiance.astype(np.float64)
    plain = scene.replace(sh=((_srgb(radiance) - 0.5) / 0.28209479177387814)[:, None, :])
    want = reference_render(plain, CAMERA, background=(0.1, 0.1, 0.1))
    assert np.abs(got.color - want["color"]).max() < 2e-3
    assert np.abs(got.alpha - want["alpha"]).max() < 1e-3
    # Shadows are in it: some splats see less than all of the lights.
    assert (visibility[0] < 0.5).sum() > 20


def test_passes_add_up_and_splats_without_material_keep_their_colours(scene):
    rng = np.random.default_rng(1)
    own = scene.replace(sh=rng.normal(0, 0.4, (len(scene), 4, 3)).astype(np.float32))
    albedo = own.extras["albedo"].copy()
    bare = np.arange(len(own)) >= len(own) - 400  # the sphere's splats: no material
    albedo[bare] = np.nan
    own.extras["albedo"] = albedo
    got = relight.render_lit(own, CAMERA, LIGHTS, passes=True, background=None)
    rows, shading = relight.lit_colors(own, CAMERA, LIGHTS)
    assert np.array_equal(rows, ~bare)
    # The sphere keeps its own view-dependent colours, the plane shows its shading.
    sh = own.sh.copy()
    sh[rows] = 0.0
    sh[rows, 0] = (_srgb(shading.radiance.astype(np.float64)) - 0.5) / 0.28209479177387814
    want = reference_render(own.replace(sh=sh), CAMERA, background=(0.0, 0.0, 0.0))
    assert np.abs(got.color - want["color"]).max() < 2e-3
    # Passes: linear radiance blended as colours are, material-less splats black.
    lin = np.zeros((len(own), 3))
    lin[rows] = shading.diffuse + shading.specular
    flat = own.replace(sh=((lin - 0.5) / 0.28209479177387814)[:, None, :])
    both = reference_render(flat, CAMERA, background=(0.0, 0.0, 0.0))["color"]
    assert np.abs(got.diffuse + got.specular - both).max() < 2e-3
    assert 0.0 <= got.shadow.min() and got.shadow.max() <= 1.0 and got.shadow.max() > 0.3


def test_cloud_without_material_renders_as_it_is(scene):
    bare = SplatCloud(scene.positions, scene.rotations, scene.log_scales, scene.opacity_logits, scene.sh)
    got = relight.render_lit(bare, CAMERA, LIGHTS)
    assert np.array_equal(got.color, render(bare, CAMERA).color)


def test_splats_with_zero_normals_keep_their_own_colours(scene):
    """Blender's own Join fills missing normals with zeros: such splats count as without a material."""
    normals = material.normals(scene).astype(np.float32)
    normals[:10] = 0.0
    zeroed = scene.replace(extras={**scene.extras, **{k: normals[:, i] for i, k in enumerate(material.NORMALS)}})
    rows = material.carried(zeroed)
    assert not rows[:10].any() and rows[10:].all()
    lit = relight.render_lit(zeroed, CAMERA, LIGHTS)
    assert np.isfinite(lit.color).all()


def test_light_linking_reaches_the_splats_of_the_rows_with_a_material(scene):
    """Receivers are one mask per splat of the whole cloud: where some splats carry no material, the
    shading of the others follows their own rows of it."""
    albedo = scene.extras["albedo"].copy()
    albedo[:50] = np.nan  # the first 50 splats: no material, shaded by nothing
    cloud = scene.replace(extras={**scene.extras, "albedo": albedo})
    plane = np.arange(len(cloud)) < len(cloud) - 400  # the sun lights the floor only
    visible = relight.visibilities(cloud, LIGHTS)
    rows, linked = relight.lit_colors(cloud, CAMERA, LIGHTS, visible=visible, receivers={1: plane})
    _, point_only = relight.lit_colors(cloud, CAMERA, LIGHTS[:1], visible={0: visible[0]})
    _, both = relight.lit_colors(cloud, CAMERA, LIGHTS, visible=visible)
    sphere = ~plane[rows]
    assert rows.sum() == len(cloud) - 50 and sphere.sum() == 400
    np.testing.assert_allclose(linked.radiance[sphere], point_only.radiance[sphere], rtol=1e-6)
    np.testing.assert_array_equal(linked.radiance[~sphere], both.radiance[~sphere])
    frame = relight.render_lit(cloud, CAMERA, LIGHTS, visible=visible, receivers={1: plane})
    assert np.isfinite(frame.color).all()
    with pytest.raises(ValueError, match="receivers must be"):
        relight.render_lit(cloud, CAMERA, LIGHTS, visible=visible, receivers={1: plane[:-1]})


class _Stop(Exception):
    pass


def test_a_light_that_gives_no_light_to_reflect_gets_no_shadow_maps(scene):
    """Diffuse and specular weights of 0 (both ray visibilities off in Blender): no maps are made for
    that light, and the frame is the one without it."""
    dark = Light("point", power=300.0, position=(0.5, 0.5, 2.0), diffuse=0.0, specular=0.0)
    seen = relight.visibilities(scene, [LIGHTS[0], dark])
    assert sorted(seen) == [0]
    without = relight.render_lit(scene, CAMERA, LIGHTS[:1]).color
    np.testing.assert_array_equal(relight.render_lit(scene, CAMERA, [LIGHTS[0], dark]).color, without)


def test_shadow_maps_report_progress_first_and_a_raise_stops_them(scene):
    """A lit render's progress follows every light's shadow maps ("shadows", rising from 0 towards 1
    over both lights), then the render's tiles; an exception raised from it (a cancel) while the
    maps are drawn stops the frame there."""
    seen = []
    relight.render_lit(scene, CAMERA, LIGHTS, progress=lambda done, total, label: seen.append((done / total, label)))
    labels = [label for _, label in seen]
    first_tiles = labels.index("render")
    assert set(labels[:first_tiles]) == {"shadows"} and set(labels[first_tiles:]) == {"render"}
    shadow = [fraction for fraction, label in seen if label == "shadows"]
    assert shadow == sorted(shadow) and shadow[0] == 0.0 and shadow[-1] == 1.0
    assert any(fraction < 0.5 for fraction in shadow) and any(fraction > 0.5 for fraction in shadow)
    calls = []

    def cancel(done, total, label):
        calls.append(label)
        if len(calls) == 3:
            raise _Stop

    with pytest.raises(_Stop):
        relight.render_lit(scene, CAMERA, LIGHTS, progress=cancel)
    assert calls == ["shadows"] * 3


def _quad(height, alpha=None):
    """A 0.6 m square mesh at `height` over the scene; with `alpha` (4x4), cut by it (MASK)."""
    corners = np.array([[-0.3, -0.3, height], [0.3, -0.3, height], [0.3, 0.3, height], [-0.3, 0.3, height]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    if alpha is None:
        return Surface(corners, faces)
    texture = np.concatenate([np.ones((4, 4, 3), np.float32), alpha[..., None]], axis=2)
    uvs = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], float)
    return Surface(corners, faces, uvs, None, [Material(texture=texture, alpha_mode="MASK")])


def test_kept_visibilities_make_again_only_what_changed(scene, monkeypatch):
    """KeptVisibilities against visibilities() made afresh, call by call: equal copies of the inputs
    make nothing; a moved light remakes its own maps alone (the world's occlusion stays); moved
    splats, a moved mesh, a mesh's alpha cut changed, or a light's shadow linking changed remake what
    depends on them."""
    made = []
    original = shadows.visibility
    monkeypatch.setattr(
        shadows, "visibility", lambda cloud, light, **kw: made.append(light.kind) or original(cloud, light, **kw)
    )
    world = World((0.1, 0.1, 0.1), 4)
    kept = relight.KeptVisibilities()

    def check(cloud, lights, meshes, blockers=None):
        """kept's result, compared with visibilities() made afresh; the maps kept made."""
        made.clear()
        got = kept(cloud, lights, world, meshes=meshes, blockers=blockers)
        count = list(made)
        want = relight.visibilities(cloud, lights, world, meshes=meshes, blockers=blockers)
        assert got.keys() == want.keys()
        for key in want:
            np.testing.assert_array_equal(got[key], want[key])
        return count

    cut = np.ones((4, 4), np.float32)
    cut[:2] = 0.0  # half the quad lets light through
    meshes = [_quad(1.4, cut)]
    assert check(scene, LIGHTS, meshes) == ["point", "sun"] + ["sun"] * 4  # the lights, then the world's 4 suns
    same, copies = copy.deepcopy(scene), copy.deepcopy(LIGHTS)  # equal values in new arrays
    assert check(same, copies, [_quad(1.4, cut.copy())]) == []
    moved = [LIGHTS[0], Light("sun", power=2.0, direction=(-0.4, 0.3, -1), angle=math.radians(4))]
    assert check(scene, moved, meshes) == ["sun"]  # the moved sun alone; the point light and the world kept
    assert check(scene, moved, [_quad(1.4)]) == ["point", "sun"] + ["sun"] * 4  # the quad no longer cut
    assert check(scene, moved, [_quad(1.5)]) == ["point", "sun"] + ["sun"] * 4  # moved
    lifted = scene.replace(positions=scene.positions + np.float32([0, 0, 0.01]))
    assert check(lifted, moved, [_quad(1.5)]) == ["point", "sun"] + ["sun"] * 4
    blockers = {0: np.arange(len(scene)) % 2 == 0}
    assert check(lifted, moved, [_quad(1.5)], blockers) == ["point"]  # its linking changed
    with pytest.raises(ValueError, match="blockers names light 2, but there are 2 lights"):
        kept(lifted, moved, world, blockers={2: blockers[0]})


@needs_numba
def test_display_dc_shows_the_radiance_as_display_srgb_on_both_paths(monkeypatch):
    """The lit colours' degree-0 coefficients: the compiled kernel and the NumPy path against the sRGB
    curve written out, across black, the curve's linear toe, mid-greys and highlights past 1."""
    from splatwright.core import jit

    rng = np.random.default_rng(3)
    radiance = np.concatenate([[[0.0, 0.002, 0.0031308]], [[-0.5, 1.0, 3.3]], rng.uniform(0, 2, (500, 3))])
    radiance = radiance.astype(np.float32)
    want = (_srgb(radiance.astype(np.float64)) - 0.5) / 0.28209479177387814
    assert jit.compiled(relight.__name__, ("_display_dc_loop",)) is not None  # numba loads here
    compiled = relight.display_dc(radiance)
    monkeypatch.setattr(jit, "compiled", lambda *_: None)
    numpy_path = relight.display_dc(radiance)
    for got in (compiled, numpy_path):
        assert got.dtype == np.float32 and got.shape == radiance.shape
        np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)


def _scattered_cloud(n=20000, seed=5):
    """Splats all around a camera looking at the origin from (0, -4, 1): small and large (up to 0.6
    m), needles and discs, faint and opaque, most outside any one view."""
    rng = np.random.default_rng(seed)
    positions = rng.uniform(-8, 8, (n, 3)).astype(np.float32)
    rotations = rng.normal(size=(n, 4)).astype(np.float32)
    log_scales = rng.uniform(np.log(0.002), np.log(0.6), (n, 3)).astype(np.float32)
    logits = rng.uniform(-4, 9, n).astype(np.float32)  # opacity 0.02 .. 0.9999
    return SplatCloud(positions, rotations, log_scales, logits, np.zeros((n, 1, 3), np.float32))


def _views():
    base = Camera.look_at((0, -4, 1), (0, 0, 0), up=(0, 0, 1), fov_deg=45, width=64, height=48)
    wide = Camera.look_at((0, -4, 1), (0, 0, 0), up=(0, 0, 1), fov_deg=120, width=80, height=40)
    shifted = dataclasses.replace(base, cx=base.cx + 40.0, cy=base.cy - 25.0)  # a lens shift
    ortho = Camera.look_at_ortho((0, -4, 1), (0, 0, 0), up=(0, 0, 1), ortho_scale=5.0, width=64, height=48)
    return {"perspective": base, "wide": wide, "lens shift": shifted, "orthographic": ortho}


@pytest.mark.parametrize("view", ["perspective", "wide", "lens shift", "orthographic"])
@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_may_show_holds_every_splat_the_render_draws(view, mode):
    """may_show against core.render's own projection (its culling: alpha 1/255 under the 0.3 px^2
    low-pass, the Jacobian clamped at the frustum margin, the near plane): never a drawn splat left
    out, and most of a cloud all around the camera left out."""
    from splatwright.core.render import project

    cloud, camera = _scattered_cloud(), _views()[view]
    cloud.antialiased = mode == "antialiased"
    drawn = project(cloud, camera, mode=mode).index
    shown = relight.may_show(cloud, camera)
    assert len(drawn) > 40
    assert shown[drawn].all()
    assert shown.sum() < min(0.6 * len(cloud), 2.5 * len(drawn))
    # The splats just past the image's edges: their centres outside, their tails drawn.
    uv, z = camera.project(cloud.positions.astype(np.float64))
    outside = (z > 0) & ((uv[:, 0] < 0) | (uv[:, 0] > camera.width) | (uv[:, 1] < 0) | (uv[:, 1] > camera.height))
    assert outside[drawn].sum() > 5


def test_a_picture_tests_and_shades_only_what_it_shows_with_the_same_pixels(scene, monkeypatch):
    """render_lit made for one picture tests the shadows only at the splats it may show whose seen
    side faces the light, and shades only those it may show: the same picture, to float32 round-off,
    as shading every splat under visibilities made everywhere, for a close-up that leaves much of the
    scene out."""
    close = Camera.look_at((0.9, -0.9, 1.0), (0.2, 0.0, 0.4), up=(0, 0, 1), fov_deg=40, width=64, height=48)
    world = World((0.05, 0.06, 0.08))
    tested = []
    visibility = shadows.visibility

    def counted(cloud, light, **options):
        tested.append(options.get("receiving"))
        return visibility(cloud, light, **options)

    monkeypatch.setattr(shadows, "visibility", counted)
    got = relight.render_lit(scene, close, LIGHTS, world, background=(0.1, 0.1, 0.1))
    restricted = [mask.sum() for mask in tested]
    assert len(restricted) == 2 and max(restricted) < 0.8 * len(scene)
    everywhere = relight.visibilities(scene, LIGHTS, world)
    rows, shading = relight.lit_colors(scene, close, LIGHTS, world, visible=everywhere)
    want = render(relight.lit_cloud(scene, rows, shading), close, (0.1, 0.1, 0.1))
    assert np.abs(got.color - want.color).max() < 1e-6
    assert np.abs(got.alpha - want.alpha).max() < 1e-6
    # Left out of the tests: splats the picture may show whose seen side faces away from the point light.
    seen = relight.may_show(scene, close)
    facing = shadows._facing(scene, LIGHTS[0], close)
    assert (seen & ~facing).sum() > 50
    assert (everywhere[0][seen & ~facing] < 0.5).sum() > 20  # in shadow there, yet reflecting none of it
