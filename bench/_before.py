"""Modules as they were before the robot work (commit BEFORE), loaded from git beside today's: the
baselines that benchmarks time in the same run as the code that replaced them."""

import subprocess
import sys
import types
from pathlib import Path

BEFORE = "024866a"
ROOT = Path(__file__).resolve().parent.parent


def module_before(path, renames=None, commit=BEFORE, suffix="before"):
    """The module at `path` (e.g. "core/collision.py") as of `commit`, importable as
    splatwright.<package>._<name>_<suffix>; `renames` rewrite its imports first (to other old modules)."""
    source = subprocess.run(
        ["git", "-C", str(ROOT), "show", f"{commit}:{path}"], check=True, capture_output=True, text=True
    ).stdout
    for old, new in (renames or {}).items():
        source = source.replace(old, new)
    package = "splatwright." + ".".join(Path(path).parent.parts)
    name = f"{package}._{Path(path).stem}_{suffix}"
    module = types.ModuleType(name)
    module.__package__ = package
    module.__file__ = str(ROOT / path)
    sys.modules[name] = module
    exec(compile(source, f"{path}@{commit}", "exec"), module.__dict__)
    return module
