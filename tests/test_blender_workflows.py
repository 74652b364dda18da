"""Blender workflows, headless: mesh to splats, animated export, the `blender -b` command and the
demo rig, with the extension installed from its zip as in test_blender_addon.py.

One worker process (this file run as a script) does every Blender-side step and saves what Blender
itself reports (evaluated meshes, UVs, colour attributes, image pixels, matrices per frame) next to
what the extension produced. The tests judge the outputs against references computed here in
float64 from those Blender numbers: barycentric surface points, an independent bilinear texture
lookup and sRGB curve, object matrices per frame, and OpenUSD read with pxr directly.
"""

import re

import numpy as np
import pytest
from blender_session import blender_fixture
from helpers import linear_to_srgb, random_cloud, read, srgb_to_linear
from workers.workflows import BUDGETS, C0, DEFAULT_AXES, EDGE_VIEW, MATERIAL_COLORS, PIXEL_FILTERS, grid_vertices

pytestmark = [pytest.mark.blender, pytest.mark.slow]  # one Blender worker per version


def _write_inputs(work):
    from splatwright.io import write_splats

    write_splats(work / "cloud.ply", random_cloud(150, sh_degree=1, seed=5))


blender = blender_fixture("workers.workflows", _write_inputs)


def bilinear_blender(pixels, uv):
    """Blender's Linear interpolation with Repeat: texel centres at (i + 0.5) / size, row 0 at v = 0."""
    h, w = pixels.shape[:2]
    x, y = uv[:, 0] * w - 0.5, uv[:, 1] * h - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    at = lambda yy, xx: pixels[yy % h, xx % w]
    return (
        at(y0, x0) * (1 - fx) * (1 - fy)
        + at(y0, x0 + 1) * fx * (1 - fy)
        + at(y0 + 1, x0) * (1 - fx) * fy
        + at(y0 + 1, x0 + 1) * fx * fy
    )


def dc_color(d):
    return 0.5 + C0 * d["splat_sh_0"].astype(np.float64)


def source_vertices(d):
    return np.column_stack([d[f"splat_extra_source_vertices.{i}"][:, 0] for i in range(3)])


def surface_points(d, vertices=None):
    """Each splat's barycentric point on its evaluated loop triangle, plus its normal offset; with
    `vertices`, on the triangle of those vertices its source_vertices name."""
    tri = d["splat_extra_source_triangle"][:, 0]
    if vertices is None:
        corners = d["co"].astype(np.float64)[d["tri_verts"][tri]]
    else:
        corners = vertices.astype(np.float64)[source_vertices(d)]
    bary = d["splat_extra_barycentric"].astype(np.float64)
    points = np.einsum("nk,nkc->nc", bary, corners)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offset = d.get("splat_extra_normal_offset", np.zeros((len(tri), 1)))[:, 0]
    return points + offset[:, None] * normal


def corner_values(d, per_loop):
    tri = d["splat_extra_source_triangle"][:, 0]
    return np.einsum(
        "nk,nkc->nc", d["splat_extra_barycentric"].astype(np.float64), per_loop[d["tri_loops"][tri]].astype(np.float64)
    )


# the Rendered look ----------------------------------------------------------------------------------------


def test_from_mesh_bakes_the_look_cycles_renders_and_leaves_the_scene_as_it_was(blender):
    """The Rendered appearance: geometry exactly as Base Color makes it, nothing left in the scene
    but the new splat object (no camera, image or changed setting), and at a view no bake used, the
    splats look like Cycles' own render of the lit ball far better than Base Color splats do."""
    res = blender.step("baked_look")
    assert res["base"]["result"] == res["baked"]["result"] == ["FINISHED"], res
    added = sorted(set(res["after"]["data"]["objects"]) - set(res["before"]["data"]["objects"]))
    assert added == res["new"] and len(added) == 1
    for kind in ("cameras", "images", "materials", "lights"):
        assert res["after"]["data"][kind] == res["before"]["data"][kind], kind
    assert res["after"]["settings"] == res["before"]["settings"]
    assert {k: v for k, v in res["after"]["flags"].items() if k in res["before"]["flags"]} == res["before"]["flags"]
    clouds = {name: saved_cloud(blender, f"baked_look_{name}") for name in ("base", "baked")}
    base, baked = blender.npz("baked_look_base"), blender.npz("baked_look_baked")
    for field in ("positions", "rotations", "log_scales", "opacity_logits", "matrix"):
        np.testing.assert_array_equal(base[field], baked[field])
    assert clouds["base"].sh_degree == 0 and clouds["baked"].sh_degree == 1
    got = held_out_psnr(blender, "baked_look_view", clouds)
    assert got["baked"] > 22 and got["baked"] > got["base"] + 6, got


