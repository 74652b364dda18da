"""Mesh to splats: splat count against PSNR and SSIM versus Blender Cycles, and conversion speed.

Bench meshes are made here from code: a UV sphere and a torus with procedural textures (smooth
colour fields, soft stripes and dots; a quarter of the torus is a flat-coloured second material)
and, as a stress case, the sphere with a patch of sharp-edged checker squares. They are written as
OBJ + MTL + PNG and read back through io.mesh. The independent reference is Blender Cycles
(headless bpy in a subprocess): emission-only materials so the image is unlit, the 'Standard' view
transform so pixels are sRGB-encoded emission, CPU, black world. Our splats are rendered by
core.render (classic mode unless stated) from four cameras in random directions (fixed seed),
framed like the target mode's own views but not among them. Errors are PSNR (dB, over the four
images together) and mean SSIM.

Rows: the mesh rasteriser the target mode compares against (versus Cycles, and its speed against
Cycles'); uniform budgets as converted, and with the silhouettes calibrated like the target mode
does; the target mode at several targets (the default marked); the default in antialiased mode.
Speed: a 100k-triangle textured sphere to 1M splats, against a straightforward per-triangle Python
loop converter (reimplemented below, timed on a subset and scaled to 100k triangles), next to the
PSNR versus Cycles that each gives at equal splat counts on the bench sphere.

    python bench/mesh2splats.py [--quick]
"""

import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from common import Row, Timing, print_rows, timeit  # noqa: E402

from splatwright.core import SplatCloud  # noqa: E402
from splatwright.core import metrics  # noqa: E402
from splatwright.core.camera import Camera, opengl_camera_to_world  # noqa: E402
from splatwright.core.mesh import Surface  # noqa: E402
from splatwright.core.mesh_refine import default_views  # noqa: E402
from splatwright.core.mesh_render import render_mesh  # noqa: E402
from splatwright.core.mesh_to_splats import DEFAULT_TARGET_PSNR, mesh_to_splats  # noqa: E402
from splatwright.core.render import render  # noqa: E402
from splatwright.io.mesh import read_mesh  # noqa: E402

TOPIC = "mesh2splats"
CYCLES_SAMPLES = 64
LABELS = {"uniform": "even budget, silhouettes calibrated", "target": "target PSNR"}


# bench meshes ------------------------------------------------------------------------------------

