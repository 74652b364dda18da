"""Ordinary Blender meshes (a crop volume, a proxy) read as NumPy arrays."""

import numpy as np


def mesh_triangles(mesh):
    """(V,3) float64 vertices and (F,3) triangles of a mesh datablock (its own data)."""
    vertices = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", vertices)
    if len(mesh.polygons) and not len(mesh.loop_triangles):
        mesh.calc_loop_triangles()
    triangles = np.empty(len(mesh.loop_triangles) * 3, np.int32)
    mesh.loop_triangles.foreach_get("vertices", triangles)
    return vertices.reshape(-1, 3).astype(np.float64), triangles.reshape(-1, 3)
