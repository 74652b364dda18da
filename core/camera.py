"""Pinhole and orthographic cameras in the core's convention: x right, y down, z forward (OpenCV).

Pixel (i, j) is sampled at its centre (i + 0.5, j + 0.5); row 0 is the top of the image. Blender
and OpenGL cameras look down -Z with +Y up; the helpers at the end convert their matrices and lens
settings to ours as pure math (no bpy), so a Blender render engine can build a Camera from values it
reads off a camera object.
"""

import math
from dataclasses import dataclass, field, replace

import numpy as np

PROJECTIONS = ("perspective", "orthographic")

# Flips y and z: OpenGL/Blender camera axes (x right, y up, -z forward) <-> ours (x right, y down, z forward).
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True, eq=False)
class Camera:
    """Intrinsics in pixels, a rigid world-to-camera transform, clip planes and the projection.

    For "orthographic", fx and fy are pixels per world unit and x_px = fx * x + cx. Splats with
    camera z <= near or z > far are culled (near 0.2 as in the 3DGS reference rasteriser).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_to_camera: np.ndarray = field(default_factory=lambda: np.eye(4))
    near: float = 0.2
    far: float = math.inf
    projection: str = "perspective"

    def __post_init__(self):
        m = np.array(self.world_to_camera, dtype=np.float64)
        object.__setattr__(self, "world_to_camera", m)
        problems = []
        for name in ("width", "height"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                problems.append(f"{name} must be a positive integer, got {value!r}")
        for name in ("fx", "fy"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                problems.append(f"{name} must be finite and > 0, got {getattr(self, name)!r}")
        for name in ("cx", "cy"):
            if not math.isfinite(getattr(self, name)):
                problems.append(f"{name} must be finite, got {getattr(self, name)!r}")
        if self.projection not in PROJECTIONS:
            problems.append(f"projection must be one of {PROJECTIONS}, got {self.projection!r}")
        if not (self.near >= 0 and self.far > self.near):
            problems.append(f"need 0 <= near < far, got near={self.near!r}, far={self.far!r}")
        if m.shape != (4, 4) or not np.isfinite(m).all():
            problems.append(f"world_to_camera must be a finite 4x4 matrix, got shape {m.shape}")
        else:
            r = m[:3, :3]
            if (
                np.abs(r @ r.T - np.eye(3)).max() > 1e-6
                or np.linalg.det(r) < 0
                or np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-12
            ):
                problems.append("world_to_camera must be rigid (a rotation and a translation)")
        if problems:
            raise ValueError("invalid camera: " + "; ".join(problems))
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    # construction ---------------------------------------------------------------------------

    @classmethod
    def look_at(cls, eye, target, up=(0.0, 1.0, 0.0), fov_deg=60.0, width=512, height=512, near=0.2, far=math.inf):
        """A centred perspective camera at `eye` looking at `target`; `fov_deg` is horizontal and
        world `up` appears up in the image."""
        if not 0.0 < fov_deg < 180.0:
            raise ValueError(f"invalid camera: fov_deg must be in (0, 180), got {fov_deg!r}")
        f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
        return cls(width, height, f, f, width / 2, height / 2, look_at_matrix(eye, target, up), near, far)

    @classmethod
    def look_at_ortho(
        cls, eye, target, up=(0.0, 1.0, 0.0), ortho_scale=2.0, width=512, height=512, near=0.2, far=math.inf
    ):
        """A centred orthographic camera; `ortho_scale` is the visible width in world units."""
        if not (math.isfinite(ortho_scale) and ortho_scale > 0):
            raise ValueError(f"invalid camera: ortho_scale must be finite and > 0, got {ortho_scale!r}")
        f = width / ortho_scale
        return cls(
            width, height, f, f, width / 2, height / 2, look_at_matrix(eye, target, up), near, far, "orthographic"
        )

    @classmethod
    def from_blender(cls, matrix_world, width, height, clip_start=0.2, clip_end=math.inf, **lens):
        """From a Blender camera object's matrix_world (any scale is removed) and its lens settings
        (the keyword arguments of `blender_intrinsics`)."""
        intr = blender_intrinsics(width, height, **lens)
        return cls(
            width,
            height,
            world_to_camera=world_to_camera_from_opengl(matrix_world),
            near=clip_start,
            far=clip_end,
            **intr,
        )

    def with_(self, **changes):
        """A copy with some fields changed (e.g. a different resolution or clip plane)."""
        return replace(self, **changes)

    # derived quantities ---------------------------------------------------------------------------

    @property
    def rotation(self):
        """World-to-camera rotation (3,3): rows are the camera's x, y, z axes in world space."""
        return self.world_to_camera[:3, :3]

    @property
    def center(self):
        """The camera position in world space (float64)."""
        return -self.rotation.T @ self.world_to_camera[:3, 3]

    @property
    def forward(self):
        """The viewing direction (camera +z) in world space."""
        return self.rotation[2].copy()

    @property
    def camera_to_world(self):
        m = np.eye(4)
        m[:3, :3] = self.rotation.T
        m[:3, 3] = self.center
        return m

    @property
    def is_orthographic(self):
        return self.projection == "orthographic"

    @property
    def fov_x_deg(self):
        """Horizontal field of view in degrees (perspective only; centred cameras)."""
        return math.degrees(2 * math.atan(0.5 * self.width / self.fx))

    def to_camera(self, points):
        """World points (N,3) -> camera coordinates (N,3), float64. Subtracting the centre first
        keeps far-from-origin scenes exact to float64 round-off."""
        p = np.asarray(points, dtype=np.float64) - self.center
        return p @ self.rotation.T

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """(unit world directions (H,W,3) through the pixels' centres, each pixel's solid angle (H,W))
        of a perspective camera: what a picture of a distant light (a sky, a sun) sums over."""
        if self.is_orthographic:
            raise ValueError("pixel_rays: an orthographic camera's pixels span no solid angle")
        x = (np.arange(self.width) + 0.5 - self.cx) / self.fx
        y = (np.arange(self.height) + 0.5 - self.cy) / self.fy
        along = np.stack(np.broadcast_arrays(x[None, :], y[:, None], 1.0), axis=-1)  # camera space, z = 1
        length = np.linalg.norm(along, axis=-1)
        return (along / length[..., None]) @ self.rotation, 1.0 / (self.fx * self.fy * length**3)

    def project(self, points):
        """World points (N,3) -> (pixel coordinates (N,2) in x right / y down, camera depth z (N,)).

        Pixel coordinates are continuous: the centre of pixel (i, j) is (i + 0.5, j + 0.5). Points
        on or behind the camera plane get NaN pixel coordinates in perspective.
        """
        c = self.to_camera(points)
        z = c[:, 2]
        if self.is_orthographic:
            x, y = c[:, 0], c[:, 1]
        else:
            safe = np.where(z > 0, z, np.nan)
            x, y = c[:, 0] / safe, c[:, 1] / safe
        return np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=1), z


