"""Mesh objects -> splat objects through the core converter (core.mesh_to_splats).

Each selected mesh is read as the depsgraph evaluates it (modifiers applied), triangulated by
Blender's own loop triangles, and handed to the core with its appearance:

- Base colour: the Principled BSDF's (or the surface shader's) Base Color / Color input. An
  unlinked value is scene-linear; an Image Texture node linked to it is sampled through its UV map
  (a UV Map node's, else the mesh's active render UV map). Byte images in the 'sRGB' colour space
  hold sRGB-encoded values and are decoded; float images are scene-linear in memory, and
  'Non-Color' / linear byte images are taken as linear.
- Colour attributes: a Color Attribute (or Attribute) node linked to the base colour gives the
  colour per corner; a mesh without materials uses its render colour attribute if it has one.
- One material per face, from the loop triangle's material index and the object's slots.

The splat object gets the mesh object's world matrix, and keeps per splat the extras
"source_triangle" (index into the evaluated mesh's loop triangles), "barycentric" (weights of the
triangle's corners) and "source_vertices" (the triangle's three vertex indices), plus the mesh
property SOURCE naming the mesh object, so weights and other vertex data can be interpolated at
each splat. Use "source_vertices" for that, not "source_triangle": Blender may split a quad along
the other diagonal once the mesh deforms. They are the original mesh's vertex indices whenever
the evaluated mesh kept its vertex count (only deforming modifiers; SOURCE says so). Meshes
deformed by an armature are converted in the armature's rest position (by default), the pose a
binding starts from.
"""

import contextlib
import json
import warnings

import bpy
import numpy as np
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty

from ...core import geometry
from ...core.bake import VIEWS_PER_DISTANCE as BAKE_VIEWS
from ...core.camera import Camera, spread_along
from ...core.memory import human_bytes
from ...core.mesh_refine import VIEW_DISTANCES, VIEWS_PER_DISTANCE, summary
from ...core.mesh_render import CYCLES_FILTER_WIDTH, DEFAULT_PIXEL_FILTER
from ...core.mesh_to_splats import DEFAULT_RENDER_MODE, DEFAULT_TARGET_PSNR, mesh_to_splats_steps
from ...core.steps import drain, mapped_steps
from ...io import written_size
from .. import data
from ..data import camera, display
from ..data.display import DISPLAY_BUDGET
from ..data.errors import EXPECTED_ERRORS
from ..data.keys import SOURCE
from ..data.modal_jobs import JobOperator
from .bake import bake_steps
from .mesh_reading import MeshConversionError, read_object, rest_pose

BAKE_SAMPLES = 16  # Cycles samples per baked view (denoised)
BAKE_DEGREE = 3
MAX_BAKE_VIEWS, MAX_BAKE_SAMPLES, MAX_BAKE_DEGREE = 256, 4096, 3
MAX_BAKE_GEOMETRY_STEPS = 100_000
VIEW_SIZE, VIEW_SIZES = 256, (16, 2048)  # pixels across a view quality is measured in / baked from
VIEW_COUNTS = (1, 64)  # views per distance around, or frames of the camera path
PATH_FRAMES_PER_VIEW = 16  # frames of the camera path looked at per view kept
# A bake's path views at most this far apart (core.camera.spread_along's radians: a turn around the
# object counts twice). bench/bake.py's quick sphere, a 1x camera still for 50 frames then turning 90
# degrees, dB at 13 frames along the turn (worst): 4 views 35.1 (30.3), 8 (this spacing) 37.2 (33.5), 13 37.3 (32.8).
BAKE_PATH_SPACING = 0.5
BAKE_PATH_FRAMES = 256  # frames of the path a bake looks at, at least (10 s at 25 fps)
VIEW_DISTANCE_LIMITS = (0.05, 100.0)  # view distances, multiples of the one framing the mesh
SUFFIX = "_splats"
DEFAULT_BUDGET = 200_000
CALIBRATE_TOOLTIP = (
    "Splat Budget: render the mesh and the splats from the views and pull solid parts in by "
    "about a pixel, so the splats' outlines match the mesh's instead of rendering a pixel fatter "
    "(a few seconds per object, for a closer look from those views). Off: no renders, the "
    "splats stay on the surface (Target PSNR always calibrates)"
)


