"""The `splatwright` command line: info and convert, checked against the clouds the tests wrote."""

import json
import os
import warnings

import numpy as np
import pytest
from helpers import random_cloud

from splatwright.cli import main
from splatwright.io import SplatFileWarning, ply


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
    assert info["extras"] == ["segment"] and info["made_for"] == "classic rendering"
    ply.write(path, cloud.replace(antialiased=True))
    code, out, err = run(capsys, "info", path, "--json")
    assert json.loads(out)["made_for"] == "antialiased rendering"


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
    for special, make in (("pipe.ply", os.mkfifo), ("folder.ply", os.mkdir)):
        if not hasattr(os, make.__name__):
            continue  # no FIFOs on Windows
        make(tmp_path / special)
        code, _, err = run(capsys, "info", tmp_path / special)  # a FIFO would hang the read
        assert code == 1 and f"{tmp_path / special}: not a regular file" in err

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


def test_sh_degree_4_converts_and_reports(capsys, tmp_path):
    """--sh-degree takes 0..4; a degree-4 PLY goes to SPZ v4 whole, or down to any lower degree."""
    cloud = random_cloud(50, sh_degree=4, seed=6)
    cloud.sh[:, 1:] = np.clip(cloud.sh[:, 1:], -0.9, 0.9)  # within SPZ's range
    ply.write(tmp_path / "d4.ply", cloud)
    code, _, err = run(capsys, "convert", tmp_path / "d4.ply", tmp_path / "d4.spz", "--no-check")
    assert code == 0, err
    code, out, err = run(capsys, "info", tmp_path / "d4.spz", "--json")
    assert code == 0 and json.loads(out)["sh_degree"] == 4, err
    code, out, err = run(capsys, "convert", tmp_path / "d4.ply", tmp_path / "d2.ply", "--sh-degree", "2", "--no-check")
    assert code == 0 and "SH degree 2" in out, err
    np.testing.assert_array_equal(ply.read(tmp_path / "d2.ply").sh, cloud.sh[:, :9])
    code, out, err = run(capsys, "convert", tmp_path / "d2.ply", tmp_path / "up.ply", "--sh-degree", "4", "--no-check")
    assert code == 0 and ply.read(tmp_path / "up.ply").sh_degree == 4, err


def test_bad_arguments_exit_non_zero(capsys, scene):
    path, _ = scene
    with pytest.raises(SystemExit) as exc:
        main(["convert", str(path), "x.ply", "--sh-degree", "5"])
    assert exc.value.code != 0
    assert "--sh-degree" in capsys.readouterr().err


# exit status: 1 for a bad file or value, 2 for bad usage; never a traceback ------------------------

OUT_OF_RANGE = [
    ("render", ["--fov", "0"], "--fov must be a horizontal field of view in degrees, between 0 and 180"),
    ("render", ["--fov", "180"], "--fov must be"),
    ("render", ["--fov", "nan"], "--fov must be"),
    ("render", ["--background", "nan,0,0"], "--background must be 3 numbers r,g,b from 0 to 1, or 'none', got nan,0,0"),
    ("render", ["--background", "2,2,2"], "--background must be 3 numbers r,g,b from 0 to 1"),
    ("render", ["--background", "0.5,0.5"], "--background must be 3 numbers"),
    ("render", ["--ortho-scale", "0"], "--ortho-scale must be a width in world units, finite and > 0, got 0"),
    ("render", ["--ortho-scale", "inf"], "--ortho-scale must be"),
    ("render", ["--up", "0,0,0"], "--up must be 3 finite numbers x,y,z, not all zero"),
    ("render", ["--camera-pos", "0,0,inf"], "--camera-pos must be 3 finite numbers"),
    ("render", ["--look-at", "1,2"], "--look-at must be 3 finite numbers"),
    ("render", ["--near", "0"], "--near must be a distance, finite and > 0"),
    ("render", ["--near", "-1"], "--near must be"),
    ("render", ["--width", "0"], "--width must be a whole number >= 1"),
    ("render", ["--height", "-3"], "--height must be a whole number >= 1"),
    (
        "render",
        ["--camera-pos", "0,0,5", "--look-at", "0,0,0", "--up", "0,0,2"],
        "--up (0,0,2) is parallel to the view direction",
    ),
    (
        "render",
        ["--camera-pos", "1,1,1", "--look-at", "1,1,1"],
        "--camera-pos, --look-at: invalid camera: eye and target",
    ),
    (
        "convert",
        ["--prune-invisible", "-1"],
        "--prune-invisible must be a blending weight from 0 up to (not including) 1",
    ),
    ("convert", ["--prune-invisible", "nan"], "--prune-invisible must be"),
    ("convert", ["--prune-opacity", "1.5"], "--prune-opacity must be an opacity from 0 to 1"),
    ("convert", ["--prune-invisible", "--views", "0"], "--views must be a whole number from 1 to 1000"),
    ("convert", ["--prune-invisible", "--view-size", "100000"], "--view-size must be a whole number of pixels"),
    ("mesh2splats", ["--target-psnr", "-5"], "--target-psnr must be a PSNR in dB, finite and > 0, got -5"),
    ("mesh2splats", ["--target-psnr", "inf"], "--target-psnr must be"),
    ("mesh2splats", ["--target-psnr", "nan"], "--target-psnr must be"),
    ("mesh2splats", ["--max-splats", "0"], "--max-splats must be a whole number from 1 to 2147483647"),
    ("mesh2splats", ["--view-size", "0"], "--view-size must be"),
    ("mesh2splats", ["--filter-width", "0"], "--filter-width must be a width in pixels, finite and > 0, got 0"),
    ("urdf2splats", ["--target-psnr", "-5"], "--target-psnr must be"),
    ("urdf2splats", ["--max-splats", "-1"], "--max-splats must be"),
    ("urdf2splats", ["--joint", "elbow=nan"], "--joint expects NAME=VALUE with finite numbers"),
    ("urdf2splats", ["--joint", "elbow"], "--joint expects NAME=VALUE"),
]


