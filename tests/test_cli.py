"""The `splatwright` command line: info and convert, checked against the clouds the tests wrote."""

import json

import numpy as np
import pytest
from helpers import random_cloud

from splatwright.cli import main
from splatwright.io import ply, SplatFileWarning


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def scene(tmp_path):
    cloud = random_cloud(321, sh_degree=2, seed=4, spread=3.0)
    cloud.extras = {"segment": np.arange(321, dtype=np.uint16)}
    path = tmp_path / "scene.ply"
    ply.write(path, cloud)
    return path, cloud


def test_info_json_matches_the_cloud_written(capsys, scene):
    path, cloud = scene
    code, out, err = run(capsys, "info", path, "--json")
    assert code == 0, err
    info = json.loads(out)
    assert info["count"] == 321 and info["sh_degree"] == 2 and info["format"] == "ply"
    assert info["bbox_min"] == cloud.positions.astype(np.float64).min(axis=0).tolist()
    assert info["bbox_max"] == cloud.positions.astype(np.float64).max(axis=0).tolist()
    opacity = 1 / (1 + np.exp(-cloud.opacity_logits.astype(np.float64)))
    assert info["opacity"]["min"] == pytest.approx(opacity.min(), rel=1e-12)
    assert info["opacity"]["max"] == pytest.approx(opacity.max(), rel=1e-12)
    largest_sigma = np.exp(cloud.log_scales.astype(np.float64)).max(axis=1)
    assert info["scale"]["median"] == pytest.approx(np.median(largest_sigma), rel=1e-12)
    assert info["non_finite_splats"] == 0 and info["problems"] == [] and info["warnings"] == []
    assert info["extras"] == ["segment"]


def test_info_text_names_every_field(capsys, scene):
    path, cloud = scene
    code, out, _ = run(capsys, "info", path)
    assert code == 0
    lines = {line.split(":", 1)[0].strip(): line.split(":", 1)[1].strip() for line in out.splitlines()}
    assert lines["count"] == "321" and lines["sh_degree"] == "2" and lines["format"] == "ply"
    assert lines["bbox_min"] == str(cloud.positions.astype(np.float64).min(axis=0).tolist())


def test_info_counts_non_finite_values_instead_of_refusing(capsys, tmp_path):
    cloud = random_cloud(40, sh_degree=1)
    cloud.opacity_logits[3] = np.nan
    cloud.positions[7, 2] = np.inf
    cloud.sh[7, 1, 0] = np.nan
    path = tmp_path / "nan.ply"
    with pytest.warns(SplatFileWarning):
        ply.write(path, cloud, nonfinite="keep")
    code, out, err = run(capsys, "info", path, "--json")
    assert code == 0, err
    info = json.loads(out)
    assert info["non_finite_splats"] == 2
    finite = np.ones(40, bool)
    finite[[3, 7]] = False
    assert info["bbox_max"] == cloud.positions[finite].astype(np.float64).max(axis=0).tolist()
    assert any("non-finite opacity_logits" in p for p in info["problems"])
    assert any("2 of 40 splats" in w for w in info["warnings"])


@pytest.mark.parametrize("degree", [0, 1, 2])
def test_convert_truncates_sh(capsys, scene, tmp_path, degree):
    path, cloud = scene
    out_path = tmp_path / f"d{degree}.ply"
    code, out, err = run(capsys, "convert", path, out_path, "--sh-degree", degree)
    assert code == 0, err
    assert f"wrote 321 splats (SH degree {degree})" in out
    back = ply.read(out_path)
    k = (degree + 1) ** 2
    np.testing.assert_array_equal(back.sh, cloud.sh[:, :k])
    for name in ("positions", "rotations", "log_scales", "opacity_logits"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cloud, name))
    np.testing.assert_array_equal(back.extras["segment"], cloud.extras["segment"])


def test_convert_without_degree_copies_byte_for_byte(capsys, scene, tmp_path):
    path, _ = scene
    code, _, err = run(capsys, "convert", path, tmp_path / "copy.ply")
    assert code == 0, err
    assert (tmp_path / "copy.ply").read_bytes() == path.read_bytes()


def test_errors_exit_non_zero_naming_file_and_problem(capsys, scene, tmp_path):
    path, cloud = scene
    missing = tmp_path / "missing.ply"
    code, _, err = run(capsys, "info", missing)
    assert code != 0 and str(missing) in err and "no such file" in err

    code, _, err = run(capsys, "convert", path, tmp_path / "out.xyz")
    assert code != 0 and "out.xyz" in err and "unknown splat file extension '.xyz'" in err
    assert not (tmp_path / "out.xyz").exists()

    cut = tmp_path / "cut.ply"
    cut.write_bytes(path.read_bytes()[:-100])
    for argv in (("info", cut), ("convert", cut, tmp_path / "o.ply")):
        code, _, err = run(capsys, *argv)
        assert code != 0 and str(cut) in err and "truncated" in err
    assert not (tmp_path / "o.ply").exists()

    bad = cloud.copy()
    bad.log_scales[5, 1] = np.nan
    nan_path = tmp_path / "nan.ply"
    with pytest.warns(SplatFileWarning):
        ply.write(nan_path, bad, nonfinite="keep")
    code, _, err = run(capsys, "convert", nan_path, tmp_path / "n.ply")
    assert code != 0 and str(nan_path) in err and "non-finite" in err and "log_scales in 1" in err

    text = tmp_path / "notes.ply"
    text.write_text("hello\n")
    code, _, err = run(capsys, "info", text)
    assert code != 0 and str(text) in err and "not a PLY file" in err


def test_bad_arguments_exit_non_zero(capsys, scene):
    path, _ = scene
    with pytest.raises(SystemExit) as exc:
        main(["convert", str(path), "x.ply", "--sh-degree", "4"])
    assert exc.value.code != 0
    assert "--sh-degree" in capsys.readouterr().err