def object_steps(
    obj,
    triangles,
    appearance,
    record,
    *,
    max_splats=None,
    target_psnr=None,
    calibrate=True,
    try_fewer=True,
    render_mode=DEFAULT_RENDER_MODE,
    material=False,
    warn=print,
    views=None,
    info=None,
    **view_options,
):
    """A generator converting one object's read mesh (read_object): yields (done, total, label) as
    mesh_to_splats_steps does (a target PSNR: a step per refinement round) and returns (cloud, record).
    `views` (core Cameras in the object's space) or `view_options` (view_size, view_distances,
    view_count of mesh_to_splats) say where quality is measured, and pixel_filter and filter_width
    with what pixel filter (ConversionJob passes the scene's); `calibrate` and `try_fewer` (a budget
    only: the silhouettes calibrated against renders from those views, and fewer splats kept where
    they render better there), `render_mode` (what the splats are made for), `material` (the
    material extras relighting shades with) and `info` as mesh_to_splats takes them."""
    steps = mesh_to_splats_steps(
        triangles.vertices,
        triangles.faces,
        max_splats=max_splats,
        target_psnr=target_psnr,
        calibrate=calibrate,
        try_fewer=try_fewer,
        render_mode=render_mode,
        material=material,
        views=views,
        info=info,
        **view_options,
        **appearance,
    )
    while True:
        with warnings.catch_warnings(record=True) as caught:  # per step: nothing held across yields
            warnings.simplefilter("always")
            try:
                step = next(steps)
            except StopIteration as stop:
                cloud = stop.value
                step = None
            except ValueError as exc:
                raise MeshConversionError(f"'{obj.name}': {exc}") from exc
        for w in caught:
            warn(f"'{obj.name}': {w.message}")
        if step is None:
            break
        yield step
    tri = cloud.extras["source_triangle"]
    cloud.extras["source_vertices"] = triangles.faces[tri].astype(np.int32)
    return cloud, record


def convert_object(
    obj,
    depsgraph,
    *,
    max_splats=None,
    target_psnr=None,
    calibrate=True,
    render_mode=DEFAULT_RENDER_MODE,
    progress=None,
    warn=print,
    rest=False,
    **view_options,
):
    """(SplatCloud in object space, source record) for one mesh object as `depsgraph` evaluates it;
    `calibrate`, `render_mode` and `view_options` as object_steps takes them."""
    read = read_object(obj, depsgraph, warn, rest)
    return drain(
        object_steps(
            obj,
            *read,
            max_splats=max_splats,
            target_psnr=target_psnr,
            calibrate=calibrate,
            render_mode=render_mode,
            warn=warn,
            **view_options,
        ),
        progress,
    )


CYCLES_PIXEL_FILTERS = {"BLACKMAN_HARRIS": "blackman-harris", "GAUSSIAN": "gaussian", "BOX": "box"}


def scene_pixel_filter(scene):
    """mesh_to_splats' pixel_filter and filter_width for the filter Cycles renders `scene` with (Film >
    Pixel Filter), so quality is measured against the edges the user's renders have; Cycles'
    defaults where its add-on is off."""
    cycles = getattr(scene, "cycles", None)
    return {
        "pixel_filter": CYCLES_PIXEL_FILTERS.get(getattr(cycles, "pixel_filter_type", ""), DEFAULT_PIXEL_FILTER),
        "filter_width": float(getattr(cycles, "filter_width", CYCLES_FILTER_WIDTH)),
    }


def mesh_objects(objects):
    """The mesh objects among `objects` that are not splat clouds, or MeshConversionError."""
    objects = list(objects)
    if not objects:
        raise MeshConversionError("nothing is selected")
    meshes = [o for o in objects if o.type == "MESH" and not data.is_splat_object(o)]
    if not meshes:
        listed = ", ".join(f"'{o.name}' ({'splat cloud' if data.is_splat_object(o) else o.type})" for o in objects[:5])
        raise MeshConversionError(f"no mesh objects to convert; {listed} cannot be converted")
    return meshes


