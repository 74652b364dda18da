"""The Blender side of tests/test_blender_lights.py (see workers/base.py): Cycles on the CPU renders a
large white diffuse plane under one light of each kind, seen straight down by an orthographic camera,
so that every pixel is the radiance the plane reflects at a known point: albedo * irradiance / pi.
Each scene renders twice with different seeds (the difference measures Cycles' noise). Nothing of the
extension is used but by sky_worlds: the lights' settings and matrices go back to the test, which
converts them; sky_worlds also asks the installed extension what it reads of each Sky Texture world
(splat_addon/render/world_panorama.py), beside Cycles' renders under it."""

import math

import numpy as np
from environment_reference import add_sun, directions

from workers.base import BlenderWorker, worker_main

SIZE = 48  # pixels each way
ORTHO_SCALE = 6.0  # metres across the picture
ALBEDO = 0.8
SAMPLES = 256
# name -> the light's settings: type, data properties, location, rotation (Euler XYZ, radians)
LIGHTS = {
    "point": ("POINT", dict(energy=120.0, shadow_soft_size=0.05, color=(1.0, 0.8, 0.6)), (0.4, -0.3, 1.6), (0, 0, 0)),
    "spot": (
        "SPOT",
        dict(energy=300.0, shadow_soft_size=0.02, spot_size=math.radians(70.0), spot_blend=0.4),
        (-0.3, 0.2, 2.0),
        (math.radians(12.0), 0.0, 0.0),
    ),
    "sun": (
        "SUN",
        dict(energy=2.5, angle=math.radians(0.5), exposure=0.5),
        (0, 0, 5),
        (math.radians(35.0), 0.0, math.radians(20)),
    ),
    "area_rectangle": (
        "AREA",
        dict(energy=150.0, shape="RECTANGLE", size=1.6, size_y=0.7),
        (0.2, 0.1, 1.1),
        (math.radians(15.0), math.radians(-10.0), math.radians(30.0)),
    ),
    "area_disk": ("AREA", dict(energy=80.0, shape="DISK", size=1.2), (-0.2, 0.3, 0.9), (0, 0, 0)),
    # Spread narrows the light to a cone (Cycles' soft-box grid), its power kept
    "area_spread": (
        "AREA",
        dict(energy=120.0, shape="RECTANGLE", size=1.2, size_y=0.8, spread=math.radians(70.0)),
        (0.3, -0.2, 1.0),
        (math.radians(10.0), 0.0, 0.0),
    ),
    # narrow spreads close over the plane: each point sees a small disc of the light (its samples
    # then lie on that disc, core.lights.spread_samples; the light's 16 would leave most points dark)
    "area_spread_narrow": (
        "AREA",
        dict(energy=200.0, shape="RECTANGLE", size=2.0, size_y=1.4, spread=math.radians(30.0)),
        (0.1, 0.2, 0.8),
        (math.radians(8.0), 0.0, math.radians(20.0)),
    ),
    "area_spread_disk": (
        "AREA",
        dict(energy=150.0, shape="DISK", size=2.0, spread=math.radians(25.0)),
        (-0.2, 0.1, 0.7),
        (0.0, math.radians(-6.0), 0.0),
    ),
    "area_spread_ellipse": (
        "AREA",
        dict(energy=150.0, shape="ELLIPSE", size=2.4, size_y=1.2, spread=math.radians(30.0)),
        (0.1, -0.1, 0.8),
        (math.radians(5.0), 0.0, math.radians(-25.0)),
    ),
    # Normalize off (Blender 4.5+): the power is per square metre of the light, not spread over it
    "area_unnormalized": (
        "AREA",
        dict(energy=40.0, shape="RECTANGLE", size=1.5, size_y=0.6, normalize=False),
        (0.1, -0.2, 1.2),
        (0, 0, 0),
    ),
}
# Principled BSDF planes seen by an orthographic camera tilted TILT from straight down, lit by a
# point light near the mirror direction: the highlight is in the picture. name -> (base colour,
# roughness, metallic, distribution: GGX single scattering, or Blender's default MULTI_GGX)
PRINCIPLED = {
    "principled_dielectric": ((0.6, 0.5, 0.4), 0.4, 0.0, "GGX"),
    "principled_metal": ((0.9, 0.6, 0.3), 0.5, 1.0, "GGX"),
    "principled_rough_metal": ((0.9, 0.6, 0.3), 0.8, 1.0, "MULTI_GGX"),
    "principled_rough_dielectric": ((0.3, 0.6, 0.4), 0.7, 0.0, "MULTI_GGX"),
    "principled_glossy_area": ((0.9, 0.6, 0.3), 0.15, 1.0, "GGX"),
    "principled_glossy_sphere": ((0.9, 0.6, 0.3), 0.1, 1.0, "GGX"),
}
# The lights of the Principled planes: a small point light, but a rectangle and a sphere mirrored by
# the glossy metals (highlights core.ltc integrates)
PRINCIPLED_LIGHTS = {
    "principled_glossy_sphere": ("POINT", dict(energy=20.0, shadow_soft_size=0.15), (0.2, 1.3, 1.5), (0, 0, 0)),
    "principled_glossy_area": (
        "AREA",
        dict(energy=8.0, shape="RECTANGLE", size=0.5, size_y=0.3),
        (0.2, 1.3, 1.5),
        (0, 0, 0),
    ),
}
# A narrow softbox over the plane with a square (0.6 m, 0.5 m up, off the light's centre, unseen by
# the camera) shadowing it: its shadow falls along the light's axis (core.shadows' Spread model)
SPREAD_SHADOW = (
    "AREA",
    dict(energy=300.0, shape="SQUARE", size=2.5, spread=math.radians(30.0)),
    (0.0, 0.0, 1.2),
    (0.0, 0.0, 0.0),
)
OCCLUDER = ((0.6, 0.3, 0.5), 0.6)  # centre, side
TILT = math.radians(40.0)
PRINCIPLED_LIGHT = ("POINT", dict(energy=60.0, shadow_soft_size=0.02), (0.2, 1.3, 1.5), (0, 0, 0))