def test_a_bake_measured_from_the_scene_camera_bakes_from_its_path(blender):
    """Measured from the scene camera (the ball rotated and scaled unevenly: its space shears the
    camera), the Rendered look is baked from its path too. Cycles' render of the path's view (through
    blender_lens' camera, perspective and orthographic) is Cycles' render through the scene camera
    itself, and from that view the same splats look like it far better than when baked only from
    views around."""
    from splatwright.core.camera import Camera
    from splatwright.core.metrics import psnr
    from splatwright.core.render import render

    res = blender.step("baked_path")
    assert res["CAMERA"]["result"] == res["AROUND"]["result"] == ["FINISHED"], res
    for kind in ("persp", "ortho"):
        view = blender.npz(f"baked_path_{kind}")
        width, height, fx, fy, cx, cy = view["intrinsics"]
        assert (width, height) == (32, 20) and abs(cx - 16) > 3 and abs(cy - 10) > 1  # a shifted lens
        assert str(view["projection"]) == ("orthographic" if kind == "ortho" else "perspective")
        own = view["scene_camera"]
        assert own.max() > 0.2 and (own == 0).mean() > 0.2
        assert psnr(view["image"], own) > 40, kind
    view = blender.npz("baked_path_persp")
    width, height, fx, fy, cx, cy = view["intrinsics"]
    own = view["scene_camera"]
    camera = Camera(int(width), int(height), fx, fy, cx, cy, view["world_to_camera"])
    clouds = {source: saved_cloud(blender, f"baked_path_{source}") for source in ("camera", "around")}
    got = {source: psnr(render(cloud, camera).color, own) for source, cloud in clouds.items()}
    np.testing.assert_array_equal(clouds["camera"].positions, clouds["around"].positions)  # only the bake differs
    assert got["camera"] > 25 and got["camera"] > got["around"] + 2.5, got  # 26.4-26.7 and 22.8-23.3 dB


def saved_cloud(blender, name):
    """The cloud a worker saved with save_object_cloud, in world space."""
    from splatwright.core import SplatCloud

    d = blender.npz(name)
    return SplatCloud(d["positions"], d["rotations"], d["log_scales"], d["opacity_logits"], d["sh"]).transformed(
        d["matrix"]
    )


def held_out_psnr(blender, view, clouds):
    """{name: PSNR of the cloud's render against Cycles' render of the lit ball at the held-out view}."""
    from splatwright.core.camera import Camera
    from splatwright.core.metrics import psnr
    from splatwright.core.render import render

    d = blender.npz(view)
    camera = Camera(48, 48, float(d["fx"]), float(d["fx"]), 24.0, 24.0, d["world_to_camera"])
    reference = d["image"]
    assert reference.max() > 0.2 and (reference == 0).mean() > 0.3  # a lit ball over black, floor unseen
    return {name: psnr(render(cloud, camera).color, reference) for name, cloud in clouds.items()}


def test_from_mesh_panel_shows_the_bake_options_only_for_the_rendered_look(blender):
    """The operator's draw(): every option in some panel, each only where the choices above it use it,
    and the bake options' numbers those the command's help gives (test_cli_from_mesh_help_...)."""
    res = blender.step("from_mesh_panel")
    shown = res["shown"]
    assert set().union(*shown.values()) - {"|"} == set(res["properties"])  # no option is lost
    bake = ["bake_views", "bake_samples", "bake_degree", "bake_geometry_steps"]
    for key, names in shown.items():
        mode, source, look = key.split("/")
        assert [n for n in names if n in bake] == (bake if look == "RENDERED" else []), key
        assert ("target_psnr" in names, "calibrate" in names) == (mode == "QUALITY", mode == "BUDGET"), key
        assert ("view_near" in names) == ("view_far" in names) == (source == "AROUND" or look == "RENDERED"), key
        assert len(names) == len(set(names)) + 1 and names.count("|") == 2, key  # three groups, each option once
    assert shown["BUDGET/CAMERA/RENDERED"] == [
        "mode",
        "max_splats",
        "calibrate",
        "memory_budget",
        "use_rest_pose",
        "|",
        "view_source",
        "view_near",
        "view_far",
        "view_count",
        "view_size",
        "|",
        "made_for",
        "appearance",
        "bake_views",
        "bake_samples",
        "bake_degree",
        "bake_geometry_steps",
        "use_material",
    ]
    assert shown["QUALITY/CAMERA/BASE_COLOR"] == [
        "mode",
        "max_splats",
        "target_psnr",
        "memory_budget",
        "use_rest_pose",
        "|",
        "view_source",
        "view_count",
        "view_size",
        "|",
        "made_for",
        "appearance",
        "use_material",
    ]
    assert res["appearances"] == ["BASE_COLOR", "RENDERED"]
    assert res["numbers"] == {
        "bake_views": [32, 1, 256],
        "bake_samples": [16, 1, 4096],
        "bake_degree": [3, 0, 3],
        "bake_geometry_steps": [0, 0, 100_000],
        "view_size": [256, 16, 2048],
    }


# install -------------------------------------------------------------------------------------------


def test_install_registers_operators_command_and_menu(blender):
    res = blender.step("install")
    assert res == {"operators": [True, True], "command_registered": True, "convert_menu": 1}


# mesh to splats ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("case", ["srgb", "float"])
def test_from_mesh_samples_the_texture_at_each_splat(blender, case):
    res = blender.step("textured")[case]
    d = blender.npz(f"textured_{case}")
    assert res["is_float"] == (case == "float")
    texels = d["texels"][..., :3].astype(np.float64)  # Blender's own pixels, bottom row first
    linear = texels if case == "float" else srgb_to_linear(texels)
    uv = corner_values(d, d["uv"])
    assert uv.min() < 0.0  # the repeat wrap is exercised
    expected = linear_to_srgb(bilinear_blender(linear, uv))
    np.testing.assert_allclose(dc_color(d), expected, atol=2e-4)
    assert np.ptp(expected, axis=0).min() > 0.3  # a real texture, not a flat colour


