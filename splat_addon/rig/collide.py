"""Collisions between two splat objects over a frame range, by the core's exact ellipsoid test.

At each frame both objects are read as they are posed and placed there (data.evaluated_cloud: the
same splats export and rendering see, in world space) and every pair of splats whose k-sigma
ellipsoids intersect is found (core.collision.ellipsoid_contacts). A bound splat object names its
splats by their largest-weight bone, so contacts are reported per bone. Splats fainter than
`min_opacity` are left out, as are splats of `ignore_bones` (say, feet that stand on the floor).

Each object gets the point attribute `splat_contact` (FLOAT): the fraction of the checked frames in
which the splat touched the other object (0 never, 1 at every frame); view it in the spreadsheet or
through an Attribute node. Export leaves it out.
"""

from dataclasses import dataclass, field

import bpy
import numpy as np
from bpy.props import BoolProperty, FloatProperty, IntProperty, StringProperty

from ...core.collision import CollisionInputError, EnvironmentIndex, ellipsoid_contacts
from ...core.frames import frame_ranges
from ...core.skinning import SkinningError
from .. import data
from ..data.errors import EXPECTED_ERRORS
from ..data.modal_jobs import JobOperator
from ..data.scene import frame_range
from . import armature as rigging

CONTACT_ATTRIBUTE = "splat_contact"
DEFAULT_SIGMA = 3.0
DEFAULT_MIN_OPACITY = 0.05


class CollisionSetupError(ValueError):
    """Objects or settings a collision check cannot use; the message names them."""


@dataclass
class FrameContacts:
    """What touched at one frame: splat pairs, splats of each object, and splats per bone."""

    frame: int
    pairs: int = 0
    splats_a: int = 0
    splats_b: int = 0
    bones_a: dict = field(default_factory=dict)  # bone name -> splats of A in contact
    bones_b: dict = field(default_factory=dict)
    deepest: float = float("inf")  # smallest sigma multiple at which a pair touches


@dataclass
class CollisionReport:
    object_a: str
    object_b: str
    k: float
    frames: list  # FrameContacts per checked frame
    contact_a: np.ndarray  # (N_a,) fraction of frames each splat of A was in contact
    contact_b: np.ndarray

    @property
    def contact_frames(self):
        return [f.frame for f in self.frames if f.pairs]

    def as_dict(self):
        """Plain numbers, for JSON."""
        frames = [
            {
                "frame": f.frame,
                "pairs": f.pairs,
                "splats_a": f.splats_a,
                "splats_b": f.splats_b,
                "bones_a": f.bones_a,
                "bones_b": f.bones_b,
                "deepest_sigma": None if np.isinf(f.deepest) else f.deepest,
            }
            for f in self.frames
        ]
        return {
            "object_a": self.object_a,
            "object_b": self.object_b,
            "sigma": self.k,
            "contact_frames": self.contact_frames,
            "frames": frames,
        }

    def summary(self):
        if not self.contact_frames:
            return f"'{self.object_a}' and '{self.object_b}' never touch in {len(self.frames)} frame(s)"
        bones = sorted({b for f in self.frames for b in f.bones_a})
        where = f" (bones of '{self.object_a}': {', '.join(bones)})" if bones else ""
        return (
            f"'{self.object_a}' touches '{self.object_b}' at {len(self.contact_frames)} of {len(self.frames)} "
            f"frame(s): {frame_ranges(self.contact_frames)}{where}"
        )


