"""Compiled kernels with numba, when it can be had; the callers keep a NumPy path for when not.

numba is imported only when a kernel module is first asked for, never by `import splatwright`,
and every way it can fail to load (not installed, built for another NumPy, a broken LLVM) leaves
`load()` returning None with the reason in `status()`, so NumPy does the work instead.

Compiled code is cached on disk, so only the first use on a machine pays for compiling (a few
seconds). The cache lives in the user's cache folder, not beside the sources: an installed Blender
extension or a site-packages folder may not be writable. It is found by the content of the source and of the
package modules it imports from (numba freezes imported constants into the compiled code), not its
place on disk, so a reinstalled extension loads its kernels instead of compiling them again.
Every version of a kernel file gets a folder of its own, so folders no process has used for
STALE_DAYS are removed when kernels are first loaded (an upgraded extension would otherwise leave
its old kernels behind for good). SPLATWRIGHT_CACHE_DIR overrides the folder;
SPLATWRIGHT_JIT=0 turns compiled kernels off (read when a kernel is first needed).
"""

import hashlib
import importlib
import os
import re
import shutil
import sys
import threading
import time
from pathlib import Path

_lock = threading.Lock()
_modules = {}  # kernel module name -> module or None
_reasons = {}  # kernel module name -> why it is not available
STALE_DAYS = 30  # a kernel folder unused this long is removed


def enabled():
    """False when SPLATWRIGHT_JIT is set to 0 / false / no / off."""
    return os.environ.get("SPLATWRIGHT_JIT", "1").strip().lower() not in ("0", "false", "no", "off")


def cache_dir():
    """Where compiled kernels are kept: SPLATWRIGHT_CACHE_DIR, else the platform's user cache folder."""
    if os.environ.get("SPLATWRIGHT_CACHE_DIR"):
        return Path(os.environ["SPLATWRIGHT_CACHE_DIR"])
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "splatwright" / "numba"


def load(name, check=None):
    """The compiled kernel module `splatwright.<name>` (e.g. "core.render_kernels"; it imports
    numba), or None when numba cannot be loaded or kernels are turned off. Imported once per
    process; `check(module)`, if given, then runs the kernels once (compiling them, or loading them
    from the cache) and must return without an error for the module to be used."""
    if not enabled():
        return None
    with _lock:
        if name not in _modules:
            try:
                _install_cache_locator()
                module = importlib.import_module(f"{__package__.rpartition('.')[0]}.{name}")
                if check is not None:
                    check(module)
                _modules[name] = module
            except Exception as exc:  # any failure to load or compile means: use NumPy
                _modules[name], _reasons[name] = None, f"{type(exc).__name__}: {exc}"
        return _modules[name]


def loaded(name):
    """Whether this process has already tried `load(name)` (so a call now returns at once, without
    compiling or reading the cache)."""
    return name in _modules or not enabled()


def compiled(module_name, names, fast=False):
    """The functions `names` of the loaded module `module_name` compiled in order with njit, each
    rebound in its module (a later one may call an earlier one: numba resolves it as a global), and
    the last returned; None when numba cannot be loaded or kernels are turned off. For kernels that
    live beside their NumPy path; compiled once per process, on first use. fast: njit's `fast`."""
    key = f"{module_name}:{names[-1]}"
    if key in _modules:  # the hot path (forward kinematics of one configuration):
        return _modules[key]  # no environment lookup once a kernel is in use
    if not enabled():
        return None
    with _lock:
        if key not in _modules:
            try:
                _install_cache_locator()
                module = sys.modules[module_name]
                for name in names:
                    function = getattr(module, name)
                    if not hasattr(function, "py_func"):  # not compiled by an earlier kernel
                        setattr(module, name, njit(function, fast=fast))
                _modules[key] = getattr(module, names[-1])
            except Exception as exc:  # any failure to load or compile means: use NumPy
                _modules[key], _reasons[key] = None, f"{type(exc).__name__}: {exc}"
        return _modules[key]


def status(name):
    """'compiled', 'not loaded yet', or why the NumPy path is used."""
    if not enabled():
        return "off (SPLATWRIGHT_JIT=0)"
    if name not in _modules:
        return "not loaded yet"
    return "compiled" if _modules[name] is not None else f"unavailable ({_reasons[name]})"


FAST = {"contract", "arcp", "nsz", "afn"}  # no flag that assumes finite numbers: NaN and inf still flow


def njit(fn=None, *, contract=False, fast=False):
    """numba.njit for our kernels: no GIL (they run on core.parallel's threads), cached on disk.
    contract=True lets the compiler fuse a * b + c into one FMA instruction (a rounding less, so
    results may differ from NumPy's in the last bit): `@njit(contract=True)`. fast=True adds FAST:
    a division may become a multiplication by a reciprocal kept for several, and library functions
    their faster forms (results within a few units in the last place of NumPy's; the shading loop's
    divisions and square roots per light sample: 8-10% of its time)."""
    if fn is None:
        return lambda f: njit(f, contract=contract, fast=fast)
    import numba

    flags = FAST if fast else {"contract"} if contract else set()
    options = {"nogil": True, "error_model": "numpy", **({"fastmath": flags} if flags else {})}
    try:
        return numba.njit(cache=True, **options)(fn)
    except RuntimeError:  # no writable cache folder anywhere: compile in every process
        return numba.njit(**options)(fn)