@pytest.mark.parametrize("case", ["srgb", "float"])
def test_from_mesh_budget_placement_and_provenance(blender, case):
    res = blender.step("textured")[case]
    d = blender.npz(f"textured_{case}")
    assert res["counts"] == list(BUDGETS)
    assert blender.step("textured")[f"{case}_{BUDGETS[0]}"]["result"] == ["FINISHED"]
    np.testing.assert_allclose(d["splat_matrix"], d["source_matrix"], atol=1e-7)
    np.testing.assert_allclose(d["position"], surface_points(d), atol=1e-5)
    tri = d["splat_extra_source_triangle"][:, 0]
    np.testing.assert_array_equal(source_vertices(d), d["tri_verts"][tri])
    np.testing.assert_allclose(d["splat_extra_barycentric"].sum(axis=1), 1.0, atol=1e-6)
    assert res["source"] == {
        "object": f"plane_{case}",
        "mesh": f"plane_{case}",
        "vertices": 20,
        "original_vertices": 20,
        "rest_pose": True,
    }
    # Blender 5.3 draws its own splat point clouds; earlier, a splat mesh with the display modifier
    native = blender.version_tuple >= (5, 3)
    assert res["form"] == ("NATIVE" if native else "MESH")
    assert res["modifiers"] == ([] if native else ["Splatwright Display"]) and res["selected"] == [res["name"]]


def test_from_mesh_applies_modifiers(blender):
    res = blender.step("textured")["arrayed"]
    d = blender.npz("arrayed")
    assert res["result"] == ["FINISHED"]
    assert len(d["tri_verts"]) == 4 * res["original_faces"]  # two copies of 4 quads, triangulated
    assert res["source"]["vertices"] == 2 * res["source"]["original_vertices"]
    np.testing.assert_allclose(d["position"], surface_points(d), atol=1e-5)
    assert d["position"][:, 0].max() > 2.5  # splats on the arrayed copy too
    np.testing.assert_allclose(dc_color(d), np.broadcast_to(linear_to_srgb([0.2, 0.5, 0.8]), (300, 3)), atol=2e-4)


def test_from_mesh_holds_the_splats_to_the_memory_budget(blender):
    from splatwright.core.mesh_refine import splats_within

    res = blender.step("textured")["held"]
    assert res["result"] == ["FINISHED"]
    cap = splats_within(int(0.08 * 2**30), res["faces"], 0)
    assert abs(res["splats"] - cap) <= 0.02 * cap


def test_from_mesh_corner_colour_attribute(blender):
    assert blender.step("colors")["painted"]["result"] == ["FINISHED"]
    d = blender.npz("painted")
    expected = linear_to_srgb(corner_values(d, d["color_Paint"][:, :3]))
    np.testing.assert_allclose(dc_color(d), expected, atol=2e-4)


def test_from_mesh_point_colours_without_material(blender):
    assert blender.step("colors")["bare"]["result"] == ["FINISHED"]
    d = blender.npz("bare")
    tri = d["splat_extra_source_triangle"][:, 0]
    corner = d["color_Tint"][:, :3].astype(np.float64)[d["tri_verts"][tri]]
    expected = linear_to_srgb(np.einsum("nk,nkc->nc", d["splat_extra_barycentric"].astype(np.float64), corner))
    np.testing.assert_allclose(dc_color(d), expected, atol=2e-4)


def test_from_mesh_one_colour_per_material(blender):
    assert blender.step("colors")["multi"]["result"] == ["FINISHED"]
    d = blender.npz("multi")
    tri = d["splat_extra_source_triangle"][:, 0]
    material = d["tri_mat"][tri]
    assert set(material) == {0, 1, 2}
    expected = linear_to_srgb(np.array(MATERIAL_COLORS))[material]
    np.testing.assert_allclose(dc_color(d), expected, atol=2e-4)


def test_from_mesh_warns_about_unfollowed_nodes(blender):
    res = blender.step("colors")["odd"]
    node = "Color node" if blender.version_tuple >= (5, 0) else "RGB node"  # its label until 5.0
    assert len(res["warnings"]) == 1 and "'odd'" in res["warnings"][0] and node in res["warnings"][0]
    np.testing.assert_allclose(res["base"], [0.25, 0.5, 0.75], atol=1e-6)


def test_from_mesh_falls_back_when_an_image_has_no_pixels(blender):
    res = blender.step("colors")["missing image"]
    assert len(res["warnings"]) == 1 and "'lost'" in res["warnings"][0] and "no pixels" in res["warnings"][0]
    assert not res["texture"]
    np.testing.assert_allclose(res["base"], [0.5, 0.25, 0.125], atol=1e-6)


def test_from_mesh_skips_faces_with_non_finite_vertices(blender):
    assert blender.step("colors")["nan vertex"]["result"] == ["FINISHED"]
    d = blender.npz("nan_vertex")
    assert len(d["position"]) == 200
    assert all(np.isfinite(v).all() for v in d.values())
    assert not (source_vertices(d) == 6).any()  # the faces around vertex 6 are left out


@pytest.mark.parametrize(
    "name, words",
    [
        ("camera", ["'Camera' (CAMERA)", "no mesh objects"]),
        ("empty mesh", ["'empty_mesh' has no faces"]),
        ("good and empty", ["'empty_mesh' has no faces"]),
        ("zero-area faces", ["'collapsed'", "positive area"]),
        ("splat object", ["splat cloud"]),
        ("nothing", ["nothing is selected"]),
    ],
)
def test_from_mesh_errors_leave_the_scene_unchanged(blender, name, words):
    case = blender.step("errors")[name]
    assert case["result"] == ["CANCELLED"]
    for word in words:
        assert word in case["error"], case["error"]
    assert case["unchanged"]


def test_from_mesh_skips_non_meshes_in_a_mixed_selection(blender):
    case = blender.step("errors")["good and camera"]
    assert case["result"] == ["FINISHED"] and case["created"] == ["good_splats.001"]


