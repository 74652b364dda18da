"""Blender's application handlers (bpy.app.handlers lists), added and removed once each: a module
names its (handler list, function) pairs and hands them here from its register() and unregister()."""


def add_handlers(pairs):
    """Append each function to its handler list, unless it is there already (a second register)."""
    for handlers, fn in pairs:
        if fn not in handlers:
            handlers.append(fn)


def remove_handlers(pairs):
    """Remove each function from its handler list, where it is."""
    for handlers, fn in pairs:
        if fn in handlers:
            handlers.remove(fn)
