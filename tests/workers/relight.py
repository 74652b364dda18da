"""The Blender side of tests/test_blender_relight.py (run in each Blender of the version matrix; see
workers/base.py): the scene's lights as the engine reads them, relit splats rendered with their
Diffuse, Specular and Shadow passes, a splat sphere's shadow on a mesh floor, and the demo rig
converted with its material, relit and rendered over two frames."""

import math
import warnings

import numpy as np
from environment_reference import add_sun

from workers.base import BlenderWorker, worker_main

ORIGIN = (0.5, -0.25, 0.0)  # the engine's frame: world shifted by -ORIGIN
# name -> (type, location, rotation (Euler XYZ), scale, settings)
LIGHTS = {
    "Point": ("POINT", (1.0, 2.0, 3.0), (0.3, 0.0, 0.0), (1.0, 1.0, 1.0), dict(energy=100.0, shadow_soft_size=0.3)),
    "Spot": (
        "SPOT",
        (-1.0, 0.5, 2.0),
        (0.3, 0.2, 0.1),
        (1.0, 1.0, 1.0),
        dict(energy=200.0, spot_size=0.8, spot_blend=0.2, shadow_soft_size=0.05, use_shadow=False),
    ),
    "Sun": ("SUN", (0.0, 0.0, 5.0), (0.4, -0.5, 1.0), (1.0, 1.0, 1.0), dict(energy=3.0, angle=0.1)),
    "Area": (
        "AREA",
        (0.0, -2.0, 1.0),
        (1.2, 0.0, 0.3),
        (2.0, 3.0, 1.0),
        dict(energy=50.0, shape="RECTANGLE", size=2.0, size_y=0.5, spread=1.2),
    ),
    "Disk": ("AREA", (2.0, 0.0, 1.0), (0.0, 0.7, 0.0), (0.5, 0.5, 0.5), dict(energy=10.0, shape="DISK", size=1.0)),
}
COLORS = {"Point": (1.0, 0.5, 0.25), "Spot": (0.2, 0.4, 1.0)}
RAYS = {"Spot": dict(visible_glossy=False), "Area": dict(visible_diffuse=False)}  # a light object's ray visibility
INSTANCE_OFFSET = (5.0, 0.0, 0.0)  # a collection instance of the point light, moved by this
EXPOSURE = 1.0  # Blender 4.5+? set where the light has it: power x 2


SIZE = (96, 72)
BALL = dict(centre=(0.0, 0.0, 0.9), radius=0.5, count=3000, albedo=(0.8, 0.3, 0.2))
SUN = dict(rotation=(0.35, 0.0, 0.6), energy=3.0, angle=0.02)
WORLD = (0.05, 0.05, 0.06)
FLOOR = dict(size=5.0, color=(0.6, 0.6, 0.6))
CAMERA = dict(location=(2.6, -3.4, 2.9), look_at=(0.0, 0.0, 0.3), lens=30.0)
SAMPLES = 8
HDRI_CAP = (0.8, 1.6, 2.4)  # textured_world's environment radiance above 30 degrees of latitude
MAP_TURN = (0.5, -0.3, 0.9)  # textured_world's Mapping node's rotation (Euler XYZ)
SUNNY_PATCH = (900.0, 850.0, 800.0)  # textured_world's sun: 2 x 2 pixels of its map this bright
# sunny_map's world: a dim sky and a sun of this elevation and azimuth (degrees from +X towards +Y),
# diameter (degrees) and irradiance (W/m^2 facing it), drawn into a map of this many pixels
SUNNY_MAP = dict(elevation=50.0, azimuth=60.0, diameter=3.0, irradiance=4.0, sky=0.05, size=(512, 256))
# sky_sun's world: a Sky Texture with its sun disc (Nishita before Blender 5.0, Multiple Scattering
# from 5.0), the sun's elevation and rotation (degrees), the Background's Strength
SKY_SUN = dict(models=("NISHITA", "MULTIPLE_SCATTERING"), elevation=50.0, rotation=30.0, strength=0.05)
LIGHT_NODE = dict(strength=2.5, color=(1.0, 0.5, 0.25))  # light_nodes' Emission node
LINKED_BALLS = {"Left": (-0.7, 0.3, 0.6), "Right": (0.7, -0.3, 0.6)}  # light_linking's balls
LINKED_RADIUS = 0.35
KEY = dict(location=(0.0, -2.0, 2.0), energy=300.0)
# shadow_linking's balls (centre, radius): the blocker on the way from KEY to the shaded one
SHADOW_BALLS = {"Shaded": ((0.0, 0.8, 0.5), 0.35), "Blocker": ((0.0, -0.74, 1.33), 0.25)}


def ball_arrays(centre, radius, count):
    """Flat splats on a sphere (a Fibonacci lattice), each facing out: positions, rotations (w,x,y,z)
    turning +Z onto the normal, log scales, opacity logits, and the normals."""
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    phi = np.pi * (1 + 5**0.5) * i
    normals = np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], axis=1)
    rotations = np.stack([1 + normals[:, 2], -normals[:, 1], normals[:, 0], np.zeros(count)], axis=1)
    rotations /= np.linalg.norm(rotations, axis=1, keepdims=True)
    spacing = radius * np.sqrt(4 * np.pi / count)
    log_scales = np.log(np.tile([spacing * 0.7, spacing * 0.7, spacing * 0.05], (count, 1)))
    positions = np.asarray(centre) + radius * normals
    return positions, rotations, log_scales, np.full(count, 3.0), normals


def floor_arrays(size, spacing):
    """Flat splats tiling a square floor at z = 0, facing up."""
    ticks = np.arange(-size / 2 + spacing / 2, size / 2, spacing)
    x, y = np.meshgrid(ticks, ticks)
    positions = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    n = len(positions)
    rotations = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    log_scales = np.log(np.tile([spacing * 0.7, spacing * 0.7, spacing * 0.05], (n, 1)))
    return positions, rotations, log_scales, np.full(n, 3.0), np.tile([0.0, 0.0, 1.0], (n, 1))