def uv_sphere(segments, rings):
    """A closed UV sphere: shared poles and seam positions, per-corner UVs with the seam split."""
    theta = np.linspace(0, np.pi, rings + 1)
    phi = np.linspace(0, 2 * np.pi, segments + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    v = np.stack([np.sin(t) * np.cos(p), np.cos(t), -np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    uv = np.stack([p / (2 * np.pi), 1 - t / np.pi], -1).reshape(-1, 2)
    r, s = (a.ravel() for a in np.meshgrid(np.arange(rings), np.arange(segments), indexing="ij"))
    i = lambda r_, s_: r_ * (segments + 1) + s_
    a, b, c, d = i(r, s), i(r + 1, s), i(r + 1, s + 1), i(r, s + 1)
    f = np.concatenate([np.stack([a, b, c], 1)[r < rings - 1], np.stack([a, c, d], 1)[r > 0]])
    return v, f, uv[f]


def torus(segments, rings, major=1.0, minor=0.38):
    u = np.linspace(0, 2 * np.pi, segments + 1)
    w = np.linspace(0, 2 * np.pi, rings + 1)
    uu, ww = np.meshgrid(u, w, indexing="ij")
    v = np.stack([(major + minor * np.cos(ww)) * np.cos(uu), minor * np.sin(ww),
                  -(major + minor * np.cos(ww)) * np.sin(uu)], -1).reshape(-1, 3)
    uv = np.stack([uu / (2 * np.pi), ww / (2 * np.pi)], -1).reshape(-1, 2)
    s, r = (a.ravel() for a in np.meshgrid(np.arange(segments), np.arange(rings), indexing="ij"))
    i = lambda s_, r_: s_ * (rings + 1) + r_
    a, b, c, d = i(s, r), i(s + 1, r), i(s + 1, r + 1), i(s, r + 1)
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v, f, uv[f]


def sphere_texture(w=1024, h=512, checker=False):
    """Smooth colour fields and soft stripes; `checker` adds a patch of sharp-edged squares."""
    y, x = np.mgrid[:h, :w] / np.array([h, w])[:, None, None]
    r = 0.55 + 0.3 * np.sin(2 * np.pi * 3 * x) * np.cos(2 * np.pi * 2 * y)
    g = 0.5 + 0.3 * np.cos(2 * np.pi * (2 * x + y)) + 0.1 * np.sin(2 * np.pi * 9 * x)
    b = 0.35 + 0.3 * y + 0.15 * np.tanh(3 * np.sin(2 * np.pi * 6 * x))
    img = np.stack([r, g, b], -1)
    if checker:
        patch = (x > 0.55) & (x < 0.8) & (y > 0.3) & (y < 0.6)
        squares = ((np.floor(x * 48) + np.floor(y * 24)) % 2)[..., None]
        img = np.where(patch[..., None], 0.15 + 0.7 * squares * np.array([1.0, 0.9, 0.3]), img)
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def torus_texture(w=1024, h=256):
    y, x = np.mgrid[:h, :w] / np.array([h, w])[:, None, None]
    stripes = 0.5 + 0.5 * np.tanh(2 * np.sin(2 * np.pi * 8 * x))
    dots = np.exp(-((np.sin(np.pi * 16 * x) ** 2 + np.sin(np.pi * 4 * y) ** 2) / 0.15))
    img = np.stack([0.2 + 0.6 * stripes, 0.25 + 0.5 * dots, 0.7 - 0.4 * stripes * y], -1)
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def write_obj(folder, name, v, f, uv, texture, face_materials=None, flat_kd=(0.6, 0.25, 0.05)):
    """OBJ + MTL + PNG; material 'painted' (texture) and, where face_materials is 1, 'flat'."""
    from PIL import Image
    Image.fromarray(texture).save(folder / f"{name}.png")
    (folder / f"{name}.mtl").write_text(f"newmtl painted\nKd 0.8 0.8 0.8\nmap_Kd {name}.png\n"
                                        f"newmtl flat\nKd {flat_kd[0]} {flat_kd[1]} {flat_kd[2]}\n")
    fm = np.zeros(len(f), int) if face_materials is None else face_materials
    lines = [f"mtllib {name}.mtl"]
    lines += [f"v {a:.9g} {b:.9g} {c:.9g}" for a, b, c in v]
    lines += [f"vt {a:.9g} {b:.9g}" for a, b in uv.reshape(-1, 2)]
    for m, material in enumerate(("painted", "flat")):
        lines.append(f"usemtl {material}")
        for k in np.flatnonzero(fm == m):
            a, b, c = f[k] + 1
            t = 3 * k + 1
            lines.append(f"f {a}/{t} {b}/{t + 1} {c}/{t + 2}")
    path = folder / f"{name}.obj"
    path.write_text("\n".join(lines) + "\n")
    return path


def bench_meshes(folder, quick):
    """name -> (Mesh, whether it counts for the 35 dB goal): smooth textures, a flat-coloured
    quarter of the torus with straight material borders, and a sharp checker as a stress case."""
    sphere = uv_sphere(48, 24) if quick else uv_sphere(96, 48)
    ring = torus(48, 24) if quick else torus(96, 48)
    centre = ring[0][ring[1]].mean(axis=1)
    quarter = (centre[:, 0] > 0) & (centre[:, 2] > 0)
    return {"sphere": read_mesh(write_obj(folder, "sphere", *sphere, sphere_texture())),
            "torus": read_mesh(write_obj(folder, "torus", *ring, torus_texture(), quarter.astype(int))),
            "sphere, sharp checker": read_mesh(write_obj(folder, "checker", *sphere, sphere_texture(checker=True)))}


def bench_cameras(mesh, size, count=4, seed=5):
    """`count` views from random directions (fixed seed), framed by the same rule as the target
    mode's own views (the bounding sphere fills a 40 degree field with 10% to spare)."""
    v = mesh.vertices
    centre = (v.min(axis=0) + v.max(axis=0)) / 2
    distance = 1.1 * np.linalg.norm(v - centre, axis=1).max() / math.sin(math.radians(20.0))
    dirs = np.random.default_rng(seed).normal(size=(count, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return [Camera.look_at(centre + distance * d, centre, fov_deg=40.0, width=size, height=size) for d in dirs]


# Cycles ----------------------------------------------------------------------------------------

def cycles_render(mesh, camera, folder, samples=CYCLES_SAMPLES):
    """Render the mesh with Blender Cycles in a subprocess; returns (display sRGB image, seconds)."""
    spec = folder / "cycles_spec.npz"
    out = folder / "cycles.png"
    textures = []
    for k, material in enumerate(mesh.materials):
        path = ""
        if material.texture is not None:
            from PIL import Image
            path = str(folder / f"cycles_tex_{k}.png")
            Image.fromarray(material.texture).save(path)
        textures.append(path)
    np.savez(spec, vertices=mesh.vertices, faces=mesh.faces, uvs=mesh.corner_uvs,
             face_materials=mesh.face_materials, base_colors=np.array([m.base_color for m in mesh.materials]),
             textures=np.array(textures), camera_to_world=opengl_camera_to_world(camera.world_to_camera),
             fov=camera.fov_x_deg, width=camera.width, height=camera.height, samples=samples)
    start = time.perf_counter()
    subprocess.run([sys.executable, __file__, "--cycles", str(spec), str(out)], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    seconds = time.perf_counter() - start
    from PIL import Image
    return np.asarray(Image.open(out).convert("RGB"), np.float64) / 255.0, seconds


def _cycles_main(spec_path, out_path):
    """Runs inside the subprocess: build the scene in bpy and render it."""
    import bpy
    import mathutils
    d = np.load(spec_path)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    mesh = bpy.data.meshes.new("mesh")
    mesh.from_pydata(d["vertices"].tolist(), [], d["faces"].tolist())
    mesh.uv_layers.new(name="UVMap").data.foreach_set("uv", d["uvs"].reshape(-1).astype(np.float32))
    mesh.polygons.foreach_set("material_index", d["face_materials"].astype(np.int32))
    for base, texture in zip(d["base_colors"], d["textures"]):
        material = bpy.data.materials.new("m")
        material.use_nodes = True
        nodes, links = material.node_tree.nodes, material.node_tree.links
        nodes.clear()
        emission = nodes.new("ShaderNodeEmission")
        emission.inputs["Strength"].default_value = 1.0
        emission.inputs["Color"].default_value = (*base, 1.0)            # scene-linear, as Kd
        if str(texture):
            image = nodes.new("ShaderNodeTexImage")
            image.image = bpy.data.images.load(str(texture))
            image.image.colorspace_settings.name = "sRGB"
            image.interpolation = "Linear"
            links.new(image.outputs["Color"], emission.inputs["Color"])
        links.new(emission.outputs["Emission"], nodes.new("ShaderNodeOutputMaterial").inputs["Surface"])
        mesh.materials.append(material)
    obj = bpy.data.objects.new("mesh", mesh)
    scene.collection.objects.link(obj)
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0, 0, 0, 1)
    scene.world = world
    cam_data = bpy.data.cameras.new("camera")
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.angle = math.radians(float(d["fov"]))
    cam_data.clip_start = 0.01
    cam = bpy.data.objects.new("camera", cam_data)
    scene.collection.objects.link(cam)
    cam.matrix_world = mathutils.Matrix(d["camera_to_world"].tolist())
    scene.camera = cam
    render_settings = scene.render
    render_settings.engine = "CYCLES"
    render_settings.resolution_x, render_settings.resolution_y = int(d["width"]), int(d["height"])
    render_settings.resolution_percentage = 100
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(d["samples"])
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 0
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.display_settings.display_device = "sRGB"
    render_settings.image_settings.file_format = "PNG"
    render_settings.image_settings.color_mode = "RGB"
    render_settings.image_settings.color_depth = "8"
    render_settings.filepath = out_path
    bpy.ops.render.render(write_still=True)


# comparisons -----------------------------------------------------------------------------------

def versus(images, references):
    """PSNR over all images together and mean SSIM."""
    mse = np.mean([np.mean((np.asarray(a, np.float64) - b) ** 2) for a, b in zip(images, references)])
    ssim = np.mean([metrics.ssim(a, b) for a, b in zip(images, references)])
    return {"psnr_db": float(10 * np.log10(1 / mse)), "ssim": float(ssim)}


def splat_error(cloud, cameras, references, mode="classic"):
    return versus([render(cloud, cam, mode=mode).color for cam in cameras], references)


def convert(mesh, **options):
    return mesh_to_splats(mesh.vertices, mesh.faces, **mesh.appearance(), **options)


# the baseline: one Python iteration per triangle -------------------------------------------------

def baseline_convert(mesh, max_splats, seed=0):
    """A straightforward per-triangle converter: per face, round(N * area share) random points
    (at least one), isotropic discs of the face's spacing, colour by nearest-texel lookup."""
    rng = np.random.default_rng(seed)
    v, f = mesh.vertices, mesh.faces
    areas = [0.5 * np.linalg.norm(np.cross(v[b] - v[a], v[c] - v[a])) for a, b, c in f]
    total = sum(areas)
    material = mesh.materials[0]
    texture = material.texture.astype(np.float64) / 255.0
    h, w = texture.shape[:2]
    out = {"p": [], "q": [], "s": [], "c": []}
    for k, (a, b, c) in enumerate(f):
        if areas[k] <= 0:
            continue
        n = max(1, round(max_splats * areas[k] / total))
        r1, r2 = np.sqrt(rng.uniform(size=n)), rng.uniform(size=n)
        bary = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], 1)
        out["p"].append(bary @ v[[a, b, c]])
        normal = np.cross(v[b] - v[a], v[c] - v[a])
        normal /= np.linalg.norm(normal)
        t1 = (v[b] - v[a]) / np.linalg.norm(v[b] - v[a])
        frame = np.stack([t1, np.cross(normal, t1), normal], 1)
        w_ = math.sqrt(max(0.0, 1 + frame[0, 0] + frame[1, 1] + frame[2, 2])) / 2
        quat = [w_, (frame[2, 1] - frame[1, 2]) / (4 * w_ + 1e-12), (frame[0, 2] - frame[2, 0]) / (4 * w_ + 1e-12),
                (frame[1, 0] - frame[0, 1]) / (4 * w_ + 1e-12)]
        out["q"].append(np.tile(quat, (n, 1)))
        sigma = math.sqrt(areas[k] / n)
        out["s"].append(np.tile([sigma, sigma, 0.01 * sigma], (n, 1)))
        uv = bary @ mesh.corner_uvs[k]
        px = (uv[:, 0] % 1 * w).astype(int).clip(0, w - 1)
        py = ((1 - uv[:, 1] % 1) * h).astype(int).clip(0, h - 1)
        out["c"].append(texture[py, px])
    return SplatCloud.from_activated(np.concatenate(out["p"]), np.concatenate(out["q"]), np.concatenate(out["s"]),
                                     np.full(sum(len(p) for p in out["p"]), 0.99), colors=np.concatenate(out["c"]))


def speed_rows(quick, sphere_mesh, cameras, references):
    """100k triangles -> 1M splats, ours against the per-triangle loop, with the PSNR each buys."""
    segments, rings = (100, 50) if quick else (318, 158)
    v, f, uv = uv_sphere(segments, rings)
    from splatwright.core.mesh import Material, Mesh
    big = Mesh(v, f, uv, None, [Material(texture=sphere_texture())])
    splats = 10 * len(f)
    big.materials[0].linear_texture()                 # decode once, outside the timing
    ours = timeit(lambda: convert(big, max_splats=splats), repeat=3 if quick else 5)
    subset = 1000 if quick else 2000
    part = Mesh(v, f[:subset], uv[:subset], None, big.materials)
    loop = timeit(lambda: baseline_convert(part, splats * subset // len(f)), repeat=3, warmup=0)
    scale = len(f) / subset
    baseline = Timing(loop.median * scale, loop.spread * scale, loop.runs)
    per_100k = 1e5 / len(f)
    equal = 60_000 if quick else 150_000
    err_ours = splat_error(convert(sphere_mesh, max_splats=equal), cameras, references)
    err_base = splat_error(baseline_convert(sphere_mesh, equal), cameras, references)
    return [Row(TOPIC, f"{len(f) // 1000}k triangles -> {splats // 1000}k splats (budget)", ours, baseline,
                error={"psnr_db": err_ours["psnr_db"], "baseline_psnr_db": err_base["psnr_db"],
                       "ssim": err_ours["ssim"], "baseline_ssim": err_base["ssim"]},
                extra={"s per 100k tris": f"{ours.median * per_100k:.2f}",
                       "baseline s per 100k tris": f"{baseline.median * per_100k:.1f} (timed on {subset} faces)",
                       "error at": f"{equal // 1000}k splats on the bench sphere"})]


# the benchmark -----------------------------------------------------------------------------------

def run(quick=False):
    size = 128 if quick else 256
    budgets = [10_000, 40_000, 160_000] if quick else [10_000, 30_000, 100_000, 300_000]
    targets = [30.0, DEFAULT_TARGET_PSNR] if quick else [30.0, 33.0, DEFAULT_TARGET_PSNR, 38.0]
    # The bench cameras frame the meshes like the target mode's own views and are not among them.
    rows, curves = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        meshes = bench_meshes(folder, quick)
        for name, mesh in meshes.items():
            cameras = bench_cameras(mesh, size)
            cycles = [cycles_render(mesh, cam, folder) for cam in cameras]
            references = [image for image, _ in cycles]
            surface = Surface(mesh.vertices, mesh.faces, **mesh.appearance())
            raster = timeit(lambda: [render_mesh(surface, cam, supersample=3) for cam in cameras], repeat=3)
            ours = [render_mesh(surface, cam, supersample=3).color for cam in cameras]
            rows.append(Row(TOPIC, f"{name}: mesh rasteriser (reference of the target mode)", raster,
                            Timing(sum(s for _, s in cycles), 0.0, 1), error=versus(ours, references),
                            extra={"faces": len(mesh.faces), "baseline": f"Cycles {CYCLES_SAMPLES} spp incl. startup"}))
            stress = "checker" in name
            curve = curves.setdefault(name, {"uniform": [], "target": []})
            own_views = default_views(surface, size)
            for n in budgets[1::2] if stress else budgets:
                timing = timeit(lambda: convert(mesh, max_splats=n), repeat=3)
                error = splat_error(convert(mesh, max_splats=n), cameras, references)
                rows.append(Row(TOPIC, f"{name}: budget {n}", timing, error=error, extra={"splats": n}))
                # The same budget with the silhouettes calibrated like the target mode's.
                start = time.perf_counter()
                cloud = convert(mesh, max_splats=n, views=own_views)
                error = splat_error(cloud, cameras, references)
                curve["uniform"].append((n, error["psnr_db"], error["ssim"]))
                rows.append(Row(TOPIC, f"{name}: budget {n}, silhouettes calibrated",
                                Timing(time.perf_counter() - start, 0.0, 1), error=error, extra={"splats": n}))
            for target in [DEFAULT_TARGET_PSNR] if stress else targets:
                info = {}
                start = time.perf_counter()
                cloud = convert(mesh, target_psnr=target, view_size=size, info=info)
                timing = Timing(time.perf_counter() - start, 0.0, 1)
                error = splat_error(cloud, cameras, references)
                curve["target"].append((len(cloud), error["psnr_db"], error["ssim"]))
                default = " (default)" if target == DEFAULT_TARGET_PSNR else ""
                rows.append(Row(TOPIC, f"{name}: target {target:g} dB{default}", timing, error=error,
                                extra={"splats": len(cloud), "own views dB": f"{info['psnr']:.2f}",
                                       "inset px": f"{info['inset_pixels']:.2f}"}))
            if stress:
                continue
            info = {}
            start = time.perf_counter()
            cloud = convert(mesh, view_size=size, render_mode="antialiased", info=info)
            timing = Timing(time.perf_counter() - start, 0.0, 1)
            rows.append(Row(TOPIC, f"{name}: target {DEFAULT_TARGET_PSNR:g} dB, antialiased mode", timing,
                            error=splat_error(cloud, cameras, references, mode="antialiased"),
                            extra={"splats": len(cloud), "own views dB": f"{info['psnr']:.2f}"}))
        sphere_cams = bench_cameras(meshes["sphere"], size)
        sphere_refs = [cycles_render(meshes["sphere"], cam, folder)[0] for cam in sphere_cams]
        rows += speed_rows(quick, meshes["sphere"], sphere_cams, sphere_refs)
    _plot(curves, HERE / "mesh2splats_curve.png")
    return rows


def _plot(curves, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for name, curve in curves.items():
        for kind, marker in (("uniform", "o-"), ("target", "s--")):
            pts = sorted(curve[kind])
            if pts:
                n, p, s = zip(*pts)
                axes[0].plot(n, p, marker, label=f"{name}, {LABELS[kind]}")
                axes[1].plot(n, s, marker, label=f"{name}, {LABELS[kind]}")
    for ax, label in zip(axes, ("PSNR vs Cycles (dB)", "SSIM vs Cycles")):
        ax.set_xscale("log")
        ax.set_xlabel("splats")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[0].axhline(35.0, color="gray", lw=0.8)
    axes[0].legend(fontsize=7)
    fig.suptitle("mesh2splats: uniform budget against target-PSNR sizing")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--cycles":
        _cycles_main(sys.argv[2], sys.argv[3])
    else:
        print_rows(run(quick="--quick" in sys.argv))
