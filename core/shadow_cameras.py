"""The cameras of a light's shadow maps, and which splats each may show (core.shadows draws the maps
through them and tests the splats in them).

- spot: one perspective camera covering its cone (a cube, as for a point light, past SPOT_CUBE_ANGLE);
- sun: one orthographic camera along its direction framing the splats' and meshes' bounds;
- point: a cube of six 90-degree perspective faces (a little over: CUBE_MARGIN) in world axes;
- area: the cube from the light's centre, in the light's own axes, without the face behind it.

Each splat reaches three standard deviations of its widest axis (reach_and_gap); a camera may show
it where that reach meets its view (near_masks), and it is tested in the one camera looking most
nearly at it (face_of).
"""

import math

import numpy as np

from . import jit, scratch
from .camera import Camera, look_at_matrix
from .parallel import in_chunks
from .render_constants import FRUSTUM_MARGIN

CUBE_MARGIN = 32  # texels of a cube face beyond its 90 degrees
SPOT_CUBE_ANGLE = math.radians(120.0)  # wider cones use the cube
BOUNDS_CHUNK = 1 << 13  # splats per step of the sun's framing (one box each, merged)
SHOWN_SIGMAS = math.sqrt(2.0 * math.log(255.0))  # the render's reach of a splat, opacity 1 (may_show)
SHOWN_PAD = 4.0  # pixels: the low-pass's 1.83 and the box's rounding


def reach_and_gap(cloud, source, shapes=None):
    """((N,) float64 three standard deviations of each splat's widest axis, (N,) float64 each splat's
    centre's distance to `source` (3,) less that reach, or None without a source), by the compiled
    kernel in one pass where it loads (exp is monotonic: the widest log-scale's exp is the widest
    scale), the widest scales read from `shapes` (core.render.Shapes of the cloud) when given."""
    n = len(cloud)
    kernel = jit.compiled(__name__, ("_reach_loop",))
    if kernel is not None:
        given = shapes is not None and shapes.widest is not None and shapes.fits(cloud)
        reach, gap = scratch.empty(n), scratch.empty(n if source is not None else 0)
        fields = [np.ascontiguousarray(a, np.float32) for a in (cloud.positions, cloud.log_scales)]
        widest = shapes.widest if given else np.zeros(0)
        origin = np.zeros(3) if source is None else source
        in_chunks(n, lambda lo, hi: kernel(lo, hi, *fields, widest, origin, reach, gap))
        return reach, (gap if source is not None else None)
    log_scales = cloud.log_scales  # column by column: a reduction along rows of three is slow
    widest = np.maximum(np.maximum(log_scales[:, 0], log_scales[:, 1]), log_scales[:, 2])
    with np.errstate(over="ignore"):
        reach = 3.0 * np.exp(widest.astype(np.float64))
    if source is None:
        return reach, None
    rel = cloud.positions.astype(np.float64) - source
    return reach, np.sqrt(np.einsum("ij,ij->i", rel, rel)) - reach


def _reach_loop(lo, hi, positions, log_scales, widest, source, reach, gap):
    """reach_and_gap for splats lo..hi (from their widest scales where that is not empty; gap only
    when it has room for them)."""
    given = widest.shape[0] > 0
    for i in range(lo, hi):
        if given:
            reach[i] = 3.0 * widest[i]
        else:
            largest = max(max(log_scales[i, 0], log_scales[i, 1]), log_scales[i, 2])
            reach[i] = 3.0 * math.exp(np.float64(largest))  # inf past float64's range, as NumPy's exp
        if gap.shape[0]:
            dx, dy = positions[i, 0] - source[0], positions[i, 1] - source[1]
            dz = positions[i, 2] - source[2]
            gap[i] = math.sqrt(dx * dx + dy * dy + dz * dz) - reach[i]


def light_cameras(light, positions, reach, gap, meshes, resolution):
    """The cameras of `light`'s maps (see the module notes), `resolution` texels a side, framing
    the splats' centres `positions` (N,3) with their `reach` and `gap` (reach_and_gap's) and the
    `meshes`' vertices."""
    kind = light.kind
    position = np.asarray(getattr(light, "position", np.zeros(3)), np.float64)
    direction = unit(light.direction)
    if kind == "sun":
        return [_sun_camera(direction, positions, reach, meshes, resolution)]
    near = near_plane(position, gap, meshes)
    if kind == "spot" and light.spot_size <= SPOT_CUBE_ANGLE:
        fov = math.degrees(min(light.spot_size * 1.1 + 0.05, math.radians(170)))
        matrix = look_at_matrix(position, position + direction, _up_for(direction))
        f = 0.5 * resolution / math.tan(math.radians(fov) / 2)
        return [Camera(resolution, resolution, f, f, resolution / 2, resolution / 2, matrix, near)]
    if kind == "area":
        x = unit(getattr(light, "x_axis", _up_for(direction)))
        axes = np.stack([x, np.cross(direction, x), direction])  # the light's frame, rows
        dirs = [axes[2], axes[0], -axes[0], axes[1], -axes[1]]  # not the face behind the light
    else:
        dirs = [np.array(d, np.float64) for d in np.vstack([np.eye(3), -np.eye(3)])]
    return [_cube_face(position, d, near, resolution) for d in dirs]


