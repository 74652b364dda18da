"""What compositing splats with meshes costs, as a ratio against the splat render of the same frame.

The frame: a trained-like cloud (bench/render.py's scene) cut by meshes, a floor tilted through the
cloud and a box standing in it, rasterised at pixel centres (core.preview.mesh_layer) as the layer.
Cases, each timed alternately with the baseline (the same splats rendered alone):

- the renderer with the layer (opaque meshes, translucent meshes at alpha 0.5, meshes out of view);
- the SPLATWRIGHT engine's own work per frame besides Cycles itself: reading the mesh layer's
  uncompressed EXR, turning it into the layer, the layer render and the Combined and Depth passes
  (and, optional, the Splats and Meshes passes), against its splat-only frame (the render, Combined
  and Depth); these cases import the extension's engine module, so they need bpy.

Errors are max abs differences, in 1/255 steps of display sRGB, against the float64 brute-force
reference (tests/reference_render.py) given the same layer, at a random sample of pixels.

    python bench/composite.py [--quick]
"""

import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

from common import Row, machine, paired, print_rows  # noqa: E402
from reference_render import reference_render  # noqa: E402
from render import seed_camera, trained_like_scene  # noqa: E402

from splatwright.core.color import srgb_to_linear  # noqa: E402
from splatwright.core.preview import Triangles, mesh_layer  # noqa: E402
from splatwright.core.render import Layer, render  # noqa: E402

TOPIC = "composite"
ERROR_PIXELS = 400


def meshes(camera):
    """A floor tilted through the cloud's depth range and a box in the middle of the view."""
    c2w = camera.camera_to_world

    def at(x, y, z):  # camera-space point -> world
        return (c2w @ np.array([x * z, y * z, z, 1.0]))[:3]

    floor = [at(-1, 0.1, 4.0), at(1, 0.1, 4.0), at(1, 1, 11.0), at(-1, 1, 11.0)]
    box = [at(x, y, z) for z in (6.0, 7.5) for y in (-0.5, 0.15) for x in (-0.3, 0.2)]
    quads = [floor] + [
        [box[i] for i in q]
        for q in ((0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5))
    ]
    corners = np.array([[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads])
    colors = np.array([[0.4, 0.4, 0.35]] * len(corners))
    colors[1 : len(quads)] = colors[len(quads) + 1 :] = [0.1, 0.5, 0.2]
    return Triangles(corners, colors)


def layers(camera):
    opaque = mesh_layer(meshes(camera), camera)
    half = Layer(opaque.color * 0.5, opaque.alpha * 0.5, opaque.depth)
    shape = (camera.height, camera.width)
    none = Layer(np.zeros(shape + (3,)), np.zeros(shape), np.full(shape, np.inf))
    return {
        "opaque meshes through the cloud": opaque,
        "translucent meshes (alpha 0.5)": half,
        "meshes out of view": none,
    }


def max_error(cloud, camera, layer, image, rng):
    pixels = np.column_stack(
        [rng.integers(0, camera.width, ERROR_PIXELS), rng.integers(0, camera.height, ERROR_PIXELS)]
    )
    x, y = pixels[:, 0], pixels[:, 1]
    ref = reference_render(
        cloud, camera, pixels=pixels, layer=(layer.color[y, x], layer.alpha[y, x], layer.depth[y, x])
    )
    return float(np.abs(image.color[y, x] - ref["color"]).max() * 255)


def mesh_exr(layer, folder):
    """The layer as the child Blender writes it: an uncompressed multilayer EXR, Combined and Depth."""
    import OpenEXR

    alpha = layer.alpha.astype(np.float32)
    straight = np.where(alpha[..., None] > 0, layer.color / np.maximum(alpha, 1e-30)[..., None], 0)
    linear = srgb_to_linear(straight) * alpha[..., None]
    channels = {f"ViewLayer.Combined.{c}": linear[..., i].astype(np.float32) for i, c in enumerate("RGB")}
    channels["ViewLayer.Combined.A"] = alpha
    channels["ViewLayer.Depth.Z"] = np.where(np.isfinite(layer.depth), layer.depth, 1e10).astype(np.float32)
    path = Path(folder) / "layer.exr"
    OpenEXR.File({"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage}, channels).write(str(path))
    return path


def engine_side(cloud, camera, layer, folder):
    """The SPLATWRIGHT engine's per-frame work without meshes, with them, and with them and the
    Splats and Meshes passes, as callables (None without bpy)."""
    try:
        from splatwright.io.exr_plain import read_plain_exr
        from splatwright.splat_addon.render import engine
        from splatwright.splat_addon.render import mesh_layer as meshes_module
        from splatwright.splat_addon.render.scene import to_scene_linear
    except ImportError:
        return None
    path = mesh_exr(layer, folder)

    def splats_only():
        image = render(cloud, camera, background=(0.1, 0.1, 0.1))
        to_scene_linear(image.color, np.ones_like(image.alpha))
        engine.composite_depth(image, None)

    def composited(passes):
        def run():
            got = meshes_module._layer_from_channels(
                read_plain_exr(path), "ViewLayer", camera.width, camera.height, False, 0.0
            )
            surface = got.as_layer()
            image = render(cloud, camera, background=None, layer=surface)
            if passes:
                engine.splat_passes(image, surface, got)
            to_scene_linear(image.color, np.ones_like(image.alpha))
            engine.composite_depth(image, surface)

        return run

    return splats_only, composited(False), composited(True)


def run(quick=False):
    camera = seed_camera(480, 270) if quick else seed_camera(960, 540)
    camera = camera.with_(near=0.2)
    cloud = trained_like_scene(60_000 if quick else 300_000, camera)
    repeat = 3 if quick else 5
    rng = np.random.default_rng(0)
    rows = []
    baseline = lambda: render(cloud, camera, background=None)  # noqa: E731
    for case, layer in layers(camera).items():
        base, ours = paired(baseline, lambda: render(cloud, camera, background=None, layer=layer), repeat)
        image = render(cloud, camera, background=None, layer=layer)
        rows.append(
            Row(
                TOPIC,
                case,
                ours,
                base,
                error={"max_err_255": max_error(cloud, camera, layer, image, rng)},
                extra={
                    "splats": len(cloud),
                    "size": f"{camera.width}x{camera.height}",
                    "covered": f"{layer.alpha.mean():.0%}",
                    "added": f"{ours.median / base.median - 1:+.1%}",
                },
            )
        )
    with tempfile.TemporaryDirectory() as folder:
        opaque = layers(camera)["opaque meshes through the cloud"]
        engine = engine_side(cloud, camera, opaque, folder)
        for case, composited in (
            ()
            if engine is None
            else (
                ("engine: EXR read, layer, composite, Combined, Depth", engine[1]),
                ("engine: the same and the Splats and Meshes passes", engine[2]),
            )
        ):
            base, ours = paired(engine[0], composited, repeat)
            rows.append(
                Row(
                    TOPIC,
                    case,
                    ours,
                    base,
                    extra={
                        "splats": len(cloud),
                        "size": f"{camera.width}x{camera.height}",
                        "added": f"{ours.median / base.median - 1:+.1%}",
                    },
                )
            )
    return rows


if __name__ == "__main__":
    print(machine())
    print_rows(run(quick="--quick" in sys.argv))