def frame_points(
    points,
    width=512,
    height=512,
    fov_deg=60.0,
    ortho_scale=None,
    eye=None,
    target=None,
    up=(0.0, 1.0, 0.0),
    direction=(1.2, 0.8, 1.0),
    near=0.2,
):
    """A camera that sees all of `points` (their bounding sphere), for previews.

    Looks at `target` (default: the centre of the points' box) from `eye` (default: along
    `direction` from the target, just far enough for the sphere to fit the narrower field of view,
    and never so close that the sphere reaches the near plane). Orthographic when `ortho_scale` is
    given (0 picks one that fits the sphere). The near plane is `near` (0.2, as for every Camera)
    wherever the camera looks. Non-finite points are ignored; with none left the unit sphere at
    the origin is framed.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    lo, hi = (pts.min(axis=0), pts.max(axis=0)) if len(pts) else (-np.ones(3), np.ones(3))
    center = (lo + hi) / 2 if target is None else np.asarray(target, dtype=np.float64)
    radius = max(float(np.linalg.norm(pts - center, axis=1).max()) if len(pts) else 1.0, 1e-6)
    aspect = width / height
    if eye is None:
        d = np.asarray(direction, dtype=np.float64)
        half = math.radians(fov_deg) / 2
        narrow = min(half, math.atan(math.tan(half) / aspect))
        distance = radius / math.sin(narrow) if ortho_scale is None else 2.0 * radius
        distance = max(distance, 1.01 * (radius + near))
        eye = center + d / np.linalg.norm(d) * distance
    if ortho_scale is None:
        return Camera.look_at(eye, center, up, fov_deg, width, height, near=near)
    scale = ortho_scale or 2.0 * radius * max(1.0, aspect)
    return Camera.look_at_ortho(eye, center, up, scale, width, height, near=near)


def look_at_matrix(eye, target, up=(0.0, 1.0, 0.0)):
    """World-to-camera (4,4) for a camera at `eye` looking at `target`, x right, y down, z forward.

    When `up` is parallel to the viewing direction, another world axis is used as up, so looking
    straight down or up still gives a valid camera.
    """
    eye, target, up = (np.asarray(v, dtype=np.float64).reshape(3) for v in (eye, target, up))
    if not (np.isfinite(eye).all() and np.isfinite(target).all() and np.isfinite(up).all()):
        raise ValueError("invalid camera: eye, target and up must be finite")
    forward = target - eye
    if np.linalg.norm(forward) == 0:
        raise ValueError("invalid camera: eye and target are the same point")
    forward /= np.linalg.norm(forward)
    for candidate in (up, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])):
        right = np.cross(forward, candidate)
        if np.linalg.norm(right) > 1e-9 * max(np.linalg.norm(candidate), 1e-300):
            break
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    m = np.eye(4)
    m[:3, :3] = np.stack([right, down, forward])
    m[:3, 3] = -m[:3, :3] @ eye
    return m


# OpenGL / Blender ---------------------------------------------------------------------------------


def world_to_camera_from_opengl(camera_to_world):
    """Our world-to-camera from an OpenGL/Blender camera-to-world matrix (camera looks down -Z,
    +Y up). Scale in the matrix (a scaled camera object) is removed; the result is rigid."""
    m = np.array(camera_to_world, dtype=np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ValueError(f"camera matrix must be a finite 4x4 matrix, got shape {m.shape}")
    axes = m[:3, :3] / np.linalg.norm(m[:3, :3], axis=0)
    rigid = np.eye(4)
    rigid[:3, :3], rigid[:3, 3] = axes, m[:3, 3]
    cv_to_world = rigid @ GL_TO_CV
    out = np.eye(4)
    out[:3, :3] = cv_to_world[:3, :3].T
    out[:3, 3] = -out[:3, :3] @ cv_to_world[:3, 3]
    return out


def opengl_camera_to_world(world_to_camera):
    """The OpenGL/Blender camera-to-world matrix (-Z forward, +Y up) of our world-to-camera."""
    w2c = np.asarray(world_to_camera, dtype=np.float64)
    c2w = np.eye(4)
    c2w[:3, :3] = w2c[:3, :3].T
    c2w[:3, 3] = -w2c[:3, :3].T @ w2c[:3, 3]
    return c2w @ GL_TO_CV


def blender_sensor_fit(width, height, sensor_fit="AUTO", pixel_aspect_x=1.0, pixel_aspect_y=1.0):
    """Resolve Blender's AUTO sensor fit to "HORIZONTAL" or "VERTICAL" (as Blender does)."""
    fit = sensor_fit.upper()
    if fit not in ("AUTO", "HORIZONTAL", "VERTICAL"):
        raise ValueError(f"sensor_fit must be AUTO, HORIZONTAL or VERTICAL, got {sensor_fit!r}")
    if fit == "AUTO":
        return "HORIZONTAL" if pixel_aspect_x * width >= pixel_aspect_y * height else "VERTICAL"
    return fit


