"""An operator's progress in the window's progress bar."""


class Progress:
    """Blender's progress API where there is a window to show it in; silent otherwise."""

    def __init__(self, context, total):
        self.wm = context.window_manager if context.window is not None else None
        if self.wm is not None:
            self.wm.progress_begin(0, max(total, 1))

    def update(self, value):
        if self.wm is not None:
            self.wm.progress_update(value)

    def end(self):
        if self.wm is not None:
            self.wm.progress_end()
