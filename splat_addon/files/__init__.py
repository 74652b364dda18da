"""Splat files: the import and export operators, export options and animation export."""
