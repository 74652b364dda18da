"""The material splats made from a mesh carry for relighting (core.material): per splat the
Base Color (albedo), normal, roughness and metallic of the surface point it stands for, read from
its "source_triangle" and "barycentric" extras once the cloud is built, so every way of building
it (budgets, targets, refinement) gets the same material."""

import numpy as np

from . import material as mat
from .mesh import Surface
from .splats import SplatCloud


def face_frames(surface: Surface) -> np.ndarray:
    """(F,3,2) the faces' local in-plane axes (t1 = first edge, t2 = normal x t1) as columns: the
    frame core.mesh_texture measures texture footprints in."""
    length = np.linalg.norm(surface.edge1, axis=1, keepdims=True)
    t1 = np.where(length > 0, surface.edge1 / np.where(length > 0, length, 1.0), [1.0, 0.0, 0.0])
    return np.stack([t1, np.cross(surface.normal, t1)], axis=2)


def local_covariances(cloud: SplatCloud, surface: Surface, tri: np.ndarray) -> np.ndarray:
    """(N,2,2) each splat's covariance seen in its face's local frame: T^T Sigma T."""
    frames = face_frames(surface)[tri]
    return np.einsum("nia,nij,njb->nab", frames, cloud.covariances(), frames)


def surface_albedo(
    cloud: SplatCloud, surface: Surface, tri: np.ndarray, bary: np.ndarray, overlap: float, texture_aware: bool
) -> np.ndarray:
    """(N,3) scene-linear Base Color in [0,1], averaged over each splat's footprint as its colour
    is (core.mesh_sampling: the in-plane Gaussian shrunk by 2 overlap with `texture_aware`, else a
    square mip footprint of the splats' spacing, sigma / overlap) but kept in linear light."""
    local = local_covariances(cloud, surface, tri)
    if texture_aware:
        linear = surface.linear_colors(tri, bary, covariance=local / (2 * overlap) ** 2)
    else:
        # The spacing 1 / sqrt(density) is the in-plane sigma over `overlap`; narrowing along one
        # edge leaves the major axis at sigma (splats narrowed both ways, in corners, read a
        # smaller footprint than their colour did).
        sigma = np.sqrt(np.maximum(np.linalg.eigvalsh(local)[:, 1], 0.0))
        linear = surface.linear_colors(tri, bary, footprint=sigma / overlap)
    return np.clip(linear, 0.0, 1.0)


def corner_normals_of(surface: Surface, corner_normals: np.ndarray | None) -> np.ndarray | None:
    """(F,3,3) float64 per-corner normals from (F,3,3) per corner or (V,3) per vertex, or None;
    ValueError for another shape."""
    if corner_normals is None:
        return None
    n = np.asarray(corner_normals, np.float64)
    if n.ndim == 2 and n.shape == (len(surface.vertices), 3):
        n = n[surface.faces]
    if n.shape != (len(surface.faces), 3, 3):
        raise ValueError(
            f"corner_normals has shape {n.shape}, expected ({len(surface.faces)}, 3, 3) per corner "
            f"or ({len(surface.vertices)}, 3) per vertex"
        )
    return n


def shading_normals(surface: Surface, tri: np.ndarray, bary: np.ndarray, corners: np.ndarray | None) -> np.ndarray:
    """(N,3) unit normals at barycentric points: the corners' normals interpolated (smooth shading,
    as a renderer interpolates them) where given, else the face's winding normal; also where the
    interpolation is not finite or vanishes."""
    face = surface.normal[tri]
    if corners is None:
        return face
    smooth = np.einsum("nk,nkc->nc", bary, corners[tri])
    length = np.linalg.norm(smooth, axis=1, keepdims=True)
    good = np.isfinite(length) & (length > 1e-12)
    return np.where(good, smooth / np.where(good, length, 1.0), face)


def with_surface_material(
    cloud: SplatCloud,
    surface: Surface,
    *,
    overlap: float = 0.8,
    texture_aware: bool = True,
    corner_normals: np.ndarray | None = None,
) -> SplatCloud:
    """`cloud` (made from `surface`, with its "source_triangle" and "barycentric" extras) with the
    material extras of core.material: albedo (surface_albedo), the normal (the `corner_normals`
    interpolated, else the face's winding normal: shading_normals; out of the solid where the part
    is one), and the face material's roughness and metallic."""
    tri = cloud.extras["source_triangle"].astype(np.int64)
    bary = cloud.extras["barycentric"].astype(np.float64)
    corners = corner_normals_of(surface, corner_normals)
    materials = surface.materials
    roughness = np.array([np.clip(m.roughness, 0.0, 1.0) for m in materials], np.float64)
    metallic = np.array([np.clip(m.metallic, 0.0, 1.0) for m in materials], np.float64)
    face_material = surface.face_materials[tri]
    # A solid's normals point out of it whichever way its faces are wound (as files and other tools
    # expect of normals), not along the winding.
    outward = surface.outward_signs()[tri]
    normals = shading_normals(surface, tri, bary, corners) * np.where(outward < 0, -1.0, 1.0)[:, None]
    return mat.with_material(
        cloud,
        albedo=surface_albedo(cloud, surface, tri, bary, overlap, texture_aware),
        normals=normals,
        roughness=roughness[face_material],
        metallic=metallic[face_material],
    )
