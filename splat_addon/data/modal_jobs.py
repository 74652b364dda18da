"""Long operators run as modal jobs: a step per timer tick, progress in the status bar, Esc to cancel.

A job (convert/from_mesh.py ConversionJob, rig/collide.py CollisionJob) has step() -> bool (more to do), cancel()
(leaves the scene as it was before the job) and done / total / label; execute() runs the same job to
its end without a window (Python, `blender -b`), so both paths compute the same thing.
"""

CANCEL_KEYS = {"ESC", "RIGHTMOUSE"}
TICK = 0.01  # seconds between steps: the interface redraws in between
PROGRESS_UNITS = 1000


class JobOperator:
    """Mixin for operators with `make_job(context)` and `finish(context, job)` (returns the operator
    result); invoke() runs the job modally, execute() at once."""

    _job = None
    _timer = None

    def execute(self, context):
        job = self._start(context)
        if job is None:
            return {"CANCELLED"}
        try:
            while job.step():
                pass
        except self.job_errors as exc:
            job.cancel()
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return self.finish(context, job)

    def invoke(self, context, event):
        if context.window is None:
            return self.execute(context)
        self._job = self._start(context)
        if self._job is None:
            return {"CANCELLED"}
        wm = context.window_manager
        self._timer = wm.event_timer_add(TICK, window=context.window)
        wm.modal_handler_add(self)
        wm.progress_begin(0, PROGRESS_UNITS)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job
        if event.type in CANCEL_KEYS and event.value == "PRESS":
            job.cancel()
            self._end(context)
            self.report({"INFO"}, f"{self.bl_label}: cancelled, nothing changed")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"RUNNING_MODAL"}
        try:
            more = job.step()
        except self.job_errors as exc:
            job.cancel()
            self._end(context)
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        context.window_manager.progress_update(int(PROGRESS_UNITS * job.done / max(job.total, 1)))
        _status(context, f"{self.bl_label}: {job.label}  ({job.done:.1f}/{job.total}, Esc to cancel)")
        if more:
            return {"RUNNING_MODAL"}
        self._end(context)
        return self.finish(context, job)

    @staticmethod
    def setup_progress(context):
        """progress(done, total, label) for make_job's own long work (a camera path stepped
        through), on the progress the job's steps show next."""
        wm = context.window_manager
        return lambda done, total, label: wm.progress_update(int(PROGRESS_UNITS * done / max(total, 1)))

    def _start(self, context):
        """The job, or None after reporting why it cannot start."""
        wm = context.window_manager
        wm.progress_begin(0, PROGRESS_UNITS)
        try:
            return self.make_job(context)
        except self.job_errors as exc:
            self.report({"ERROR"}, str(exc))
            return None
        finally:
            wm.progress_end()

    def _end(self, context):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        _status(context, None)


def _status(context, text):
    workspace = getattr(context, "workspace", None)
    if workspace is not None:
        workspace.status_text_set(text)