def splat_objects_pair(scene, name_a, name_b, context=None):
    """The two splat objects to test: named, or (for empty names) the active object and the one
    other selected object."""
    if not name_a or not name_b:
        if context is None:
            raise CollisionSetupError("name both objects")
        active = context.view_layer.objects.active
        others = [o for o in context.selected_objects if o != active]
        name_a = name_a or (active.name if active is not None else "")
        name_b = name_b or (others[0].name if len(others) == 1 else "")
        if not name_a or not name_b:
            raise CollisionSetupError("name both objects, or select two with one of them active")
    objects = []
    for name in (name_a, name_b):
        obj = scene.objects.get(name)
        if obj is None:
            raise CollisionSetupError(f"no object named '{name}' in scene '{scene.name}'")
        if not data.is_splat_object(obj):
            raise CollisionSetupError(f"'{name}' ({obj.type.lower()}) is not a splat object")
        objects.append(obj)
    if objects[0] == objects[1]:
        raise CollisionSetupError(f"'{name_a}' cannot collide with itself")
    return objects


def _labels(obj):
    """(bone names, per-splat bone index or -1) of a splat object; ([], None) when unbound."""
    bound = rigging.main_bones(obj)
    return bound if bound is not None else ([], None)


def _own_splats(touched, own_count, shown_count):
    """Indices of the object's own splats among `touched` splats of what the scene shows: modifiers
    that copy the splats whole (Array, Mirror) show own_count * k of them, copy j of splat i at
    j * own_count + i. None when the shown splats cannot be traced back (a changed count otherwise)."""
    if shown_count == own_count:
        return touched
    if own_count == 0 or shown_count % own_count:
        return None
    return np.unique(touched % own_count)


def _kept(cloud, bones, labels, ignore, min_opacity):
    keep = cloud.opacities >= min_opacity
    ignored = [i for i, name in enumerate(bones) if name in ignore]
    if ignored:
        keep &= ~np.isin(labels, ignored)
    return np.flatnonzero(keep)


def _check_finite(frame, *objects_and_clouds):
    """CollisionSetupError naming the object and frame where a splat the test reads holds NaN/Inf."""
    for obj, cloud in objects_and_clouds:
        bad = np.zeros(len(cloud), bool)
        for name in ("positions", "rotations", "log_scales", "opacity_logits"):
            values = getattr(cloud, name)
            bad |= ~np.isfinite(values).all(axis=tuple(range(1, values.ndim)))
        if bad.any():
            raise CollisionSetupError(
                f"frame {frame}: {int(bad.sum())} splats of '{obj.name}' hold NaN or infinite values"
            )


def _per_bone(bones, labels):
    counts = np.bincount(labels[labels >= 0], minlength=len(bones))
    return {bones[i]: int(c) for i, c in enumerate(counts) if c}


class _Environment:
    """B's environment index, rebuilt only when B's splats moved since the last frame."""

    def __init__(self):
        self.cloud, self.index = None, None

    def get(self, cloud):
        same = self.cloud is not None and all(
            np.array_equal(getattr(self.cloud, f), getattr(cloud, f))
            for f in ("positions", "rotations", "log_scales", "opacity_logits")
        )
        if not same:
            self.cloud, self.index = cloud, EnvironmentIndex(cloud)
        return self.index