def test_from_mesh_target_psnr(blender):
    res = blender.step("target_psnr")
    assert res["result"] == ["FINISHED"], res["error"]
    assert 0 < res["count"] <= 4000
    # The scene camera's path at frames 1 and 10, seen from the object moved to x = 0.5.
    np.testing.assert_allclose(res["path_centres"], [[-0.5, -4.0, 1.0], [1.5, -4.0, 1.0]], atol=1e-5)
    assert res["frame_after"] == 4 and all(w == 32 for w, _ in res["path_sizes"])
    # A target it cannot reach still converts (a warning says what was reached and why).
    assert res["missed"]["result"] == ["FINISHED"] and 0 < res["missed"]["count"] <= 300
    # Mirrored and scaled unevenly, measured from the camera: the views stand where the camera is in
    # the object's space, and the conversion runs.
    inverse = np.linalg.inv(np.array(res["mirrored_matrix"]))
    eyes = np.array([[0.0, -4.0, 1.0, 1.0], [2.0, -4.0, 1.0, 1.0]]) @ inverse.T
    np.testing.assert_allclose(res["mirrored_centres"], eyes[:, :3], atol=1e-5)
    assert res["mirrored"]["result"] == ["FINISHED"] and 0 < res["mirrored"]["count"] <= 300, res["mirrored"]
    # A moving object: each frame's camera where it stood from the object then, moved to where the
    # object stands now (world=True, a bake's path).
    now = np.array(res["moving_now"])
    assert 0.5 < now[0] < 3.5
    expected = [
        now + np.array(eye) - np.array([x, 0.0, 0.0]) for eye, x in (((0.0, -4.0, 1.0), 0.5), ((2.0, -4.0, 1.0), 3.5))
    ]
    np.testing.assert_allclose(res["moving_world_centres"], expected, atol=1e-5)
    # Still for 20 frames, then a quarter turn: one view where it stands, three along the turn (frames
    # spread evenly would give two the same, at 0, 0, 31.5 and 90 degrees).
    centres = np.array(res["turn_centres"])
    np.testing.assert_allclose(np.linalg.norm(centres, axis=1), 4.0, atol=1e-5)
    angles = np.degrees(np.arctan2(centres[:, 0], -centres[:, 1]))
    np.testing.assert_allclose(angles, [0.0, 30.0, 60.0, 90.0], atol=2.3)  # a frame turns 4.5 degrees
    # A bake's path (View Count 2) takes views enough to keep them 0.5 apart (a quarter turn counts pi):
    # eight, in world space where the object stands, at most a frame from 90 / 7 degrees apart.
    baked = np.array(res["baked_turn_centres"]) - [0.5, 0.0, 0.0]
    turned = np.degrees(np.arctan2(baked[:, 0], -baked[:, 1]))
    assert len(baked) == 8 and turned[0] == 0.0, turned
    np.testing.assert_allclose(np.diff(turned[1:]), 90.0 / 7, atol=4.5)
    # Measured and baked from the same walk: frames 1-40 each set once, then the current frame again.
    assert res["bake_frame_sets"] == 40 + 1


def test_the_mesh_reference_filters_pixels_as_cycles_does(blender):
    """Mesh to Splats measures its quality against core.mesh_render: its pixel filter must be the one
    Cycles renders the scene with, or the converter chases an edge profile users never see. Each of
    Cycles' filters, against Cycles' own render of a slanted edge, and Mesh to Splats takes the
    scene's."""
    import math

    from splatwright.core.camera import Camera
    from splatwright.core.mesh import Material
    from splatwright.core.mesh_render import render_mesh

    res = blender.step("pixel_filter")
    assert res["default"] == ["BLACKMAN_HARRIS", 1.5]
    images = blender.npz("pixel_filter")
    size, angle = EDGE_VIEW[0], math.radians(EDGE_VIEW[1])
    along, across, far = (
        np.array([math.sin(angle), math.cos(angle), 0]),
        np.array([math.cos(angle), -math.sin(angle), 0]),
        1e3,
    )
    plane = far * np.array([-along, along, along + across, across - along])
    camera = Camera.look_at_ortho((0, 0, 10), (0, 0, 0), ortho_scale=float(size), width=size, height=size)
    ours = lambda **kw: (
        render_mesh(
            plane,
            camera,
            faces=[[0, 1, 2], [0, 2, 3]],  # noqa: E731
            materials=[Material(base_color=(1, 1, 1))],
            supersample=16,
            **kw,
        ).alpha
    )
    kinds = {"BLACKMAN_HARRIS": "blackman-harris", "GAUSSIAN": "gaussian", "BOX": "box"}
    for kind, width in PIXEL_FILTERS:
        name = f"{kind}_{width}"
        assert res[name] == {"pixel_filter": kinds[kind], "filter_width": width}
        cycles = images[name]
        edge = (cycles > 0.002) & (cycles < 0.998)
        rms = lambda image: float(np.sqrt(np.mean((image - cycles)[edge] ** 2)))  # noqa: E731
        assert edge.sum() >= size  # the edge crosses every row
        error = rms(ours(**res[name]))
        assert error < 0.008, name  # 1024 samples, not denoised
        # and another filter is far off: a box for Cycles' default, the default for the others
        wrong = ours(pixel_filter="box") if kind == "BLACKMAN_HARRIS" else ours()
        assert rms(wrong) > 2.5 * error, name


