"""Writes under hostile conditions, for every writer: full disk, read-only or missing folder, a folder
in the way, symlinks, permissions, and a process killed mid-write (a real SIGKILL in a subprocess).
The rule (io/common.py, _partial): a partial file `<target>.splatwright-partial-<pid>` beside the
target, renamed over it only when whole; never a torn target, never a stray temporary."""

import errno
import os
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import PLATFORM_SKIP, random_cloud

from splatwright.io import SplatFileError, common, read_splats, sog, write_splats
from splatwright.io.exr import read_exr
from splatwright.io.image import write_image

pytestmark = pytest.mark.filterwarnings("ignore::splatwright.io.SplatFileWarning")

TESTS = Path(__file__).parent
SPLAT_FORMATS = {
    "ply": ".ply",
    "compressed_ply": ".compressed.ply",
    "spz": ".spz",
    "splat": ".splat",
    "usda": ".usda",
    "usdc": ".usdc",
    "usdz": ".usdz",
    "sog": ".sog",
    "glb": ".glb",
}
EXTENSIONS = {**SPLAT_FORMATS, "png": ".png", "exr": ".exr"}
BY_NAME = ("usda", "usdc", "usdz", "exr")  # libraries writing by name: atomic_path
KINDS = list(EXTENSIONS)


def write(kind, path, n=60, seed=0):
    """Write `n` splats (or an image of n x 8 pixels) in the format `kind` to `path`."""
    if kind in SPLAT_FORMATS:
        write_splats(path, random_cloud(n, sh_degree=1, seed=seed))
    else:
        rgb = np.random.default_rng(seed).random((n, 8, 3))
        write_image(
            path, {"color": rgb, "alpha": np.ones((n, 8)), "depth": np.full((n, 8), 2.0)} if kind == "exr" else rgb
        )


def count(kind, path):
    """What `path` holds, read back: its splats, or its image's rows."""
    if kind in SPLAT_FORMATS:
        return len(read_splats(path))
    if kind == "exr":
        return read_exr(path)["R"].shape[0]
    data = Path(path).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return int.from_bytes(data[20:24], "big")  # IHDR height


def target(tmp_path, kind, name="out"):
    return tmp_path / f"{name}{EXTENSIONS[kind]}"


def partials(folder):
    return sorted(p.name for p in Path(folder).iterdir() if common.PARTIAL_TAG in p.name)


# the partial's name, and nothing else appears -----------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_partial_is_named_for_its_target_and_nothing_else_appears(tmp_path, kind, monkeypatch):
    path = target(tmp_path, kind)
    seen = []
    replace = os.replace

    fsync = os.fsync
    synced = []

    def watch(src, dst):
        seen.append((Path(src).name, Path(dst).name, sorted(os.listdir(tmp_path))))
        synced.append("rename")
        replace(src, dst)

    def record(fd):
        synced.append("folder" if stat.S_ISDIR(os.fstat(fd).st_mode) else os.fstat(fd).st_size)
        fsync(fd)

    monkeypatch.setattr(os, "replace", watch)
    monkeypatch.setattr(os, "fsync", record)
    write(kind, path)
    partial = f"{path.name}.splatwright-partial-{os.getpid()}"
    assert seen == [(partial, path.name, [partial])]  # no tmpXXXX folder, no second file
    assert os.listdir(tmp_path) == [path.name] and count(kind, path) == 60
    assert synced == [path.stat().st_size, "rename", "folder"]  # the whole file, then the rename


# failures: the old file stays, no partial is left, the error names the file ----------------------


@pytest.fixture(params=KINDS)
def old_file(request, tmp_path):
    kind = request.param
    path = target(tmp_path, kind)
    write(kind, path, n=10, seed=1)
    return kind, path, path.read_bytes()


def assert_untouched(path, before):
    assert path.read_bytes() == before
    assert os.listdir(path.parent) == [path.name]