class CameraPath:
    """The scene camera over the scene's frame range as each object sees it, stepped through once
    (`looked_at` frames spread over the range; the current frame is restored): views() then picks
    from it without touching the scene. Views are `size` pixels wide, of the render's aspect. A heavy
    rig can make the walk take seconds: each frame is passed to `progress(done, total, label)`."""

    def __init__(self, scene, objects, size, looked_at, progress=None):
        cam = scene.camera
        if cam is None:
            raise MeshConversionError("the scene has no camera to measure the splats' quality from")
        render = scene.render
        self.camera_name = cam.name
        self.width = max(1, int(size))
        self.height = max(
            1,
            round(
                self.width
                * render.resolution_y
                * render.pixel_aspect_y
                / max(render.resolution_x * render.pixel_aspect_x, 1e-9)
            ),
        )
        spread = np.linspace(scene.frame_start, scene.frame_end, max(int(looked_at), 1))
        self.frames = np.unique(np.round(spread).astype(int))
        self.now = {obj: np.array(obj.matrix_world, dtype=np.float64) for obj in objects}
        self.relative = {obj: [] for obj in objects}  # the camera in the object's space, per frame
        self.lenses = []  # its clip range and lens settings, per frame
        current, subframe = scene.frame_current, scene.frame_subframe
        try:
            for done, frame in enumerate(self.frames, 1):
                scene.frame_set(int(frame))
                cam_world = np.array(cam.matrix_world, dtype=np.float64)
                self.lenses.append(
                    dict(
                        clip_start=cam.data.clip_start,
                        clip_end=cam.data.clip_end,
                        **camera.lens_settings(cam.data, render),
                    )
                )
                for obj in objects:
                    self.relative[obj].append(np.linalg.inv(np.array(obj.matrix_world, dtype=np.float64)) @ cam_world)
                if progress is not None:
                    progress(done, len(self.frames), "camera path frames")
        finally:
            scene.frame_set(current, subframe=subframe)

    def views(self, obj, count, world=False, spacing=None):
        """[core Camera]: `count` frames spread by how much the object's view changes
        (core.camera.spread_along; with `spacing`, more where it changes by more than that between
        them, up to VIEW_COUNTS' most), in the object's own space, or with `world` in world space
        where the object stands now (the path as the object sees it, for a bake)."""
        to_world = self.now[obj] if world else np.eye(4)
        path = [
            self._camera(to_world @ relative, lens, frame)
            for relative, lens, frame in zip(self.relative[obj], self.lenses, self.frames)
        ]
        return [path[i] for i in spread_along(path, count, _bounds_centre(obj, to_world), spacing, most=VIEW_COUNTS[1])]

    def _camera(self, matrix, lens, frame):
        # A non-uniformly scaled object's space shears the camera: its nearest rotation (views of
        # such an object are approximate in its space). A mirrored object's mirrors it: the view
        # mirrored left to right sees the same surface.
        matrix = matrix.copy()
        matrix[:3, :3] = geometry.polar_rotation(matrix[:3, :3])
        if np.linalg.det(matrix[:3, :3]) < 0:
            matrix[:3, 0] *= -1.0
        try:
            return Camera.from_blender(matrix, self.width, self.height, **lens)
        except ValueError as exc:
            raise MeshConversionError(f"camera '{self.camera_name}' at frame {int(frame)}: {exc}") from exc


def frames_looked_at(count, spacing=None):
    """How many frames of a camera path to look at for `count` views: PATH_FRAMES_PER_VIEW per view,
    and at least BAKE_PATH_FRAMES where views are added by `spacing`."""
    looked_at = PATH_FRAMES_PER_VIEW * max(int(count), 1)
    return looked_at if spacing is None else max(looked_at, BAKE_PATH_FRAMES)


