"""Robots made of splats: the visuals of every link converted to splats, bound rigidly to their
link and posed by forward kinematics.

`splat_robot(tree, parts)` takes (link index, core.mesh.Mesh in the visual's frame, visual origin
in the link's frame) parts, places every part where its link is at the zero configuration, and
converts them all in one core.mesh_to_splats call, so one density (or one target PSNR) covers the
whole robot and small links get their fair share. Each splat remembers its link (`links`, and the
extra "link" in files), so `SplatRobot.pose(q)` moves each exactly as its link moves
(core.skinning's rigid case) and `SplatRobot.gaussians()` is ready for core.collision.
io.urdf.read_robot builds one from a URDF file.
"""

from dataclasses import dataclass

import numpy as np

from .mesh import Material, Mesh
from .mesh_to_splats import mesh_to_splats
from .skinning import Binding, skin

DEFAULT_SPLATS = 60_000
CYLINDER_SEGMENTS = 48
SPHERE_RINGS = 24


@dataclass(eq=False)
class SplatRobot:
    """tree: the KinematicTree; cloud: the splats at the zero configuration, in the world (the
    tree's root frame); links: (N,) the link index of each splat; name: the robot's name."""

    tree: object
    cloud: object
    links: np.ndarray
    name: str = "robot"

    def deform(self, q=None, base=None):
        """Per-link rigid maps from the rest cloud to configuration q (with the roots at `base`)."""
        return self.tree.forward_kinematics(q, base=base) @ np.linalg.inv(self.tree.rest_transforms())

    def pose(self, q=None, base=None):
        """The splats at configuration q: centres, orientations and SH turned with their links."""
        return skin(self.cloud, Binding.rigid(self.links), self.deform(q, base))

    def gaussians(self, opacity_weights=True):
        """The rest splats as core.collision.Gaussians with their links: for overlap_at and
        pose_robot."""
        from .collision import Gaussians

        return Gaussians.from_cloud(self.cloud, opacity_weights, links=self.links, name="robot")


def splat_robot(tree, parts, max_splats=DEFAULT_SPLATS, target_psnr=None, name="robot", **options):
    """A SplatRobot from visual parts [(link index, Mesh in the visual frame, (4,4) visual origin in
    the link frame)]; `max_splats`, `target_psnr` and other options go to mesh_to_splats."""
    if not parts:
        raise ValueError("a splat robot needs at least one visual")
    rest = tree.rest_transforms()
    meshes, face_links = [], []
    for link, mesh, origin in parts:
        m = rest[link] @ np.asarray(origin, np.float64)
        meshes.append(
            Mesh(
                mesh.vertices @ m[:3, :3].T + m[:3, 3],
                mesh.faces,
                mesh.corner_uvs,
                mesh.face_materials,
                mesh.materials,
                mesh.corner_colors,
            )
        )
        face_links.append(np.full(len(mesh.faces), link, np.int32))
    whole = join_meshes(meshes)
    # A budget stays on the surfaces (no silhouette calibration) unless asked: contacts use the splats.
    options.setdefault("calibrate", False)
    cloud = mesh_to_splats(
        whole.vertices, whole.faces, **whole.appearance(), max_splats=max_splats, target_psnr=target_psnr, **options
    )
    links = np.concatenate(face_links)[cloud.extras["source_triangle"]]
    cloud.extras = {"link": links.astype(np.int32)}
    return SplatRobot(tree, cloud, links.astype(np.int64), name)


