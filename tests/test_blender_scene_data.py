"""Splat objects as users leave them, and Blender 5.3's own splat point clouds, headless on every Blender
of the version matrix with the extension installed from its zip.

Exports are judged against float64 references computed here from the clouds the worker made: the
edit made in Edit Mode, the maps the modifiers apply (an Array offset, a mirror, a geometry-nodes
Transform), a shape key's offset, and the instance matrices Blender reports. Renders of instances and
edits are judged against renders of the same splats as plain objects. Native point clouds, built in
the worker attribute by attribute as Blender's importer stores them, are judged against the same
cloud held as a splat mesh: the two forms must export, transform, join, collide, pose and render alike.
"""

import numpy as np
import pytest
from blender_session import blender_fixture
from helpers import (
    assert_clouds_equal,
    check_transformed,
    euler_matrix,
    format_errors,
    random_cloud,
    read,
    skip_platform,
)
from workers.base import random_cloud_arrays
from workers.scene_data import (
    ARRAY_OFFSET,
    DUPLICATE,
    EDIT_OFFSET,
    GN_ROTATION,
    GN_SCALE,
    INSTANCE,
    NATIVE_TRANSFORM,
    SHAPE_OFFSET,
    N,
)

from splatwright.core import geometry
from splatwright.io.exr import read_exr

pytestmark = [pytest.mark.blender, pytest.mark.slow]  # one Blender worker per version

blender = blender_fixture("workers.scene_data")


def affine(linear, translation=(0, 0, 0)):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = linear, translation
    return m


def image(blender, name):
    channels = read_exr(blender.out / f"{name}.exr")
    return np.stack([channels[c] for c in "RGBA"], axis=-1)


def assert_same_image(blender, a, b, atol=1e-5):
    first, second = image(blender, a), image(blender, b)
    assert np.abs(first[..., :3] - first[..., :3].mean()).max() > 0.01  # something is drawn
    np.testing.assert_allclose(first, second, atol=atol)


def assert_close_clouds(a, b, opacity=1e-7):
    """Two exports of the same splats that took different float32 paths: centres, covariances,
    opacities and colours as format_errors measures them."""
    errors = format_errors(a, b)
    assert errors["positions"] < 1e-5 and errors["covariance"] < 1e-5, errors
    assert errors["opacity"] <= opacity and errors["colour"] < 1e-6, errors


def finished(case):
    assert case["result"] == ["FINISHED"], case


# edit mode, modifiers, shape keys -------------------------------------------------------------------


def test_edit_mode_edits_reach_export_animation_and_render(blender):
    res = blender.step("edit_mode")
    for key in ("export", "animation", "render", "reference_render"):
        finished(res[key])
    assert res["mode"] == "EDIT"
    expected = random_cloud(N, 2, seed=1)
    expected.positions[0] += EDIT_OFFSET
    exported = read(blender.out / "edit.ply")
    np.testing.assert_allclose(exported.positions, expected.positions, atol=1e-6)
    assert_clouds_equal(exported.replace(positions=expected.positions), expected)
    for frame in (1, 2):
        assert_clouds_equal(read(blender.out / f"edit_{frame:04d}.ply"), exported)
    assert_same_image(blender, "edit_render", "edit_reference")


def test_array_modifier_copies_splats_with_its_offset(blender):
    finished(blender.step("modifiers")["array"])
    source, exported = random_cloud(N, 2, seed=2), read(blender.out / "mod_array.ply")
    assert len(exported) == 2 * N
    assert_clouds_equal(exported[:N], source)
    check_transformed(source, exported[N:], affine(np.eye(3), ARRAY_OFFSET), np.eye(3))


def test_mirror_modifier_mirrors_orientations_and_colours(blender):
    finished(blender.step("modifiers")["mirror"])
    source, exported = random_cloud(N, 2, seed=2), read(blender.out / "mod_mirror.ply")
    assert len(exported) == 2 * N
    assert_clouds_equal(exported[:N], source)
    mirror = np.diag([-1.0, 1.0, 1.0])
    check_transformed(source, exported[N:], affine(mirror), mirror)


