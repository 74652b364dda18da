"""The main job and the economies.

The demo runs as a user runs it (`python -m splatwright demo --out DIR`, bpy in that process) and
every output is judged by another reader: PNG by Pillow, EXR by OpenEXR, PLY by plyfile, OpenUSD by
pxr, against the numbers the summary prints. The economies are checked against independent
computations: float64 brute-force blending weights per splat, opacity masks computed here, pxr's
view of half-float attributes, and PSNR recomputed from renders.
"""

import json
import re
import subprocess
import sys

import numpy as np
import plyfile
import pytest
from helpers import random_cloud
from reference_render import ALPHA_MAX, ALPHA_MIN, T_MIN, _project_all

from splatwright.cli import main
from splatwright.core import SplatCloud, economy
from splatwright.core.camera import Camera
from splatwright.core.render import render
from splatwright.io import ply, read_splats, usd

RENDER_FRAMES = (6, 12, 18, 24)
WALL = 21 * 21


# blending weights: brute force ----------------------------------------------------------------------


def brute_contributions(cloud, camera):
    """(N,) largest T * alpha of each splat over every pixel, by the reference rasteriser's rules
    written out pixel-parallel and splat by splat, in float64."""
    splats = _project_all(cloud, camera, "classic")
    # _project_all's splats, in its order: finite, inside the clip range, stable by float32 depth
    fields = (
        cloud.positions,
        cloud.rotations,
        cloud.log_scales,
        cloud.opacity_logits[:, None],
        cloud.sh.reshape(len(cloud), -1),
    )
    idx = np.flatnonzero(np.all([np.isfinite(f).all(axis=1) for f in fields], axis=0))
    z = camera.to_camera(cloud.positions[idx])[:, 2]
    idx, z = idx[(z > camera.near) & (z <= camera.far)], z[(z > camera.near) & (z <= camera.far)]
    idx = idx[np.argsort(z.astype(np.float32), kind="stable")]
    assert len(idx) == len(splats["z"])
    rows, cols = np.mgrid[0 : camera.height, 0 : camera.width]
    px, py = cols.ravel() + 0.5, rows.ravel() + 0.5
    trans, done = np.ones(len(px)), np.zeros(len(px), bool)
    best = np.zeros(len(cloud))
    for k, i in enumerate(idx):
        dx, dy = px - splats["mean"][k, 0], py - splats["mean"][k, 1]
        con = splats["conic"][k]
        alpha = np.minimum(
            ALPHA_MAX,
            splats["opacity"][k] * np.exp(-0.5 * (con[0, 0] * dx * dx + 2 * con[0, 1] * dx * dy + con[1, 1] * dy * dy)),
        )
        use = ~done & (alpha >= ALPHA_MIN)
        after = trans * (1.0 - alpha)
        stop = use & (after < T_MIN)
        done |= stop
        use &= ~stop
        best[i] = np.where(use, trans * alpha, 0.0).max(initial=0.0)
        trans = np.where(use, after, trans)
    return best