def test_from_mesh_calibrates_silhouettes_only_when_asked(blender):
    """Calibrate Silhouettes (on by default) renders the mesh and the splats; off, nothing is rendered
    and every splat lies on its triangle (Blender's own loop triangles), the budget spent either way."""
    res = blender.step("calibration")
    assert res["default"] is True and res["made_for"] == "ANTIALIASED"
    off, on, antialiased = res["off"], res["on"], res["antialiased"]
    assert off["result"] == on["result"] == antialiased["result"] == ["FINISHED"], (off["error"], on["error"])
    assert off["count"] == on["count"] == antialiased["count"] == 1500
    assert (off["antialiased"], on["antialiased"], antialiased["antialiased"]) == (False, False, True)
    # calibrated for the other mode, the splats sit elsewhere: antialiased outlines need no pull inwards
    a, c = blender.npz("calibration_antialiased"), blender.npz("calibration_on")
    assert not np.allclose(a["splat_extra_normal_offset"], c["splat_extra_normal_offset"])
    assert off["renders"] == {"mesh": 0, "splats": 0}
    assert on["renders"]["mesh"] > 0 and on["renders"]["splats"] > 0
    d = blender.npz("calibration_off")
    np.testing.assert_array_equal(d["splat_extra_normal_offset"], 0.0)
    np.testing.assert_allclose(d["position"], surface_points(d), atol=1e-5)


# the demo rig --------------------------------------------------------------------------------------


def test_demo_rig_structure(blender):
    res = blender.step("demo_rig")
    assert res["bones"] == ["Base", "Upper", "Fore", "Hand"]
    assert res["parents"] == [None, "Base", "Upper", "Fore"]
    assert sorted(res["groups"]) == sorted(res["bones"])
    assert res["modifiers"] == [["ARMATURE", "Demo Arm Rig"]]
    assert res["frames"] == [1, 24] and res["animated"] and res["camera"] == "Demo Camera"
    assert res["textured"] and len(res["materials"]) == 4
    env = res["environment"]
    assert env["splat"] and env["count"] == 3000 and env["source"]["object"] == "Demo Environment"


def test_demo_rig_weights_are_smooth_and_normalised(blender):
    d = blender.npz("demo_rig")
    w = d["weights"]
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
    blended = (w > 1e-3).sum(axis=1) > 1
    assert blended.sum() > 0.2 * len(w)  # joints bend, they do not break
    z = d["rest"][:, 2]
    # weights are a smooth function of height: no jump between neighbouring rings
    order = np.argsort(z)
    assert np.abs(np.diff(w[order], axis=0)).max() < 0.6


def test_demo_rig_pose_is_blenders_armature_deformation(blender):
    """At frame 12 Blender's evaluated mesh equals the weighted bone deformation of the rest mesh."""
    d = blender.npz("demo_rig")
    np.testing.assert_allclose(d["body_matrix"], d["arm_matrix"], atol=1e-7)  # armature space = object space
    rest = np.column_stack([d["rest"], np.ones(len(d["rest"]))])
    blended = np.einsum("vb,bij->vij", d["weights"], d["deform"])
    expected = np.einsum("vij,vj->vi", blended, rest)[:, :3]
    np.testing.assert_allclose(d["posed"], expected, atol=1e-5)
    assert np.abs(d["posed"] - d["rest"]).max() > 1.0  # the pose really bends


def test_from_mesh_of_a_posed_rig_uses_the_rest_pose(blender):
    res = blender.step("rest_pose")
    assert res["pose_position"] == "POSE"  # restored after the conversion
    mesh = blender.npz("rig_mesh")
    for key, verts in (("rest", mesh["rest"]), ("posed", mesh["posed"])):
        assert res[key]["result"] == ["FINISHED"]
        assert res[key]["source"]["rest_pose"] == (key == "rest")
        # source_vertices index the original vertices (a deform-only stack keeps them); the rest and
        # posed meshes may split quads along different diagonals, so source_triangle is not enough
        assert res[key]["source"]["vertices"] == res[key]["source"]["original_vertices"]
        d = blender.npz(f"rig_{key}")
        np.testing.assert_allclose(d["position"], surface_points(d, verts), atol=1e-5)
    rest, posed = blender.npz("rig_rest")["position"], blender.npz("rig_posed")["position"]
    assert np.abs(rest - posed).max() > 1.0


# animated export ---------------------------------------------------------------------------------------


def _moved(cloud, matrix, conversion=np.linalg.inv(DEFAULT_AXES)):
    m = conversion @ np.array(matrix)
    return cloud.positions.astype(np.float64) @ m[:3, :3].T + m[:3, 3]


def test_animation_ply_sequence_follows_the_object(blender):
    res = blender.step("animation")
    assert res["ply"]["result"] == ["FINISHED"]
    files = sorted(p.name for p in (blender.out / "seq").iterdir())
    assert files == ["anim_0002.ply", "anim_0003.ply", "anim_0004.ply"]
    source = read(blender.work / "cloud.ply")
    for frame in (2, 3, 4):
        got = read(blender.out / "seq" / f"anim_{frame:04d}.ply")
        np.testing.assert_allclose(got.positions, _moved(source, res["matrices"][str(frame)]), atol=2e-5)
    assert res["frame_after"] == 3  # the scene's frame is restored


def test_animation_without_hashes_uses_the_scene_range(blender):
    res = blender.step("animation")
    assert res["plain"]["result"] == ["FINISHED"]
    assert sorted(p.name for p in (blender.out / "plain").iterdir()) == ["anim_0001.ply", "anim_0003.ply"]


