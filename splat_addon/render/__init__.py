"""Rendering: the SPLATWRIGHT engine, the Rendered viewport, and the meshes rendered by a child
Blender and composited in depth order."""