def verb_argv(verb, scene_path, out):
    return {
        "render": ["render", scene_path, "-o", out],
        "convert": ["convert", scene_path, out],
        "mesh2splats": ["mesh2splats", scene_path.with_suffix(".obj"), out],
        "urdf2splats": ["urdf2splats", scene_path.with_suffix(".urdf"), out],
    }[verb]


@pytest.mark.parametrize("verb, options, message", OUT_OF_RANGE)
def test_out_of_range_options_exit_1_naming_the_option(capsys, scene, tmp_path, verb, options, message):
    path, _ = scene
    out = tmp_path / ("o.png" if verb == "render" else "o.ply")
    code, _, err = run(capsys, *verb_argv(verb, path, out), *options)
    assert code == 1 and err == f"splatwright {verb}: error: {err.split('error: ', 1)[1]}"
    assert message in err and "Traceback" not in err
    assert not out.exists()


def test_an_image_too_big_for_memory_is_refused_before_the_file_is_read(capsys, tmp_path, monkeypatch):
    from splatwright.core import render

    monkeypatch.setattr(render, "physical_memory", lambda: 16 * 2**30)
    code, _, err = run(
        capsys, "render", tmp_path / "never_read.ply", "-o", tmp_path / "o.png", "--width", 40000, "--height", 40000
    )
    assert code == 1 and "--width, --height: a 40000x40000 render needs" in err
    assert "more than this machine's 16.0 GiB" in err and "never_read" not in err


def test_file_errors_exit_1(capsys, scene, tmp_path):
    path, _ = scene
    code, _, err = run(capsys, "info", tmp_path / "missing.ply")
    assert code == 1 and "no such file" in err
    (tmp_path / "taken.ply").mkdir()
    code, _, err = run(capsys, "convert", path, tmp_path / "taken.ply")
    assert code == 1 and f"{tmp_path / 'taken.ply'}: is a folder, not a file" in err
    code, _, err = run(capsys, "render", path, "-o", tmp_path / "nowhere" / "o.png", "--width", 8, "--height", 8)
    assert code == 1 and f"the folder {tmp_path / 'nowhere'} does not exist" in err


@pytest.mark.parametrize(
    "argv",
    [
        ["render", "x.ply", "-o", "o.png", "--fov", "abc"],
        ["render", "x.ply", "-o", "o.png", "--width", "1.5"],
        ["convert", "x.ply"],
        ["convert", "x.ply", "y.ply", "--bogus"],
    ],
)
def test_usage_errors_exit_2(capsys, argv):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2 and "usage: splatwright" in capsys.readouterr().err