def _bounds_centre(obj, matrix):
    """The centre of an object's bounding box, through `matrix` from its own space."""
    corners = np.array([corner[:] for corner in obj.bound_box], dtype=np.float64)
    return matrix[:3, :3] @ ((corners.min(axis=0) + corners.max(axis=0)) / 2) + matrix[:3, 3]


class ConversionJob:
    """Mesh objects converted a step at a time, for a modal operator (Esc between steps) and for
    batch use alike. The meshes are read when the job is made (in their armatures' rest position
    with `use_rest_pose`); the steps then touch no Blender data (a baked look's Cycles views each
    undo what they set up within their step), so a job stopped part-way (cancel()) leaves the scene
    as it was. step() does one step (a refinement round of one object
    with a target PSNR, a splat count a budget tries) and returns False once every object is
    converted; `results` then holds [(source object, cloud, record)], which create() links into
    the scene. `done` / `total` / `label` say how far it is (objects as units). `calibrate=False`
    makes a budget conversion render nothing (see object_steps)."""

    def __init__(
        self,
        context,
        objects,
        *,
        max_splats=None,
        target_psnr=None,
        calibrate=True,
        use_rest_pose=True,
        render_mode=DEFAULT_RENDER_MODE,
        material=False,
        warn=print,
        views=None,
        bake=None,
        **view_options,
    ):
        # Splats whose look is baked keep the whole budget: fewer render the Base Color better, not the lit look.
        self.options = dict(
            max_splats=max_splats,
            target_psnr=target_psnr,
            calibrate=calibrate,
            render_mode=render_mode,
            material=material,
            warn=warn,
            try_fewer=bake is None,
            **scene_pixel_filter(context.scene),
            **view_options,
        )
        self.views = views  # {object: [core Camera]} or None (views around each mesh)
        self.bake = bake  # bake.bake_steps' options (the Rendered look), or None
        if bake is not None and not hasattr(context.scene, "cycles"):
            raise MeshConversionError("the Rendered look is rendered by Cycles, whose add-on is not enabled")
        self.scene, self.use_rest_pose = context.scene, use_rest_pose
        self.infos = []  # mesh_to_splats' info of each object, as results fill
        with rest_pose(objects) if use_rest_pose else contextlib.nullcontext():
            depsgraph = context.evaluated_depsgraph_get()
            self.inputs = [(obj, *read_object(obj, depsgraph, warn, use_rest_pose)) for obj in objects]
        self.results, self.total, self.done, self.label = [], len(objects), 0.0, ""
        self._steps = None

    def _object_steps(self, index, views):
        """Convert one object, then (with `bake`) bake its look: half the object's progress each."""
        obj, triangles = self.inputs[index][:2]
        info = self.infos[index]
        steps = object_steps(*self.inputs[index], **self.options, views=views, info=info)
        share = 1.0 if self.bake is None else 0.5
        cloud, record = yield from _scaled(steps, 0.0, share)
        if self.bake is not None:
            options = dict(self.bake)
            path = (options.pop("paths", None) or {}).get(obj, ())
            baking = bake_steps(
                self.scene, obj, cloud, triangles.vertices, path=path, info=info.setdefault("bake", {}), **options
            )
            with rest_pose([obj]) if self.use_rest_pose else contextlib.nullcontext():
                cloud = yield from _scaled(baking, 0.5, 0.5)
        return cloud, record

    def step(self):
        """One step; False when there is nothing left to do."""
        index = len(self.results)
        if index == len(self.inputs):
            return False
        obj = self.inputs[index][0]
        if self._steps is None:
            self.infos = self.infos[:index] + [{}]
            views = None if self.views is None else self.views[obj]
            self._steps = self._object_steps(index, views)
        try:
            done, total, label = next(self._steps)
        except StopIteration as stop:
            self.results.append((obj, *stop.value))
            self._steps = None
            self.done = float(len(self.results))
            return len(self.results) < len(self.inputs)
        self.done, self.label = index + (done / total if total else 1.0), f"{obj.name}: {label}"
        return True

    def run(self, progress=None):
        """Every step; progress(done, total, label) after each. Returns the results."""
        while self.step():
            if progress:
                progress(self.done, self.total, self.label)
        return self.results

    def cancel(self):
        """Stop: the steps under way are dropped, nothing was or will be added to the scene."""
        if self._steps is not None:
            self._steps.close()
        self._steps, self.inputs = None, self.inputs[: len(self.results)]