# environment's map: a radiance of bands 0-2, different per channel, as functions of the direction
# (x, y, z); positive everywhere (R from 0.2, G from 0.2, B from 0.2)
ENVIRONMENT = (
    lambda x, y, z: 1.0 + 0.6 * y + 0.4 * x * z,
    lambda x, y, z: 1.0 + 0.5 * z + 0.3 * (x * x - y * y),
    lambda x, y, z: 0.6 - 0.4 * x + 0.3 * z * z,
)
ENVIRONMENT_SIZE = (128, 64)  # the map's pixels, width by height
ENVIRONMENT_TURN = (0.4, -0.2, 1.1)  # environment's second render: a Mapping node's rotation (Euler XYZ)
# environment's third: the map at 512 x 256 with a sun (a disc of this diameter at this latitude and
# longitude, radians, giving this irradiance, W/m^2, to a surface facing it)
SUN_IN_MAP = dict(
    diameter=math.radians(4.0), latitude=math.radians(35.0), longitude=math.radians(-60.0), irradiance=15.0
)
BALL_ORTHO_SCALE = 2.4  # the camera's view of environment's ball (radius 1)


def environment_pixels(size=ENVIRONMENT_SIZE, sun=False):
    """(H, W, 4) float32 ENVIRONMENT's map at its pixels' centres, rows from the bottom, with the
    directions Blender reads an equirectangular map with (measured in Cycles: u = 0.5 looks along +X,
    0.25 along +Y; row 0 at latitude -90 degrees); with `sun`, SUN_IN_MAP's disc on it."""
    width, height = size
    d, _ = directions(height, width)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    pixels = np.ones((height, width, 4), np.float32)
    for channel, radiance in enumerate(ENVIRONMENT):
        pixels[..., channel] = radiance(x, y, z)
    if sun:
        sun_in_map = {k: SUN_IN_MAP[k] for k in ("latitude", "longitude", "diameter", "irradiance")}
        pixels = add_sun(pixels, **sun_in_map).astype(np.float32)
    return pixels