def _cube_face(position, forward, near, resolution):
    matrix = look_at_matrix(position, position + forward, _up_for(forward))
    # A little over 90 degrees: the filter's taps around a splat near a face's edge still read
    # this face's map (each splat is tested on the face it is most central in).
    f = resolution / 2 - min(CUBE_MARGIN, resolution / 8)
    return Camera(resolution, resolution, f, f, resolution / 2, resolution / 2, matrix, near)


def _sun_camera(direction, positions, reach, meshes, resolution):
    """An orthographic camera along `direction` framing the splats' positions (N,3) and the mesh
    vertices, square texels."""
    up = _up_for(direction)
    frame = look_at_matrix(np.zeros(3), direction, up)[:3, :3]
    lo, hi = bounds_in(frame, positions, reach)
    for mesh in meshes:
        local = np.asarray(mesh.vertices, np.float64) @ frame.T
        lo, hi = np.minimum(lo, local.min(axis=0)), np.maximum(hi, local.max(axis=0))
    extent = max(hi[0] - lo[0], hi[1] - lo[1], 1e-9) * 1.02
    centre = frame.T @ ((lo + hi) / 2)
    depth = hi[2] - lo[2]
    eye = centre - direction * (depth / 2 + 1.0 + 0.01 * extent)
    f = resolution / extent
    matrix = look_at_matrix(eye, centre, up)
    return Camera(resolution, resolution, f, f, resolution / 2, resolution / 2, matrix, 0.5, projection="orthographic")