def bpy_camera(worker, viewport):
    """The core camera of the scene's camera, as the viewport builds one from a region's view and
    projection matrices (region_camera; composite.py's viewport step builds them the same way)."""
    bpy = worker.bpy
    cam = bpy.context.scene.camera
    projection = cam.calc_matrix_camera(bpy.context.evaluated_depsgraph_get(), x=SIZE[0], y=SIZE[1])

    class Region:
        width, height = SIZE

    class RegionData:
        view_matrix, window_matrix = cam.matrix_world.inverted(), projection

    return viewport.region_camera(Region, RegionData)


def _warned(call):
    """(call(), ["Category: message", ...] of the warnings it raised)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        value = call()
    return value, [f"{w.category.__name__}: {w.message}" for w in caught]


def _named(names):
    """An owner's linking names (the object's, and its instancer's) as one key: "Ball" or "Ball in
    Instancer"."""
    return " in ".join(names)


class Worker(BlenderWorker):
    steps = (
        "install",
        "lights",
        "passes",
        "splats_shadow_meshes",
        "meshes_shadow_splats",
        "textured_world",
        "light_nodes",
        "engine_reports",
        "animation_frames",
        "sunny_map",
        "sky_sun",
        "light_linking",
        "shadow_linking",
        "mesh_shadow_linking",
        "rig",
    )
    keep_objects = ("Camera",)
    orphan_kinds = ("meshes", "materials", "actions", "lights", "collections")

    def install(self):
        self.install_extension()
        return {}

    def add_light(self, name, kind, location, rotation, scale, settings, collection=None):
        bpy = self.bpy
        data = bpy.data.lights.new(name, kind)
        for key, value in settings.items():
            setattr(data, key, value)
        data.color = COLORS.get(name, (1.0, 1.0, 1.0))
        obj = bpy.data.objects.new(name, data)
        (collection or bpy.context.scene.collection).objects.link(obj)
        obj.location, obj.rotation_euler, obj.scale = location, rotation, scale
        return obj

    def lights(self):
        """Every kind of light, one with exposure where Blender has it, one with Normalize off
        where it has that, and a collection instance: the engine's Light fields of each."""
        bpy = self.bpy
        scene = bpy.context.scene
        for obj in [o for o in scene.objects if o.type == "LIGHT"]:
            bpy.data.objects.remove(obj)
        for name, spec in LIGHTS.items():
            obj = self.add_light(name, *spec)
            for key, value in RAYS.get(name, {}).items():
                setattr(obj, key, value)
        has_exposure = hasattr(bpy.data.lights["Point"], "exposure")
        if has_exposure:
            bpy.data.lights["Sun"].exposure = EXPOSURE
        has_normalize = hasattr(bpy.data.lights["Disk"], "normalize")
        if has_normalize:
            bpy.data.lights["Disk"].normalize = False
        group = bpy.data.collections.new("Lamps")
        self.add_light("Lamp", "POINT", (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), dict(energy=5.0), group)
        holder = bpy.data.objects.new("Holder", None)
        holder.instance_type, holder.instance_collection = "COLLECTION", group
        holder.location = INSTANCE_OFFSET
        scene.collection.objects.link(holder)
        bpy.context.view_layer.update()
        lights = self.module("splat_addon.render.lights")
        depsgraph = bpy.context.evaluated_depsgraph_get()
        fields = []
        for inst in depsgraph.object_instances:
            if inst.object.type == "LIGHT":
                matrix = np.array(inst.matrix_world, dtype=np.float64)
                record = lights.light_fields(inst.object.data, matrix, np.array(ORIGIN), inst.object)
                record = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in record.items()}
                fields.append({"name": inst.object.name, **record})
        made = []
        try:  # the core's Light, where core/lights.py takes these fields
            made = [
                {"kind": light.kind, "position": np.asarray(light.position).tolist(), "power": float(light.power)}
                for light in lights.scene_lights(depsgraph, np.array(ORIGIN))
            ]
        except ImportError as exc:
            made = str(exc)
        return {"fields": fields, "exposure": has_exposure, "normalize": has_normalize, "scene_lights": made}

    # relit renders --------------------------------------------------------------------------------

    def material_cloud(self, arrays, albedo):
        """A SplatCloud of (positions, rotations, log_scales, opacity_logits, normals) with a grey SH
        colour and the material relighting shades."""
        core, material = self.module("core"), self.module("core.material")
        positions, rotations, log_scales, logits, normals = arrays
        sh = np.zeros((len(positions), 1, 3))
        sh[:, 0] = 0.2  # the unlit look, unlike the lit one
        cloud = core.SplatCloud(positions, rotations, log_scales, logits, sh)
        return material.with_material(cloud, albedo=np.tile(albedo, (len(cloud), 1)), normals=normals)

    def stage(self, mesh_engine="NONE"):
        """Camera, sun, world colour and render settings of every relit step."""
        bpy = self.bpy
        from mathutils import Vector

        scene = bpy.context.scene
        for obj in [o for o in scene.objects if o.type == "LIGHT"]:
            bpy.data.objects.remove(obj)
        self.add_light(
            "Sun", "SUN", (0.0, 0.0, 5.0), SUN["rotation"], (1, 1, 1), dict(energy=SUN["energy"], angle=SUN["angle"])
        )
        cam = scene.camera
        cam.location = CAMERA["location"]
        cam.rotation_euler = (
            (Vector(CAMERA["look_at"]) - Vector(CAMERA["location"])).to_track_quat("-Z", "Y").to_euler()
        )
        cam.data.lens = CAMERA["lens"]
        scene.world.color = WORLD
        if scene.world.node_tree is not None:
            background = next(n for n in scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground")
            background.inputs["Color"].default_value = (*WORLD, 1.0)
            background.inputs["Strength"].default_value = 1.0
        render = scene.render
        render.resolution_x, render.resolution_y = SIZE
        render.resolution_percentage = 100
        render.film_transparent = False
        render.dither_intensity = 0.0
        render.engine = "SPLATWRIGHT"
        scene.view_settings.view_transform = "Standard"
        scene.cycles.samples = SAMPLES
        scene.cycles.use_denoising = False
        scene.cycles.device = "CPU"
        scene.splatwright_mesh_engine = mesh_engine
        bpy.context.view_layer.use_pass_z = True
        bpy.context.view_layer.splatwright_use_pass_splats = True

    def splat_object(self, name, cloud, relit=True):
        obj, _ = self.module("splat_addon.data").new_splat_object(cloud, name, self.bpy.context.scene.collection)
        obj.splatwright_relight = relit
        return obj

    def floor_mesh(self):
        bpy = self.bpy
        bpy.ops.mesh.primitive_plane_add(size=FLOOR["size"])
        floor = bpy.context.active_object
        floor.name = "Floor"
        mat = bpy.data.materials.new("Floor")
        if bpy.app.version < (5, 0, 0):
            mat.use_nodes = True
        bsdf = next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = (*FLOOR["color"], 1.0)
        floor.data.materials.append(mat)
        return floor

    def engine_inputs(self, name):
        """What the engine reads of the scene (its frame shifted by the camera's position): the cloud
        with its relit mask, the lights and the world, saved for the tests to render with the core."""
        bpy = self.bpy
        scene = bpy.context.scene
        depsgraph = bpy.context.evaluated_depsgraph_get()
        origin = self.origin()
        relit = self.module("splat_addon.render.relit")
        lights = self.module("splat_addon.render.lights")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cloud, lit, _ = relit.scene_cloud(depsgraph, origin)
        extras = {f"extra_{k}": v for k, v in cloud.extras.items()}
        self.save(
            name,
            positions=cloud.positions,
            rotations=cloud.rotations,
            log_scales=cloud.log_scales,
            opacity_logits=cloud.opacity_logits,
            sh=cloud.sh,
            lit=np.zeros(len(cloud), bool) if lit is None else lit,
            origin=origin,
            **extras,
        )
        light_fields = []
        for inst in depsgraph.object_instances:
            if inst.object.type == "LIGHT":
                fields = lights.light_fields(inst.object.data, np.array(inst.matrix_world), origin)
                light_fields.append({k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in fields.items()})
        return {
            "lights": light_fields,
            "world": list(self.module("splat_addon.render.scene").world_color(scene)),
            "origin": origin.tolist(),
            "warnings": [str(w.message) for w in caught],
        }

    def origin(self):
        """The frame the engine renders in (engine.render_origin of the scene's camera)."""
        return self.module("splat_addon.render.engine").render_origin(self.bpy.context.scene.camera)

    def write(self, name):
        scene = self.bpy.context.scene
        self.image_format(scene.render.image_settings, "OPEN_EXR_MULTILAYER", color_depth="32", exr_codec="ZIP")
        scene.render.filepath = str(self.out / f"{name}.exr")
        self.bpy.ops.render.render(write_still=True)

    def camera_record(self):
        from workers.composite import Worker as Composite

        return Composite.camera_record(self)

    def passes(self):
        """A relit splat ball beside an unlit cloud, splats only: the Diffuse, Specular and Shadow passes
        in a multilayer EXR, and what the engine read to make them; then with the sun's Diffuse, then
        Glossy ray visibility off, and with the sun hidden."""
        self.stage("NONE")
        ball = self.splat_object(
            "Ball",
            self.material_cloud(ball_arrays(**{k: BALL[k] for k in ("centre", "radius", "count")}), BALL["albedo"]),
        )
        plain = self.splat_object("Plain", self.random_cloud(300, 1, seed=4, spread=0.3), relit=False)
        plain.location = (-1.2, 0.8, 0.5)
        bare = self.splat_object("Bare", self.random_cloud(50, 1, seed=5, spread=0.1), relit=True)  # no material
        bare.location = (1.2, 0.8, 0.5)
        self.bpy.context.view_layer.update()
        res = self.engine_inputs("passes_inputs")
        self.write("passes")
        res["viewport_lit"] = self.viewport_picture("passes_viewport")
        sun = self.bpy.data.objects["Sun"]
        for ray in ("diffuse", "glossy"):  # the sun's ray visibility, one at a time
            setattr(sun, f"visible_{ray}", False)
            self.bpy.context.view_layer.update()
            self.write(f"passes_no_{ray}")
            setattr(sun, f"visible_{ray}", True)
        sun.hide_render = True
        self.bpy.context.view_layer.update()
        self.write("passes_no_sun")
        sun.hide_render = False
        panel = self.module("splat_addon.ui.panel")
        res.update(
            camera=self.camera_record(),
            status={o.name: panel.material_status(o) for o in (ball, plain, bare)},
            registered=self.bpy.context.scene.render.engine,
        )
        return res

    def viewport_picture(self, name):
        """The Rendered viewport's full picture from the scene camera (its view and projection
        matrices, as composite.py's viewport step builds them), made on this thread."""
        viewport = self.module("splat_addon.render.viewport")

        class Engine:
            def tag_redraw(self):
                pass

        port = viewport.Viewport(Engine())
        try:
            port.update(self.bpy.context.evaluated_depsgraph_get())
            view = viewport.View(bpy_camera(self, viewport))
            self.save(name, rgba=port.picture(view, 1.0, lambda: None))
        finally:
            port.stop()
        return port.inputs[3] is not None

    def splats_shadow_meshes(self):
        """The relit ball over a mesh floor that Cycles renders, with Relight on and off."""
        self.stage("CYCLES")
        self.floor_mesh()
        ball = self.splat_object(
            "Ball",
            self.material_cloud(ball_arrays(**{k: BALL[k] for k in ("centre", "radius", "count")}), BALL["albedo"]),
        )
        self.bpy.context.view_layer.update()
        res = self.engine_inputs("shadow_inputs")
        res["stand_in"] = self.stand_in_within_budgets()
        self.write("ball_relit")
        ball.splatwright_relight = False
        self.write("ball_unlit")
        res["camera"] = self.camera_record()
        return res

    def light_linking(self):
        """Two relit balls and a key light whose receiver collection includes the left one and
        excludes the right: rendered with the key lighting both (no linking), linked, and hidden; and
        the engine's light linking masks, then with the two states swapped."""
        self.stage("NONE")
        bpy = self.bpy
        balls = {}
        for name, centre in LINKED_BALLS.items():
            arrays = ball_arrays(centre, LINKED_RADIUS, 1500)
            balls[name] = self.splat_object(name, self.material_cloud(arrays, BALL["albedo"]))
        key = self.add_light("Key", "POINT", KEY["location"], (0, 0, 0), (1, 1, 1), dict(energy=KEY["energy"]))
        bpy.context.view_layer.update()
        self.write("link_all")
        receivers = bpy.data.collections.new("Key Receivers")
        receivers.objects.link(balls["Right"])
        receivers.objects.link(balls["Left"])
        right, left = receivers.collection_objects  # in the order of receivers.objects
        right.light_linking.link_state = "EXCLUDE"  # the left ball included, the right one excluded
        key.light_linking.receiver_collection = receivers
        bpy.context.view_layer.update()
        self.write("link_left")
        res = {"camera": self.camera_record(), "origin": list(self.origin())}
        res["included"] = self.linking_masks()
        right.light_linking.link_state, left.light_linking.link_state = "INCLUDE", "EXCLUDE"
        bpy.context.view_layer.update()
        res["excluded"] = self.linking_masks()
        key.hide_render = True
        bpy.context.view_layer.update()
        self.write("link_none")
        # The key drawn only by a collection instance whose instancer sets the receiver collection:
        # the instancer's linking rules the instance's light, as Cycles reads it
        key.hide_render, key.light_linking.receiver_collection = False, None
        source = bpy.data.collections.new("Key Source")
        for collection in list(key.users_collection):
            collection.objects.unlink(key)
        source.objects.link(key)
        instancer = bpy.data.objects.new("Key Instancer", None)
        instancer.instance_type, instancer.instance_collection = "COLLECTION", source
        bpy.context.scene.collection.objects.link(instancer)
        instancer.light_linking.receiver_collection = receivers
        bpy.context.view_layer.update()
        res["instanced"] = self.linking_masks()
        bpy.data.objects.remove(instancer)
        return res

    def shadow_linking(self):
        """A ball between a key light and another ball, the sun off: rendered with no shadow linking,
        with the key's blocker collection excluding the near ball, and with that ball moved out of
        the key's way; and the engine's masks."""
        self.stage("NONE")
        bpy = self.bpy
        bpy.data.lights["Sun"].energy = 0.0
        balls = {}
        for name, (centre, radius) in SHADOW_BALLS.items():
            cloud = self.material_cloud(ball_arrays(centre, radius, 1500), BALL["albedo"])
            balls[name] = self.splat_object(name, cloud)
        key = self.key_light()
        self.write("block_all")
        self.blockers_excluding(key, balls["Blocker"])
        self.write("block_linked")
        res = self.linking_record()
        balls["Blocker"].location = (0.0, 0.0, 20.0)  # far above: out of the key's way
        bpy.context.view_layer.update()
        self.write("block_moved")
        # The blocker back in place, drawn only as a collection instance: linked by its instancer
        balls["Blocker"].location = (0.0, 0.0, 0.0)
        source = bpy.data.collections.new("Blocker Source")  # not in the scene: drawn by the instancer
        for collection in list(balls["Blocker"].users_collection):
            collection.objects.unlink(balls["Blocker"])
        source.objects.link(balls["Blocker"])
        instancer = bpy.data.objects.new("Blocker Instancer", None)
        instancer.instance_type, instancer.instance_collection = "COLLECTION", source
        bpy.context.scene.collection.objects.link(instancer)
        key.light_linking.blocker_collection = None
        bpy.context.view_layer.update()
        self.write("block_instanced")  # no linking: the instance shadows as the ball did
        self.blockers_excluding(key, instancer)
        self.write("block_instancer_out")  # its instancer excluded: as with the ball moved away
        res["instanced_masks"] = self.linking_masks()
        key.light_linking.blocker_collection = None
        bpy.data.objects.remove(instancer)
        return res

    def mesh_shadow_linking(self):
        """A relit splat ball over a Cycles floor, a mesh ball between it and a key light, the sun
        off. The key's blocker collection excluding the mesh ball (block_mesh_out) against the mesh
        ball moved out of the way (block_mesh_moved) and left where it is unlinked (block_mesh_all),
        rendered and in the Rendered viewport (viewport_mesh_*);
        then, the mesh ball away, the collection including the splat ball (stand_in_in), excluding
        it (stand_in_out), and the ball unlit (stand_in_none: no stand-in); the engine's masks."""
        self.stage("CYCLES")
        bpy = self.bpy
        bpy.data.lights["Sun"].energy = 0.0
        self.floor_mesh()
        centre, radius = SHADOW_BALLS["Shaded"]
        shaded = self.splat_object("Shaded", self.material_cloud(ball_arrays(centre, radius, 1500), BALL["albedo"]))
        centre, radius = SHADOW_BALLS["Blocker"]
        bpy.ops.mesh.primitive_uv_sphere_add(radius=radius, location=centre, segments=32, ring_count=16)
        blocker = bpy.context.active_object
        blocker.name = "MeshBlocker"
        key = self.key_light()
        self.write("block_mesh_all")
        self.viewport_picture("viewport_mesh_all")
        blockers = self.blockers_excluding(key, blocker)
        self.write("block_mesh_out")
        self.viewport_picture("viewport_mesh_out")
        res = self.linking_record()
        key.light_linking.blocker_collection = None
        blocker.location = (0.0, 0.0, 20.0)  # far above: out of the key's way
        bpy.context.view_layer.update()
        self.write("block_mesh_moved")
        self.viewport_picture("viewport_mesh_moved")
        blockers.objects.unlink(blocker)
        blockers.objects.link(shaded)
        key.light_linking.blocker_collection = blockers
        for state, name in (("INCLUDE", "stand_in_in"), ("EXCLUDE", "stand_in_out")):
            blockers.collection_objects[0].light_linking.link_state = state
            bpy.context.view_layer.update()
            self.write(name)
        key.light_linking.blocker_collection = None
        shaded.splatwright_relight = False
        bpy.context.view_layer.update()
        self.write("stand_in_none")
        return res

    def key_light(self):
        """The shadow linking steps' key light, a small point light."""
        key = self.add_light("Key", "POINT", KEY["location"], (0, 0, 0), (1, 1, 1), dict(energy=KEY["energy"]))
        key.data.shadow_soft_size = 0.05
        self.bpy.context.view_layer.update()
        return key

    def blockers_excluding(self, light, obj):
        """A new blocker collection of `light` that excludes `obj` (and names nothing else)."""
        blockers = self.bpy.data.collections.new("Key Blockers")
        blockers.objects.link(obj)
        blockers.collection_objects[0].light_linking.link_state = "EXCLUDE"
        light.light_linking.blocker_collection = blockers
        self.bpy.context.view_layer.update()
        return blockers

    def linking_record(self):
        """The camera, the engine's frame origin and the engine's linking masks (linking_masks)."""
        origin = list(self.origin())
        return {"camera": self.camera_record(), "origin": origin, "masks": self.linking_masks()}

    def linking_masks(self):
        """Per light the engine reads: how many splats of each ball it lights and how many shadow it
        (None: every splat)."""
        bpy = self.bpy
        relit = self.module("splat_addon.render.relit")
        depsgraph = bpy.context.evaluated_depsgraph_get()
        cloud, lit, owners = relit.scene_cloud(depsgraph, np.zeros(3))
        meshes = relit.occluders(depsgraph, np.zeros(3))
        found, receivers, blockers, mesh_blockers = relit.linked_lights(depsgraph, np.zeros(3), owners, meshes)
        names, index = owners
        out = {}
        for kind, masks in (("lit", receivers), ("blocking", blockers)):
            for k, light in enumerate(found):
                mask = masks.get(k)
                counts = None if mask is None else {_named(n): int(mask[index == i].sum()) for i, n in enumerate(names)}
                out[f"{light.kind} {kind}"] = counts
        for k, surfaces in mesh_blockers.items():  # only the lights whose blockers leave a mesh out
            mesh_names, triangle_owner = meshes.owners
            taken = np.concatenate([triangle_owner[s.faces[:, 0] // 3] for s in surfaces] or [np.zeros(0, int)])
            counts = {_named(n): int((taken == i).sum()) for i, n in enumerate(mesh_names)}
            out[f"{found[k].kind} mesh blocking"] = counts
        return out

    def stand_in_within_budgets(self):
        """The relit ball's shadow stand-in under an ample budget, one that holds only the coarse
        shape, and one that holds neither: (triangles or None, warnings) each, and the splat count."""
        relit = self.module("splat_addon.render.relit")
        casters = self.module("core.shadow_casters")
        cloud, lit, _ = relit.scene_cloud(self.bpy.context.evaluated_depsgraph_get(), np.zeros(3))
        count = int(casters.casting(cloud[lit]).sum())
        coarse = count * len(casters.SHAPES[1][1]) * casters.BYTES_PER_TRIANGLE
        out = {"count": count}
        for name, budget in (("ample", 1 << 40), ("coarse", coarse), ("none", coarse - 1)):
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                made = relit.shadow_casters(cloud, lit, np.zeros(3), budget=budget)
            out[name] = (None if made is None else len(made[1]), [str(w.message) for w in caught])
        return out

    def meshes_shadow_splats(self):
        """A mesh ball over a relit splat floor: the mesh's shadow on the splats."""
        bpy = self.bpy
        self.stage("CYCLES")
        floor = self.material_cloud(floor_arrays(FLOOR["size"], 0.05), FLOOR["color"])
        self.splat_object("SplatFloor", floor)
        bpy.ops.mesh.primitive_uv_sphere_add(radius=BALL["radius"], location=BALL["centre"], segments=48, ring_count=24)
        bpy.context.view_layer.update()
        res = self.engine_inputs("floor_inputs")
        self.write("floor_relit")
        res["camera"] = self.camera_record()
        # The world alone, unoccluded and occluded by the ball (World Occlusion directions).
        bpy.data.objects["Sun"].hide_render = True
        scene = bpy.context.scene
        for name, directions in (("floor_world", 0), ("floor_world_occluded", 24)):
            scene.splatwright_world_occlusion = directions
            self.write(name)
        res["world_occlusion"] = self.module("splat_addon.render.lights").scene_world(scene).occlusion
        res["viewport_world_maps"] = self.viewport_world_maps()
        scene.splatwright_world_occlusion = 0
        return res

    def textured_world(self):
        """The world a relit scene sees when an Environment Texture without an image feeds its
        Background's Color, one with a float image bright above 30 degrees of latitude (its Strength
        2), one with an sRGB image of grey 0.5, the float one looked up through a Mapping node turning
        the Generated direction by MAP_TURN (Point, then Texture), then through one fed nothing, the
        float one with a sun in it (SUNNY_PATCH) plain and turned, a Value node its Strength, then
        neither: (colour, warnings, environment coefficients or None, the sun's direction, power and
        colour or None) of lights.scene_world each time."""
        bpy = self.bpy
        self.stage("NONE")
        scene = bpy.context.scene
        tree = scene.world.node_tree
        background = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeBackground")
        lights = self.module("splat_addon.render.lights")
        texture, value = tree.nodes.new("ShaderNodeTexEnvironment"), tree.nodes.new("ShaderNodeValue")
        texture.name, value.name = "Sky HDRI", "Brightness"
        cap = bpy.data.images.new("Cap", 64, 48, float_buffer=True)
        pixels = np.zeros((48, 64, 4), np.float32)
        pixels[32:, :, :3] = HDRI_CAP  # rows from the bottom: the top 16 of 48 lie above 30 degrees
        pixels[..., 3] = 1.0
        cap.pixels.foreach_set(pixels.ravel())
        sunny = bpy.data.images.new("Sunny", 64, 48, float_buffer=True)
        pixels[36:38, 40:42, :3] = SUNNY_PATCH  # a sun: 4 pixels far brighter than the rest
        sunny.pixels.foreach_set(pixels.ravel())
        grey = bpy.data.images.new("Grey", 16, 8)  # 8-bit, sRGB
        grey.pixels.foreach_set(np.full(16 * 8 * 4, 0.5, np.float32))
        out = {"cap_space": cap.colorspace_settings.name, "grey_space": grey.colorspace_settings.name}
        mapping, coordinates = tree.nodes.new("ShaderNodeMapping"), tree.nodes.new("ShaderNodeTexCoord")
        mapping.inputs["Rotation"].default_value = MAP_TURN
        turned = {"point": "POINT", "texture_turn": "TEXTURE", "remapped": "POINT", "sunny_turned": "POINT"}
        names = ("texture", "hdri", "srgb", "point", "texture_turn", "remapped", "sunny", "sunny_turned")
        for name in (*names, "strength", "plain"):
            for link in list(tree.links):
                if link.to_node in (background, texture, mapping):
                    tree.links.remove(link)
            plain = name in ("texture", "strength", "plain")  # no image
            texture.image = {"srgb": grey, "sunny": sunny, "sunny_turned": sunny}.get(name, None if plain else cap)
            background.inputs["Strength"].default_value = 1.0 if plain or name == "srgb" else 2.0
            if texture.image is not None or name == "texture":
                tree.links.new(texture.outputs["Color"], background.inputs["Color"])
            if name in turned:
                mapping.vector_type = turned[name]
                tree.links.new(mapping.outputs["Vector"], texture.inputs["Vector"])
                if name != "remapped":  # the Generated direction turned; remapped: the mapping fed nothing
                    tree.links.new(coordinates.outputs["Generated"], mapping.inputs["Vector"])
            if name == "strength":
                tree.links.new(value.outputs["Value"], background.inputs["Strength"])
            world, caught = _warned(lambda: lights.scene_world(scene))
            environment = None if world.environment is None else world.environment.tolist()
            sun = None if world.sun is None else (list(world.sun.direction), world.sun.power, list(world.sun.color))
            out[name] = (list(world.color), caught, environment, sun)
        background.inputs["Strength"].default_value = 1.0
        tree.nodes.remove(texture)
        tree.nodes.remove(value)
        tree.nodes.remove(mapping)
        tree.nodes.remove(coordinates)
        bpy.data.images.remove(cap)
        bpy.data.images.remove(sunny)
        bpy.data.images.remove(grey)
        return out

    def light_nodes(self):
        """A point light whose nodes set its Emission Strength and Color (Use Nodes on where Blender
        has it), then a Value node on the Strength: (colour, warnings) of lights.scene_lights' light
        each time, beside its colour without nodes."""
        bpy = self.bpy
        self.stage("NONE")
        bpy.data.lights["Sun"].energy = 0.0  # a light of no power is left out
        key = self.add_light("Key", "POINT", KEY["location"], (0, 0, 0), (1, 1, 1), dict(energy=KEY["energy"]))
        lights = self.module("splat_addon.render.lights")

        def read():
            bpy.context.view_layer.update()
            found, caught = _warned(lambda: lights.scene_lights(bpy.context.evaluated_depsgraph_get(), np.zeros(3)))
            (light,) = found
            return list(light.color), caught

        out = {"plain": read()}
        if key.data.node_tree is None or bpy.app.version < (5, 0, 0):  # Use Nodes makes them (deprecated in 5)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                key.data.use_nodes = True
        tree = key.data.node_tree
        emission = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeEmission")
        emission.inputs["Strength"].default_value = LIGHT_NODE["strength"]
        emission.inputs["Color"].default_value = (*LIGHT_NODE["color"], 1.0)
        out["emission"] = read()
        value = tree.nodes.new("ShaderNodeValue")
        value.name = "IES Stand-in"
        tree.links.new(value.outputs["Value"], emission.inputs["Strength"])
        out["driven"] = read()
        bpy.data.objects.remove(key)
        return out

    def engine_reports(self):
        """A final render (F12) of a relit ball under an environment texture (Background's Color)
        and a light whose Emission Strength a Value node drives, drawn three times by collection
        instances: the warnings the engine reports, (kinds, message) each, as it hands them to its
        `report`."""
        bpy = self.bpy
        self.stage("NONE")
        scene = bpy.context.scene
        tree = scene.world.node_tree
        background = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeBackground")
        texture = tree.nodes.new("ShaderNodeTexEnvironment")
        texture.name = "Sky HDRI"
        texture.image = bpy.data.images.new("Sky", 16, 8, float_buffer=True)
        tree.links.new(texture.outputs["Color"], background.inputs["Color"])
        keys = bpy.data.collections.new("Keys")  # in no scene: drawn only by its instances
        key = self.add_light("Key", "POINT", KEY["location"], (0, 0, 0), (1, 1, 1), dict(energy=KEY["energy"]), keys)
        if key.data.node_tree is None or bpy.app.version < (5, 0, 0):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                key.data.use_nodes = True
        nodes = key.data.node_tree
        value = nodes.nodes.new("ShaderNodeValue")
        value.name = "IES Stand-in"
        emission = next(n for n in nodes.nodes if n.bl_idname == "ShaderNodeEmission")
        nodes.links.new(value.outputs["Value"], emission.inputs["Strength"])
        instancers = []
        for k in range(3):
            instancer = bpy.data.objects.new(f"Keys{k}", None)
            instancer.instance_type, instancer.instance_collection = "COLLECTION", keys
            instancer.location = (0.3 * k, 0.0, 0.0)
            scene.collection.objects.link(instancer)
            instancers.append(instancer)
        cloud = self.material_cloud(ball_arrays(**{k: BALL[k] for k in ("centre", "radius", "count")}), BALL["albedo"])
        ball = self.splat_object("Ball", cloud)
        try:
            reports = self.reported(bpy.ops.render.render)
        finally:
            for obj in (ball, *instancers, key):
                bpy.data.objects.remove(obj)
            bpy.data.collections.remove(keys)
            bpy.data.images.remove(texture.image)
            tree.nodes.remove(texture)
        return reports

    def reported(self, call):
        """The warnings the engine reports while call() runs, (kinds, message) each, as it hands them
        to its `report` (a RenderEngine's own report cannot be replaced from Python)."""
        data = self.module("splat_addon.data")
        reported_warnings, reports = data.reported_warnings, []

        def kept(report):
            return reported_warnings(
                lambda kinds, message: (reports.append((sorted(kinds), message)), report(kinds, message))
            )

        data.reported_warnings = kept
        try:
            call()
        finally:
            data.reported_warnings = reported_warnings
        return reports

    def animation_frames(self):
        """A relit splat ball over a relit splat floor (splats only, the world occluded from 8
        directions) rendered as an animation of three frames, the camera moved from frame 1 to 2 and
        the sun turned from 2 to 3, then each frame as a still: the frames at which the sun's maps and
        the world's occlusion were made during the animation, and the free bytes core.scratch keeps
        after each of its frames and after the job."""
        bpy = self.bpy
        self.stage("NONE")
        scene = bpy.context.scene
        ball = ball_arrays(**{k: BALL[k] for k in ("centre", "radius", "count")})
        self.splat_object("SplatFloor", self.material_cloud(floor_arrays(FLOOR["size"], 0.05), FLOOR["color"]))
        self.splat_object("Ball", self.material_cloud(ball, BALL["albedo"]))
        scene.splatwright_world_occlusion = 8
        cam, sun = scene.camera, bpy.data.objects["Sun"]
        cam.keyframe_insert("location", frame=1)
        cam.location.x += 0.3
        cam.keyframe_insert("location", frame=2)
        sun.keyframe_insert("rotation_euler", frame=2)
        sun.rotation_euler.x += 0.2
        sun.keyframe_insert("rotation_euler", frame=3)
        scene.frame_start, scene.frame_end = 1, 3
        shadows, ambient = self.module("core.shadows"), self.module("core.ambient")
        scratch = self.module("core.scratch")
        originals = shadows.visibility, ambient.world_visibility
        made, inside, kept = {"sun": [], "world": []}, [], []

        def counted(name, original):
            def call(*args, **kwargs):
                if not inside:  # the world's occlusion draws suns of its own
                    made[name].append(scene.frame_current)
                inside.append(name == "world")
                try:
                    return original(*args, **kwargs)
                finally:
                    inside.pop()

            return call

        self.image_format(scene.render.image_settings, "OPEN_EXR_MULTILAYER", color_depth="32", exr_codec="ZIP")
        scene.render.filepath = str(self.out / "animation_####")

        def after_frame(*_):
            kept.append(scratch.kept_bytes()[1])

        shadows.visibility, ambient.world_visibility = counted("sun", originals[0]), counted("world", originals[1])
        bpy.app.handlers.render_post.append(after_frame)
        try:
            bpy.ops.render.render(animation=True)
        finally:
            shadows.visibility, ambient.world_visibility = originals
            bpy.app.handlers.render_post.remove(after_frame)
        after_job = scratch.kept_bytes()[1]
        for frame in (1, 2, 3):
            scene.frame_set(frame)
            self.write(f"still_{frame}")
        scene.splatwright_world_occlusion = 0
        return dict(made=made, free_after_frames=kept, free_after_job=after_job)

    def sunny_map(self):
        """world_shadow under an Environment Texture of a dim sky with a sun in it (SUNNY_MAP)."""
        width, height = SUNNY_MAP["size"]
        sky = np.full((height, width, 4), SUNNY_MAP["sky"], np.float32)
        sky[..., 3] = 1.0
        sun = dict(diameter=math.radians(SUNNY_MAP["diameter"]), irradiance=SUNNY_MAP["irradiance"])
        sun.update(latitude=math.radians(SUNNY_MAP["elevation"]), longitude=math.radians(SUNNY_MAP["azimuth"]))

        def world():
            texture, image = self.world_map(add_sun(sky, **sun), "Sunny")
            return lambda: (
                self.bpy.context.scene.world.node_tree.nodes.remove(texture),
                self.bpy.data.images.remove(image),
            )

        return self.world_shadow("sunny_map", world)

    def sky_sun(self):
        """world_shadow under a Sky Texture with its sun disc (SKY_SUN; the model of each Blender)."""
        bpy = self.bpy

        def world():
            tree = bpy.context.scene.world.node_tree
            background = next(n for n in tree.nodes if n.bl_idname == "ShaderNodeBackground")
            sky = tree.nodes.new("ShaderNodeTexSky")
            sky.sky_type = SKY_SUN["models"][bpy.app.version >= (5, 0, 0)]
            sky.sun_elevation, sky.sun_rotation = math.radians(SKY_SUN["elevation"]), math.radians(SKY_SUN["rotation"])
            tree.links.new(sky.outputs["Color"], background.inputs["Color"])
            background.inputs["Strength"].default_value = SKY_SUN["strength"]
            return lambda: tree.nodes.remove(sky)

        def viewport():
            """The Rendered viewport's world light: the sun the final render read ("after"); once the
            sun is raised 10 degrees, none at first and the world asked for ("asked"), then, with
            that render done ("ready"), the raised sun's direction ("raised")."""
            viewport, mesh_layer = (self.module(f"splat_addon.render.{name}") for name in ("viewport", "mesh_layer"))
            ready = []

            def sun():
                depsgraph = bpy.context.evaluated_depsgraph_get()
                return viewport.picture_inputs(depsgraph, world_ready=lambda: ready.append(1))[3].world.sun

            after = sun() is not None
            sky = next(n for n in bpy.context.scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeTexSky")
            sky.sun_elevation += math.radians(10.0)
            asked = sun() is None
            mesh_layer.wait_world_jobs(timeout=120)
            raised = sun()
            # a world whose render fails: asked for once, lit by its colour on every update after
            rendered, tries = mesh_layer._rendered, []

            def failing(*args):
                tries.append(1)
                raise RuntimeError("a world that cannot be rendered")

            mesh_layer._rendered = failing
            try:
                sky.sun_elevation += math.radians(5.0)
                failed = []
                for _ in range(3):  # three scene updates, each after the last one's render is over
                    failed.append(sun() is None)
                    mesh_layer.wait_world_jobs(timeout=120)
            finally:
                mesh_layer._rendered = rendered
            out = {"after": after, "asked": asked, "ready": len(ready), "raised": list(-raised.direction)}
            return {**out, "failed": failed, "tries": len(tries)}

        return self.world_shadow("sky_sun", world, viewport)

    def world_shadow(self, name, world, after=lambda: None):
        """A relit splat ball over a relit splat floor (splats only) with no light but the world that
        world() sets up (returning what undoes it): the multilayer EXR `name` (its Shadow pass), the
        camera, the warnings the engine reported and what after() gives once it has rendered."""
        bpy = self.bpy
        self.stage("NONE")
        bpy.data.objects["Sun"].hide_render = True
        ball = ball_arrays(**{k: BALL[k] for k in ("centre", "radius", "count")})
        floor = self.splat_object("SplatFloor", self.material_cloud(floor_arrays(FLOOR["size"], 0.05), FLOOR["color"]))
        ball = self.splat_object("Ball", self.material_cloud(ball, BALL["albedo"]))
        undo = world()
        try:
            reports = self.reported(lambda: self.write(name))
            later = after()
        finally:
            undo()
            bpy.data.objects["Sun"].hide_render = False
            for obj in (floor, ball):
                bpy.data.objects.remove(obj)
        return {"camera": self.camera_record(), "origin": self.origin().tolist(), "reports": reports, "after": later}

    def viewport_world_maps(self):
        """How often the Rendered viewport makes the world's occlusion over four scene updates: the
        first picture, a moved light (kept), a moved mesh, and a moved splat object (both made again)."""
        bpy = self.bpy
        ambient = self.module("core.ambient")
        viewport = self.module("splat_addon.render.viewport")
        made, original = [], ambient.world_visibility

        def counted(*args, **kwargs):
            made.append(1)
            return original(*args, **kwargs)

        class Engine:
            def tag_redraw(self):
                pass

        sun, ball = bpy.data.objects["Sun"], next(o for o in bpy.data.objects if o.type == "MESH")
        floor = bpy.data.objects["SplatFloor"]
        moves = [(None, 0, 0.0), (sun, 2, 6.0), (ball, 0, 0.2), (floor, 1, 0.1)]  # object, axis, metres
        counts, port = [], viewport.Viewport(Engine())
        ambient.world_visibility = counted
        try:
            for obj, axis, shift in moves:
                if obj is not None:
                    obj.location[axis] += shift
                bpy.context.view_layer.update()
                port.update(bpy.context.evaluated_depsgraph_get())
                port.inputs[3].shade(port.inputs[0], bpy_camera(self, viewport))
                counts.append(len(made))
        finally:
            ambient.world_visibility = original
            port.stop()
        return counts

    def rig(self):
        """The demo rig's arm converted with its material, bound, relit, over the demo's mesh floor:
        frames 1 and 12 rendered with Relight on and off."""
        bpy = self.bpy
        scene = bpy.context.scene
        rig = self.module("splat_addon.convert.demo_rig").build_demo_rig(scene, 0, calibrate=False)
        self.select([rig.body])
        bpy.ops.splat.from_mesh(max_splats=4000, calibrate=False, use_material=True)
        splats = bpy.context.active_object
        rig.body.hide_render = True
        self.select([splats, rig.armature], active=rig.armature)
        bound = self.call(bpy.ops.splat.bind_armature, armature=rig.armature.name)
        splats.splatwright_relight = True
        render = scene.render
        render.engine = "SPLATWRIGHT"
        render.resolution_x, render.resolution_y = 128, 96
        render.resolution_percentage = 100
        scene.cycles.samples = SAMPLES
        scene.cycles.use_denoising = False
        scene.cycles.device = "CPU"
        scene.splatwright_mesh_engine = "CYCLES"
        bpy.context.view_layer.splatwright_use_pass_splats = True
        res = {"bind": bound, "frames": {}}
        for frame in (1, 12):
            scene.frame_set(frame)
            splats.splatwright_relight = True
            res["frames"][frame] = self.engine_inputs(f"rig_inputs_{frame}")
            self.write(f"rig_relit_{frame}")
            splats.splatwright_relight = False
            self.write(f"rig_unlit_{frame}")
        res["camera"] = self.camera_record()
        res["sun"] = np.array(rig.light.matrix_world).tolist()
        return res


if __name__ == "__main__":
    worker_main(Worker)
