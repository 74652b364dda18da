"""Alpha-cut leaves through Blender, in every Blender of the version matrix (the worker is
tests/workers/alpha_cut.py): the alpha mode Mesh to Splats reads from each node setup, and a leaf
quad converted with the glTF importer's alpha clip keeps splats only where the image's alpha
passes the cutoff."""

import numpy as np
import pytest
from blender_session import blender_fixture
from workers.alpha_cut import CUTOFF, SETUPS

pytestmark = [pytest.mark.blender, pytest.mark.slow]

blender = blender_fixture("workers.alpha_cut")


def test_the_alpha_mode_is_read_from_the_node_setup(blender):
    res = blender.step("modes")
    expected = {k: [mode, cutoff, mode] for k, (mode, cutoff) in SETUPS.items()}
    if "clip" not in res:  # a Blender without Material.blend_method
        expected.pop("clip")
    assert {k: [v[0], pytest.approx(v[1], abs=1e-6), v[2]] for k, v in res.items()} == expected


def bilinear_alpha(leaf, uv):
    """The image's alpha (uint8 RGBA, row 0 at the top) read bilinearly at texel centres, float64."""
    h, w = leaf.shape[:2]
    alpha = leaf[..., 3].astype(np.float64) / 255
    x, y = uv[:, 0] * w - 0.5, (1 - uv[:, 1]) * h - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    a = lambda r, c: alpha[r % h, c % w]  # noqa: E731
    top = (1 - fx) * a(y0, x0) + fx * a(y0, x0 + 1)
    bottom = (1 - fx) * a(y0 + 1, x0) + fx * a(y0 + 1, x0 + 1)
    return (1 - fy) * top + fy * bottom


def test_a_leaf_quad_keeps_splats_only_on_the_leaves(blender):
    res = blender.step("convert")
    assert res["result"] == ["FINISHED"], res
    cut, whole = blender.npz("convert_gltf"), blender.npz("convert_unlinked")
    uv = cut["positions"][:, [0, 2]].astype(np.float64)  # the quad is x = u, z = v, y = 0
    assert np.abs(cut["positions"][:, 1]).max() < 1e-6
    alpha = bilinear_alpha(cut["leaf"], uv)
    assert res["counts"]["alpha_held"] == pytest.approx(cut["leaf"][..., 3].mean() / 255, abs=1e-6)
    assert alpha.min() >= CUTOFF - 1e-3  # no splat centre on a cut-out
    # and the leaves covered: the share of the splats kept is about the leaves' share of the quad
    share = res["counts"]["gltf"] / res["counts"]["unlinked"]
    leaves = float((bilinear_alpha(cut["leaf"], whole["positions"][:, [0, 2]].astype(np.float64)) >= CUTOFF).mean())
    assert res["counts"]["unlinked"] > 2000
    assert 0.75 * leaves < share <= 1.02 * leaves, (share, leaves)