def _scaled(steps, start, share):
    """The steps of a generator with its (done, total) as a fraction start + share * done / total of 1;
    returns its value."""
    return mapped_steps(
        steps, lambda done, total, label: (start + share * (done / total if total else 1.0), 1.0, label)
    )


def convert_objects(
    context,
    objects,
    *,
    max_splats=None,
    target_psnr=None,
    calibrate=True,
    use_rest_pose=True,
    render_mode=DEFAULT_RENDER_MODE,
    material=False,
    progress=None,
    warn=print,
    infos=None,
    bake=None,
    **view_options,
):
    """[(source object, cloud, record)] for mesh objects; nothing in the scene changes.

    progress(done, total, label) sees the whole selection as one task of len(objects) units (a
    baked look adds a step per Cycles view and per fitting iteration).
    `calibrate`: a budget's silhouettes calibrated against renders (object_steps);
    `render_mode`: "classic" or "antialiased", the rendering the splats are made for (and keep);
    `material`: the splats carry the material relighting shades them with (core.material);
    `bake`: bake_options() for the Rendered look, None for the Base Color;
    `view_options`: views (measured_views' mapping) or view_size, view_distances, view_count;
    `infos`, a list, receives each object's mesh_to_splats info (with "bake" when baked)."""
    job = ConversionJob(
        context,
        objects,
        max_splats=max_splats,
        target_psnr=target_psnr,
        calibrate=calibrate,
        use_rest_pose=use_rest_pose,
        render_mode=render_mode,
        material=material,
        warn=warn,
        bake=bake,
        **view_options,
    )
    try:
        results = job.run(progress)
    except BaseException:
        job.cancel()  # the steps under way clean up now (a bake's folder of views)
        raise
    if infos is not None:
        infos.extend(job.infos)
    return results


def create_splat_objects(context, results):
    """Link one splat object per conversion result, each beside and placed like its source; on
    failure the scene is left as it was."""
    created = []
    try:
        for source, cloud, record in results:
            collection = source.users_collection[0] if source.users_collection else context.scene.collection
            obj, _ = data.new_splat_object(cloud, source.name + SUFFIX, collection, source.matrix_world.copy())
            created.append(obj)
            obj.data[SOURCE] = json.dumps(record)
            display.add_display(obj, min(1.0, DISPLAY_BUDGET / max(len(cloud), 1)))
    except BaseException:
        remove_objects(created)
        raise
    return created


def remove_objects(objects):
    """Remove splat objects this module created, with their data (meshes or point clouds)."""
    for obj in objects:
        data.remove_splat_object(obj)


def from_mesh(context, objects, **options):
    """Convert mesh objects to new splat objects (see convert_objects for the options); returns them."""
    return create_splat_objects(context, convert_objects(context, mesh_objects(objects), **options))


def view_distances(near, far):
    """The view distances for a near..far range: near, the whole-mesh framing (1) if inside, far."""
    near, far = sorted((float(near), float(far)))
    return tuple(sorted({near, far} | ({1.0} if near < 1.0 < far else set())))


def measured_views(scene, objects, source, count, size, near, far, bake=False, progress=None):
    """(ConversionJob's keyword arguments saying where quality is measured, bake_options' `paths`).
    From the scene camera (`source` "CAMERA"), its path stepped through once for both: `count`
    frames measured in each object's space and, with `bake`, the views baked from too in world
    space (at least `count`, more where the view changes by more than BAKE_PATH_SPACING between
    them). Around the meshes ("AROUND"): `count` views at each distance of near..far, no paths.
    Views are `size` pixels across; `progress` is CameraPath's."""
    if source != "CAMERA":
        return {"view_distances": view_distances(near, far), "view_count": count, "view_size": size}, None
    path = CameraPath(scene, objects, size, frames_looked_at(count, BAKE_PATH_SPACING if bake else None), progress)
    views = {obj: path.views(obj, count) for obj in objects}
    paths = {obj: path.views(obj, count, world=True, spacing=BAKE_PATH_SPACING) for obj in objects} if bake else None
    return {"views": views}, paths