def blender_intrinsics(
    width,
    height,
    lens=50.0,
    sensor_width=36.0,
    sensor_height=24.0,
    sensor_fit="AUTO",
    shift_x=0.0,
    shift_y=0.0,
    type="PERSP",
    ortho_scale=None,
    pixel_aspect_x=1.0,
    pixel_aspect_y=1.0,
):
    """fx, fy, cx, cy and projection for a Blender camera, following Blender's view-plane rules.

    `lens` and the sensor sizes are in mm; `shift_*` and `ortho_scale` are relative to the fitted
    sensor dimension (the larger image side under AUTO, which always uses sensor_width). `type`
    is the camera's "PERSP" or "ORTHO" (panoramic cameras have no pinhole model).
    """
    kind = type.upper()
    if kind not in ("PERSP", "ORTHO"):
        raise ValueError(f"Blender camera type {type!r} is not supported (PERSP or ORTHO)")
    fit = blender_sensor_fit(width, height, sensor_fit, pixel_aspect_x, pixel_aspect_y)
    ycor = pixel_aspect_y / pixel_aspect_x
    # The fitted dimension in (horizontal-)pixel units, which shift and the sensor refer to.
    view = width if fit == "HORIZONTAL" else ycor * height
    if kind == "ORTHO":
        if ortho_scale is None or not ortho_scale > 0:
            raise ValueError(f"an orthographic camera needs ortho_scale > 0, got {ortho_scale!r}")
        fx = view / ortho_scale
    else:
        sensor = sensor_height if sensor_fit.upper() == "VERTICAL" else sensor_width
        if not (lens > 0 and sensor > 0):
            raise ValueError(f"lens and sensor size must be > 0, got lens={lens!r}, sensor={sensor!r}")
        fx = lens * view / sensor
    return {
        "fx": fx,
        "fy": fx / ycor,
        "cx": width / 2 - shift_x * view,
        "cy": height / 2 + shift_y * view / ycor,
        "projection": "orthographic" if kind == "ORTHO" else "perspective",
    }