def hard_cloud():
    """Random splats behind an opaque wall, plus the hard cases: behind and on the near plane,
    off-image, too faint for 1/255, needles, pancakes, tiny and huge scales, identical depths,
    non-unit and zero quaternions, NaN."""
    cloud = random_cloud(150, sh_degree=1, seed=7, spread=0.6)
    cloud.positions[:, 2] += 3.0
    cloud.opacity_logits[:] = np.abs(cloud.opacity_logits) - 1.0
    grid = np.linspace(-1.0, 1.0, 21)
    wall = SplatCloud.from_activated(
        positions=np.column_stack([np.repeat(grid, 21), np.tile(grid, 21), np.full(WALL, 2.0)]),
        rotations=np.tile([1.0, 0, 0, 0], (WALL, 1)),
        scales=np.tile([0.15, 0.15, 0.001], (WALL, 1)),
        opacities=np.full(WALL, 0.999),
        colors=np.full((WALL, 3), 0.5),
    )
    wall = wall.replace(sh=np.concatenate([wall.sh, np.zeros((WALL, 3, 3))], axis=1))
    extra = random_cloud(12, sh_degree=1, seed=8, spread=0.1)
    extra.positions[:] = [
        [0, 0, -1],
        [0, 0, 0.25],
        [40, 0, 3],
        [0.1, 0.1, 3],
        [0.2, 0, 2.5],
        [0.2, 0.1, 2.5],
        [0.3, -0.2, 2.5],
        [-0.3, 0.3, 2.7],
        [-0.3, 0.3, 2.7],
        [0, 0.3, 1.0],
        [0.1, 0, 1.5],
        [0, 0, 3],
    ]
    extra.opacity_logits[:] = 3.0
    extra.opacity_logits[3] = np.log((1 / 300) / (1 - 1 / 300))  # never reaches 1/255
    extra.log_scales[4] = np.log([0.3, 1e-4, 1e-4])  # needle
    extra.log_scales[5] = np.log([0.2, 0.2, 1e-6])  # pancake
    extra.log_scales[6] = np.log(1e-7)  # tiny
    extra.log_scales[9] = np.log(1e4)  # huge (faint)
    extra.opacity_logits[9] = -4.0
    extra.rotations[10] = 0.0  # zero quaternion
    extra.rotations[7] *= 1e3
    extra.positions[11, 0] = np.nan
    return SplatCloud.concatenate([wall, cloud, extra])


def views_for(cloud):
    straight = Camera.look_at((0, 0, 0), (0, 0, 3), up=(0, -1, 0), fov_deg=50, width=40, height=30, near=0.25)
    return [
        straight,
        Camera.look_at((0, 0, 0), (0, 0, 3), fov_deg=170, width=24, height=20),
        Camera.look_at((0.5, 0.2, 0), (0, 0, 3), fov_deg=40, width=1, height=1),
        Camera.look_at((0, 0, 0), (0.2, 0.3, 2.5), fov_deg=0.5, width=16, height=12),
        *economy.orbit_views(economy.cloud_points(cloud), count=2, width=32, height=24),
    ]


def test_contributions_equal_float64_brute_force_on_hard_cases():
    cloud = hard_cloud()
    views = views_for(cloud)
    with np.errstate(all="ignore"):
        want = np.max([brute_contributions(cloud, cam) for cam in views], axis=0)
    got = economy.contributions(cloud, views)
    assert got.shape == (len(cloud),) and got.dtype == np.float32 and np.isfinite(got).all()
    np.testing.assert_array_equal(got > 0, want > 0)
    np.testing.assert_allclose(got, want, atol=2e-6)
    straight = economy.contributions(cloud, views[:1])
    middle = slice(WALL, WALL + 150)
    behind = (np.abs(cloud.positions[middle, :2]).max(axis=1) < 0.25) & (cloud.positions[middle, 2] > 2.3)
    hidden = np.arange(len(cloud))[middle][behind]
    assert len(hidden) > 10 and not straight[hidden].any()  # behind the opaque wall
    n = len(cloud)
    assert not straight[n - 12 : n - 9].any()  # behind, on near, off-image
    assert got[n - 9] == 0 and got[n - 1] == 0  # too faint; NaN
    assert (got[n - 8 : n - 5] > 0).all()  # needle, pancake, tiny: seen


def test_contributions_follow_the_stop_rule():
    """Three broad splats of opacity 0.98 in a row, filling the view: the third would take T below
    1e-4 (0.02^3 = 8e-6), so every pixel stops before it and it adds nothing, nor do the two small
    splats behind it."""
    stack = SplatCloud.from_activated(
        positions=[[0, 0, 2.0], [0, 0, 2.1], [0, 0, 2.2], [0, 0, 2.3], [0.001, 0, 2.4]],
        rotations=np.tile([1.0, 0, 0, 0], (5, 1)),
        scales=[[1, 1, 1]] * 3 + [[0.001] * 3] * 2,
        opacities=[0.98] * 3 + [0.9] * 2,
        colors=np.full((5, 3), 0.5),
    )
    cam = Camera.look_at((0, 0, 0), (0, 0, 1), fov_deg=10, width=9, height=9)
    want = brute_contributions(stack, cam)
    got = economy.contributions(stack, [cam])
    assert (want[:2] > 0).all() and (want[2:] == 0).all()
    # the second splat's weight is T * alpha with T = 1 - 0.98 g: the compiled compositor's exp (4e-7
    # relative) comes out 20x larger in T, as any rounding of alpha near 1 does
    np.testing.assert_allclose(got, want, atol=1e-6)
    np.testing.assert_array_equal(got > 0, want > 0)


