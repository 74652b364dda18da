"""The Blender side of tests/test_blender_composite.py (run in each Blender of the version matrix; see
workers/base.py): a plane and a sphere crossing a splat cloud, rendered by Cycles alone and by the
SPLATWRIGHT engine compositing the splats with Cycles' meshes, through F12's operator, the command
verb and over an animation."""

import numpy as np

from workers.base import BlenderWorker, random_cloud_arrays, worker_main

SIZE = (64, 48)
EMISSION_SIZE = (192, 144)  # larger: the emission comparison is about the inside of surfaces
CLOUD = dict(n=500, sh_degree=1, seed=21, spread=0.55)
CLOUD_CENTRE = (0.1, 0.0, 0.45)
CAMERA = dict(location=(1.6, -4.6, 2.3), look_at=(0.0, 0.0, 0.35), lens=35.0)
PLANE = dict(size=4.0, location=(0.0, 0.0, 0.0), color=(0.55, 0.5, 0.4))
SPHERE = dict(radius=0.55, location=(0.35, 0.1, 0.5), color=(0.8, 0.15, 0.1))
WORLD = (0.05, 0.08, 0.12)
EMISSION = {"Plane": (0.2, 0.45, 0.9), "Sphere": (0.95, 0.6, 0.1)}
SPHERE_MOVE = (-0.6, 0.0, 0.2)  # frame 2 of the animation: the sphere moved by this
GLASS = dict(size=1.5, location=(-0.45, -0.45, 0.85), color=(0.1, 0.9, 0.3), alpha=0.6)  # upright, translucent
SAMPLES = 8


def oracle_cloud_arrays():
    """The splat cloud of every step: random SH splats around the plane and the sphere."""
    arrays = random_cloud_arrays(CLOUD["n"], CLOUD["sh_degree"], CLOUD["seed"], CLOUD["spread"])
    rng = np.random.default_rng(CLOUD["seed"] + 1)
    arrays["positions"] = arrays["positions"] * np.array([1.2, 1.2, 0.6]) + np.array(CLOUD_CENTRE)
    arrays["log_scales"] = rng.uniform(-3.4, -2.2, arrays["log_scales"].shape)
    arrays["opacity_logits"] = rng.normal(1.0, 1.5, len(arrays["opacity_logits"]))
    return arrays