def test_full_disk_at_fsync(old_file, monkeypatch, capfd):
    kind, path, before = old_file

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(SplatFileError) as exc:
        write(kind, path, n=40)
    assert exc.value.path == str(path)
    assert "No space left on device" in str(exc.value) and "the disk is full" in str(exc.value)
    assert_untouched(path, before)
    assert capfd.readouterr().err == ""


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason=PLATFORM_SKIP + "needs /dev/full")
@pytest.mark.parametrize("kind", [k for k in KINDS if k not in BY_NAME])
def test_full_disk_mid_write(tmp_path, kind, monkeypatch):
    """The writer's own writes fail: every byte goes to /dev/full, which refuses them (ENOSPC)."""
    path = target(tmp_path, kind)
    write(kind, path, n=10, seed=1)
    before = path.read_bytes()
    fdopen = os.fdopen

    def onto_full_disk(fd, mode="r", *args, **kwargs):
        full = os.open("/dev/full", os.O_WRONLY)
        os.dup2(full, fd)
        os.close(full)
        return fdopen(fd, mode, *args, **kwargs)

    monkeypatch.setattr(os, "fdopen", onto_full_disk)
    with pytest.raises(SplatFileError, match="No space left on device") as exc:
        write(kind, path, n=40)
    assert exc.value.path == str(path)
    assert_untouched(path, before)


@pytest.fixture
def read_only(monkeypatch):
    """Make a folder unwritable: chmod 0555, or (root ignores that) os.open refusing files in it."""
    folders = []
    real_open = os.open

    def refuse(path, flags, *args, **kwargs):
        if flags & os.O_CREAT and any(Path(path).parent == f for f in folders):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real_open(path, flags, *args, **kwargs)

    def make(folder):
        folders.append(Path(folder))
        folder.chmod(0o555)
        if os.geteuid() == 0:
            monkeypatch.setattr(os, "open", refuse)

    yield make
    for folder in folders:
        folder.chmod(0o755)


def test_read_only_folder(old_file, read_only, capfd):
    kind, path, before = old_file
    read_only(path.parent)
    with pytest.raises(SplatFileError) as exc:
        write(kind, path, n=40)
    assert exc.value.path == str(path)
    assert f"no permission to write in the folder {path.parent}" in str(exc.value)
    assert_untouched(path, before)
    assert capfd.readouterr().err == ""  # no C++ error lines from OpenUSD or OpenEXR


@pytest.mark.parametrize("kind", KINDS)
def test_a_folder_in_the_way(tmp_path, kind, capfd):
    path = target(tmp_path, kind)
    path.mkdir()
    (path / "keep.txt").write_text("mine")
    with pytest.raises(SplatFileError, match="is a folder, not a file") as exc:
        write(kind, path)
    assert exc.value.path == str(path)
    assert os.listdir(tmp_path) == [path.name] and os.listdir(path) == ["keep.txt"]
    assert capfd.readouterr().err == ""


@pytest.mark.parametrize("kind", KINDS)
def test_missing_folder(tmp_path, kind, capfd):
    path = tmp_path / "nowhere" / f"out{EXTENSIONS[kind]}"
    with pytest.raises(SplatFileError, match=f"the folder {tmp_path / 'nowhere'} does not exist") as exc:
        write(kind, path)
    assert exc.value.path == str(path)
    assert os.listdir(tmp_path) == []
    assert capfd.readouterr().err == ""


def test_pipes_and_devices_are_refused(tmp_path):
    """Nothing can be renamed over a device or pipe without replacing it: refused, left as it is."""
    os.mkfifo(tmp_path / "pipe.ply")
    (tmp_path / "null.ply").symlink_to(os.devnull)
    for name in ("pipe.ply", "null.ply"):
        with pytest.raises(SplatFileError, match="not a regular file"):
            write("ply", tmp_path / name)
    assert stat.S_ISFIFO((tmp_path / "pipe.ply").stat().st_mode) and os.path.exists(os.devnull)


# permissions and symlinks -------------------------------------------------------------------------


def test_a_private_file_stays_private(old_file):
    kind, path, _ = old_file
    path.chmod(0o600)
    write(kind, path, n=40)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600 and count(kind, path) == 40


@pytest.mark.parametrize("kind", KINDS)
def test_a_new_file_gets_the_umask_default(tmp_path, kind):
    path = target(tmp_path, kind)
    old = os.umask(0o027)
    try:
        write(kind, path)
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o640


@pytest.mark.parametrize("kind", KINDS)
def test_a_symlink_is_written_through(tmp_path, kind):
    """The link's target gets the new contents (its partial beside it); the link stays a link."""
    real = target(tmp_path / "store", kind, "real")
    real.parent.mkdir()
    write(kind, real, n=10)
    link = target(tmp_path, kind, "link")
    link.symlink_to(real)
    write(kind, link, n=40)
    assert link.is_symlink() and os.readlink(link) == str(real)
    assert count(kind, real) == 40
    assert os.listdir(tmp_path / "store") == [real.name]
    assert sorted(os.listdir(tmp_path)) == sorted(["store", link.name])  # nothing written beside the link