def blender_lens(camera, sensor_width=36.0):
    """The lens settings (blender_intrinsics' keyword arguments) under which a Blender camera of
    `camera`'s resolution sees as `camera` does: its focal lengths as a lens on a horizontally
    fitted sensor, its principal point as a shift, unequal fx and fy as a pixel aspect."""
    width, height = camera.width, camera.height
    ycor = camera.fx / camera.fy
    lens = {
        "sensor_width": sensor_width,
        "sensor_height": sensor_width,
        "sensor_fit": "HORIZONTAL",
        "shift_x": (width / 2 - camera.cx) / width,
        "shift_y": (camera.cy - height / 2) * ycor / width,
        "pixel_aspect_x": max(1.0, 1.0 / ycor),
        "pixel_aspect_y": max(1.0, ycor),
    }  # Blender's are >= 1
    if camera.is_orthographic:
        return {**lens, "type": "ORTHO", "ortho_scale": width / camera.fx, "lens": 50.0}
    return {**lens, "type": "PERSP", "ortho_scale": None, "lens": camera.fx * sensor_width / width}


def spread_along(cameras, count, centre, spacing=None, most=None):
    """Indices (ascending) of at most `count` cameras of a path, spread evenly by how much the view
    of `centre` changes along it: step by step, the camera's turn around the centre plus the log of
    its distance ratio, the turn of its forward axis and the log of its zoom (radians; a tenfold
    dolly counts as 2.3, a turn around the centre facing it twice its angle). A highlight is right
    only near a view it was baked from, so views go where the view changes, not where the frames
    are: a camera standing still for half the path gets one view there, a path that never changes
    one view. With `spacing` (radians of that change), more than `count` where the path needs them
    to keep neighbours within `spacing`, up to `most`."""
    if not len(cameras):
        return np.zeros(0, int)
    along = _path_change(cameras, np.asarray(centre, np.float64))
    if spacing is not None:
        needed = int(np.ceil(along[-1] / spacing)) + 1
        count = max(int(count), min(needed, len(cameras) if most is None else int(most)))
    if count <= 1 or along[-1] <= 1e-9:
        return np.zeros(1, int)
    targets = np.linspace(0.0, along[-1], int(count))
    after = np.clip(np.searchsorted(along, targets), 1, len(along) - 1)
    nearest = np.where(targets - along[after - 1] <= along[after] - targets, after - 1, after)
    return np.unique(nearest)


def _path_change(cameras, centre):
    """spread_along's change of view from the first camera to each, (n,) radians."""
    offset = np.array([cam.center for cam in cameras]) - centre
    distance = np.maximum(np.linalg.norm(offset, axis=1), 1e-12)
    forward = np.array([cam.forward for cam in cameras])
    zoom = np.log([cam.fx for cam in cameras])
    turn = lambda a, b: np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))  # noqa: E731
    steps = (
        turn(offset[:-1], offset[1:])
        + np.abs(np.diff(np.log(distance)))
        + turn(forward[:-1], forward[1:])
        + np.abs(np.diff(zoom))
    )
    return np.concatenate([[0.0], np.cumsum(steps)])
