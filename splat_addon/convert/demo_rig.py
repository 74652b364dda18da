"""The demo rig, built from code (no binary assets): a four-link robot arm of prisms on a round
base, skinned to an armature and animated over 24 frames, with a camera, a light and a static
environment (a floor and a box the arm reaches over).

Z is up. The arm stands on the origin: Base (a cylinder, z 0..0.3), Upper (a box, z 0.3..1.5),
Fore (a box, z 1.5..2.5) and Hand (a textured box, z 2.5..2.8), one bone each, chained. Each vertex
is weighted to the bones by its height: fully to its own link, blended smoothly (smoothstep) over
BLEND either side of each joint, so the surface bends instead of breaking. Upper and Fore tip
towards -Y by up to 35 and 50 degrees at frame 12 while Hand twists; frames 1 and 24 are the rest
pose. At frame 12 the forearm passes just over the box.
"""

from dataclasses import dataclass

import bpy
import numpy as np

BONES = ("Base", "Upper", "Fore", "Hand")
JOINTS = (0.0, 0.3, 1.5, 2.5, 2.8)  # bone i runs from JOINTS[i] to JOINTS[i + 1] along z
LINKS = (  # (radius of the circumscribed circle, sides, colour (linear), textured)
    (0.5, 24, (0.05, 0.05, 0.06), False),
    (0.21, 4, (0.9, 0.35, 0.04), False),
    (0.18, 4, (0.05, 0.25, 0.8), False),
    (0.16, 4, (1.0, 1.0, 1.0), True),
)
BLEND = 0.15  # half width of the weight blend at each joint
RING_SPACING = 0.05
FRAMES = (1, 24)
POSE = {  # frame 12: bone -> Euler XYZ in radians (bone space: the bone's Y runs along it)
    "Upper": (np.radians(35.0), 0.0, 0.0),
    "Fore": (np.radians(50.0), 0.0, 0.0),
    "Hand": (0.0, np.radians(90.0), 0.0),
}
ENVIRONMENT_BOX = ((0.0, -1.6, 0.9), 0.6)  # centre, edge length
FLOOR_SIZE = 6.0
CAMERA_LOCATION = (5.5, -6.0, 3.2)
LOOK_AT = (0.0, -0.4, 1.2)


@dataclass
class DemoRig:
    armature: object  # the Armature object
    body: object  # the skinned mesh (vertex groups + Armature modifier)
    camera: object
    light: object
    environment_mesh: object  # floor + box, a plain mesh
    environment: object  # its splats (a splat object), or None when not made


# geometry -------------------------------------------------------------------------------------------


def _ring_heights(z0, z1):
    """Heights of the vertex rings of a link: evenly spaced, plus both ends of every joint blend."""
    count = max(2, int(round((z1 - z0) / RING_SPACING)) + 1)
    extra = [j + d for j in JOINTS for d in (-BLEND, BLEND) if z0 < j + d < z1]
    return np.unique(np.round(np.concatenate([np.linspace(z0, z1, count), extra]), 9))


def prism(radius, sides, z0, z1):
    """A capped prism along z: (vertices (V,3), faces as lists of vertex indices, per-face corner
    UVs). Side UVs wrap around (u) and run up (v) the prism; the caps get planar UVs."""
    heights = _ring_heights(z0, z1)
    angles = np.pi / sides + 2 * np.pi * np.arange(sides) / sides  # boxes sit square to the axes
    ring = np.stack([radius * np.cos(angles), radius * np.sin(angles)], axis=1)
    vertices = np.concatenate([np.column_stack([ring, np.full(sides, z)]) for z in heights])
    faces, uvs = [], []
    for r in range(len(heights) - 1):
        v0, v1 = (heights[r] - z0) / (z1 - z0), (heights[r + 1] - z0) / (z1 - z0)
        for s in range(sides):
            t = (s + 1) % sides
            faces.append([r * sides + s, r * sides + t, (r + 1) * sides + t, (r + 1) * sides + s])
            u0, u1 = s / sides, (s + 1) / sides
            uvs.append([(u0, v0), (u1, v0), (u1, v1), (u0, v1)])
    cap_uv = [tuple(0.5 + 0.5 * p / radius) for p in ring]
    top = len(heights) - 1
    faces += [list(range(sides))[::-1], [top * sides + s for s in range(sides)]]
    uvs += [cap_uv[::-1], cap_uv]
    return vertices, faces, uvs


