"""Tests of ``dslrxr simulate`` and ``dslrxr diagnose``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import tifffile

from scenes import PHANTOM_SCENE_TOML
from napari_dslrxr._cli.simulate import parse_effect_option
from napari_dslrxr.cli import main
from napari_dslrxr.core import io
from napari_dslrxr.core.errors import ParameterError
from napari_dslrxr.core.simulation.simulator import phantom_thickness_mm

SCENE = PHANTOM_SCENE_TOML


def test_effect_option_syntax():
    name, params = parse_effect_option("heel_effect=0.05")
    assert name == "heel_effect" and params["h1"] == 0.05 and params["h2"] == 0.0
    name, params = parse_effect_option("mirror_ghost=epsilon:0.03,shift_mm:1.5")
    assert params == {"epsilon": 0.03, "shift_mm": 1.5, "axis_deg": 0.0}
    with pytest.raises(ParameterError, match="--effect 'mirror_ghost=epsilon'"):
        parse_effect_option("mirror_ghost=epsilon")


def _scene(tmp_path, size=96):
    io.write_tiff(tmp_path / "thickness.tif", phantom_thickness_mm((size, size)))
    (tmp_path / "scene.toml").write_text(SCENE)
    return tmp_path / "scene.toml"


def test_simulate_then_diagnose_names_the_injected_term(tmp_path, capsys):
    scene = _scene(tmp_path)
    rec = tmp_path / "rec.tif"
    assert main(["simulate", str(scene), "-o", str(rec), "--effect", "mirror_ghost=epsilon:0.03,shift_mm:0.4",
                 "--seed", "4"]) == 0
    data = tifffile.imread(rec)
    assert data.shape == (96, 96) and data.dtype == np.float32
    assert json.loads(rec.with_name("rec.tif.json").read_text())["parameters"]["seed"] == 4
    assert main(["diagnose", str(scene), str(rec), "-o", str(tmp_path / "rep"), "--binning", "1"]) == 0
    result = json.loads((tmp_path / "rep" / "diagnosis.json").read_text())
    assert json.loads((tmp_path / "rep" / "diagnosis_details.json").read_text())["binning"] == 1
    assert set(result["registration"]) == {"shift_x_px", "shift_y_px", "scale", "rotation_deg"}
    assert result["added"][0]["runner_up"]
    assert [a["effect"] for a in result["added"]] == ["mirror_ghost"]
    assert abs(result["added"][0]["params"]["shift_mm"] - 0.4) < 0.05
    assert (tmp_path / "rep" / "report.html").is_file()
    assert "mirror_ghost" in capsys.readouterr().out


def test_simulate_is_deterministic_and_main_amplitude_form_works(tmp_path):
    scene = _scene(tmp_path, 64)
    for name in ("a.tif", "b.tif"):
        assert main(["simulate", str(scene), "-o", str(tmp_path / name), "--effect", "heel_effect=0.05"]) == 0
    assert (tmp_path / "a.tif").read_bytes() == (tmp_path / "b.tif").read_bytes()


def test_cli_errors_are_one_line(tmp_path, capsys):
    scene = _scene(tmp_path, 64)
    assert main(["simulate", str(scene), "-o", str(tmp_path / "r.tif"), "--effect", "glare=0.1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dslrxr: error:") and "did you mean 'veiling_glare'" in err and err.count("\n") == 1
    assert main(["simulate", str(scene), "-o", str(tmp_path / "thickness.tif")]) == 2  # would overwrite input
    io.write_tiff(tmp_path / "small.tif", np.zeros((32, 32), np.float32))
    assert main(["diagnose", str(scene), str(tmp_path / "small.tif"), "-o", str(tmp_path / "rep")]) == 2
    assert "does not match" in capsys.readouterr().err
    assert main(["diagnose", str(scene), str(tmp_path / "small.tif"), "-o", str(tmp_path / "rep"),
                 "--binning", "half"]) == 2
    err = capsys.readouterr().err
    assert "binning must be 'auto' or an integer >= 1" in err and err.count("\n") == 1
