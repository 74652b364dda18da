"""Float64 brute-force light visibility and the scenes shadow tests share (tests and benchmarks only).

Splats block a ray as the renderer's splats block a pixel's: a splat j takes alpha_j = min(0.99,
o_j exp(-q_j / 2)) of it, q_j the Mahalanobis distance of the ray's line to its centre (the smallest
along the line, which is what the 2D EWA footprint evaluates), and the light reaching a point is the
product of (1 - alpha_j) over the splats between it and the light, averaged over points on the
light's emitting disc (or directions within the sun's). Splats whose closest point to the ray lies
within a few standard deviations of the receiver's own centre (along the ray, both splats' extents)
count as its own surface, not a blocker. Splats that surely take less than 1/255 of every ray are
left out before the sums (_near_rays), which changes nothing but the time. Meshes block by exact
ray-triangle intersection. It shares no code with core/shadows.py; from the core it uses only the
quaternion -> matrix helper.
"""

import math

import numpy as np

from splatwright.core import geometry
from splatwright.core.lights import sphere_directions, spread_factor
from splatwright.core.shading import ggx_parts
from splatwright.core.splats import SplatCloud, logit

OWN_SURFACE = 3.0  # standard deviations along the ray that belong to the receiver and its neighbour
REACH_SIGMAS = math.sqrt(2 * math.log(255.0))  # beyond, a splat takes less than 1/255 of a ray


def surface_splats(points, normals, sigma, thickness=0.05, opacity=0.95):
    """Flat splats on a surface: tangent standard deviation `sigma`, `thickness` x that along the normal."""
    points, normals = np.asarray(points, np.float64), np.asarray(normals, np.float64)
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    rot = np.stack([t1, t2, normals], axis=2)  # columns: the splat's axes
    n = len(points)
    scales = np.tile([sigma, sigma, sigma * thickness], (n, 1))
    cloud = SplatCloud(
        points, geometry.matrices_to_quaternions(rot), np.log(scales), np.full(n, logit(opacity)), np.zeros((n, 1, 3))
    )
    cloud.extras.update({"nx": normals[:, 0], "ny": normals[:, 1], "nz": normals[:, 2]})
    return cloud


def plane_cloud(half=1.5, count=60, z=0.0):
    """A square of side 2 half in the z = `z` plane, count x count splats facing +z."""
    g = (np.arange(count) + 0.5) / count * 2 * half - half
    x, y = np.meshgrid(g, g)
    points = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)
    spacing = 2 * half / count
    return surface_splats(points, np.tile([0.0, 0.0, 1.0], (len(points), 1)), 0.6 * spacing)


def sphere_cloud(centre, radius, count=1500):
    """A shell of `count` splats on a sphere (a Fibonacci lattice), normals outward."""
    k = np.arange(count) + 0.5
    phi = np.arccos(1 - 2 * k / count)
    theta = math.pi * (1 + math.sqrt(5)) * k
    normals = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)
    spacing = radius * math.sqrt(4 * math.pi / count)
    return surface_splats(np.asarray(centre) + radius * normals, normals, 0.6 * spacing)


def ball_surface(centre, radius, segments=48, rings=24):
    """A closed UV sphere as a core.mesh.Surface (an occluder for shadow tests)."""
    from splatwright.core.mesh import Surface

    theta, phi = np.meshgrid(
        np.linspace(0, math.pi, rings + 1), np.arange(segments) * 2 * math.pi / segments, indexing="ij"
    )
    ring = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1).reshape(-1, 3)
    a = (np.arange(rings)[:, None] * segments + np.arange(segments)[None, :]).ravel()
    b = (np.arange(rings)[:, None] * segments + (np.arange(segments)[None, :] + 1) % segments).ravel()
    faces = np.concatenate([np.stack([a, a + segments, b], 1), np.stack([b, a + segments, b + segments], 1)])
    return Surface(np.asarray(centre) + radius * ring, faces)


def light_samples(light, receiver, count):
    """(count, 3) points on the light's emitting disc as the receiver sees it (or, for the sun,
    far points along directions within its disc); stratified, concentric."""
    k = np.arange(count) + 0.5
    r, t = np.sqrt(k / count), k * math.pi * (3 - math.sqrt(5))
    disc = np.stack([r * np.cos(t), r * np.sin(t)], axis=1)
    if light.kind == "sun":
        axis = -np.asarray(light.direction, np.float64)
        size, far = math.tan(light.angle / 2), 1e6
    elif light.kind == "area":
        x = np.asarray(light.x_axis, np.float64)
        y = np.cross(np.asarray(light.direction, np.float64), x)
        sx, sy = light.extent
        if light.round:
            offsets = disc[:, :1] * 0.5 * sx * x + disc[:, 1:] * 0.5 * sy * y
        else:
            g = int(math.ceil(math.sqrt(count)))
            u = (np.arange(g) + 0.5) / g - 0.5
            uu, vv = np.meshgrid(u, u)
            offsets = uu.reshape(-1, 1) * sx * x + vv.reshape(-1, 1) * sy * y
        return np.asarray(light.position) + offsets
    else:
        axis = np.asarray(light.position, np.float64) - receiver
        size, far = light.radius, 1.0
    axis = axis / np.linalg.norm(axis)
    u = np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    if light.kind == "sun":
        dirs = axis + size * (disc[:, :1] * u + disc[:, 1:] * v)
        return receiver + far * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    return np.asarray(light.position) + size * (disc[:, :1] * u + disc[:, 1:] * v)


def _splat_frames(cloud):
    rot = geometry.quaternions_to_matrices(cloud.rotations.astype(np.float64))
    scales = np.exp(cloud.log_scales.astype(np.float64))
    inverse = np.einsum("nij,nj,nkj->nik", rot, 1.0 / scales**2, rot)  # Sigma^-1
    cov = np.einsum("nij,nj,nkj->nik", rot, scales**2, rot)
    return inverse, cov