class CollisionJob:
    """A collision check a frame at a time, for a modal operator (Esc between frames) and for batch
    use alike. step() checks the next frame and returns False once all are checked; finish() puts the
    scene's frame back, writes `splat_contact` (with `write_attribute`) and returns the
    CollisionReport; cancel() puts the frame back and writes nothing, leaving the scene as it was.
    `done` / `total` / `label` say how far it is."""

    def __init__(
        self,
        context,
        obj_a,
        obj_b,
        frames,
        k=DEFAULT_SIGMA,
        min_opacity=DEFAULT_MIN_OPACITY,
        ignore_bones=(),
        write_attribute=True,
    ):
        frames = list(frames)
        if not frames:
            raise CollisionSetupError("no frames to check")
        if not 0 < k < np.inf:
            raise CollisionSetupError(f"the sigma multiple must be positive and finite, got {k}")
        if not 0 <= min_opacity <= 1:
            raise CollisionSetupError(f"the minimum opacity must be between 0 and 1, got {min_opacity}")
        self.ignore = set(ignore_bones)
        (self.bones_a, self.labels_a), (self.bones_b, self.labels_b) = _labels(obj_a), _labels(obj_b)
        unknown = self.ignore - set(self.bones_a) - set(self.bones_b)
        if unknown:
            raise CollisionSetupError(
                f"no bones named {', '.join(sorted(unknown))} bind '{obj_a.name}' or '{obj_b.name}'"
            )
        self.context, self.obj_a, self.obj_b, self.frames = context, obj_a, obj_b, frames
        self.k, self.min_opacity, self.write_attribute = float(k), min_opacity, write_attribute
        self.hits_a, self.hits_b = np.zeros(data.splat_count(obj_a.data)), np.zeros(data.splat_count(obj_b.data))
        self.traced = [True, True]  # whether every frame's contacts map back onto each object's splats
        scene = context.scene
        self.restore = (scene.frame_current, scene.frame_subframe)
        self.environment, self.results = _Environment(), []
        self.total, self.done, self.label = len(frames), 0, ""

    def step(self):
        """Check the next frame; False when every frame is checked."""
        if self.done == self.total:
            return False
        frame = self.frames[self.done]
        found = self._check(frame)
        self.results.append(found)
        self.done += 1
        self.label = f"frame {frame}: {found.pairs} splat pairs in contact"
        return self.done < self.total

    def _check(self, frame):
        context, obj_a, obj_b = self.context, self.obj_a, self.obj_b
        context.scene.frame_set(frame)
        depsgraph = context.evaluated_depsgraph_get()
        cloud_a, cloud_b = data.evaluated_cloud(obj_a, depsgraph), data.evaluated_cloud(obj_b, depsgraph)
        _check_finite(frame, (obj_a, cloud_a), (obj_b, cloud_b))
        shown_a = self.labels_a if self.labels_a is not None else np.full(len(cloud_a), -1)
        shown_b = self.labels_b if self.labels_b is not None else np.full(len(cloud_b), -1)
        keep_a = _kept(cloud_a, self.bones_a, shown_a, self.ignore, self.min_opacity)
        keep_b = _kept(cloud_b, self.bones_b, shown_b, self.ignore, self.min_opacity)
        if not (len(keep_a) and len(keep_b)):
            return FrameContacts(frame)
        contacts = ellipsoid_contacts(cloud_a[keep_a], self.environment.get(cloud_b[keep_b]), k=self.k)
        touched_a, touched_b = keep_a[np.unique(contacts.robot)], keep_b[np.unique(contacts.env)]
        for side, (hits, touched, cloud) in enumerate(
            ((self.hits_a, touched_a, cloud_a), (self.hits_b, touched_b, cloud_b))
        ):
            own = _own_splats(touched, len(hits), len(cloud))
            if own is None:
                self.traced[side] = False
            else:
                hits[own] += 1
        return FrameContacts(
            frame,
            len(contacts),
            len(touched_a),
            len(touched_b),
            _per_bone(self.bones_a, shown_a[touched_a]),
            _per_bone(self.bones_b, shown_b[touched_b]),
            float(contacts.sigma.min(initial=np.inf)),
        )

    def _restore_frame(self):
        current, subframe = self.restore
        self.context.scene.frame_set(current, subframe=subframe)

    def cancel(self):
        """Stop: the scene's frame goes back, nothing is written."""
        self._restore_frame()

    def finish(self):
        """The report of the frames checked; the frame goes back and `splat_contact` is written."""
        self._restore_frame()
        checked = max(len(self.results), 1)
        report = CollisionReport(
            self.obj_a.name, self.obj_b.name, self.k, self.results, self.hits_a / checked, self.hits_b / checked
        )
        if self.write_attribute:
            for obj, values, ok in (
                (self.obj_a, report.contact_a, self.traced[0]),
                (self.obj_b, report.contact_b, self.traced[1]),
            ):
                if ok:
                    write_contact(obj, values)
        return report