def test_animation_usd_has_one_time_sample_per_frame(blender):
    """Read with pxr directly: Y-up stage, time codes = frames, world positions = Blender's (x, z, -y)."""
    from pxr import Usd, UsdGeom

    res = blender.step("animation")
    assert res["usd"]["result"] == ["FINISHED"]
    stage = Usd.Stage.Open(str(blender.out / "anim.usd"))
    assert UsdGeom.GetStageUpAxis(stage) == "Y"
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (1.0, 4.0)
    assert stage.GetTimeCodesPerSecond() == pytest.approx(30 / 1.001, rel=1e-6)  # the scene's rate
    assert stage.GetFramesPerSecond() == pytest.approx(30 / 1.001, rel=1e-6)
    prim = stage.GetPrimAtPath("/Splats")
    positions = prim.GetAttribute("positions")
    assert positions.GetTimeSamples() == [1.0, 2.0, 3.0, 4.0]
    source = read(blender.work / "cloud.ply")
    blender_to_usd = np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
    for frame in range(1, 5):
        world = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(frame)).T  # stands the values up
        got = np.array(positions.Get(frame), dtype=np.float64) @ world[:3, :3].T + world[:3, 3]
        np.testing.assert_allclose(got, _moved(source, res["matrices"][str(frame)], blender_to_usd), atol=2e-5)
    # the uniform scale keyed at frame 4 scales every sigma
    scales = np.sort(np.array(prim.GetAttribute("scales").Get(4), dtype=np.float64), axis=1)
    np.testing.assert_allclose(scales, np.sort(source.scales, axis=1) * 1.5, rtol=2e-5)


def test_animation_selected_only(blender):
    from pxr import Usd

    res = blender.step("animation")
    assert res["usd_selected"]["result"] == ["FINISHED"]
    stage = Usd.Stage.Open(str(blender.out / "anim_sel.usda"))
    prim = stage.GetPrimAtPath("/Splats")
    assert prim.GetAttribute("positions").GetTimeSamples() == [1.0, 2.0]


@pytest.mark.parametrize(
    "name, words",
    [
        ("missing folder", ["nowhere", "does not exist"]),
        ("backwards", ["5-2", "ends before it starts"]),
        ("unknown extension", ["never.xyz", "unknown splat file extension"]),
        ("not splats", ["no splat objects selected", "'Camera' (CAMERA)"]),
    ],
)
def test_animation_errors_write_nothing(blender, name, words):
    res = blender.step("animation")["bad"]
    assert res[name]["result"] == ["CANCELLED"]
    for word in words:
        assert word in res[name]["error"], res[name]["error"]
    assert res["written"] == []


def test_sequence_names_are_deterministic(blender):
    names = {(p, f): name for p, f, name in blender.step("frame_names")["names"]}
    assert names[("/a/shot_####.ply", 7)] == "/a/shot_0007.ply"
    assert names[("/a/shot.ply", 7)] == "/a/shot_0007.ply"
    assert names[("/a/shot_##.ply", 123)] == "/a/shot_123.ply"  # padding is a minimum width
    assert names[("/a/v#_f###.spz", 5)] == "/a/v#_f005.spz"  # the last run of # is the frame
    assert names[("/a/shot_####.ply", -3)] == "/a/shot_-003.ply"
    assert names[("/a/shot.ply", 12345)] == "/a/shot_12345.ply"
    assert names[("/a/shot", 2)] == "/a/shot_0002"


# the blender -b command ------------------------------------------------------------------------------


def _outcome(blender, name):
    return blender.step("cli")["outcomes"][name]


def test_cli_export_ply_sequence(blender):
    res = blender.step("cli")
    run = res["outcomes"]["export ply"]
    assert run["code"] == 0, run["stderr"]
    assert [line for line in run["stdout"].splitlines() if "frame" in line and "->" in line] != []
    source = read(blender.work / "cloud.ply")
    for frame in (1, 2, 3):
        got = read(blender.out / "cli" / f"seq_{frame:04d}.ply")
        np.testing.assert_allclose(got.positions, _moved(source, res["matrices"][str(frame)]), atol=2e-5)
    step = _outcome(blender, "export step")
    assert step["code"] == 0 and {"step_0001.ply", "step_0004.ply"} <= set(res["files"])
    assert "step_0002.ply" not in res["files"]


def test_cli_export_usd_with_format_and_objects(blender):
    from pxr import Usd

    run = _outcome(blender, "export usd")
    assert run["code"] == 0, run["stderr"]
    stage = Usd.Stage.Open(str(blender.out / "cli" / "anim.usd"))
    prim = stage.GetPrimAtPath("/Splats")
    assert prim.GetAttribute("positions").GetTimeSamples() == [2.0, 3.0, 4.0]


def test_cli_export_axes(blender):
    res = blender.step("cli")
    assert res["outcomes"]["export axes"]["code"] == 0
    got = read(blender.out / "cli" / "axes_0004.ply")
    source = read(blender.work / "cloud.ply")
    np.testing.assert_allclose(got.positions, _moved(source, res["matrices"]["4"], np.eye(4)), atol=2e-5)