def reference_visibility(cloud, light, receivers, samples=1, meshes=()):
    """(len(receivers),) float64 light fraction at the centres of splats `receivers` (indices)."""
    pos = cloud.positions.astype(np.float64)
    inverse, cov = _splat_frames(cloud)
    opacity = 1.0 / (1.0 + np.exp(-cloud.opacity_logits.astype(np.float64)))
    widest = np.exp(cloud.log_scales.astype(np.float64).max(axis=1))
    out = np.empty(len(receivers))
    for row, i in enumerate(receivers):
        ends = light_samples(light, pos[i], samples)  # (S,3)
        seg = ends - pos[i]
        length = np.linalg.norm(seg, axis=1)
        d = seg / length[:, None]  # (S,3)
        near = _near_rays(pos - pos[i], d, widest)
        near[i] = True  # the receiver: its extent sets what counts as its own surface
        k = int(np.count_nonzero(near[:i]))  # the receiver's place among the splats kept
        dd = (d[:, :, None] * d[:, None, :]).reshape(-1, 9)
        rel, inv_k = pos[near] - pos[i], inverse[near]  # (K,3), (K,3,3)
        m = np.einsum("nij,nj->ni", inv_k, rel)  # Sigma^-1 rel
        a, b = dd @ inv_k.reshape(-1, 9).T, d @ m.T  # d^T Sigma^-1 d, d^T Sigma^-1 rel: (S,K)
        t = b / a  # closest approach along each ray
        q = np.maximum(np.einsum("ni,ni->n", rel, m)[None, :] - b * b / a, 0.0)
        sigma = np.sqrt(dd @ cov[near].reshape(-1, 9).T)  # (S,K) each splat's standard deviation along each ray
        between = (t > OWN_SURFACE * (sigma[:, k : k + 1] + sigma)) & (t < length[:, None])
        alpha = np.minimum(0.99, opacity[near][None, :] * np.exp(-0.5 * q))
        alpha = np.where(between & (alpha >= 1.0 / 255.0), alpha, 0.0)
        alpha[:, k] = 0.0
        light_left = np.exp(np.log1p(-alpha).sum(axis=1))
        for mesh in meshes:
            light_left = light_left * ~_hits_mesh(mesh, pos[i], d, length)
        out[row] = np.average(light_left, weights=_sample_weights(light, d, length))
    return out


def _sample_weights(light, d, length):
    """(S,) what each light sample sends to the receiver, up to a common factor: equal, but for an
    area light narrowed by its Spread, its radiance towards the receiver (spread_factor) times its
    cosine over the squared distance (the light reaches it from a disc of the light only)."""
    if light.kind != "area" or light.spread >= math.pi:
        return np.ones(len(d))
    cos_emit = np.maximum(-(d @ np.asarray(light.direction, np.float64)), 0.0)
    weights = cos_emit * spread_factor(light, cos_emit) / length**2
    return weights if weights.sum() > 0 else np.ones(len(d))


def _near_rays(rel, dirs, widest):
    """(N,) bool: the splats (centres `rel` from the receiver, widest standard deviations `widest`)
    that may take 1/255 of one of the rays `dirs` (S,3, unit), all others surely not. A splat takes
    that much only within sqrt(2 ln 255) of its standard deviations of the ray's line, so its centre
    lies within that many times `widest` of it; and every line lies within |rel| |d_s - d_0| of the
    central line d_0 at the point nearest the splat, so testing the central one with that slack
    keeps every splat that matters."""
    central = dirs.mean(axis=0)
    central /= np.linalg.norm(central)
    spread = np.linalg.norm(dirs - central, axis=1).max()
    distance = np.linalg.norm(rel, axis=1)
    off_axis = np.sqrt(np.maximum(distance**2 - (rel @ central) ** 2, 0.0))
    return off_axis - distance * spread <= 1.001 * REACH_SIGMAS * widest + 1e-12


def _hits_mesh(mesh, origin, dirs, length):
    """(S,) whether each ray origin + t dir, 0 < t < length, meets a triangle (Moller-Trumbore)."""
    tri = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(dirs[:, None, :], e2[None])  # (S,F,3)
    det = np.einsum("fi,sfi->sf", e1, p)
    ok = np.abs(det) > 1e-14
    inv = 1.0 / np.where(ok, det, 1.0)
    s = origin - tri[:, 0]  # (F,3)
    u = np.einsum("fi,sfi->sf", s, p) * inv
    qv = np.cross(s, e1)  # (F,3)
    v = np.einsum("si,fi->sf", dirs, qv) * inv
    t = np.einsum("fi,fi->f", e2, qv)[None, :] * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9) & (t < length[:, None])
    return hit.any(axis=1)


def lobe_open_share(points, eye, roughness, open_sky, count):
    """Each floor point's (M,3; normal +z) share of its GGX lobe (D G / (4 n.v), seen from `eye`)
    over the upper half of `count` directions of the sphere (float64) whose rays `open_sky(point,
    directions (D,3)) -> (D,) bool` leaves open: the world's light a glossy floor reflects."""
    up = sphere_directions(count)
    up = up[up[:, 2] > 0]
    shares = []
    for p in points:  # a loop over a test's points
        view = (eye - p) / np.linalg.norm(eye - p)
        weight, _ = ggx_parts(np.tile([0.0, 0.0, 1.0], (len(up), 1)), np.tile(view, (len(up), 1)), up,
                              np.full(len(up), max(roughness**2, 1e-3)))  # fmt: skip
        shares.append((weight * open_sky(p, up)).sum() / weight.sum())
    return np.array(shares)
