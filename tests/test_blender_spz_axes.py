"""The axes of SPZ files and where imported splats stand, in Blender 5.3 next to its own importers.

The worker (tests/workers/spz_axes.py) opens the same files with Blender's `wm.spz_import` /
`wm.ply_import` and with Splatwright's import at each Placement, imports SPZ files in the axes the
dialog's SPZ Axes names, and exports SPZ in each. Judged here: Splatwright's "As Blender's Importer"
against Blender's own clouds (values, transforms and what they export back to), its Upright placement
against Blender's world positions, and the SPZ files against splatwright.io.
"""

import numpy as np
import pytest
from blender_session import blender_fixture
from helpers import covariances, random_cloud, read

pytestmark = [pytest.mark.blender, pytest.mark.slow]

UPRIGHT = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # file x, y, z -> Blender x, z, -y


def _write_inputs(work):
    from splatwright.io import spz, write_splats

    source = random_cloud(200, 3, 1)
    source.sh[:, 1:] = np.clip(source.sh[:, 1:], -0.9, 0.9)  # within SPZ's range: no clamping warning
    write_splats(work / "src.spz", source)
    write_splats(work / "src.ply", random_cloud(200, 3, 2))
    plain = random_cloud(150, 2, 3)
    plain.sh[:, 1:] = np.clip(plain.sh[:, 1:], -0.9, 0.9)
    write_splats(work / "plain.ply", plain)
    spz.write(work / "wild.spz", plain, axes=None)  # PLY's values, no record: as many files in the wild
    spz.write(work / "tagged.spz", plain, version=4, spz_axes="rdf")
    spz.write(work / "tagged3.spz", plain, version=3, spz_axes="rdf")  # the record after the blocks


blender = blender_fixture("workers.spz_axes", _write_inputs, since="5.3")


def placed(blender, tag):
    """(world positions, world covariances, native attributes, matrix) of a recorded object."""
    saved = blender.npz(tag)
    matrix = saved["matrix"]
    linear = matrix[:3, :3]
    world = saved["position"].astype(np.float64) @ linear.T + matrix[:3, 3]
    cov = covariances(saved["rotation"], np.log(saved["scale"].astype(np.float64)))
    return world, linear @ cov @ linear.T, saved, matrix


@pytest.mark.parametrize("axes", ["", "_axes"])
@pytest.mark.parametrize("name", ["src_spz", "src_ply"])
def test_as_blenders_importer_is_blenders_placement(blender, name, axes):
    """Values and transforms as Blender's importer makes them (with Forward/Up at their defaults, and
    changed: Blender's importers have no such settings)."""
    landing = blender.step("placement")["landing"]
    world, cov, theirs, matrix = placed(blender, f"{name}_blender")
    ours_world, ours_cov, ours, ours_matrix = placed(blender, f"{name}_BLENDER{axes}")
    np.testing.assert_array_equal(matrix, np.eye(4))
    np.testing.assert_array_equal(ours_matrix, np.eye(4))  # Blender's: values placed, no transform
    np.testing.assert_allclose(ours_world, world, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ours_cov, cov, rtol=0, atol=1e-6 * np.abs(cov).max())
    for key in ("radiance_base", "radiance_sh_0", "radiance_sh_4", "radiance_sh_14"):
        np.testing.assert_allclose(ours[key], theirs[key], rtol=0, atol=2e-6, err_msg=key)
    assert landing[f"{name}_BLENDER{axes}"] == ("RAW" if name == "src_ply" else "UPRIGHT")


@pytest.mark.parametrize("name", ["src_spz", "src_ply"])
def test_upright_stands_like_blenders_spz_import(blender, name):
    """Splatwright's own placement: the values kept, the upright turn in the object's transform, where
    Blender's SPZ importer stands a capture (and its PLY importer's capture, turned upright)."""
    blender.step("placement")
    world, cov, _, _ = placed(blender, f"{name}_blender")
    ours_world, ours_cov, ours, matrix = placed(blender, f"{name}_UPRIGHT")
    np.testing.assert_allclose(matrix[:3, :3], UPRIGHT, atol=1e-7)
    turn = UPRIGHT if name == "src_ply" else np.eye(3)  # Blender's PLY import lies on its side
    np.testing.assert_allclose(ours_world, world @ turn.T, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ours_cov, turn @ cov @ turn.T, rtol=0, atol=1e-6 * np.abs(cov).max())


@pytest.mark.parametrize("name", ["src_spz", "src_ply"])
def test_placed_as_blenders_exports_back_to_the_file(blender, name):
    blender.step("placement")
    source = read(blender.work / name.replace("_", "."))
    written = read(blender.out / f"{name}_as_blender.ply")
    np.testing.assert_allclose(written.positions, source.positions, rtol=0, atol=1e-6)
    want = covariances(source.rotations, source.log_scales)
    got = covariances(written.rotations, written.log_scales)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5 * np.abs(want).max())
    np.testing.assert_allclose(written.sh, source.sh, rtol=0, atol=2e-6)


def test_spz_axes_read_an_rdf_file_upright(blender):
    """wild.spz holds PLY's values without saying so: read as RDF it stands where plain.ply does; by
    default (RUB) upside down (a half turn about x: up and front reversed). tagged.spz says RDF in its
    record, which Auto follows."""
    blender.step("spz_axes_import")
    plain, _, _, _ = placed(blender, "plain")
    step = 2.0**-12  # SPZ's fixed point
    np.testing.assert_allclose(placed(blender, "wild_rdf")[0], plain, rtol=0, atol=step)
    np.testing.assert_allclose(placed(blender, "tagged_auto")[0], plain, rtol=0, atol=step)
    half_turn = np.diag([1.0, -1.0, -1.0])
    np.testing.assert_allclose(placed(blender, "wild_auto")[0], plain @ half_turn.T, rtol=0, atol=step)


@pytest.mark.parametrize("tag", ["tagged_blender", "tagged3_blender"])
def test_blenders_spz_importer_and_the_record(blender, tag):
    """What Blender 5.3's SPZ importer makes of v4 and v3 files whose record says RDF, against
    Splatwright's reading of them (the record honoured) and the RUB reading (the record ignored)."""
    blender.step("spz_axes_import")
    plain, _, _, _ = placed(blender, "plain")
    theirs, _, _, _ = placed(blender, tag)
    half_turn = np.diag([1.0, -1.0, -1.0])
    ignored = np.abs(theirs - plain @ half_turn.T).max() <= 2.0**-12
    honoured = np.abs(theirs - plain).max() <= 2.0**-12
    assert ignored and not honoured  # Blender 5.3 reads every SPZ as RUB: its record unread


@pytest.mark.parametrize("version", ["3", "4"])
@pytest.mark.parametrize("axes", ["RUB", "RDF"])
def test_export_dialog_writes_the_axes_asked(blender, axes, version):
    from splatwright.io import spz

    res = blender.step("spz_axes_export")
    name = f"export_{axes}_{version}.spz"
    assert res[name]["error"] is None
    facts = {}
    written = spz.read(blender.out / name, facts=facts)
    recorded = None if (axes, version) == ("RUB", "3") else axes
    assert (facts["version"], facts["axes"], facts["axes_record"]) == (int(version), axes, recorded)
    plain = read(blender.work / "plain.ply")
    np.testing.assert_allclose(written.positions, plain.positions, rtol=0, atol=2.0**-12)
    stored = spz.read(blender.out / name, axes=None).positions
    flip = np.diag([1.0, -1.0, -1.0]) if axes == "RUB" else np.eye(3)
    np.testing.assert_allclose(stored, plain.positions @ flip, rtol=0, atol=2.0**-12)