def bake_options(
    samples=BAKE_SAMPLES,
    views=BAKE_VIEWS,
    degree=BAKE_DEGREE,
    size=VIEW_SIZE,
    distances=None,
    paths=None,
    geometry_steps=0,
):
    """bake.bake_steps' options for the Rendered look: `views` Cycles views of `samples` samples at
    each view distance (`distances`, default core.mesh_refine's), `size` pixels across, fitted to SH
    of `degree`, then `geometry_steps` steps fitting the splats too; `paths` ({object: [core
    Camera]} in world space, measured_views' paths), the views each object is rendered from, baked
    from too and weighted first."""
    return dict(
        samples=samples,
        count=views,
        size=size,
        distances=distances,
        degree=degree,
        paths=paths,
        geometry_steps=geometry_steps,
    )


def conversion_report(count, info):
    """What a report says of one converted object: its splat count, the quality reached and where
    (mesh_refine.summary), and for a baked look its fit."""
    quality = summary(info)
    return f"{count} splats{', ' + quality if quality else ''}{baked_summary(info)}"


def baked_summary(info):
    """What a report adds for a baked object (its info): the PSNR reached on the Cycles views."""
    bake = info.get("bake", {})
    colours, splats = bake.get("psnr"), bake.get("geometry", {}).get("psnr")
    if not colours:
        return ""
    fitted = f", then splats fitted to {splats[-1]:.1f} dB" if splats else ""
    return f", baked from Cycles views to {colours[-1]:.1f} dB{fitted}"


def sizing(mode, max_splats, target_psnr):
    """(max_splats, target_psnr) for mesh_to_splats: a budget, or a target PSNR capped by max_splats."""
    if mode == "BUDGET":
        return max_splats, None
    return max_splats, target_psnr


# the operator ----------------------------------------------------------------------------------------


def shown_options(mode, view_source, appearance):
    """The operator's options its panel shows for these choices, in groups (size, views, look): a
    Target PSNR only when sizing by it, Calibrate Silhouettes only with a budget (a target always
    calibrates), Near and Far where views are placed around the mesh (measuring Around, or baking),
    the bake options only for the Rendered look."""
    size = ["mode", "max_splats", "target_psnr" if mode == "QUALITY" else "calibrate", "memory_budget", "use_rest_pose"]
    around = view_source == "AROUND" or appearance == "RENDERED"
    views = ["view_source", *(("view_near", "view_far") if around else ()), "view_count", "view_size"]
    bake = ("bake_views", "bake_samples", "bake_degree", "bake_geometry_steps") if appearance == "RENDERED" else ()
    look = ["made_for", "appearance", *bake, "use_material"]
    return [size, views, look]