def bounds_in(frame, positions, reach):
    """(lo (3,), hi (3,)) float64: the box, in the axes of `frame` (3,3 rows), of the centres
    `positions` (N,3) each padded by its `reach` (N,); by the compiled kernel, chunk by chunk, where
    it loads (a sun's map framed in NumPy took a tenth of its visibility at 410k splats)."""
    kernel = jit.compiled(__name__, ("_bounds_loop",))
    if kernel is None:
        local = positions.astype(np.float64) @ frame.T
        # per axis: faster than along rows
        lo = np.array([(local[:, axis] - reach).min(initial=np.inf) for axis in range(3)])
        hi = np.array([(local[:, axis] + reach).max(initial=-np.inf) for axis in range(3)])
        return lo, hi
    n = len(positions)
    parts = np.empty((max(-(-n // BOUNDS_CHUNK), 1), 6))
    parts[:, :3], parts[:, 3:] = np.inf, -np.inf
    points = np.ascontiguousarray(positions, np.float32)
    rows = np.ascontiguousarray(frame, np.float64)
    in_chunks(n, lambda a, b: kernel(a, b, points, reach, rows, parts[a // BOUNDS_CHUNK]), chunk=BOUNDS_CHUNK)
    return parts[:, :3].min(axis=0), parts[:, 3:].max(axis=0)


def _bounds_loop(lo, hi, positions, reach, frame, out):
    """bounds_in for splats lo..hi into out (6,): min x, y, z, then max x, y, z (kept in locals
    through the loop: writing out each time made it four times slower)."""
    x0, y0, z0, x1, y1, z1 = out[0], out[1], out[2], out[3], out[4], out[5]
    for i in range(lo, hi):
        p0, p1, p2, r = positions[i, 0], positions[i, 1], positions[i, 2], reach[i]
        x = frame[0, 0] * p0 + frame[0, 1] * p1 + frame[0, 2] * p2
        y = frame[1, 0] * p0 + frame[1, 1] * p1 + frame[1, 2] * p2
        z = frame[2, 0] * p0 + frame[2, 1] * p1 + frame[2, 2] * p2
        x0, x1 = min(x0, x - r), max(x1, x + r)
        y0, y1 = min(y0, y - r), max(y1, y + r)
        z0, z1 = min(z0, z - r), max(z1, z + r)
    out[0], out[1], out[2], out[3], out[4], out[5] = x0, y0, z0, x1, y1, z1


def near_plane(position, gap, meshes):
    """A near plane in front of everything the light sees: half the nearest splat's surface distance
    (gap, reach_and_gap's) or mesh vertex's."""
    d = gap if len(gap) else np.ones(1)
    for m in meshes:
        d = np.append(d, np.linalg.norm(m.vertices - position, axis=1).min())
    nearest = float(np.min(d)) if len(d) else 1.0
    return float(np.clip(0.5 * nearest, 1e-4, 0.05))


def near_masks(cameras, positions, reach, pad=2.0, margin=1.0):
    """(F, N) bool: _near_mask of every camera, by the compiled kernel in one pass over the splats
    when it loads."""
    kernel = jit.compiled(__name__, ("_near_loop",))
    if kernel is None:
        points = positions.astype(np.float64)
        masks = [_near_mask(camera, points, reach, pad, margin) for camera in cameras]
        return np.array(masks).reshape(len(cameras), -1)
    params = np.array([_near_params(camera, pad, margin) for camera in cameras]).reshape(-1, 10)
    rotations = np.array([camera.rotation for camera in cameras], np.float64).reshape(-1, 3, 3)
    out = scratch.empty((len(cameras), len(positions)), np.bool_)
    positions = np.ascontiguousarray(positions, np.float32)
    in_chunks(len(positions), lambda lo, hi: kernel(lo, hi, positions, reach, params, rotations, out))
    return out


def may_show(camera: Camera, positions, reach) -> np.ndarray:
    """(N,) bool: every splat core.render draws through `camera` (a superset), from the centres
    `positions` (N,3) and three standard deviations of the widest axes, `reach` (N,)
    (reach_and_gap's). The render draws a splat to alpha 1/255: sqrt(2 ln 255) = 3.33 standard
    deviations of its screen covariance widened by the 0.3 px^2 low-pass (at most 1.83 px more),
    whose Jacobian grows the splat by sqrt(1 + t^2) at a view tangent t clamped to FRUSTUM_MARGIN
    times the image's."""
    reach = np.asarray(reach, np.float64) * (SHOWN_SIGMAS / 3.0)
    return near_masks([camera], positions, reach, pad=SHOWN_PAD, margin=FRUSTUM_MARGIN)[0]


def _near_params(camera, pad, margin):
    """A camera as _near_loop reads it: centre (3), the image's tangent bounds x0, x1, y0, y1 (in
    metres across for an orthographic camera) `pad` pixels beyond its edges, the near plane,
    orthographic, and the growth of a reach seen at `margin` times the widest tangent."""
    x0, x1 = (-camera.cx - pad) / camera.fx, (camera.width - camera.cx + pad) / camera.fx
    y0, y1 = (-camera.cy - pad) / camera.fy, (camera.height - camera.cy + pad) / camera.fy
    widest = math.sqrt(1 + (margin * max(-x0, x1, -y0, y1)) ** 2)
    return [*camera.center, x0, x1, y0, y1, camera.near, float(camera.is_orthographic), widest]


def _near_loop(lo, hi, positions, reach, params, rotations, out):
    """_near_mask for splats lo..hi and every camera (rows of params and rotations) into out (F,N)."""
    for f in range(params.shape[0]):
        x0, x1, y0, y1 = params[f, 3], params[f, 4], params[f, 5], params[f, 6]
        near, ortho, widest = params[f, 7], params[f, 8] > 0.5, params[f, 9]
        for i in range(lo, hi):
            px, py, pz = positions[i, 0] - params[f, 0], positions[i, 1] - params[f, 1], positions[i, 2] - params[f, 2]
            x = rotations[f, 0, 0] * px + rotations[f, 0, 1] * py + rotations[f, 0, 2] * pz
            y = rotations[f, 1, 0] * px + rotations[f, 1, 1] * py + rotations[f, 1, 2] * pz
            r = reach[i]
            if ortho:
                out[f, i] = x0 - r <= x <= x1 + r and y0 - r <= y <= y1 + r
                continue
            z = rotations[f, 2, 0] * px + rotations[f, 2, 1] * py + rotations[f, 2, 2] * pz
            slack = r * widest
            out[f, i] = z + r > near and x0 * z - slack <= x <= x1 * z + slack and y0 * z - slack <= y <= y1 * z + slack


def _near_mask(camera, points, reach, pad=2.0, margin=1.0):
    """Splats whose `reach` may meet the camera's image `pad` pixels beyond its edges (a cone or box
    test, the reach grown as near_params says)."""
    *_, x0, x1, y0, y1, _, _, widest = _near_params(camera, pad, margin)
    x, y, z = camera.to_camera(points).T
    if camera.is_orthographic:
        return (x0 - reach <= x) & (x <= x1 + reach) & (y0 - reach <= y) & (y <= y1 + reach)
    slack = reach * widest
    inside_x = (x0 * z - slack <= x) & (x <= x1 * z + slack)
    return (z + reach > camera.near) & inside_x & (y0 * z - slack <= y) & (y <= y1 * z + slack)


def face_of(cameras, points):
    """(N,) index of the view (of `cameras`) each splat is tested in: the cube face its direction
    falls in most centrally (the largest forward component); -1 where no view looks (behind an area
    light)."""
    if len(cameras) == 1:
        return np.zeros(len(points), np.int64)
    rel = points - cameras[0].center
    forward = np.stack([camera.forward for camera in cameras])
    along = rel @ forward.T
    best = np.argmax(along, axis=1)
    behind = along[np.arange(len(points)), best] <= 0
    return np.where(behind, -1, best)


def _up_for(direction):
    """An up vector not parallel to `direction`."""
    return np.array([0.0, 0.0, 1.0]) if abs(direction[2]) < 0.9 else np.array([0.0, 1.0, 0.0])


def unit(v):
    """`v` (3,) as a float64 unit vector."""
    v = np.asarray(v, np.float64).reshape(3)
    return v / np.linalg.norm(v)