def test_geometry_nodes_transform_turns_and_stretches_splats(blender):
    res = blender.step("modifiers")
    finished(res["transform"])
    assert res["transform_form"] == ("NATIVE" if blender.version_tuple >= (5, 3) else "MESH")  # as new ones are
    source, exported = random_cloud(N, 2, seed=2), read(blender.out / "mod_transform.ply")
    turn = euler_matrix(GN_ROTATION)
    check_transformed(source, exported, affine(turn @ np.diag(GN_SCALE)))
    np.testing.assert_allclose(geometry.polar_rotation(turn @ np.diag(GN_SCALE)), turn, atol=1e-12)
    from splatwright.core import sh as shmod

    dirs = np.random.default_rng(3).normal(size=(N, 3))
    np.testing.assert_allclose(shmod.colors(exported.sh, dirs @ turn.T), shmod.colors(source.sh, dirs), atol=2e-5)


def test_shape_keys_move_centres_only(blender):
    finished(blender.step("modifiers")["shaped"])
    source, exported = random_cloud(N, 2, seed=2), read(blender.out / "mod_shaped.ply")
    expected = source.positions.copy()
    expected[1] += SHAPE_OFFSET
    np.testing.assert_allclose(exported.positions, expected, atol=1e-6)
    assert_clouds_equal(exported.replace(positions=source.positions), source)


# instances --------------------------------------------------------------------------------------------


def test_collection_instances_and_linked_duplicates_export_with_their_matrices(blender):
    res = blender.step("instances")
    finished(res["visible"])
    finished(res["selected_empty"])
    assert res["form"] == ("NATIVE" if blender.version_tuple >= (5, 3) else "MESH")  # as new ones are
    source = random_cloud(N, 3, seed=3)
    instance, duplicate = (np.array(res["matrices"][k]) for k in ("instance", "duplicate"))
    np.testing.assert_allclose(
        instance[:3, :3], euler_matrix(INSTANCE["rotation_euler"]) * INSTANCE["scale"][0], atol=1e-6
    )
    np.testing.assert_allclose(duplicate[:3, 3], DUPLICATE["location"], atol=1e-6)
    check_transformed(source, read(blender.out / "inst_empty.ply"), instance, instance[:3, :3] / INSTANCE["scale"][0])
    both = read(blender.out / "inst_visible.ply")
    assert len(both) == 2 * N
    first_is_instance = np.allclose(
        both.positions[:N], source.positions @ instance[:3, :3].T + instance[:3, 3], atol=1e-4
    )
    inst_part, dup_part = (both[:N], both[N:]) if first_is_instance else (both[N:], both[:N])
    check_transformed(source, inst_part, instance)
    check_transformed(source, dup_part, duplicate)


def test_instances_render_like_the_same_splats_as_objects(blender):
    res = blender.step("instances")
    finished(res["render"])
    finished(res["reference_render"])
    assert_same_image(blender, "inst_render", "inst_reference")


def test_splats_drawn_through_nested_collection_instances_export_and_render_where_blender_draws_them(blender):
    """Two levels of collection instances (an instancing Empty inside an instanced collection):
    the splats export once, under the outer matrix times the inner one, whether every visible
    splat or the outer Empty selected is exported, and render as those exported splats do."""
    res = blender.step("nested_instances")
    for key in ("visible", "selected_outer", "render", "reference_render"):
        finished(res[key])
    inner, outer = (np.array(res["matrices"][k]) for k in ("inner", "outer"))
    np.testing.assert_allclose(outer[:3, 3], DUPLICATE["location"], atol=1e-6)
    np.testing.assert_allclose(inner[:3, 3], INSTANCE["location"], atol=1e-6)
    source = random_cloud(N, 3, seed=4)
    for name in ("nested_visible.ply", "nested_outer.ply"):
        check_transformed(source, read(blender.out / name), outer @ inner)
    assert_same_image(blender, "nested_render", "nested_reference")


