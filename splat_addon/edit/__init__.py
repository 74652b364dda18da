"""Editing splat objects: clean-up and grading settings, Apply Splat Transform, Join, Convert Form,
and Blender's own Apply completed for splats."""