def bone_weights(z):
    """(V, 4) weights of the bones at heights z: smoothstep blends at the joints, summing to 1."""

    def above(joint):
        t = np.clip((z - joint + BLEND) / (2 * BLEND), 0.0, 1.0)
        return t * t * (3 - 2 * t)

    steps = [np.ones_like(z)] + [above(j) for j in JOINTS[1:-1]] + [np.zeros_like(z)]
    return np.stack([steps[i] - steps[i + 1] for i in range(len(BONES))], axis=1)


def checker_image(name="Splatwright Demo Checker", size=64, cells=8):
    """A packed sRGB checker of two colours, made from code."""
    image = bpy.data.images.get(name)
    if image is None:
        image = bpy.data.images.new(name, size, size)
        cell = np.arange(size) * cells // size
        odd = (cell[:, None] + cell[None, :]) % 2 == 1
        pixels = np.where(odd[..., None], (0.95, 0.8, 0.1, 1.0), (0.15, 0.15, 0.15, 1.0)).astype(np.float32)
        image.pixels.foreach_set(pixels.ravel())
        image.pack()
    return image


def _material(name, color, texture=None):
    mat = bpy.data.materials.new(name)
    if bpy.app.version < (5, 0, 0):
        mat.use_nodes = True
    bsdf = next(n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled")
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    if texture is not None:
        node = mat.node_tree.nodes.new("ShaderNodeTexImage")
        node.image = texture
        mat.node_tree.links.new(node.outputs["Color"], bsdf.inputs["Base Color"])
    mat.diffuse_color = (*color, 1.0)
    return mat


def _mesh_object(name, parts, collection):
    """A mesh object from [(vertices, faces, uvs, material)] parts, one material slot per part."""
    vertices, faces, uvs, materials, face_mats = [], [], [], [], []
    for i, (v, f, uv, mat) in enumerate(parts):
        offset = sum(len(x) for x in vertices)
        vertices.append(v)
        faces += [[k + offset for k in face] for face in f]
        uvs += uv
        face_mats += [i] * len(f)
        materials.append(mat)
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(np.concatenate(vertices).tolist(), [], faces)
    layer = mesh.uv_layers.new(name="UVMap")
    layer.uv.foreach_set("vector", np.array([c for face in uvs for c in face], np.float32).ravel())
    mesh.polygons.foreach_set("material_index", np.array(face_mats, np.int32))
    for mat in materials:
        mesh.materials.append(mat)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    collection.objects.link(obj)
    return obj


# the rig ---------------------------------------------------------------------------------------------


def _armature(scene, collection):
    arm_data = bpy.data.armatures.new("Demo Arm Rig")
    arm = bpy.data.objects.new("Demo Arm Rig", arm_data)
    collection.objects.link(arm)
    view_layer = bpy.context.view_layer
    previous = view_layer.objects.active
    view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    parent = None
    for name, head, tail in zip(BONES, JOINTS[:-1], JOINTS[1:]):
        bone = arm_data.edit_bones.new(name)
        bone.head, bone.tail = (0.0, 0.0, head), (0.0, 0.0, tail)
        bone.roll = 0.0
        if parent is not None:
            bone.parent, bone.use_connect = parent, True
        parent = bone
    bpy.ops.object.mode_set(mode="OBJECT")
    view_layer.objects.active = previous
    return arm


def _skin(body, arm):
    """Vertex groups named by bone with height-blended weights, and an Armature modifier."""
    z = np.empty(len(body.data.vertices) * 3, np.float32)
    body.data.vertices.foreach_get("co", z)
    weights = bone_weights(z.reshape(-1, 3)[:, 2].astype(np.float64))
    for b, name in enumerate(BONES):
        group = body.vertex_groups.new(name=name)
        w = weights[:, b]
        for value in np.unique(w[w > 0]):  # one call per distinct weight (one per ring height)
            group.add(np.flatnonzero(w == value).tolist(), float(value), "REPLACE")
    mod = body.modifiers.new("Armature", "ARMATURE")
    mod.object = arm
    body.parent = arm


def _animate(scene, arm):
    middle = (FRAMES[0] + FRAMES[1]) // 2
    for name in BONES:
        pose_bone = arm.pose.bones[name]
        pose_bone.rotation_mode = "XYZ"
        for frame in (FRAMES[0], middle, FRAMES[1]):
            pose_bone.rotation_euler = POSE.get(name, (0.0, 0.0, 0.0)) if frame == middle else (0.0, 0.0, 0.0)
            pose_bone.keyframe_insert("rotation_euler", frame=frame)
    scene.frame_start, scene.frame_end, scene.frame_step = FRAMES[0], FRAMES[1], 1


def _camera_and_light(scene, collection):
    from mathutils import Vector

    cam = bpy.data.objects.new("Demo Camera", bpy.data.cameras.new("Demo Camera"))
    cam.location = CAMERA_LOCATION
    cam.rotation_euler = (Vector(LOOK_AT) - Vector(CAMERA_LOCATION)).to_track_quat("-Z", "Y").to_euler()
    cam.data.lens = 40.0
    light = bpy.data.objects.new("Demo Light", bpy.data.lights.new("Demo Light", "SUN"))
    light.rotation_euler = (np.radians(40.0), np.radians(10.0), np.radians(30.0))
    for obj in (cam, light):
        collection.objects.link(obj)
    scene.camera = cam
    return cam, light


def _environment_mesh(collection):
    half = FLOOR_SIZE / 2
    floor = (
        np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], float),
        [[0, 1, 2, 3]],
        [[(0, 0), (1, 0), (1, 1), (0, 1)]],
        _material("Demo Floor", (0.3, 0.3, 0.28)),
    )
    centre, edge = ENVIRONMENT_BOX
    corners = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)], float) * edge / 2 + centre
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    box = (corners, quads, [[(0, 0), (1, 0), (1, 1), (0, 1)]] * 6, _material("Demo Box", (0.1, 0.6, 0.2)))
    return _mesh_object("Demo Environment", [floor, box], collection)