@pytest.mark.parametrize("kind", KINDS)
def test_a_dangling_symlink_gets_its_target_made(tmp_path, kind):
    real = target(tmp_path, kind, "real")
    link = target(tmp_path, kind, "link")
    link.symlink_to(real.name)  # relative, as ln -s makes it
    write(kind, link, n=40)
    assert link.is_symlink() and count(kind, real) == 40
    assert sorted(os.listdir(tmp_path)) == sorted([real.name, link.name])


def test_symlink_to_a_missing_folder_and_a_loop(tmp_path):
    link = tmp_path / "link.ply"
    link.symlink_to(tmp_path / "gone" / "x.ply")
    with pytest.raises(SplatFileError, match="does not exist"):
        write("ply", link)
    loop = tmp_path / "loop.ply"
    loop.symlink_to(loop)
    with pytest.raises(SplatFileError, match="loops"):
        write("ply", loop)
    assert loop.is_symlink() and link.is_symlink()


# sweeping what a killed write left -----------------------------------------------------------------


def dead_pid():
    child = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(child.stdout)


def test_sweep_removes_partials_of_dead_processes_and_old_ones(tmp_path):
    dead, alive, now = dead_pid(), os.getpid(), time.time()
    files = {
        f"a.ply.splatwright-partial-{dead}": True,  # its writer is gone
        f"b.usdz.splatwright-partial-{dead}-2.layer": True,
        f"b.usdc.splatwright-partial-{dead}.pgbJio": True,  # pxr's own temporary, killed in Save
        f"c.ply.splatwright-partial-{alive}": False,  # being written now
        f"d.ply.splatwright-partial-{alive}-1": True,  # alive, but a day old
        "e.splatwright-partial-notes.txt": False,  # no pid: not ours
        "f.ply": False,
    }
    for name in files:
        (tmp_path / name).write_bytes(b"x")
    old = now - common.STALE_AFTER - 60
    os.utime(tmp_path / f"d.ply.splatwright-partial-{alive}-1", (old, old))
    write("ply", tmp_path / "new.ply")
    kept = sorted(name for name, swept in files.items() if not swept) + ["new.ply"]
    assert sorted(os.listdir(tmp_path)) == sorted(kept)


# kill -9 mid-write ---------------------------------------------------------------------------------

KILLED_SPLATS = 3000