class Worker(BlenderWorker):
    steps = ("install", "oracle", "emission", "translucent", "command", "animation", "viewport")
    keep_objects = ("Camera", "Light")
    orphan_kinds = ("meshes", "materials", "actions")

    # the scene ------------------------------------------------------------------------------------

    def build(self, emission=False):
        """Plane, sphere, splats, camera, world and Cycles settings; returns the splat object."""
        bpy = self.bpy
        from mathutils import Vector

        scene = bpy.context.scene
        bpy.ops.mesh.primitive_plane_add(size=PLANE["size"], location=PLANE["location"])
        bpy.context.active_object.name = "Plane"
        bpy.ops.mesh.primitive_uv_sphere_add(radius=SPHERE["radius"], location=SPHERE["location"])
        bpy.context.active_object.name = "Sphere"
        for name, spec in (("Plane", PLANE), ("Sphere", SPHERE)):
            color = EMISSION[name] if emission else spec["color"]
            scene.objects[name].data.materials.append(self.material(name, color, emission))
        ext = self.module("splat_addon")
        splats, _ = ext.data.new_splat_object(
            self.module("core").SplatCloud(**oracle_cloud_arrays()), "Splats", scene.collection
        )
        cam = scene.camera
        cam.location = CAMERA["location"]
        cam.rotation_euler = (
            (Vector(CAMERA["look_at"]) - Vector(CAMERA["location"])).to_track_quat("-Z", "Y").to_euler()
        )
        cam.data.lens = CAMERA["lens"]
        background = next(n for n in scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground")
        background.inputs["Color"].default_value = (*WORLD, 1.0)
        background.inputs["Strength"].default_value = 0.0 if emission else 1.0
        render = scene.render
        render.resolution_x, render.resolution_y = EMISSION_SIZE if emission else SIZE
        render.resolution_percentage = 100
        render.film_transparent = False
        render.dither_intensity = 0.0
        scene.view_settings.view_transform = "Standard"
        scene.cycles.samples = 16 if emission else SAMPLES
        scene.cycles.use_denoising = False
        scene.cycles.device = "CPU"
        scene.splatwright_mesh_engine = "CYCLES"
        bpy.context.view_layer.use_pass_z = True
        bpy.context.view_layer.splatwright_use_pass_splats = True
        bpy.context.view_layer.update()
        return splats

    def material(self, name, color, emission, alpha=1.0):
        """Principled with a base colour, or flat emission; emission with alpha < 1 is mixed with a
        Transparent BSDF, which Cycles counts as that alpha."""
        bpy = self.bpy
        mat = bpy.data.materials.new(name)
        if bpy.app.version < (5, 0, 0):
            mat.use_nodes = True
        tree = mat.node_tree
        nodes = tree.nodes
        if emission:
            nodes.remove(next(n for n in nodes if n.bl_idname == "ShaderNodeBsdfPrincipled"))
            node = nodes.new("ShaderNodeEmission")
            node.inputs["Color"].default_value = (*color, 1.0)
            node.inputs["Strength"].default_value = 1.0
            output = next(n for n in nodes if n.bl_idname == "ShaderNodeOutputMaterial")
            shader = node.outputs["Emission"]
            if alpha < 1.0:
                mix = nodes.new("ShaderNodeMixShader")
                mix.inputs[0].default_value = alpha
                tree.links.new(nodes.new("ShaderNodeBsdfTransparent").outputs[0], mix.inputs[1])
                tree.links.new(shader, mix.inputs[2])
                shader = mix.outputs[0]
            tree.links.new(shader, output.inputs["Surface"])
        else:
            bsdf = next(n for n in nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
            bsdf.inputs["Base Color"].default_value = (*color, 1.0)
        return mat

    def camera_record(self):
        scene = self.bpy.context.scene
        cam = scene.camera
        d = cam.data
        return {
            "matrix_world": np.array(cam.matrix_world).tolist(),
            "lens": d.lens,
            "sensor_width": d.sensor_width,
            "sensor_height": d.sensor_height,
            "sensor_fit": d.sensor_fit,
            "shift_x": d.shift_x,
            "shift_y": d.shift_y,
            "type": d.type,
            "ortho_scale": d.ortho_scale,
            "clip_start": d.clip_start,
            "clip_end": d.clip_end,
            "pixel_aspect_x": scene.render.pixel_aspect_x,
            "pixel_aspect_y": scene.render.pixel_aspect_y,
            "resolution": [scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage],
        }

    # rendering ------------------------------------------------------------------------------------

    def write(self, name, kind):
        """Render the scene with its engine to out/<name>.<kind> (PNG or multilayer EXR)."""
        bpy = self.bpy
        scene = bpy.context.scene
        if kind == "png":
            self.image_format(scene.render.image_settings, "PNG", color_mode="RGBA", color_depth="8")
        else:
            self.image_format(scene.render.image_settings, "OPEN_EXR_MULTILAYER", color_depth="32", exr_codec="ZIP")
        scene.render.filepath = str(self.out / f"{name}.{kind}")
        bpy.ops.render.render(write_still=True)

    def cycles_alone(self, splats, name):
        """The meshes as Cycles renders them with the splat object hidden: the oracle's opaque layer."""
        scene = self.bpy.context.scene
        scene.render.engine = "CYCLES"
        splats.hide_render = True
        self.write(name, "exr")
        splats.hide_render = False
        scene.render.engine = "SPLATWRIGHT"

    def composited(self, name):
        self.bpy.context.scene.render.engine = "SPLATWRIGHT"
        self.write(name, "exr")
        self.write(name, "png")

    # steps ------------------------------------------------------------------------------------------

    def install(self):
        self.install_extension()
        return {"mesh_engine": self.bpy.context.scene.splatwright_mesh_engine}

    def oracle(self):
        splats = self.build()
        scene = self.bpy.context.scene
        res = {"camera": self.camera_record()}
        for film in ("opaque", "transparent"):
            scene.render.film_transparent = film == "transparent"
            self.cycles_alone(splats, f"meshes_{film}")
            self.composited(f"composite_{film}")
        return res

    def emission(self):
        splats = self.build(emission=True)
        self.composited("emission")
        depsgraph = self.bpy.context.evaluated_depsgraph_get()
        triangles = {}
        for name in EMISSION:
            obj = self.bpy.context.scene.objects[name].evaluated_get(depsgraph)
            mesh = obj.data
            mesh.calc_loop_triangles()
            co = np.empty(len(mesh.vertices) * 3, np.float64)
            mesh.vertices.foreach_get("co", co)
            tris = np.empty(len(mesh.loop_triangles) * 3, np.int64)
            mesh.loop_triangles.foreach_get("vertices", tris)
            co = co.reshape(-1, 3) @ np.array(obj.matrix_world)[:3, :3].T + np.array(obj.matrix_world)[:3, 3]
            triangles[name] = co[tris.reshape(-1, 3)]
        self.save("emission_triangles", **triangles)
        return {"camera": self.camera_record(), "hidden": splats.hide_render}

    def translucent(self):
        """A translucent upright plane through the cloud, partly over the world, partly over the
        ground; the film opaque. Cycles also renders the meshes alone, all together, the glass alone
        and the rest alone (film transparent): the single-layer and the two-layer truths."""
        bpy = self.bpy
        splats = self.build(emission=True)
        scene = bpy.context.scene
        background = next(n for n in scene.world.node_tree.nodes if n.bl_idname == "ShaderNodeBackground")
        background.inputs["Strength"].default_value = 1.0
        scene.render.resolution_x, scene.render.resolution_y = SIZE
        bpy.ops.mesh.primitive_plane_add(size=GLASS["size"], location=GLASS["location"], rotation=(np.pi / 2, 0, 0))
        glass = bpy.context.active_object
        glass.name = "Glass"
        glass.data.materials.append(self.material("Glass", GLASS["color"], True, GLASS["alpha"]))
        bpy.context.view_layer.update()
        self.composited("translucent")
        self.cycles_alone(splats, "tr_meshes_opaque")
        scene.render.film_transparent = True
        self.cycles_alone(splats, "tr_meshes")
        solid = [scene.objects["Plane"], scene.objects["Sphere"]]
        for shown, name in (([glass], "tr_glass"), (solid, "tr_solid")):
            hidden = [o for o in [glass] + solid if o not in shown]
            for obj in hidden:
                obj.hide_render = True
            self.cycles_alone(splats, name)
            for obj in hidden:
                obj.hide_render = False
        return {"camera": self.camera_record()}

    def command(self):
        self.build()
        self.composited("f12")
        self.image_format(self.bpy.context.scene.render.image_settings, "OPEN_EXR_MULTILAYER", color_depth="32")
        command = self.module("splat_addon.command")
        codes = [
            command.execute(["render", str(self.out / "verb_####.exr"), "--frames", "1"]),
            command.execute(["render", str(self.out / "verb_none_####.png"), "--frames", "1", "--meshes", "none"]),
        ]
        return {"codes": codes, "mesh_engine_after": self.bpy.context.scene.splatwright_mesh_engine}

    def animation(self):
        splats = self.build()
        scene = self.bpy.context.scene
        sphere = scene.objects["Sphere"]
        for frame, offset in ((1, (0.0, 0.0, 0.0)), (2, SPHERE_MOVE)):
            sphere.location = np.add(SPHERE["location"], offset)
            sphere.keyframe_insert("location", frame=frame)
        scene.frame_start, scene.frame_end = 1, 2
        for frame in (1, 2):
            scene.frame_set(frame)
            self.cycles_alone(splats, f"anim_meshes_{frame}")
        scene.frame_set(1)
        self.image_format(scene.render.image_settings, "OPEN_EXR_MULTILAYER", color_depth="32")
        scene.render.filepath = str(self.out / "anim_####")
        self.bpy.ops.render.render(animation=True)
        return {"frame_after": scene.frame_current}

    def viewport(self):
        """The Rendered viewport's picture, headless: the region camera from the scene camera's view
        and projection matrices, the picture at full and coarse scale through the progressive
        renderer, and the mesh layer it composites with."""
        import time

        bpy = self.bpy
        self.build()
        scene = bpy.context.scene
        depsgraph = bpy.context.evaluated_depsgraph_get()
        cam = scene.camera
        view = np.array(cam.matrix_world.inverted())
        projection = np.array(cam.calc_matrix_camera(depsgraph, x=SIZE[0], y=SIZE[1]))
        viewport = self.module("splat_addon.render.viewport")
        preview = self.module("core.preview")

        class Region:
            width, height = SIZE

        class RegionData:
            view_matrix, window_matrix = cam.matrix_world.inverted(), projection

        class Engine:
            redraws = 0

            def tag_redraw(self):
                Engine.redraws += 1

        engine = Engine()
        port = viewport.Viewport(engine)
        port.update(depsgraph)
        camera = viewport.region_camera(Region, RegionData)
        frames, start = [], time.monotonic()
        try:
            while time.monotonic() - start < 60:
                frame = port.progressive.show(viewport.View(camera))
                if frame is not None and (not frames or frames[-1] is not frame):
                    frames.append(frame)
                    if frame.scale == 1.0:
                        break
                time.sleep(0.01)
        finally:
            port.stop()
        cloud, meshes, background, _ = port.inputs
        layer = preview.mesh_layer(meshes, camera)
        self.save(
            "viewport",
            full=frames[-1].image,
            coarse=frames[0].image,
            layer_color=layer.color,
            layer_alpha=layer.alpha,
            layer_depth=layer.depth,
            world=view,
            projection=projection,
        )
        return {
            "camera": self.camera_record(),
            "scales": [f.scale for f in frames],
            "redraws": Engine.redraws,
            "splats": len(cloud),
            "triangles": len(meshes),
            "background": list(background),
            "mesh_triangles": sum(
                len(o.data.polygons) * 2 for o in scene.objects if o.type == "MESH" and o.name != "Splats"
            ),
        }


if __name__ == "__main__":
    worker_main(Worker)
