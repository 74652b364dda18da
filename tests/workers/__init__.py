"""Worker modules of the headless Blender tests (see base.py)."""