def kill_while_writing(kind, path):
    """Run in a child process: write `path`, SIGKILL ourselves part way. Writers that write through
    an open file die after the first half of their first write reaches the partial; libraries
    writing by name (pxr, OpenEXR) die once the file is written, before the rename."""

    def die():
        os.kill(os.getpid(), signal.SIGKILL)

    if kind in BY_NAME:
        os.replace = lambda *args: die()
    else:
        fdopen = os.fdopen

        class DyingFile:
            def __init__(self, f):
                self.f = f

            def write(self, data):
                self.f.write(bytes(memoryview(data).cast("B")[: max(1, len(data) // 2)]))
                self.f.flush()
                die()

            def __getattr__(self, name):
                return getattr(self.f, name)

            def __enter__(self):
                return self

            def __exit__(self, *exc):
                return self.f.__exit__(*exc)

        os.fdopen = lambda *args, **kwargs: DyingFile(fdopen(*args, **kwargs))
    write(kind, path, n=KILLED_SPLATS)


@pytest.fixture(scope="module")
def killed(tmp_path_factory):
    """{kind: (path, bytes before, child pid, return code)}, the children run side by side."""
    runs = {}
    for kind in KINDS:
        path = target(tmp_path_factory.mktemp(f"killed_{kind}"), kind)
        write(kind, path, n=10, seed=1)
        code = (
            f"import sys; sys.path.insert(0, {str(TESTS)!r}); import test_hostile_write as t; "
            f"t.kill_while_writing({kind!r}, {str(path)!r})"
        )
        runs[kind] = (path, path.read_bytes(), subprocess.Popen([sys.executable, "-c", code], cwd=TESTS))
    return {kind: (path, before, child.pid, child.wait(timeout=120)) for kind, (path, before, child) in runs.items()}


@pytest.mark.parametrize("kind", KINDS)
def test_kill_mid_write_leaves_the_old_file_and_a_partial_the_next_write_sweeps(killed, kind):
    path, before, pid, code = killed[kind]
    assert code == -signal.SIGKILL
    assert path.read_bytes() == before and count(kind, path) == 10
    partial = path.parent / f"{path.name}.splatwright-partial-{pid}"
    assert partials(path.parent) == [partial.name] and partial.stat().st_size > 0
    write(kind, path, n=40)
    assert os.listdir(path.parent) == [path.name] and count(kind, path) == 40


# groups of files: all or none -----------------------------------------------------------------------


def fail_on_fsync(monkeypatch, call):
    calls = []
    fsync = os.fsync

    def maybe_fail(fd):
        calls.append(fd)
        if len(calls) == call:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        fsync(fd)

    monkeypatch.setattr(os, "fsync", maybe_fail)


def test_publish_together_makes_a_group_appear_whole_or_not_at_all(tmp_path, monkeypatch):
    names = [tmp_path / f"frame_{i}.ply" for i in range(3)]
    write("ply", names[1], n=5)
    before = names[1].read_bytes()
    fail_on_fsync(monkeypatch, 3)  # the third file's data does not reach the disk
    with pytest.raises(SplatFileError, match="No space left") as exc, common.publish_together():
        for path in names:
            write("ply", path, n=40)
            assert not (tmp_path / "frame_0.ply").exists()  # held back until the group is whole
    assert exc.value.path == str(names[2])
    assert os.listdir(tmp_path) == [names[1].name] and names[1].read_bytes() == before
    monkeypatch.undo()
    with common.publish_together():
        for path in names:
            with common.publish_together():  # an inner group joins the outer one
                write("ply", path, n=40)
            assert not names[0].exists()
    assert sorted(os.listdir(tmp_path)) == [p.name for p in names] and count("ply", names[2]) == 40


@pytest.mark.parametrize("kind, files", [("gltf", ["out.bin", "out.gltf"]), ("sog", ["meta.json"])])
def test_multi_file_formats_keep_the_old_set_when_one_file_fails(tmp_path, monkeypatch, kind, files):
    path = tmp_path / ("out.gltf" if kind == "gltf" else "meta.json")
    write_splats(path, random_cloud(10, sh_degree=1, seed=1))
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert set(files) <= set(before)
    fail_on_fsync(monkeypatch, len(before))  # the last file of the new set fails
    with pytest.raises(SplatFileError, match="No space left") as exc:
        write_splats(path, random_cloud(40, sh_degree=1))
    assert exc.value.path == str(path)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_openusd_failing_to_save_is_a_splat_file_error_and_leaves_nothing(tmp_path, monkeypatch, capfd):
    """pxr's own temporary (`<partial>.XXXXXX`) goes with the partial; nothing is printed."""
    from splatwright.io import usd

    author = usd.stages.PXR._author_stage

    def blocked(path, layer_path, *args):
        os.mkdir(layer_path + ".in_the_way")  # pxr saves, then cannot rename onto a folder
        try:
            author(path, layer_path + ".in_the_way", *args)
        finally:
            os.rmdir(layer_path + ".in_the_way")

    monkeypatch.setattr(usd.stages.PXR, "_author_stage", blocked)
    path = tmp_path / "out.usdc"
    with pytest.raises(SplatFileError, match="OpenUSD could not write it: .*Is a directory") as exc:
        write("usdc", path)
    assert exc.value.path == str(path) and os.listdir(tmp_path) == []
    assert capfd.readouterr().err == ""


@pytest.mark.parametrize("made", [True, False], ids=["existing", "dangling"])
@pytest.mark.parametrize("link_name, real_name", [("x.gltf", "real.gltf"), ("meta.json", "meta.json")])
def test_companion_files_land_beside_the_file_a_symlink_names(tmp_path, made, link_name, real_name):
    """A .gltf names its .bin, a SOG meta.json its images, by a name relative to itself: they go
    beside the file the link points to, and both the link and that file read back."""
    (tmp_path / "A").mkdir()
    (tmp_path / "B").mkdir()
    real, link = tmp_path / "B" / real_name, tmp_path / "A" / link_name
    if made:
        write_splats(real, random_cloud(10, sh_degree=1))
    link.symlink_to(real)
    write_splats(link, random_cloud(40, sh_degree=1, seed=2))
    assert os.listdir(tmp_path / "A") == [link_name] and link.is_symlink()
    images = [name for names in sog.FILES.values() for name in names]
    expected = ["real.bin", "real.gltf"] if real_name == "real.gltf" else ["meta.json", *images]
    assert sorted(os.listdir(tmp_path / "B")) == sorted(expected)
    assert len(read_splats(real)) == 40 and len(read_splats(link)) == 40