# Blender's own Apply -----------------------------------------------------------------------------------


def test_blenders_apply_rotation_scale_and_all_keeps_the_splats_where_they_were(blender):
    res = blender.step("blender_apply")
    forms = ["mesh_form"] + (["native_form"] if "native_form before" in res else [])
    for form in forms:
        for stage in ("before", "rotation_scale", "all"):
            finished(res[f"{form} {stage}"])
        basis = np.array(res[f"{form} basis"])
        np.testing.assert_allclose(basis[:3, :3], np.eye(3), atol=1e-6)  # only the location is left
        assert res[f"{form} identity"]
        before = read(blender.out / f"apply_{form}_before.ply")
        for stage in ("rs", "all"):
            assert_close_clouds(read(blender.out / f"apply_{form}_{stage}.ply"), before, opacity=0)


# Blender 5.3's own splat point clouds -----------------------------------------------------------------


def native_step(blender, name):
    res = blender.step(name)
    if "skipped" in res:
        skip_platform(f"Blender {res['skipped']} cannot make point clouds from Python (4.5 and later can)")
    return res


def test_native_point_clouds_are_read_like_splat_meshes(blender):
    res = native_step(blender, "native_forms")
    assert res["forms"] == ["MESH", "NATIVE"]
    # as Blender 5.3's importers make them where the types exist (FLOAT4 from 5.2, the splat type 5.3)
    assert res["layout"] == [
        "FLOAT4" if blender.version_tuple >= (5, 2) else "FLOAT_COLOR",
        "GAUSSIAN_SPLAT" if blender.version_tuple >= (5, 3) else None,
    ]
    # made without Splatwright, off SPZ's grid: a PLY's values in its own axes (written back in them)
    assert res["landed_raw"] == [False, True]
    for case in res["export"] + res["render"]:
        finished(case)
    ours, theirs = read(blender.out / "nat_ours.ply"), read(blender.out / "nat_theirs.ply")
    # the object transform applied exactly to the native values too
    source = random_cloud(N, 3, seed=4)
    matrix = affine(
        euler_matrix(NATIVE_TRANSFORM["rotation_euler"]) @ np.diag(NATIVE_TRANSFORM["scale"]),
        NATIVE_TRANSFORM["location"],
    )
    check_transformed(source, ours, matrix)
    assert_close_clouds(theirs, ours)
    assert_same_image(blender, "nat_ours", "nat_theirs")


def test_native_round_trip_loses_only_what_float32_activation_loses(blender):
    """PLY values -> Blender's linear scale and sigmoid opacity in float32 -> PLY: what is lost."""
    native_step(blender, "native_forms")
    source = random_cloud(N, 3, seed=4)
    ours, theirs = read(blender.out / "nat_ours.ply"), read(blender.out / "nat_theirs.ply")
    p = source.opacities
    # float32 keeps the opacity to half an ulp; the logit moves by that over p (1 - p)
    bound = np.spacing(np.float32(p)).astype(np.float64) / (p * (1 - p))
    logit_error = np.abs(theirs.opacity_logits.astype(np.float64) - ours.opacity_logits)
    assert np.all(logit_error <= bound + 1e-6), (logit_error.max(), bound.max())
    print(f"\nopacity logit lost in float32 sigmoid: max {logit_error.max():.2e} (bound {bound.max():.2e})")


def test_native_and_mesh_forms_collide_alike(blender):
    res = native_step(blender, "native_forms")
    ours, theirs = res["contacts"]
    assert ours["pairs"] > 0
    assert theirs.pop("deepest_sigma") == pytest.approx(ours.pop("deepest_sigma"), rel=1e-6)
    assert theirs == ours
    assert res["contact_values"][0] == res["contact_values"][1]