class SPLAT_OT_from_mesh(JobOperator, bpy.types.Operator):
    """Convert the selected mesh objects (modifiers applied) to splat objects placed like them
    (from the interface a step at a time: Esc cancels and changes nothing)"""

    bl_idname = "splat.from_mesh"
    bl_label = "Mesh to Splats"
    bl_options = {"REGISTER", "UNDO"}
    job_errors = (MeshConversionError, *EXPECTED_ERRORS)
    _skipped = ()

    mode: EnumProperty(
        name="Size By",
        default="BUDGET",
        items=(
            (
                "BUDGET",
                "Splat Budget",
                "At most Max Splats splats per object, spread evenly over the surface "
                "(fewer when more render worse from the views)",
            ),
            (
                "QUALITY",
                "Target PSNR",
                "Refine until renders of the splats reach Target PSNR against the "
                "mesh, with at most Max Splats splats per object",
            ),
        ),
    )
    max_splats: IntProperty(
        name="Max Splats",
        default=DEFAULT_BUDGET,
        min=1,
        description="Splats per object (the budget, or the cap with a target PSNR)",
    )
    target_psnr: FloatProperty(
        name="Target PSNR",
        default=DEFAULT_TARGET_PSNR,
        min=10.0,
        max=80.0,
        subtype="NONE",
        unit="NONE",
        description="Render quality to reach, in dB",
    )
    calibrate: BoolProperty(name="Calibrate Silhouettes", default=True, description=CALIBRATE_TOOLTIP)
    memory_budget: FloatProperty(
        name="Memory Budget (GiB)",
        default=0.0,
        min=0.0,
        soft_max=64.0,
        description="The most memory one object's conversion may take; 0: half the memory free when it "
        "starts. A conversion that reaches it keeps the splats that fit and says so",
    )
    use_rest_pose: BoolProperty(
        name="Rest Pose",
        default=True,
        description="Convert meshes deformed by an armature in its rest position "
        "(the pose a binding to that armature starts from)",
    )
    view_source: EnumProperty(
        name="Measure From",
        default="AROUND",
        items=(
            ("AROUND", "Around", "Views all around each mesh at the near, whole and far distances"),
            (
                "CAMERA",
                "Scene Camera",
                "The scene camera along its animation: View Count frames of the "
                "scene's frame range, spread by how much the view changes",
            ),
        ),
    )
    view_near: FloatProperty(
        name="Near",
        default=VIEW_DISTANCES[0],
        min=VIEW_DISTANCE_LIMITS[0],
        max=VIEW_DISTANCE_LIMITS[1],
        description="Closest view distance, a multiple of the one that frames the whole mesh",
    )
    view_far: FloatProperty(
        name="Far",
        default=VIEW_DISTANCES[-1],
        min=VIEW_DISTANCE_LIMITS[0],
        max=VIEW_DISTANCE_LIMITS[1],
        description="Farthest view distance, a multiple of the one that frames the whole mesh",
    )
    view_count: IntProperty(
        name="View Count",
        default=VIEWS_PER_DISTANCE,
        min=VIEW_COUNTS[0],
        max=VIEW_COUNTS[1],
        description="Views at each distance (Around), or frames of the camera path (a Rendered "
        "look bakes from more where the camera moves far)",
    )
    view_size: IntProperty(
        name="View Size",
        default=VIEW_SIZE,
        min=VIEW_SIZES[0],
        max=VIEW_SIZES[1],
        description="Pixels across each view quality is measured in",
    )
    made_for: EnumProperty(
        name="Made For",
        default=DEFAULT_RENDER_MODE.upper(),
        items=(
            (
                "ANTIALIASED",
                "Antialiased Rendering",
                "Splats sized for antialiased (opacity-compensated, "
                "Mip-Splatting) rendering: outlines right at every distance in "
                "Splatwright's renders and in viewers that read SPZ's flag "
                "(classic viewers draw them about a pixel fatter)",
            ),
            (
                "CLASSIC",
                "Classic Rendering",
                "Splats sized for classic 3DGS rendering, for viewers that cannot "
                "render antialiased: outlines right at the views' distances only",
            ),
        ),
    )
    appearance: EnumProperty(
        name="Appearance",
        default="BASE_COLOR",
        items=(
            ("BASE_COLOR", "Base Color", "The surface's Base Color (texture, colour attribute), unlit"),
            (
                "RENDERED",
                "Rendered (Cycles)",
                "The look Cycles renders in this scene (its lights, world and "
                "shadows, shading and speculars), baked into the splats' colours "
                "from Cycles views around each mesh and, measured from the scene "
                "camera, from its path too (highlights are right near views baked "
                "from)",
            ),
        ),
    )
    use_material: BoolProperty(
        name="Material for Relighting",
        default=False,
        description="The splats also carry the surface's material (Base Color, normal, Roughness, "
        "Metallic of a Principled BSDF) so the Splatwright engine can light them with the scene's "
        "lights; their own colour stays the look chosen above",
    )
    bake_views: IntProperty(
        name="Bake Views",
        default=BAKE_VIEWS,
        min=1,
        max=MAX_BAKE_VIEWS,
        description="Cycles views at each distance (Near, 1, Far) baked from (Rendered)",
    )
    bake_samples: IntProperty(
        name="Bake Samples",
        default=BAKE_SAMPLES,
        min=1,
        max=MAX_BAKE_SAMPLES,
        description="Cycles samples per baked view, denoised (Rendered)",
    )
    bake_degree: IntProperty(
        name="Bake SH Degree",
        default=BAKE_DEGREE,
        min=0,
        max=MAX_BAKE_DEGREE,
        description="Spherical-harmonics degree of the baked colours: 0 view-independent, "
        "higher for speculars (Rendered)",
    )
    bake_geometry_steps: IntProperty(
        name="Bake Geometry Steps",
        default=0,
        min=0,
        max=MAX_BAKE_GEOMETRY_STEPS,
        description="After the colours, steps fitting the splats' positions, shapes and "
        "opacities to the Cycles views too: a truer look between the "
        "views where it is shading (close-ups of glossy facets can lose), "
        "about 0.2 s a step for 20k splats at 256 px, 0.9 s without numba "
        "(Rendered; 0: colours only)",
    )

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT"

    def draw(self, context):
        """The redo panel in groups, each option only where the choices above it use it."""
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        for i, names in enumerate(shown_options(self.mode, self.view_source, self.appearance)):
            if i:
                layout.separator()
            col = layout.column(align=True)
            for name in names:
                col.prop(self, name)

    def make_job(self, context):
        max_splats, target_psnr = sizing(self.mode, self.max_splats, self.target_psnr)
        objects = mesh_objects(context.selected_objects)
        self._skipped = [o.name for o in context.selected_objects if o not in objects]
        baked = self.appearance == "RENDERED"
        views, paths = measured_views(
            context.scene,
            objects,
            self.view_source,
            self.view_count,
            self.view_size,
            self.view_near,
            self.view_far,
            bake=baked,
            progress=self.setup_progress(context),
        )
        bake = (
            bake_options(
                self.bake_samples,
                self.bake_views,
                self.bake_degree,
                self.view_size,
                view_distances(self.view_near, self.view_far),
                paths,
                self.bake_geometry_steps,
            )
            if baked
            else None
        )
        return ConversionJob(
            context,
            objects,
            max_splats=max_splats,
            target_psnr=target_psnr,
            calibrate=self.calibrate,
            use_rest_pose=self.use_rest_pose,
            render_mode=self.made_for.lower(),
            material=self.use_material,
            warn=lambda message: self.report({"WARNING"}, message),
            bake=bake,
            memory_budget=int(self.memory_budget * 2**30) or None,
            **views,
        )

    def finish(self, context, job):
        try:
            created = create_splat_objects(context, job.results)
        except EXPECTED_ERRORS as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        if self._skipped:
            self.report({"WARNING"}, f"not meshes, skipped: {', '.join(self._skipped)}")
        for obj in context.view_layer.objects:
            obj.select_set(False)
        for obj in created:
            obj.select_set(True)
        context.view_layer.objects.active = created[-1]
        for (source, cloud, _), info in zip(job.results, job.infos):
            missed = info.get("reached") is False
            self.report({"WARNING"} if missed else {"INFO"}, f"'{source.name}': {conversion_report(len(cloud), info)}")
        total = sum(len(cloud) for _, cloud, _ in job.results)
        size = sum(written_size(cloud, "ply") for _, cloud, _ in job.results)
        self.report(
            {"INFO"}, f"made {total} splats from {len(created)} mesh object(s), about {human_bytes(size)} as PLY"
        )
        return {"FINISHED"}


def menu_convert(self, context):
    self.layout.operator(SPLAT_OT_from_mesh.bl_idname)


CLASSES = (SPLAT_OT_from_mesh,)
MENUS = ((bpy.types.VIEW3D_MT_object_convert, menu_convert),)
