"""Splats bound to armatures and collisions between splat objects, headless, with the extension
installed from its zip as in test_blender_addon.py.

One worker process (this file run as a script) does every Blender-side step and saves what Blender
itself computes (the Armature modifier's evaluated vertices, bone matrices, vertex-group weights read
one vertex at a time, renders) next to what the extension produced. The tests judge the extension
against those Blender numbers and against references computed here in float64: barycentric weight
interpolation, distances to bone segments, L Sigma L^T for rigidly bound splats, renders of splats
made from the posed mesh, and a brute-force ellipsoid contact test.
"""

import json

import numpy as np
import pytest
from blender_session import blender_fixture
from helpers import covariances, linear_to_srgb, psnr, skip_platform
from workers.rigging import BENT_FRAME, RENDER_SIZE, RIG_BONES

from splatwright.io.exr import read_exr

pytestmark = [pytest.mark.blender, pytest.mark.slow]  # one Blender worker per version

blender = blender_fixture("workers.rigging")


def segment_distances(points, heads, tails):
    d = np.empty((len(points), len(heads)))
    for b, (h, t) in enumerate(zip(heads, tails)):
        axis = t - h
        s = np.clip((points - h) @ axis / (axis @ axis), 0.0, 1.0)
        d[:, b] = np.linalg.norm(points - h - s[:, None] * axis, axis=1)
    return d


# install --------------------------------------------------------------------------------------------


def test_install_registers_operators_menus_deformer_and_handlers(blender):
    res = blender.step("install")
    assert res["operators"] == [True, True]
    assert res["menus"] == {"VIEW3D_MT_object_parent": 1, "VIEW3D_MT_object": 2}  # Check Collisions, Join Splats
    assert res["posers"] == ["rig.armature.poser"]  # registered by the rigging itself
    # weights cache (4), native poses (1), Blender's Apply completed (2), where its importers put clouds (2)
    assert res["handlers"] == 9


def test_handlers_follow_the_extension(blender):
    assert blender.step("reregister") == {"off": 0, "on": 9}


# posing against Blender's Armature modifier -----------------------------------------------------------