def test_pruning_invisible_splats_leaves_the_renders_of_those_views_unchanged():
    cloud = hard_cloud()
    cloud = cloud[cloud.finite_mask()]
    views = views_for(cloud)
    keep = economy.visible_mask(cloud, views)
    assert 0 < keep.sum() < len(cloud)
    for cam in views:
        full, kept = render(cloud, cam), render(cloud[keep], cam)
        # only the stop rule can tell them apart: a splat that stops a pixel adds no weight itself
        assert np.abs(full.color - kept.color).max() <= 2 * T_MIN
        assert np.abs(full.alpha - kept.alpha).max() <= 2 * T_MIN
    faint = economy.visible_mask(cloud, views, min_weight=0.05)
    want = np.max([brute_contributions(cloud, cam) for cam in views], axis=0) > 0.05
    np.testing.assert_array_equal(faint, want)


def test_opacity_mask_and_bad_thresholds():
    cloud = random_cloud(1000, seed=3)
    direct = 1.0 / (1.0 + np.exp(-cloud.opacity_logits.astype(np.float64))) >= 0.3
    np.testing.assert_array_equal(economy.opacity_mask(cloud, 0.3), direct)
    assert economy.opacity_mask(cloud, 0.0).all() and not economy.opacity_mask(cloud, 1.0).any()
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="opacity threshold"):
            economy.opacity_mask(cloud, bad)


def test_orbit_views_frame_every_point_from_spread_directions():
    cloud = random_cloud(400, seed=5, spread=2.0)
    cloud.positions[:, 0] += 1e3
    points = economy.cloud_points(cloud)
    views = economy.orbit_views(points, count=6, width=64, height=48)
    between = economy.orbit_views(points, count=6, width=64, height=48, phase=0.5)
    centre = (points.min(axis=0).astype(np.float64) + points.max(axis=0)) / 2
    for cam in views + between:
        uv, z = cam.project(points)
        assert (z > cam.near).all() and (uv >= 0).all() and (uv[:, 0] <= 64).all() and (uv[:, 1] <= 48).all()
        np.testing.assert_allclose(cam.forward, (centre - cam.center) / np.linalg.norm(centre - cam.center), atol=1e-12)
    directions = np.array([-c.forward for c in views + between])
    cosines = directions @ directions.T - 2 * np.eye(12)
    assert cosines.max() < 0.95  # twelve different directions
    assert abs(directions.sum(axis=0)).max() < 0.5 * 12 / 4  # spread around, not to one side
    with pytest.raises(ValueError):
        economy.orbit_views(points, count=0)


def test_image_error_is_rgba_psnr_and_max_abs():
    cloud = random_cloud(300, seed=9)
    cloud.positions[:, 2] += 4
    views = economy.orbit_views(economy.cloud_points(cloud), count=3, width=40, height=30)
    changed = cloud.replace(sh=cloud.sh * 0.9)[:250]
    error = economy.image_error(cloud, changed, views)
    a = [render(cloud, cam, background=None) for cam in views]
    b = [render(changed, cam, background=None) for cam in views]
    rgba = lambda r: np.clip(np.concatenate([r.color, r.alpha[..., None]], axis=2).astype(np.float64), 0, 1)
    diff = np.concatenate([(rgba(x) - rgba(y)).ravel() for x, y in zip(a, b)])
    assert error.psnr == pytest.approx(10 * np.log10(1 / np.mean(diff**2)), rel=1e-9)
    assert error.max_abs == pytest.approx(np.abs(diff).max(), rel=1e-6)
    assert len(error.view_psnr) == 3
    same = economy.image_error(economy.render_views(cloud, views), cloud, views)
    assert same.psnr == float("inf") and same.max_abs == 0.0
    empty = SplatCloud.empty(1)
    assert economy.image_error(empty, empty, economy.orbit_views(economy.cloud_points(empty), 2, 1)).psnr == float(
        "inf"
    )