def test_the_installed_command_prints_one_line_and_no_traceback(scene, tmp_path):
    """Through the real entry point (python -m splatwright), as a user runs it."""
    import subprocess
    import sys

    path, _ = scene
    for options, code, message in ((["--fov", "0"], 1, "--fov must be"), (["--fov", "x"], 2, "invalid float value")):
        done = subprocess.run(
            [sys.executable, "-m", "splatwright", "render", str(path), "-o", str(tmp_path / "o.png"), *options],
            capture_output=True,
            text=True,
            cwd=tmp_path,
        )
        assert done.returncode == code and message in done.stderr and "Traceback" not in done.stderr


def test_options_in_range_still_render(capsys, scene, tmp_path):
    path, _ = scene
    out = tmp_path / "o.png"
    code, stdout, err = run(
        capsys,
        "render",
        path,
        "-o",
        out,
        "--width",
        16,
        "--height",
        12,
        "--fov",
        179,
        "--background",
        "none",
        "--up",
        "0,-1,0",
        "--near",
        "0.01",
    )
    assert code == 0, err
    assert "at 16x12" in stdout and out.read_bytes()[16:24] == (16).to_bytes(4, "big") + (12).to_bytes(4, "big")


# hostile and damaged files: one line, exit 1; names outside the folder only with --allow-outside ----


def damaged_files(folder):
    """Files of every format our writers make, cut short (not at a record boundary) or to four bytes."""
    from splatwright.io import write_splats

    cloud = random_cloud(30, sh_degree=1, seed=9)
    for name in ("a.ply", "b.compressed.ply", "c.spz", "d.splat", "e.sog", "f.glb", "g.usdc", "h.usda"):
        path = folder / name
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", SplatFileWarning)  # formats that drop SH degree 1
            write_splats(path, cloud)
        data = path.read_bytes()
        yield path.with_name(f"cut_{name}"), data[: len(data) // 2 - 1]
        yield path.with_name(f"four_{name}"), data[:4]


def test_damaged_files_of_every_format_exit_1_with_one_line(capsys, tmp_path):
    for path, data in damaged_files(tmp_path):
        path.write_bytes(data)
        verbs = (["info", path], ["convert", path, tmp_path / "out.ply"], ["render", path, "-o", tmp_path / "o.png"])
        for argv in verbs:
            code, _, err = run(capsys, *argv)
            assert code == 1, (argv, err)
            assert err.startswith(f"splatwright {argv[0]}: error: ") and err.count("\n") == 1, err
            assert path.name in err and "Traceback" not in err
    assert not (tmp_path / "out.ply").exists() and not (tmp_path / "o.png").exists()


def test_system_errors_name_the_file_and_exit_1_but_defects_keep_their_traceback(capsys, scene, monkeypatch):
    import splatwright.io

    path, _ = scene
    for error, words in (
        (PermissionError(13, "Permission denied", str(path)), f"{path}: Permission denied"),
        (MemoryError(), f"{path}: not enough memory for it"),
    ):

        def fail(*args, error=error, **kwargs):
            raise error

        monkeypatch.setattr(splatwright.io, "read_splats", fail)
        code, _, err = run(capsys, "info", path)
        assert code == 1 and err == f"splatwright info: error: {words}\n"
    monkeypatch.setattr(splatwright.io, "read_splats", lambda *a, **k: [][1])  # a defect, not a bad file
    with pytest.raises(IndexError):
        main(["info", str(path)])


def test_allow_outside_lets_a_file_name_files_outside_its_folder(capsys, tmp_path):
    from splatwright.io import gltf

    model = tmp_path / "model"
    model.mkdir()
    gltf.write(model / "v.gltf", random_cloud(5, sh_degree=0, seed=3))
    (model / "v.bin").rename(tmp_path / "v.bin")
    doc = json.loads((model / "v.gltf").read_text())
    doc["buffers"][0]["uri"] = "../v.bin"
    (model / "v.gltf").write_text(json.dumps(doc))
    code, _, err = run(capsys, "info", model / "v.gltf")
    assert code == 1 and "v.gltf" in err and "../v.bin" in err and err.count("\n") == 1
    code, out, err = run(capsys, "info", model / "v.gltf", "--allow-outside", "--json")
    assert code == 0, err
    assert json.loads(out)["count"] == 5
    with pytest.raises(SystemExit) as exc:
        main(["info", "--allow-outside"])
    assert exc.value.code == 2