def join_meshes(meshes):
    """One Mesh from several: faces re-indexed, materials concatenated, UVs and colours kept per
    corner (parts without UVs get 0, parts without colours get white)."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
    material_offsets = np.cumsum([0] + [max(len(m.materials), 1) for m in meshes])
    faces = [m.faces + o for m, o in zip(meshes, offsets)]
    any_uv = any(m.corner_uvs is not None for m in meshes)
    any_color = any(m.corner_colors is not None for m in meshes)
    uvs, colors, face_materials, materials = [], [], [], []
    for m, o in zip(meshes, material_offsets):
        f = len(m.faces)
        uvs.append(m.corner_uvs if m.corner_uvs is not None else np.zeros((f, 3, 2)))
        colors.append(_corner_colors(m) if m.corner_colors is not None else np.ones((f, 3, 3)))
        fm = np.zeros(f, np.int64) if m.face_materials is None else np.asarray(m.face_materials, np.int64)
        face_materials.append(fm + o)
        materials += list(m.materials) or [Material(name="default")]
    return Mesh(
        np.concatenate([m.vertices for m in meshes]),
        np.concatenate(faces),
        np.concatenate(uvs) if any_uv else None,
        np.concatenate(face_materials),
        materials,
        np.concatenate(colors) if any_color else None,
    )


def _corner_colors(mesh):
    c = np.asarray(mesh.corner_colors, np.float64)
    if c.ndim == 2:  # per vertex -> per corner
        c = c[mesh.faces]
    return c[:, :, :3]


def visual_mesh(geometry, size=(), mesh=None, scale=(1.0, 1.0, 1.0), color=None):
    """The Mesh of one visual in its own frame: a tessellated box / cylinder / sphere of `size`, or
    `mesh` scaled by `scale`; `color` (scene-linear RGB) replaces the materials' colours."""
    if geometry == "mesh":
        scale = np.asarray(scale, np.float64)
        faces = mesh.faces if np.prod(scale) > 0 else mesh.faces[:, ::-1]  # a mirror flips winding
        out = Mesh(
            mesh.vertices * scale, faces, mesh.corner_uvs, mesh.face_materials, mesh.materials, mesh.corner_colors
        )
    else:
        vertices, faces = primitive(geometry, size)
        out = Mesh(vertices, faces)
    if color is not None:
        out.materials = [Material(base_color=tuple(color))]
        out.face_materials, out.corner_uvs, out.corner_colors = None, None, None
    return out


def primitive(kind, size):
    """(vertices, faces) of a closed, outward-wound triangle mesh: 'box' (size x, y, z, centred),
    'cylinder' (radius, length, along z, centred) or 'sphere' (radius,)."""
    if kind == "box":
        corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
        quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        faces = [(a, b, c) for a, b, c, d in quads] + [(a, c, d) for a, b, c, d in quads]
        return corners * 0.5 * np.asarray(size, np.float64), np.array(faces)
    if kind == "cylinder":
        radius, length = size
        n = CYLINDER_SEGMENTS
        angle = 2 * np.pi * np.arange(n) / n
        ring = np.column_stack([radius * np.cos(angle), radius * np.sin(angle)])
        vertices = np.concatenate(
            [
                np.column_stack([ring, np.full(n, -length / 2)]),
                np.column_stack([ring, np.full(n, length / 2)]),
                [[0, 0, -length / 2], [0, 0, length / 2]],
            ]
        )
        k, k1 = np.arange(n), (np.arange(n) + 1) % n
        side = np.concatenate([np.column_stack([k, k1, k1 + n]), np.column_stack([k, k1 + n, k + n])])
        caps = np.concatenate(
            [np.column_stack([np.full(n, 2 * n), k1, k]), np.column_stack([np.full(n, 2 * n + 1), k + n, k1 + n])]
        )
        return vertices, np.concatenate([side, caps])
    if kind == "sphere":
        (radius,) = size
        rings, n = SPHERE_RINGS, 2 * SPHERE_RINGS
        theta = np.pi * np.arange(1, rings) / rings
        phi = 2 * np.pi * np.arange(n) / n
        body = np.stack(
            [
                np.outer(np.sin(theta), np.cos(phi)),
                np.outer(np.sin(theta), np.sin(phi)),
                np.outer(np.cos(theta), np.ones(n)),
            ],
            axis=-1,
        ).reshape(-1, 3)
        vertices = radius * np.concatenate([[[0, 0, 1]], body, [[0, 0, -1]]])
        ring = lambda r: 1 + r * n + np.arange(n)
        nxt = lambda r: 1 + r * n + (np.arange(n) + 1) % n
        faces = [np.column_stack([np.zeros(n, int), ring(0), nxt(0)])]
        for r in range(rings - 2):
            faces += [
                np.column_stack([ring(r), ring(r + 1), nxt(r + 1)]),
                np.column_stack([ring(r), nxt(r + 1), nxt(r)]),
            ]
        bottom = len(vertices) - 1
        faces.append(np.column_stack([np.full(n, bottom), nxt(rings - 2), ring(rings - 2)]))
        return vertices, np.concatenate(faces)
    raise ValueError(f"unknown primitive '{kind}' (known: box, cylinder, sphere)")