def test_apply_splat_transform_and_join_on_native_point_clouds(blender):
    res = native_step(blender, "native_forms")
    for case in res["apply"] + res["join"]:
        finished(case)
    for matrix in res["applied_matrices"]:
        np.testing.assert_allclose(matrix, np.eye(4), atol=0)
    ours, theirs = read(blender.out / "nat_ours_applied.ply"), read(blender.out / "nat_theirs_applied.ply")
    assert_close_clouds(ours, read(blender.out / "nat_ours.ply"))
    assert_close_clouds(theirs, ours)
    assert res["joined_forms"] == ["MESH", "NATIVE"] and res["joined_raw"] == [False, True]
    joined_ours, joined_theirs = read(blender.out / "nat_ours_joined.ply"), read(blender.out / "nat_theirs_joined.ply")
    assert len(joined_ours) == len(joined_theirs) == N + N // 2
    assert_close_clouds(joined_theirs, joined_ours)
    second = random_cloud(N // 2, 3, seed=5)
    duplicate = affine(euler_matrix(DUPLICATE["rotation_euler"]) @ np.diag(DUPLICATE["scale"]), DUPLICATE["location"])
    check_transformed(second, joined_ours[N:], duplicate)


def test_forms_convert_both_ways_exactly(blender):
    res = native_step(blender, "native_forms")
    finished(res["to_native"])
    finished(res["to_mesh"])
    assert res["converted_form"] == "NATIVE" and res["back_form"] == "MESH"
    joined = read(blender.out / "nat_ours_joined.ply")
    assert_clouds_equal(read(blender.out / "nat_converted.ply"), joined)
    assert_clouds_equal(read(blender.out / "nat_back.ply"), joined)


def test_native_splats_bind_and_pose_like_splat_meshes(blender):
    res = native_step(blender, "native_rig")
    finished(res["bind"])
    assert res["weights"] == ["splat_weight:Lower", "splat_weight:Upper"]
    for case in res["export"] + res["render"]:
        finished(case)
    ours, theirs = read(blender.out / "rig_ours.ply"), read(blender.out / "rig_theirs.ply")
    assert_close_clouds(theirs, ours, opacity=1e-6)
    arrays = random_cloud_arrays(N, 3, seed=7)
    rest = arrays["positions"] * [0.4, 0.4, 1.2]
    matrix = affine(
        euler_matrix(NATIVE_TRANSFORM["rotation_euler"]) @ np.diag(NATIVE_TRANSFORM["scale"]),
        NATIVE_TRANSFORM["location"],
    )
    unposed = rest @ matrix[:3, :3].T + matrix[:3, 3]
    assert np.abs(ours.positions - unposed).max() > 0.1  # the pose moved them
    assert_same_image(blender, "rig_ours", "rig_theirs")


def test_blender_draws_bound_native_splats_posed(blender):
    """The attributes Blender's own viewport and renderers draw hold our exact posed splats (object
    space) at the current frame, to float32."""
    native_step(blender, "native_rig")
    d = blender.npz("rig_drawn")
    sign = np.sign(np.sum(d["rotation"] * d["exact_rotations"], axis=1, keepdims=True))  # q and -q agree
    errors = {
        "position": np.abs(d["position"] - d["exact_positions"]).max(),
        "rotation": np.abs(d["rotation"] * sign - d["exact_rotations"]).max(),
        "scale": np.abs(d["scale"] / d["exact_scales"] - 1).max(),
        "opacity": np.abs(d["radiance__base"][:, 3] - d["exact_opacities"]).max(),
        "sh": max(np.abs(d[f"radiance__sh_{j}"] - d["exact_sh"][:, j + 1]).max() for j in range(15)),
    }
    print(f"\nposed native splats as Blender draws them, against our exact pose: {errors}")
    assert errors["position"] < 1e-6 and errors["rotation"] < 1e-6 and errors["scale"] < 1e-6
    assert errors["opacity"] < 1e-7 and errors["sh"] < 1e-6
    assert np.abs(d["position"] - random_cloud_arrays(N, 3, seed=7)["positions"] * [0.4, 0.4, 1.2]).max() > 0.1