@pytest.mark.parametrize(
    "name, code, words",
    [
        ("backwards", 1, ["3-1", "ends before it starts"]),
        ("not frames", 1, ["a-b", "A-B"]),
        ("unknown object", 1, ["no object named 'Nope'"]),
        ("not splats", 1, ["not splat objects", "'Grid' (MESH)"]),
        ("missing folder", 1, ["nowhere", "does not exist"]),
        ("format clash", 1, ["x.usdc", "--format is ply"]),
        ("unknown extension", 1, ["x.xyz", "unknown splat file extension"]),
        ("no output", 2, ["output"]),
        ("unknown verb", 2, ["frobnicate"]),
        ("render unknown object", 1, ["no object named 'moving_missing'"]),
        ("from-mesh camera", 1, ["not mesh objects", "'Camera' (CAMERA)"]),
        ("from-mesh unknown", 1, ["no object named 'Nope'"]),
        ("from-mesh bad extension", 1, ["grid.xyz", "unknown splat file extension"]),
        ("from-mesh target uncalibrated", 1, ["--no-calibrate", "--target-psnr"]),
        ("from-mesh bake views 0", 2, ["argument --bake-views", "from 1 to 256, got 0"]),
        ("from-mesh bake samples 2.5", 2, ["argument --bake-samples", "whole number", "'2.5'"]),
        ("from-mesh bake degree 5", 2, ["argument --bake-degree", "invalid choice: 5"]),
        ("from-mesh appearance shiny", 2, ["argument --appearance", "'shiny'", "base-color", "rendered"]),
        ("from-mesh bake unlit", 2, ["--bake-samples", "only with --appearance rendered"]),
        ("from-mesh view size 8", 2, ["argument --view-size", "from 16 to 2048, got 8"]),
        ("from-mesh view count 0", 2, ["argument --view-count", "from 1 to 64, got 0"]),
        ("from-mesh view near x", 2, ["argument --view-near", "expected a number, got 'x'"]),
        ("from-mesh view far 500", 2, ["argument --view-far", "from 0.05 to 100, got 500"]),
        ("from-mesh measure from sky", 2, ["argument --measure-from", "'sky'", "around", "camera"]),
        ("from-mesh from no camera", 1, ["the scene has no camera"]),
        ("render panoramic", 1, ["PANO"]),
        ("render no camera", 1, ["no camera"]),
    ],
)
def test_cli_failures_exit_non_zero_with_a_message(blender, name, code, words):
    run = _outcome(blender, name)
    assert run["code"] == code
    for word in words:
        assert word in run["stderr"], run["stderr"]
    if "new_objects" in run:
        assert run["new_objects"] == 0
    files = blender.step("cli")["files"]
    assert not any(f.startswith(("x.", "x_", "cam", "grid.xyz", "pano", "nocam", "none")) for f in files)


def test_cli_render_frames_through_the_engine(blender):
    from PIL import Image

    res = blender.step("cli")
    run = res["outcomes"]["render"]
    assert run["code"] == 0, run["stderr"]
    assert "frame_0001.png" in res["files"] and "frame_0002.png" in res["files"]
    first, second = (np.asarray(Image.open(blender.out / "cli" / f"frame_000{f}.png"), np.float64) for f in (1, 2))
    assert first.shape[:2] == (24, 32)
    assert np.abs(first - second).max() > 10  # the splats moved between the frames
    assert _outcome(blender, "render no hash")["code"] == 0 and "plain_0004.png" in res["files"]
    assert _outcome(blender, "render exr")["code"] == 0
    assert (blender.out / "cli" / "deep_0003.exr").read_bytes()[:4] == b"\x76\x2f\x31\x01"  # OpenEXR magic
    # the scene's own settings are back as they were
    after = res["after"]
    assert after == {"frame": 2, "engine": after["engine"], "filepath": "//untouched_", "hidden": [], "format": "PNG"}
    assert after["engine"] != "SPLATWRIGHT"


def test_cli_from_mesh_writes_splats_in_world_space(blender):
    res = blender.step("cli")
    run = res["outcomes"]["from-mesh ply"]
    assert run["code"] == 0, run["stderr"]
    assert run["new_objects"] == 1
    cloud = read(blender.out / "cli" / "grid.ply")
    assert len(cloud) == 250
    # the file keeps the provenance extras: rebuild each centre from the grid's own quads
    verts = grid_vertices(wobble=0.2)
    columns = lambda name: np.column_stack([cloud.extras[f"{name}_{i}"] for i in range(3)])  # PLY splits them
    corners = verts[columns("source_vertices")]
    local = np.einsum("nk,nkc->nc", columns("barycentric").astype(np.float64), corners)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    local += cloud.extras.get("normal_offset", np.zeros(len(cloud)))[:, None] * normal
    world = local @ np.array(res["grid_matrix"])[:3, :3].T + np.array(res["grid_matrix"])[:3, 3]
    expected = world @ np.linalg.inv(DEFAULT_AXES)[:3, :3].T
    np.testing.assert_allclose(cloud.positions, expected, atol=2e-5)
    assert run["renders"] == {"mesh": 0, "splats": 0}  # --no-calibrate
    np.testing.assert_array_equal(cloud.extras["normal_offset"], 0.0)
    blend = _outcome(blender, "from-mesh blend")
    assert blend["code"] == 0 and (blender.out / "cli" / "grid.blend").stat().st_size > 1000
    assert res["calibrate_default"] is True  # as the operator's (test_from_mesh_calibrates_...)
    assert cloud.antialiased  # antialiased by default, as the operator's
    made = _outcome(blender, "from-mesh classic")
    assert made["code"] == 0, made["stderr"]
    assert not read(blender.out / "cli" / "grid_classic.spz").antialiased  # SPZ's flag, from --mode


def test_cli_from_mesh_measures_where_it_is_asked(blender):
    """--measure-from camera: the mesh rendered once per view of the camera path (--view-count 2, but
    the camera stands still: one); around, once per view at each distance of --view-near..--view-far
    (0.7, 1, 2.5: six); each run's line says which view was worst, of how many."""
    for name, views, where in (("from-mesh from camera", 1, ""), ("from-mesh around", 6, "x the framing distance")):
        run = _outcome(blender, name)
        assert run["code"] == 0, run["stderr"]
        assert run["renders"]["mesh"] == views, (name, run["renders"])
        line = [text for text in run["stdout"].splitlines() if text.startswith("splatwright: Grid_splats")]
        assert len(line) == 1 and "100 splats, " in line[0] and f" of {views}" in line[0], run["stdout"]
        assert where in line[0] and ("x the framing" in line[0]) == bool(where), line
        # The camera path's frames stepped through, with progress lines (its end at least).
        walked = re.findall(r"\[(\d+)/(\d+)\] camera path frames", run["stdout"])
        assert bool(walked) == (name == "from-mesh from camera"), run["stdout"]
        assert not walked or walked[-1][0] == walked[-1][1], walked