# convert with economies -----------------------------------------------------------------------------


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def table(out):
    """The economy table: {label: [numbers...]} (splats, bytes and, when checked, PSNR and max abs)."""
    rows = {}
    for line in out.splitlines()[1:]:
        if line.startswith(("error:", "wrote ")):
            continue
        label, rest = line[:34].strip(), line[34:]
        rows[label] = [float(x) for x in re.findall(r"(?<![\d.])[+-]?(?:\d+\.?\d*|inf)(?![\d.]*%)", rest)]
    return rows


@pytest.fixture
def source(tmp_path):
    cloud = random_cloud(1500, sh_degree=3, seed=21, spread=0.5)
    cloud.log_scales[:] -= 0.5
    path = tmp_path / "in.ply"
    ply.write(path, cloud)
    return path, cloud


def test_convert_prune_opacity_matches_a_direct_mask(capsys, source, tmp_path):
    path, cloud = source
    out_path = tmp_path / "out.ply"
    code, out, err = run(capsys, "convert", path, out_path, "--prune-opacity", 0.4, "--no-check")
    assert code == 0, err
    keep = 1.0 / (1.0 + np.exp(-cloud.opacity_logits.astype(np.float64))) >= 0.4
    vertex = plyfile.PlyData.read(str(out_path))["vertex"]
    assert vertex.count == keep.sum() < len(cloud)
    np.testing.assert_array_equal(np.column_stack([vertex["x"], vertex["y"], vertex["z"]]), cloud.positions[keep])
    rows = table(out)
    assert "PSNR" not in out and rows["as .ply"] == [1500, path.stat().st_size]
    assert rows["prune opacity < 0.4"] == [keep.sum(), out_path.stat().st_size]
    assert f"wrote {keep.sum()} splats (SH degree 3)" in out


def test_convert_half_usd_stays_within_half_rounding_and_prints_the_measured_error(capsys, source, tmp_path):
    path, cloud = source
    out_path = tmp_path / "out.usdc"
    code, out, err = run(capsys, "convert", path, out_path, "--half", "--views", 4, "--view-size", 48)
    assert code == 0, err
    from pxr import Usd

    stage = Usd.Stage.Open(str(out_path))
    prim = stage.GetPrimAtPath("/Splats")
    values = {a.GetName(): np.asarray(a.Get()) for a in prim.GetAttributes() if a.HasAuthoredValue()}
    half_bound = lambda got, want: np.abs(got - want) <= np.maximum(2.0**-11 * np.abs(want), 2.0**-25)
    assert values["scalesh"].dtype == np.float16
    assert half_bound(values["scalesh"].astype(np.float64), np.exp(cloud.log_scales.astype(np.float64))).all()
    opacity = 1.0 / (1.0 + np.exp(-cloud.opacity_logits.astype(np.float64)))
    assert half_bound(values["opacitiesh"].astype(np.float64), opacity).all()
    sh = np.abs(values["radiance:sphericalHarmonicsCoefficientsh"].astype(np.float64)).reshape(len(cloud), 16, 3)
    assert half_bound(sh, np.abs(cloud.sh.astype(np.float64))).all()
    # the printed error, recomputed from renders of the written file
    rows = table(out)
    assert rows["half floats"][:2] == [1500, out_path.stat().st_size]
    assert rows["half floats"][1] < 0.6 * rows["as .usdc"][1]
    views = economy.orbit_views(economy.cloud_points(cloud), count=4, width=48, phase=0.5)
    back = usd.read(out_path)
    diffs = []
    for cam in views:
        want, got = render(cloud, cam, background=None), render(back, cam, background=None)
        diffs.append(
            np.clip(np.dstack([got.color, got.alpha]), 0, 1).astype(np.float64)
            - np.clip(np.dstack([want.color, want.alpha]), 0, 1)
        )
    diff = np.concatenate([d.ravel() for d in diffs])
    psnr_db, max_abs = rows["half floats"][2:]
    assert psnr_db == pytest.approx(10 * np.log10(1 / np.mean(diff**2)), abs=0.006)
    assert max_abs == pytest.approx(np.abs(diff).max(), abs=6e-5)
    assert psnr_db > 50 and rows["as .usdc"][2:] == [float("inf"), 0.0]