def check_collisions(
    context,
    obj_a,
    obj_b,
    frames,
    k=DEFAULT_SIGMA,
    min_opacity=DEFAULT_MIN_OPACITY,
    ignore_bones=(),
    write_attribute=True,
    progress=None,
):
    """Test splat objects `obj_a` and `obj_b` for contact at each of `frames`; returns a
    CollisionReport and (with `write_attribute`) writes `splat_contact` on both. The scene's frame
    is restored. progress(done, total, FrameContacts) is called after each frame."""
    job = CollisionJob(context, obj_a, obj_b, frames, k, min_opacity, ignore_bones, write_attribute)
    try:
        while job.done < job.total:
            job.step()
            if progress:
                progress(job.done, job.total, job.results[-1])
    except BaseException:
        job.cancel()
        raise
    return job.finish()


def write_contact(obj, values):
    data.set_attribute(obj.data, CONTACT_ATTRIBUTE, "FLOAT", values)


# the operator ---------------------------------------------------------------------------------------


class SPLAT_OT_check_collisions(JobOperator, bpy.types.Operator):
    """Find the frames and bones at which two splat objects touch (exact k-sigma ellipsoid test) and
    store each splat's share of frames in contact in its 'splat_contact' attribute (from the interface a
    frame at a time: Esc cancels and changes nothing)"""

    bl_idname = "splat.check_collisions"
    bl_label = "Check Splat Collisions"
    bl_options = {"REGISTER", "UNDO"}
    job_errors = (CollisionSetupError, CollisionInputError, SkinningError, *EXPECTED_ERRORS)

    object_a: StringProperty(
        name="Object A", default="", description="A splat object, e.g. a rigged avatar (empty: the active object)"
    )
    object_b: StringProperty(
        name="Object B", default="", description="The other splat object (empty: the other selected object)"
    )
    use_scene_range: BoolProperty(
        name="Scene Frame Range", default=True, description="Check the scene's frame range and step"
    )
    frame_start: IntProperty(name="Start", default=1, description="First frame (without the scene range)")
    frame_end: IntProperty(name="End", default=250, description="Last frame (without the scene range)")
    frame_step: IntProperty(name="Step", default=1, min=1, description="Frames between checked frames")
    sigma: FloatProperty(
        name="Sigma",
        default=DEFAULT_SIGMA,
        min=0.1,
        max=10.0,
        description="Splats touch when their ellipsoids of this many standard deviations meet",
    )
    min_opacity: FloatProperty(
        name="Min Opacity",
        default=DEFAULT_MIN_OPACITY,
        min=0.0,
        max=1.0,
        description="Leave out splats fainter than this",
    )
    ignore_bones: StringProperty(
        name="Ignore Bones",
        default="",
        description="Comma-separated bones whose splats are left out (e.g. feet on a floor)",
    )

    @classmethod
    def poll(cls, context):
        return context.mode == "OBJECT"

    def make_job(self, context):
        scene = context.scene
        obj_a, obj_b = splat_objects_pair(scene, self.object_a, self.object_b, context)
        start, end, step = (
            (scene.frame_start, scene.frame_end, scene.frame_step)
            if self.use_scene_range
            else (self.frame_start, self.frame_end, self.frame_step)
        )
        ignore = [n.strip() for n in self.ignore_bones.split(",") if n.strip()]
        return CollisionJob(context, obj_a, obj_b, frame_range(start, end, step), self.sigma, self.min_opacity, ignore)

    def finish(self, context, job):
        report = job.finish()
        self.report({"INFO"}, report.summary())
        return {"FINISHED"}


def menu_object(self, context):
    self.layout.operator(SPLAT_OT_check_collisions.bl_idname)


CLASSES = (SPLAT_OT_check_collisions,)
MENUS = ((bpy.types.VIEW3D_MT_object, menu_object),)