def test_cli_from_mesh_help_lists_the_bake_options(blender):
    run = _outcome(blender, "from-mesh help")
    assert run["code"] == 0 and run["stderr"] == ""
    text = " ".join(run["stdout"].split())  # argparse wraps the help
    for words in (
        "--appearance {base-color,rendered}",
        "--mode {classic,antialiased}",
        "--bake-views N",
        "(1-256; default 32)",
        "--bake-samples N",
        "(1-4096; default 16)",
        "--bake-degree D",
        "(0-3; default 3)",
        "--bake-geometry-steps N",
        "default 0, colours only",
        "--view-size PX",
        "(16-2048; default 256)",
        "--measure-from {around,camera}",
        "--view-count N",
        "(1-64; default 4)",
        "--view-near X",
        "(0.05-100; default 0.5)",
        "--view-far X",
        "(0.05-100; default 3)",
    ):
        assert words in text, words


def test_cli_from_mesh_bakes_the_look_cycles_renders(blender):
    """`from-mesh --appearance rendered`: a progress line per Cycles view, the splats' geometry that of
    the base-colour run with SH of the asked degree, nothing left behind but the output file and the
    new splat object, and at a view no bake used the splats look like Cycles' own render of the lit
    ball far better than the base-colour run's."""
    res = blender.step("cli_bake")
    base, baked = res["base"], res["baked"]
    assert base["code"] == baked["code"] == 0, (base["stderr"], baked["stderr"])
    views = [line for line in baked["stdout"].splitlines() if "bake: Cycles view" in line]
    assert len(views) == 9 and views[-1].endswith("ball: bake: Cycles view 9/9")  # 3 at each of 3 distances
    fitting = [line.rsplit(" ", 1)[1].split("/") for line in baked["stdout"].splitlines() if "fitting colours" in line]
    assert [int(i) for i, _ in fitting] == list(range(1, len(fitting) + 1)) and len(fitting) > 5
    done = [float(line.split("[")[1].split("/")[0]) for line in baked["stdout"].splitlines() if "] " in line]
    assert done == sorted(done) and done[-1] <= 1.0
    assert "ball_splats.001: 600 splats, " in baked["stdout"] and ", baked from Cycles views to" in baked["stdout"]
    assert "Cycles" not in base["stdout"] and baked["renders"]["mesh"] > 0  # both calibrated (the default)
    # the scene and the files as they were, but the new splat object and the output file
    before, after = res["before"], res["after"]
    assert sorted(set(after["data"]["objects"]) - set(before["data"]["objects"])) == ["ball_splats.001"]
    for kind in ("cameras", "images", "materials", "lights"):
        assert after["data"][kind] == before["data"][kind], kind
    assert after["settings"] == before["settings"]
    assert {k: v for k, v in after["flags"].items() if k in before["flags"]} == before["flags"]
    assert res["files_before"] == {"out": ["base.ply"], "temp": []}
    assert res["files_after"] == {"out": ["baked.ply", "base.ply"], "temp": []}  # its views' folder removed
    files = {name: read(blender.out / "cli_bake" / f"{name}.ply") for name in ("base", "baked", "fitted")}
    np.testing.assert_array_equal(files["baked"].positions, files["base"].positions)
    np.testing.assert_array_equal(files["baked"].log_scales, files["base"].log_scales)
    assert files["base"].sh_degree == 0 and files["baked"].sh_degree == 1
    clouds = {name: cloud.transformed(DEFAULT_AXES) for name, cloud in files.items()}  # file -> Blender axes
    got = held_out_psnr(blender, "cli_bake_view", clouds)
    assert got["baked"] > 22 and got["baked"] > got["base"] + 6, got
    # --bake-geometry-steps: after the colours, the splats themselves fitted, a progress line a step
    fitted = res["fitted"]
    assert fitted["code"] == 0, fitted["stderr"]
    steps = [line.rsplit(" ", 1)[1] for line in fitted["stdout"].splitlines() if "fitting splats" in line]
    assert steps == [f"{i}/60" for i in range(1, 61)], steps[-3:]
    assert ", then splats fitted to" in fitted["stdout"]
    moved = np.linalg.norm(files["fitted"].positions - files["baked"].positions, axis=1)
    assert 0 < np.median(moved) < 0.05 * np.ptp(files["baked"].positions, axis=0).max()
    assert got["fitted"] > got["baked"] - 0.1, got  # 60 steps at 32 px: +0.02-0.3 dB
    # the flags mean what the operator's options do: its bake of the same ball with the same settings
    operator = saved_cloud(blender, "baked_look_baked")
    nearest = np.linalg.norm(clouds["baked"].positions[:, None] - operator.positions[None], axis=2).argmin(axis=1)
    assert len(set(nearest)) == len(operator)  # the same splats, in the file's order
    np.testing.assert_allclose(clouds["baked"].positions, operator.positions[nearest], atol=1e-5)
    np.testing.assert_allclose(clouds["baked"].sh, operator.sh[nearest], atol=1e-4)


def test_command_survives_re_registration(blender):
    res = blender.step("reregister")
    assert res["enabled"] and res["re_enabled"]
    assert res["disabled_handle"] is False and res["types_left"] == []