def test_convert_sh_degree_saves_exact_bytes_and_prune_invisible_drops_the_hidden_core(capsys, tmp_path):
    # an opaque shell of flat splats around a core that no outside view can see
    rng = np.random.default_rng(4)
    normals = rng.normal(size=(4000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    shell = SplatCloud.from_activated(
        positions=normals,
        rotations=np.tile([1.0, 0, 0, 0], (4000, 1)),
        scales=np.full((4000, 3), 0.1),
        opacities=np.full(4000, 0.99),
        colors=rng.uniform(0, 1, (4000, 3)),
    )
    core = random_cloud(500, sh_degree=0, seed=5, spread=0.15)
    core = core.replace(opacity_logits=np.full(500, 4.0, np.float32), log_scales=np.full((500, 3), np.log(0.03)))
    cloud = SplatCloud.concatenate([shell, core])
    cloud = cloud.replace(sh=np.concatenate([cloud.sh, rng.normal(0, 0.05, (4500, 3, 3))], axis=1))
    path, out_path = tmp_path / "ball.ply", tmp_path / "small.ply"
    ply.write(path, cloud)
    code, out, err = run(
        capsys, "convert", path, out_path, "--prune-invisible", "--sh-degree", 0, "--views", 8, "--view-size", 64
    )
    assert code == 0, err
    back = ply.read(out_path)
    inside = np.linalg.norm(back.positions, axis=1) < 0.7
    assert not inside.any() and len(back) > 3900  # the core is gone, the shell is kept
    rows = table(out)
    pruned, reduced = rows["prune invisible"], rows["SH degree 1 -> 0"]
    header = sum(len(f"property float f_rest_{j}\n") for j in range(9))
    assert pruned[1] - reduced[1] == len(back) * 9 * 4 + header  # nine f_rest floats per splat
    assert reduced[:2] == [len(back), out_path.stat().st_size]
    assert pruned[2] > 40 and reduced[2] < pruned[2]  # hidden splats cost nothing; SH does


def test_convert_refuses_bad_economy_options(capsys, source, tmp_path):
    path, _ = source
    for argv, words in (
        (("--prune-opacity", 1.5), "--prune-opacity must be an opacity from 0 to 1, got 1.5"),
        (("--prune-invisible", "--views", 0), "--views must be a whole number from 1 to 1000"),
    ):
        assert main(["convert", str(path), str(tmp_path / "o.ply"), *map(str, argv)]) == 1
        assert words in capsys.readouterr().err
    assert not (tmp_path / "o.ply").exists()


# the demo --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "splatwright", "demo", "--out", str(out)], capture_output=True, text=True, timeout=600
    )
    log = f"exit {proc.returncode}\n--- stdout\n{proc.stdout[-6000:]}\n--- stderr\n{proc.stderr[-4000:]}"
    assert proc.returncode == 0, log
    return out, proc.stdout, json.loads((out / "summary.json").read_text())


@pytest.mark.blender
@pytest.mark.slow
def test_demo_runs_every_step_and_names_its_folder(demo):
    out, stdout, summary = demo
    for k in range(1, 10):
        assert f"[{k}/9] " in stdout
    assert f"summary (every output is in {out.resolve()}):" in stdout
    assert summary["outputs"] == str(out.resolve())
    steps = {k: v for k, v in summary["seconds"].items() if k != "total"}  # timed in bench/, not here
    assert len(steps) == 9 and 0 < sum(steps.values()) <= summary["seconds"]["total"] + 0.01
    for name, size in summary["files"].items():
        assert (out / name).stat().st_size == size > 0
    assert len(summary["files"]) == len([p for p in out.rglob("*") if p.is_file()]) - 1  # + summary.json


@pytest.mark.blender
@pytest.mark.slow
def test_demo_pose_check_parses_and_clears_30_db(demo):
    _, stdout, summary = demo
    printed = re.search(r"frame 12: PSNR ([\d.]+) dB \(centres only: ([\d.]+) dB\)", stdout)
    assert printed, stdout
    pose = summary["pose_check"]
    assert float(printed.group(1)) == pose["psnr_db"] >= 30
    assert float(printed.group(2)) == pose["centres_only_psnr_db"] < pose["psnr_db"] - 3
    assert summary["binding"]["weights_from"] == "mesh 'Demo Arm'" and summary["binding"]["unbound"] == 0


@pytest.mark.blender
@pytest.mark.slow
def test_demo_png_and_exr_frames_show_the_posed_arm(demo):
    """The arm's splats stand on the environment's meshes: the Meshes pass (Cycles) holds the floor
    and the box, not the arm; the Splats pass holds the arm; Combined is the splats over the meshes."""
    from PIL import Image

    from splatwright.core.color import linear_to_srgb
    from splatwright.demo import WORLD_COLOR
    from splatwright.io.exr import read_exr

    out, _, summary = demo
    assert summary["render"]["frames"] == list(RENDER_FRAMES) and summary["render"]["meshes"] == "Cycles"
    png = {}
    for frame in RENDER_FRAMES:
        image = Image.open(out / "render" / f"frame_{frame:04d}.png")
        assert image.size == (480, 360)
        png[frame] = np.asarray(image.convert("RGB"), np.float64) / 255
        path = out / "render" / f"frame_{frame:04d}.exr"
        channels = {k: v for part in range(4) for k, v in read_exr(path, part=part).items()}
        rgb, meshes, splats = (
            np.dstack([channels[f"ViewLayer.{name}.{c}"] for c in "RGBA"]) for name in ("Combined", "Meshes", "Splats")
        )
        assert rgb.shape == (360, 480, 4) and np.isfinite(rgb).all()
        # Standard view transform: the PNG is the EXR's scene-linear colour in sRGB (dither aside)
        assert np.abs(linear_to_srgb(np.clip(rgb[..., :3], 0, 1)) - png[frame]).max() < 3 / 255
        depth = channels["ViewLayer.Depth.Z"]
        hit = depth < 1e9
        assert 0.3 < hit.mean() < 0.9  # the floor, the box and the arm, not the sky
        z = depth[hit]
        assert 3 < z.min() and z.max() < 25  # the camera is ~9 m from the arm
        sky = linear_to_srgb(np.array(WORLD_COLOR))
        # the sky, but for the outlines (Cycles' depth is one sample's, its colour filtered)
        assert (np.abs(png[frame][~hit] - sky).max(axis=-1) <= 2 / 255).mean() > 0.99
        arm = splats[..., 3] > 0.5
        assert 1000 < arm.sum() < 0.3 * arm.size  # the arm's splats, in front of the meshes
        assert (meshes[..., 3] == 1).all()  # the film is opaque: Cycles' world included
        # where the arm covers the floor, Combined shows the arm, not the floor behind it
        assert np.abs(rgb[..., :3] - meshes[..., :3])[splats[..., 3] > 0.99].max(axis=-1).mean() > 0.05
    moved = np.abs(png[12] - png[24]).max(axis=2) > 0.1
    assert moved.sum() > 500  # bent at 12, at rest at 24


@pytest.mark.blender
@pytest.mark.slow
def test_demo_exports_read_back_consistently(demo):
    from pxr import Usd, UsdGeom

    from splatwright import demo as demo_module

    out, _, summary = demo
    arm, env = demo_module.ARM_SPLATS, demo_module.ENVIRONMENT_SPLATS
    assert summary["arm_splats"] == arm and summary["environment_splats"] == env
    scene = plyfile.PlyData.read(str(out / "scene_0012.ply"))["vertex"]
    assert scene.count == arm + env == summary["exports"]["ply_splats"]
    names = sorted(p.name for p in (out / "arm_ply").iterdir())
    assert names == [f"arm_{f:04d}.ply" for f in range(1, 25)]
    frames = {f: read_splats(out / "arm_ply" / f"arm_{f:04d}.ply") for f in (1, 12, 24)}
    assert all(len(c) == arm for c in frames.values())
    # exports hold the scene, not the from-mesh bookkeeping that ties splats to their triangles
    provenance = ("source_triangle", "barycentric", "source_vertices")
    assert not [p.name for p in scene.properties if p.name.startswith(provenance)]
    assert not [k for c in frames.values() for k in c.extras if k.startswith(provenance)]
    xyz = lambda v: np.column_stack([v["x"], v["y"], v["z"]])
    np.testing.assert_array_equal(xyz(scene)[:arm], frames[12].positions)  # the arm comes first
    np.testing.assert_array_equal(frames[1].positions, frames[24].positions)  # rest pose at both ends
    assert np.abs(frames[12].positions - frames[1].positions).max() > 0.5
    stage = Usd.Stage.Open(str(out / "arm.usdc"))
    prims = [p for p in stage.Traverse() if p.GetTypeName() == "ParticleField3DGaussianSplat"]
    assert len(prims) == 1
    positions = prims[0].GetAttribute("positions")
    assert positions.GetTimeSamples() == list(range(1, 25))
    at_12 = np.asarray(positions.Get(12), np.float64)
    assert at_12.shape == (arm, 3)
    # the file holds the model's (3DGS, y down) values under a transform standing them up in
    # OpenUSD's Y-up world: there y and z flip
    world = np.array(UsdGeom.Xformable(prims[0]).ComputeLocalToWorldTransform(12)).T
    np.testing.assert_allclose(at_12 @ world[:3, :3].T + world[:3, 3], frames[12].positions * [1, -1, -1], atol=1e-6)


@pytest.mark.blender
@pytest.mark.slow
def test_demo_collisions_and_extras(demo):
    out, stdout, summary = demo
    contacts = json.loads((out / "contacts.json").read_text())
    hits = summary["collisions"]
    assert hits["contact_frames"] == contacts["contact_frames"]
    assert 12 in hits["contact_frames"] and 1 not in hits["contact_frames"] and 24 not in hits["contact_frames"]
    bent = next(f for f in contacts["frames"] if f["frame"] == 12)
    assert bent["pairs"] == hits["pairs_at_bent_frame"] > 0 and "Base" not in bent["bones_a"]
    assert f"{hits['pairs_at_bent_frame']} splat pairs at frame 12" in stdout
    assert len(read_splats(out / "seed_cube.ply")) == 1000
    assert (out / "demo.blend").stat().st_size > 100_000


def test_demo_fails_clearly_when_it_cannot_write(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    proc = subprocess.run(
        [sys.executable, "-m", "splatwright", "demo", "--out", str(blocker / "out")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1
    assert "splatwright demo: error: cannot create the output folder" in proc.stderr and str(blocker) in proc.stderr


@pytest.mark.blender
@pytest.mark.slow
def test_demo_names_the_step_that_failed(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "render").write_text("a file where the frames' folder goes")
    proc = subprocess.run(
        [sys.executable, "-m", "splatwright", "demo", "--out", str(out)], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert (
        "splatwright demo: error: step 'render PNG and EXR frames: the arm's splats on the meshes' failed"
        in proc.stderr
    )
    assert "[5/9]" in proc.stdout and "[7/9]" not in proc.stdout and "summary" not in proc.stdout
    assert not (out / "summary.json").exists()