def native(blender):
    """Whether this Blender makes splat objects native point clouds (5.3 and later), not splat meshes."""
    return blender.version_tuple >= (5, 3)


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_skinned_centres_equal_blenders_armature_modifier(blender, mode):
    """Rolls, scaled bones (uniform and not), unnormalised and missing weights, a non-deforming bone, an
    object scaled non-uniformly and an armature placed off the origin: Blender's own result to 1e-5
    (its Armature modifier on the splat mesh, or on a plain mesh of native splats' centres with the
    same vertex groups)."""
    res = blender.step("skinning")
    assert res["form"] == ("NATIVE" if native(blender) else "MESH") and res["armature"] == "Rig"
    assert res["modifiers"] == ([] if native(blender) else ["ARMATURE", "NODES"])
    d = blender.npz("skinning")
    ours, theirs = d[f"{mode}_positions"], d[f"{mode}_blender"]
    scale = np.abs(theirs).max()
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-5 * scale)
    assert np.abs(theirs - d["rest_positions"]).max() > 0.3  # the pose really moves them
    unbound = slice(0, 20)  # no groups, or only Ctrl
    np.testing.assert_allclose(ours[unbound], d["rest_positions"][unbound], atol=1e-6)
    if native(blender):
        # Blender draws native splats from their attributes, which hold our posed splats
        np.testing.assert_allclose(d[f"{mode}_display"], ours, rtol=0, atol=1e-6)
    else:
        # the viewport display draws the posed centres (the Armature modifier runs before it)
        np.testing.assert_allclose(d[f"{mode}_display"], theirs, atol=1e-6)


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_blender_draws_native_splats_posed_whole(blender, mode):
    """Bound native splats: the attributes Blender's viewport, EEVEE and Cycles draw hold the posed
    splats, orientations, sizes, opacities and SH included, not only the centres."""
    if not native(blender):
        skip_platform(f"Blender {blender.version} makes splat meshes, whose display draws centres")
    d = blender.npz("skinning")
    rotations = d[f"{mode}_rotations"].astype(np.float64)
    drawn = d[f"{mode}_drawn_rotation"].astype(np.float64)
    np.testing.assert_allclose(drawn, rotations, rtol=0, atol=1e-6 * np.abs(rotations).max())
    assert np.abs(drawn - d["rest_rotations"]).max() > 0.1  # turned, not the rest pose
    np.testing.assert_allclose(d[f"{mode}_drawn_scale"], np.exp(d[f"{mode}_log_scales"].astype(np.float64)), rtol=1e-6)
    sh = d[f"{mode}_sh"].astype(np.float64)
    base = d[f"{mode}_drawn_radiance_base"]
    np.testing.assert_allclose(base[:, :3], sh[:, 0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(
        base[:, 3], 1 / (1 + np.exp(-d[f"{mode}_opacity_logits"].astype(np.float64))), rtol=0, atol=1e-6
    )
    for j in range(1, sh.shape[1]):
        np.testing.assert_allclose(d[f"{mode}_drawn_radiance_sh_{j - 1}"], sh[:, j], rtol=0, atol=1e-6)
    assert np.abs(sh[:, 1:] - d["rest_sh"][:, 1:]).max() > 0.05  # SH turned with the bones


def test_posing_keeps_the_splats_own_values(blender):
    """However often the pose is drawn, the object's own splats stay the rest pose they were."""
    d = blender.npz("skinning")
    for field in ("positions", "rotations", "sh"):
        np.testing.assert_array_equal(d[f"kept_{field}"], d[f"rest_{field}"].astype(np.float32))
    np.testing.assert_allclose(d["kept_log_scales"], d["rest_log_scales"], rtol=1e-6)


def test_modes_differ_where_bones_disagree(blender):
    d = blender.npz("skinning")
    assert np.abs(d["lbs_positions"] - d["dqs_positions"]).max() > 1e-2


def test_weights_edited_after_posing_are_followed(blender):
    d = blender.npz("skinning")
    theirs = d["repainted_blender"]
    np.testing.assert_allclose(d["repainted_positions"], theirs, rtol=0, atol=1e-5 * np.abs(theirs).max())
    assert np.abs(d["repainted_positions"] - d["lbs_positions"]).max() > 1e-2


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_the_modifiers_vertex_group_mask_is_followed(blender, mode):
    """A mask group painted by hand and inverted: Blender blends each vertex between rest and posed by it."""
    d = blender.npz("skinning")
    theirs = d[f"masked_{mode}_blender"]
    np.testing.assert_allclose(d[f"masked_{mode}_positions"], theirs, rtol=0, atol=1e-5 * np.abs(theirs).max())
    assert np.abs(theirs - d["repainted_positions"]).max() > 1e-2  # the mask changes the pose
    if native(blender):  # and what Blender draws
        np.testing.assert_allclose(d[f"masked_{mode}_display"], d[f"masked_{mode}_positions"], rtol=0, atol=1e-6)


def test_reading_weights_leaves_the_users_depsgraph_alone(blender):
    """The first pose of a splat mesh reads its vertex groups through a temporary object: that object
    lives in a scene of its own, so a depsgraph the caller holds is not re-evaluated with it and then
    left pointing at it once freed (a crash when the caller went on to read its instances)."""
    res = blender.step("weights_read_aside")
    assert res["scene"] not in res["evaluated"]
    assert res["instances"][0] == res["instances"][1]
    assert res["unchanged"]
    assert res["cached"] == [True, True]  # the read of the mask does not drop the weights just read
    assert res["moved"] > 1e-2


@pytest.mark.parametrize("mode", ["lbs", "dqs"])
def test_rigidly_bound_splats_turn_and_stretch_with_their_bone(blender, mode):
    """A splat in one group moves by that bone's deform matrix D (object space) exactly: its
    covariance becomes L Sigma L^T, L the linear part of D, whatever D's scale."""
    d = blender.npz("skinning")
    names = list(d["bones"])
    w = d["weights"]
    deforming = [names.index(b) for b in RIG_BONES if RIG_BONES[b][5]]
    single = np.flatnonzero(((w[:, deforming] > 0).sum(axis=1) == 1) & (w[:, names.index("Ctrl")] == 0))
    assert len(single) >= 100
    bone = np.array(deforming)[np.argmax(w[single][:, deforming], axis=1)]
    lin = d["deform"][bone, :3, :3]
    rest = covariances(d["rest_rotations"][single], d["rest_log_scales"][single])
    expected = lin @ rest @ np.swapaxes(lin, 1, 2)
    posed = covariances(d[f"{mode}_rotations"][single], d[f"{mode}_log_scales"][single])
    size = np.abs(expected).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(posed / size, expected / size, atol=2e-5)
    assert {names[b] for b in bone} == {"Root", "Mid", "Side", "Tip"}


# binding ----------------------------------------------------------------------------------------------


def test_weights_transfer_exactly_from_the_skinned_mesh(blender):
    res = blender.step("transfer")
    assert res["bind"]["result"] == ["FINISHED"]
    assert res["form"] == ("NATIVE" if native(blender) else "MESH")
    assert sorted(res["groups"]) == ["Base", "Fore", "Hand", "Upper"]  # vertex groups, or weight attributes
    assert res["armature"] == "Demo Arm Rig"
    assert res["modifiers"] == ([] if native(blender) else [["ARMATURE", "Demo Arm Rig"], ["NODES", None]])
    assert res["parent"] == "Demo Arm Rig" and res["matrix_kept"]
    d = blender.npz("transfer")
    corners = d["source_vertices"].astype(int)
    expected = np.einsum("nk,nkb->nb", d["barycentric"].astype(np.float64), d["source"][corners])
    expected /= expected.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(d["weights"], expected, atol=2e-6)
    assert ((d["weights"] > 0).sum(axis=1) > 1).mean() > 0.2  # joints blend


def test_a_lost_source_mesh_falls_back_to_bone_weights(blender):
    orphan = blender.step("transfer")["orphan"]
    assert orphan["source"] == "bones"
    assert any("source mesh 'Demo Arm' is gone" in w for w in orphan["warnings"])


def test_one_influence_keeps_the_largest_bone(blender):
    assert blender.step("transfer")["single"]["result"] == ["FINISHED"]
    d, single = blender.npz("transfer"), blender.npz("transfer_single")["weights"]
    np.testing.assert_array_equal((single > 0).sum(axis=1), 1)
    np.testing.assert_allclose(single.sum(axis=1), 1.0, atol=1e-6)
    clear = np.sort(d["weights"], axis=1)[:, -1] > np.sort(d["weights"], axis=1)[:, -2] + 1e-4
    np.testing.assert_array_equal(np.argmax(single, axis=1)[clear], np.argmax(d["weights"], axis=1)[clear])


def test_weights_from_bones_follow_segment_distances(blender):
    """Without a source mesh: (d_min / d_b)^4 over the deforming bones' rest segments (armature
    space), weights under 1% dropped, the two largest kept, normalised."""
    res = blender.step("bone_weights")
    assert res["bind"]["result"] == ["FINISHED"] and res["preserve_volume"] is True
    assert res["preserve_volume_stored"] is True  # the modifier's, or the native splats' property
    if native(blender):  # what Blender draws right after binding: the posed splats, not the rest
        to_posed, to_rest = res["drawn_posed"]
        assert to_posed <= 1e-6 and to_rest > 0.1
    assert sorted(res["groups"]) == ["Mid", "Root", "Side", "Tip"]  # Ctrl does not deform
    d = blender.npz("bone_weights")
    names = list(d["bones"])
    deforming = [names.index(b) for b in RIG_BONES if RIG_BONES[b][5]]
    points = d["positions"] @ d["to_arm"][:3, :3].T + d["to_arm"][:3, 3]
    dist = segment_distances(points, d["heads"][deforming], d["tails"][deforming])
    raw = (dist.min(axis=1, keepdims=True) / dist) ** 4
    raw[raw < 0.01 * raw.sum(axis=1, keepdims=True)] = 0.0
    order = np.argsort(-raw, axis=1)
    raw[np.arange(len(raw))[:, None], order[:, 2:]] = 0.0
    expected = np.zeros_like(d["weights"])
    expected[:, deforming] = raw / raw.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(d["weights"], expected, atol=2e-6)
    assert ((d["weights"] > 0).sum(axis=1) == 2).any()


# rendering --------------------------------------------------------------------------------------------


def test_posed_splat_avatar_renders_like_splats_of_the_posed_mesh(blender):
    """The demo arm bent at frame 12: its bound splats against splats made from the posed mesh, over
    the box around both renders (the background would flatter the number)."""
    res = blender.step("render")
    assert res["bind"]["result"] == ["FINISHED"] and res["engine"]["result"] == ["FINISHED"]
    d = blender.npz("render")
    covered = (d["ours_alpha"] > 0.01) | (d["reference_alpha"] > 0.01)
    rows, cols = np.nonzero(covered)
    box = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    scores = {
        name: psnr(d[f"{name}_color"][box], d["reference_color"][box]) for name in ("ours", "centres_only", "rest")
    }
    print(
        f"\nposed splats vs splats of the posed mesh, {RENDER_SIZE} px, over "
        f"{np.ptp(rows) + 1}x{np.ptp(cols) + 1} px: "
        f"PSNR {scores['ours']:.1f} dB (whole image {psnr(d['ours_color'], d['reference_color']):.1f} dB); "
        f"centres only {scores['centres_only']:.1f} dB; unposed {scores['rest']:.1f} dB"
    )
    assert scores["ours"] >= 30.0
    assert scores["centres_only"] < scores["ours"] - 3 and scores["rest"] < 20
    # the render engine poses the same splats through its own render depsgraph
    channels = read_exr(blender.out / "engine.exr")
    engine = linear_to_srgb(np.stack([channels[c] for c in "RGB"], axis=-1))
    np.testing.assert_allclose(engine, np.clip(d["ours_color"], 0, 1), atol=1e-3)


# bad input ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, words",
    [
        ("active not an armature", ["not an armature"]),
        ("unknown armature", ["no object named 'Nope'"]),
        ("camera as armature", ["'Camera'", "not an armature"]),
        ("no active object", ["no armature given"]),
        ("no splat objects", ["no splat objects", "'Demo Arm'"]),
        ("nothing selected", ["no splat objects"]),
        ("unknown object", ["no object named 'Nope'"]),
        ("same object", ["itself"]),
        ("not splats", ["'Demo Arm'", "not a splat object"]),
        ("backwards", ["ends before it starts"]),
        ("unknown bone", ["no bones named Nope"]),
    ],
)
def test_bad_input_reports_and_changes_nothing(blender, name, words):
    case = blender.step("errors")[name]
    assert case["result"] == ["CANCELLED"] and case["unchanged"]
    for word in words:
        assert word in case["error"]
    assert case.get("frame", 1) == 1


# collisions ------------------------------------------------------------------------------------------------


def contact_sigma_brute(mean_a, cov_a, mean_b, cov_b, samples=401, refine=60):
    """Brute force: mu = sqrt(max_s f(s)), f(s) = s(1-s) d^T (s A + (1-s) B)^-1 d, by a grid over s in
    (0, 1), then a ternary search (f is concave) between the best grid point's neighbours."""
    d = mean_a - mean_b

    def f(s):  # s: (S, P) -> (S, P)
        m = s[..., None, None] * cov_a + (1 - s[..., None, None]) * cov_b
        x = np.linalg.solve(m, np.broadcast_to(d[..., None], m.shape[:-1] + (1,)))[..., 0]
        return s * (1 - s) * np.einsum("spi,pi->sp", x, d)

    grid = np.linspace(0, 1, samples)
    best = np.argmax(f(np.broadcast_to(grid[1:-1, None], (samples - 2, len(d)))), axis=0) + 1
    lo, hi = grid[best - 1], grid[best + 1]
    for _ in range(refine):
        a, b = lo + (hi - lo) / 3, hi - (hi - lo) / 3
        fa, fb = f(np.stack([a, b]))
        lo, hi = np.where(fa < fb, a, lo), np.where(fa < fb, hi, b)
    return np.sqrt(np.maximum(f(0.5 * (lo + hi)[None])[0], 0.0))


def small_case(d, key, frame):
    mean = d[f"{key}{frame}_positions"].astype(np.float64)
    cov = covariances(d[f"{key}{frame}_rotations"], d[f"{key}{frame}_log_scales"])
    opacity = 1 / (1 + np.exp(-d[f"{key}{frame}_opacity_logits"].astype(np.float64)))
    return mean, cov, opacity


def test_small_collision_case_against_brute_force_and_the_core(blender):
    from splatwright.core import SplatCloud
    from splatwright.core.collision import ellipsoid_contacts

    res = blender.step("collide_small")
    assert res["bind"]["result"] == ["FINISHED"] and res["op"]["result"] == ["FINISHED"]
    assert res["frame_after"] == 2
    d = blender.npz("collide_small")
    main_bone = np.argmax(d["weights"], axis=1)
    hits = {"a": np.zeros(len(d["contact_a"])), "b": np.zeros(len(d["contact_b"]))}
    for frame, found in zip((1, 2, 3), res["report"]["frames"]):
        (ma, ca, oa), (mb, cb, ob) = small_case(d, "a", frame), small_case(d, "b", frame)
        ka, kb = np.flatnonzero(oa >= 0.05), np.flatnonzero(ob >= 0.05)
        pa, pb = np.repeat(ka, len(kb)), np.tile(kb, len(ka))
        near = np.linalg.norm(ma[pa] - mb[pb], axis=1) <= 3.0 * (
            np.sqrt(np.linalg.eigvalsh(ca[pa])[:, 2]) + np.sqrt(np.linalg.eigvalsh(cb[pb])[:, 2])
        )
        pa, pb = pa[near], pb[near]
        mu = contact_sigma_brute(ma[pa], ca[pa], mb[pb], cb[pb])
        assert np.all(np.abs(mu - 3.0) > 1e-6)  # no pair on the fence
        touching = mu <= 3.0
        assert found["frame"] == frame and found["pairs"] == touching.sum()
        hits["a"][np.unique(pa[touching])] += 1
        hits["b"][np.unique(pb[touching])] += 1
        bones = np.bincount(main_bone[np.unique(pa[touching])], minlength=2)
        assert found["bones_a"] == {n: int(c) for n, c in zip(("Lower", "Upper"), bones) if c}
        # the core called directly on the same clouds agrees
        cloud = lambda key: SplatCloud(
            *(d[f"{key}{frame}_{f}"] for f in ("positions", "rotations", "log_scales", "opacity_logits")),
            np.zeros((len(d[f"{key}{frame}_positions"]), 1, 3)),
        )
        core = ellipsoid_contacts(cloud("a")[ka], cloud("b")[kb], k=3.0)
        assert len(core) == found["pairs"]
    assert res["report"]["contact_frames"] == [3]
    assert hits["b"][:5].sum() == 0  # faint splats are left out
    np.testing.assert_allclose(d["contact_a"], hits["a"] / 3, atol=1e-7)
    np.testing.assert_allclose(d["contact_b"], hits["b"] / 3, atol=1e-7)
    assert d["contact_a"].max() == pytest.approx(1 / 3)


def test_demo_arm_touches_the_box_only_when_bent(blender):
    res = blender.step("collide_demo")
    assert res["bind"]["result"] == ["FINISHED"] and res["op"]["result"] == ["FINISHED"]
    frames = {f["frame"]: f for f in res["report"]["frames"]}
    contact = res["report"]["contact_frames"]
    print(
        f"\ndemo arm vs environment: contact at frames {contact}; frame {BENT_FRAME}: {frames[BENT_FRAME]['bones_a']}"
    )
    assert BENT_FRAME in contact and 1 not in contact and 24 not in contact
    assert set(frames[BENT_FRAME]["bones_a"]) <= {"Fore", "Hand"} and frames[BENT_FRAME]["bones_a"]
    assert res["contact_splats"] > 0 and 0 < res["contact_max"] <= len(contact) / 24 + 1e-6
    assert "splat_contact" not in res["exported_extras"] and "contact" not in res["exported_extras"]
    # without leaving the base out, the base stands on the floor at every frame
    assert res["with_base"]["frames"][0]["bones_a"].get("Base", 0) > 0


def test_cli_collide(blender):
    cli = blender.step("collide_demo")["cli"]
    ok = cli["ok"]
    assert ok["code"] == 0, ok["stderr"]
    lines = ok["stdout"].splitlines()
    assert lines[0].startswith("splatwright: collide 'Demo Arm_splats' with 'Demo Environment_splats', frames 1-12 (2)")
    assert "[2/2] frame 12:" in ok["stdout"] and "Fore" in lines[2] and lines[-1].startswith("splatwright: done:")
    report = json.loads((blender.out / "collide.json").read_text())
    assert report["contact_frames"] == [12] and [f["frame"] for f in report["frames"]] == [1, 12]
    for name, words in (
        ("unknown", "no object named 'Nope'"),
        ("bad sigma", "must be positive"),
        ("missing folder", "does not exist"),
    ):
        assert cli[name]["code"] == 1 and words in cli[name]["stderr"]
    assert not (blender.out / "nowhere").exists()