def build_demo_rig(scene, environment_splats=20_000, calibrate=True):
    """Build the demo rig into `scene` (its own collection); returns a DemoRig.

    environment_splats: the splat budget of the environment made from its mesh with from_mesh
    (0 or None: the mesh only), its silhouettes calibrated unless `calibrate` is False. The scene's
    frame range becomes 1-24; frame 1 is current.
    """
    collection = bpy.data.collections.new("Splatwright Demo")
    scene.collection.children.link(collection)
    texture = checker_image()
    parts = []
    for i, (name, (radius, sides, color, textured)) in enumerate(zip(BONES, LINKS)):
        v, f, uv = prism(radius, sides, JOINTS[i], JOINTS[i + 1])
        parts.append((v, f, uv, _material(f"Demo {name}", color, texture if textured else None)))
    body = _mesh_object("Demo Arm", parts, collection)
    arm = _armature(scene, collection)
    _skin(body, arm)
    _animate(scene, arm)
    cam, light = _camera_and_light(scene, collection)
    env_mesh = _environment_mesh(collection)
    environment = None
    if environment_splats:
        from . import from_mesh

        results = from_mesh.convert_objects(bpy.context, [env_mesh], max_splats=environment_splats, calibrate=calibrate)
        environment = from_mesh.create_splat_objects(bpy.context, results)[0]
        env_mesh.hide_render = True
    scene.frame_set(FRAMES[0])
    return DemoRig(arm, body, cam, light, env_mesh, environment)