# Blender's own world HDRIs (datafiles/studiolights/world: Poly Haven's, CC0) that light studio_worlds' ball
STUDIO_WORLDS = ("sunrise", "forest", "courtyard", "interior")


# Sky Texture worlds that light sky_worlds' ball: the sky model of each Blender (Nishita before 5.0,
# its disc model's successor from 5.0; Hosek / Wilkie in both), the sun's elevation and rotation
# (degrees), whether its disc shows, and whether the engine is made to look for the sun elsewhere
# first (world_panorama.sun_direction pointing away: it must search the panorama); every other
# setting the node's default
SKY_WORLDS = {
    "disc": (("NISHITA", "MULTIPLE_SCATTERING"), 35.0, 40.0, True, False),
    "smooth": (("HOSEK_WILKIE", "HOSEK_WILKIE"), 35.0, 40.0, False, False),
    "searched": (("NISHITA", "MULTIPLE_SCATTERING"), 50.0, 120.0, True, True),
}


class Worker(BlenderWorker):
    steps = (*LIGHTS, *PRINCIPLED, "area_spread_shadow", "environment", "studio_worlds", "sky_worlds")
    keep_objects = ("Camera",)
    orphan_kinds = ("meshes", "materials", "lights")

    def scene(self, principled=None):
        """The plane, the camera (straight down, or tilted for a Principled plane) and Cycles'
        settings: direct light only (nothing else in the scene to bounce off), no denoiser, a box
        pixel as small as Cycles allows."""
        bpy = self.bpy
        scene = bpy.context.scene
        bpy.ops.mesh.primitive_plane_add(size=60.0, location=(0.0, 0.0, 0.0))
        material = bpy.data.materials.new("Plane")
        material.use_nodes = True
        nodes = material.node_tree.nodes
        nodes.clear()
        if principled is None:
            bsdf = nodes.new("ShaderNodeBsdfDiffuse")
            bsdf.inputs["Color"].default_value = (ALBEDO, ALBEDO, ALBEDO, 1.0)
            bsdf.inputs["Roughness"].default_value = 0.0
        else:
            bsdf = nodes.new("ShaderNodeBsdfPrincipled")
            color, roughness, metallic, bsdf.distribution = principled
            bsdf.inputs["Base Color"].default_value = (*color, 1.0)
            bsdf.inputs["Roughness"].default_value = roughness
            bsdf.inputs["Metallic"].default_value = metallic
        output = nodes.new("ShaderNodeOutputMaterial")
        material.node_tree.links.new(bsdf.outputs["BSDF"], output.inputs["Surface"])
        bpy.context.active_object.data.materials.append(material)
        cam = scene.camera
        tilt = 0.0 if principled is None else TILT
        cam.location = (0.0, -10.0 * math.sin(tilt), 10.0 * math.cos(tilt))
        cam.rotation_euler = (tilt, 0.0, 0.0)
        cam.data.type, cam.data.ortho_scale = "ORTHO", ORTHO_SCALE
        background = next(n for n in scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground")
        background.inputs["Strength"].default_value = 0.0
        render = scene.render
        render.engine = "CYCLES"
        render.resolution_x = render.resolution_y = SIZE
        render.resolution_percentage = 100
        render.dither_intensity = 0.0
        scene.view_settings.view_transform = "Standard"
        scene.cycles.device = "CPU"
        scene.cycles.samples = SAMPLES
        scene.cycles.use_adaptive_sampling = False
        scene.cycles.use_denoising = False
        scene.cycles.filter_width = 0.01
        self.image_format(render.image_settings, "OPEN_EXR", color_depth="32")

    def light(self, name):
        spec = SPREAD_SHADOW if name == "area_spread_shadow" else LIGHTS.get(name) or PRINCIPLED_LIGHTS.get(name)
        spec = spec or PRINCIPLED_LIGHT
        kind, settings, location, rotation = spec
        bpy = self.bpy
        data = bpy.data.lights.new(name, kind)
        for key, value in settings.items():
            if hasattr(data, key):  # Normalize and Exposure came after 4.2
                setattr(data, key, value)
        obj = bpy.data.objects.new(name, data)
        bpy.context.scene.collection.objects.link(obj)
        obj.location, obj.rotation_euler = location, rotation
        bpy.context.view_layer.update()
        return obj

    def render(self, name, seed):
        bpy = self.bpy
        bpy.context.scene.cycles.seed = seed
        bpy.ops.render.render()
        path = self.out / f"{name}_{seed}.exr"
        bpy.data.images["Render Result"].save_render(str(path))
        loaded = bpy.data.images.load(str(path))
        pixels = np.empty(len(loaded.pixels), np.float32)
        loaded.pixels.foreach_get(pixels)
        bpy.data.images.remove(loaded)
        return pixels.reshape(SIZE, SIZE, 4)[::-1, :, :3]  # row 0 at the top

    def record(self, obj):
        """What the test needs to build the same light: the data's settings and the world matrix."""
        data = obj.data
        rec = {"type": data.type, "energy": data.energy, "color": list(data.color)}
        rec["exposure"] = getattr(data, "exposure", 0.0)
        rec["normalize"] = getattr(data, "normalize", True)
        for key in ("shadow_soft_size", "spot_size", "spot_blend", "angle", "shape", "size", "size_y", "spread"):
            if hasattr(data, key):
                rec[key] = getattr(data, key)
        rec["matrix_world"] = [list(row) for row in obj.matrix_world]
        return rec

    def run_light(self, name):
        self.scene(PRINCIPLED.get(name))
        obj = self.light(name)
        images = [self.render(name, seed) for seed in (0, 1)]
        self.save(name, first=images[0], second=images[1])
        camera = [list(row) for row in self.bpy.context.scene.camera.matrix_world]
        return {"light": self.record(obj), "albedo": ALBEDO, "size": SIZE, "ortho_scale": ORTHO_SCALE, "camera": camera}

    def point(self):
        return self.run_light("point")

    def spot(self):
        return self.run_light("spot")

    def sun(self):
        return self.run_light("sun")

    def area_rectangle(self):
        return self.run_light("area_rectangle")

    def area_disk(self):
        return self.run_light("area_disk")

    def area_spread(self):
        return self.run_light("area_spread")

    def area_spread_narrow(self):
        return self.run_light("area_spread_narrow")

    def area_spread_disk(self):
        return self.run_light("area_spread_disk")

    def area_spread_ellipse(self):
        return self.run_light("area_spread_ellipse")

    def area_unnormalized(self):
        return self.run_light("area_unnormalized")

    def area_spread_shadow(self):
        """SPREAD_SHADOW's light over the plane, OCCLUDER's square between them (it casts shadows but
        no camera ray sees it); its corners go back to the test."""
        bpy = self.bpy
        self.scene()
        obj = self.light("area_spread_shadow")
        centre, side = OCCLUDER
        bpy.ops.mesh.primitive_plane_add(size=side, location=centre)
        square = bpy.context.active_object
        square.visible_camera = False
        corners = [list(square.matrix_world @ v.co) for v in square.data.vertices]
        faces = [list(p.vertices) for p in square.data.polygons]
        images = [self.render("area_spread_shadow", seed) for seed in (0, 1)]
        self.save("area_spread_shadow", first=images[0], second=images[1])
        record = {"light": self.record(obj), "albedo": ALBEDO, "size": SIZE, "ortho_scale": ORTHO_SCALE}
        return {**record, "occluder": {"vertices": corners, "faces": faces}}

    def ball_scene(self):
        """scene()'s settings and material with a white diffuse ball (radius 1, smooth) in place of the
        plane, seen along +Y by the orthographic camera (BALL_ORTHO_SCALE): the ball."""
        bpy = self.bpy
        self.scene()
        plane = bpy.context.active_object
        material = plane.data.materials[0]
        bpy.data.objects.remove(plane)
        bpy.ops.mesh.primitive_uv_sphere_add(segments=192, ring_count=96, radius=1.0, location=(0.0, 0.0, 0.0))
        ball = bpy.context.active_object
        ball.data.materials.append(material)
        bpy.ops.object.shade_smooth()
        cam = bpy.context.scene.camera
        cam.location, cam.rotation_euler = (0.0, -10.0, 0.0), (math.pi / 2, 0.0, 0.0)
        cam.data.ortho_scale = BALL_ORTHO_SCALE
        return ball

    def environment(self):
        """A white diffuse ball (radius 1, smooth) alone under an equirectangular Environment Texture
        of ENVIRONMENT's map, seen along +Y by the orthographic camera: the map's pixels and two
        renders, then two with the map looked up through a Mapping node (ENVIRONMENT_TURN), then two
        of the map with a sun in it (SUN_IN_MAP)."""
        bpy = self.bpy
        ball = self.ball_scene()
        scene = bpy.context.scene
        pixels = environment_pixels()
        texture, image = self.world_map(pixels, "Environment")
        tree = scene.world.node_tree
        background = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeBackground")
        background.inputs["Strength"].default_value = 1.0
        scene.render.film_transparent = True  # the map itself out of the picture
        try:
            images = [self.render("environment", seed) for seed in (0, 1)]
            # the same map looked up through a Mapping node (Point) turning the Generated direction
            coordinates, mapping = tree.nodes.new("ShaderNodeTexCoord"), tree.nodes.new("ShaderNodeMapping")
            mapping.inputs["Rotation"].default_value = ENVIRONMENT_TURN
            tree.links.new(coordinates.outputs["Generated"], mapping.inputs["Vector"])
            tree.links.new(mapping.outputs["Vector"], texture.inputs["Vector"])
            images += [self.render("environment_turned", seed) for seed in (0, 1)]
            tree.nodes.remove(coordinates)
            tree.nodes.remove(mapping)
            sunny = environment_pixels((512, 256), sun=True)  # a sun in the map, fine enough to hold it
            image.scale(512, 256)
            image.pixels.foreach_set(sunny.ravel())
            images += [self.render("environment_sun", seed) for seed in (0, 1)]
        finally:
            scene.render.film_transparent = False
            tree.nodes.remove(texture)
            bpy.data.images.remove(image)
            bpy.data.objects.remove(ball)
        self.save("environment", first=images[0], second=images[1], map=pixels[..., :3])
        self.save("environment_turned", first=images[2], second=images[3])
        self.save("environment_sun", first=images[4], second=images[5], map=sunny[..., :3])
        camera = [list(row) for row in scene.camera.matrix_world]
        return {"albedo": ALBEDO, "size": SIZE, "ortho_scale": BALL_ORTHO_SCALE, "camera": camera}

    def studio_worlds(self):
        """environment's ball under each of Blender's own world HDRIs of STUDIO_WORLDS, as Blender
        reads the file: each map's pixels and two renders."""
        bpy = self.bpy
        ball = self.ball_scene()
        scene = bpy.context.scene
        folder = bpy.utils.system_resource("DATAFILES", path="studiolights/world")
        tree = scene.world.node_tree
        background = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeBackground")
        background.inputs["Strength"].default_value = 1.0
        texture = tree.nodes.new("ShaderNodeTexEnvironment")
        tree.links.new(texture.outputs["Color"], background.inputs["Color"])
        scene.render.film_transparent = True
        try:
            for name in STUDIO_WORLDS:
                image = bpy.data.images.load(f"{folder}/{name}.exr")
                texture.image = image
                width, height = image.size
                pixels = np.empty(width * height * image.channels, np.float32)
                image.pixels.foreach_get(pixels)
                images = [self.render(f"studio_{name}", seed) for seed in (0, 1)]
                rows = pixels.reshape(height, width, image.channels)[..., :3]
                self.save(f"studio_{name}", first=images[0], second=images[1], map=rows)
                bpy.data.images.remove(image)
        finally:
            scene.render.film_transparent = False
            tree.nodes.remove(texture)
            bpy.data.objects.remove(ball)
        return {"albedo": ALBEDO, "size": SIZE, "ortho_scale": BALL_ORTHO_SCALE}

    def sky_worlds(self):
        """environment's ball under each Sky Texture world of SKY_WORLDS: two renders each, and what
        the installed extension reads of the world's light (mesh_layer.render's world: its
        coefficients and sun), for the SPLATWRIGHT engine to light relit splats with; and whether
        reading each world again gave what it kept, and reading it changed did not."""
        bpy = self.bpy
        self.install_extension()
        mesh_layer = self.module("splat_addon.render.mesh_layer")
        world_panorama = self.module("splat_addon.render.world_panorama")
        aimed = world_panorama.sun_direction
        ball = self.ball_scene()
        scene = bpy.context.scene
        tree = scene.world.node_tree
        background = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeBackground")
        background.inputs["Strength"].default_value = 1.0
        sky = tree.nodes.new("ShaderNodeTexSky")
        sun_size = float(sky.sun_size)
        tree.links.new(sky.outputs["Color"], background.inputs["Color"])
        scene.render.film_transparent = True
        kept = []

        def read():
            depsgraph = bpy.context.evaluated_depsgraph_get()
            return mesh_layer.render(depsgraph, "CYCLES", SIZE, SIZE, layer=False, world=True)[1]

        try:
            for name, (models, elevation, rotation, disc, searched) in SKY_WORLDS.items():
                sky.sky_type = models[bpy.app.version >= (5, 0, 0)]
                sky.sun_elevation, sky.sun_rotation = math.radians(elevation), math.radians(rotation)
                sky.sun_disc = disc
                images = [self.render(f"sky_{name}", seed) for seed in (0, 1)]
                if searched:
                    world_panorama.sun_direction = lambda node: -aimed(node)
                try:
                    light = read()
                finally:
                    world_panorama.sun_direction = aimed
                kept.append(read() is light)  # the same world again: not rendered again
                sun = light.sun
                found = {} if sun is None else {"towards": -sun.direction, "angle": sun.angle}
                if sun is not None:
                    found["irradiance"] = sun.power * sun.color
                self.save(f"sky_{name}", first=images[0], second=images[1], coefficients=light.environment, **found)
            sky.sun_elevation += 0.1
            kept.append(read() is light)  # a changed world: rendered again
        finally:
            scene.render.film_transparent = False
            tree.nodes.remove(sky)
            bpy.data.objects.remove(ball)
        return {"albedo": ALBEDO, "size": SIZE, "ortho_scale": BALL_ORTHO_SCALE, "sun_size": sun_size, "kept": kept}

    def principled_dielectric(self):
        return self.run_light("principled_dielectric")

    def principled_metal(self):
        return self.run_light("principled_metal")

    def principled_rough_metal(self):
        return self.run_light("principled_rough_metal")

    def principled_rough_dielectric(self):
        return self.run_light("principled_rough_dielectric")

    def principled_glossy_area(self):
        return self.run_light("principled_glossy_area")

    def principled_glossy_sphere(self):
        return self.run_light("principled_glossy_sphere")


if __name__ == "__main__":
    worker_main(Worker)