def prefetcher():
    """prefetch(array, i) for kernels: asks the CPU to start loading the cache line of array[i]
    (a C-contiguous array, i a flat index) without waiting for it, so a miss overlaps other work."""
    from llvmlite import ir
    from numba.core import cgutils, types
    from numba.extending import intrinsic

    @intrinsic
    def prefetch(typingctx, array, i):
        def codegen(context, builder, signature, args):
            base = context.make_array(signature.args[0])(context, builder, args[0]).data
            i64 = context.cast(builder, args[1], signature.args[1], types.int64)
            byte_ptr, int32 = ir.IntType(8).as_pointer(), ir.IntType(32)
            fn = cgutils.get_or_insert_function(
                builder.module, ir.FunctionType(ir.VoidType(), [byte_ptr, int32, int32, int32]), "llvm.prefetch.p0i8"
            )
            # a read, kept in every cache level, of data
            builder.call(fn, [builder.bitcast(builder.gep(base, [i64]), byte_ptr), int32(0), int32(3), int32(1)])
            return context.get_dummy_value()

        return types.void(array, i), codegen

    return prefetch


_installed = False


def _install_cache_locator():
    """Put our cache folder first in numba's list of cache locations, for this package's files
    only (other numba users in the same process, say in Blender, keep numba's own choice)."""
    global _installed
    if _installed:
        return
    from numba.core import caching

    impl = getattr(caching, "CacheImpl", None) or caching._CacheImpl
    package = __package__.rpartition(".")[0]  # "splatwright", or the name Blender imports it by
    root = cache_dir()
    prune_stale(root)
    folders = {}  # (module, file) -> its folder: hashed once per process, not once per kernel function

    class SplatwrightCacheLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
        def __init__(self, py_func, py_file):
            self._py_file = py_file
            self._lineno = py_func.__code__.co_firstlineno
            key = (py_func.__module__, py_file)
            if key not in folders:
                folders[key] = str(root / _cache_subpath(*key))
            self._cache_path = folders[key]
            try:
                os.utime(self._cache_path)  # in use: not stale
            except OSError:
                pass

        def get_cache_path(self):
            return self._cache_path

        @classmethod
        def from_function(cls, py_func, py_file):
            # Our modules only, by name: a library installed in a virtual environment inside the
            # project's folder keeps numba's own choice.
            if not py_func.__module__.startswith(package + "."):
                return None
            return super().from_function(py_func, py_file)  # None when the folder is not writable

    impl._locator_classes.insert(0, SplatwrightCacheLocator)
    _installed = True


def prune_stale(root, days=STALE_DAYS):
    """Remove the kernel folders in `root` that no process has used for `days` (their time stamp,
    touched on every use); errors (another process removing or using one) are ignored."""
    cutoff = time.time() - days * 86400
    try:
        folders = [p for p in Path(root).iterdir() if p.is_dir()]
    except OSError:
        return
    for folder in folders:
        try:
            if folder.stat().st_mtime < cutoff:
                shutil.rmtree(folder)
        except OSError:
            pass


def _cache_subpath(module, py_file):
    """The cache folder of a module's kernels: its folder's name and a hash of its name and of its
    sources (kernel_sources), not of where it lies, so an extension installed again (a new folder
    each time in some setups) finds its kernels compiled, two versions of the package never
    overwrite each other's, and the same file imported under another name (pip's splatwright,
    Blender's bl_ext...) keeps its own."""
    digest = hashlib.sha1(module.encode())
    for path in kernel_sources(py_file):
        with open(path, "rb") as f:
            digest.update(b"\0" + f.read())
    return f"{os.path.basename(os.path.dirname(os.path.abspath(py_file)))}_{digest.hexdigest()}"


_RELATIVE_IMPORT = re.compile(rb"^[ \t]*from[ \t]+(\.+)([\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n]*)", re.MULTILINE)


def kernel_sources(py_file) -> list[str]:
    """The files whose text a module's compiled kernels depend on, sorted: the module and, through
    its relative imports, every module of the package it reads from. numba freezes a kernel's
    global constants into the compiled code, so a constant changed in a module the kernel imports it
    from (core.lights' SPREAD_ANGLES in core.shading's loop) must change the kernel's folder too."""
    seen: set[str] = set()
    todo = [os.path.abspath(py_file)]
    while todo:  # a loop over the package's modules, each read once
        path = todo.pop()
        if path in seen or not os.path.isfile(path):
            continue
        seen.add(path)
        with open(path, "rb") as f:
            text = f.read()
        for dots, name, names in _RELATIVE_IMPORT.findall(text):
            base = os.path.dirname(path)
            for _ in range(len(dots) - 1):
                base = os.path.dirname(base)
            if name:
                target = os.path.join(base, *name.decode().split("."))
                todo += [target + ".py", os.path.join(target, "__init__.py")]
            else:  # from . import a, b
                todo += [os.path.join(base, word.decode() + ".py") for word in re.findall(rb"\w+", names)]
    return sorted(seen)
