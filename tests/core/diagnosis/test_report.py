"""Tests of the diagnosis outputs: JSON in the issue's shape, residual TIFFs, offline HTML."""

from __future__ import annotations

import base64
import json
import re

import numpy as np
import pytest
import tifffile

from napari_dslrxr.core.diagnosis import diagnose_scene
from napari_dslrxr.core.errors import OutputError
from napari_dslrxr.core.diagnosis.report import write_report
from napari_dslrxr.core.simulation.simulator import parse_scene, phantom_thickness_mm, simulate_recording


@pytest.fixture(scope="module")
def glare_result():
    scene = parse_scene({"geometry": {"source_to_detector_mm": 1200.0, "source_to_object_mm": 1000.0,
                                      "pixel_pitch_mm": 0.1},
                         "object": {"material": "aluminium"}, "source": {"kvp": 60}},
                        thickness=phantom_thickness_mm((96, 96)))
    recording, _ = simulate_recording(scene, effects={"veiling_glare": {"eta": 0.06, "range_mm": 1.0}}, seed=2)
    return diagnose_scene(scene, recording)


def test_report_files_shapes_and_offline_html(glare_result, tmp_path):
    paths = write_report(glare_result, tmp_path / "rep", parameters={"x": 1})
    data = json.loads(paths["diagnosis"].read_text())
    assert set(data) == {"base", "registration", "noise", "mismatch", "added", "final", "unexplained",
                         "unexplained_signatures"}
    assert set(data["base"]) == {"chi2_per_dof", "bic"}
    assert isinstance(data["mismatch"]["regions"], list)
    assert data["added"][0]["effect"] == "veiling_glare"
    assert {"effect", "params", "uncertainty", "delta_bic", "chi2_per_dof", "runner_up", "runner_up_delta_bic",
            "ambiguous"} <= set(data["added"][0])
    assert "runner-up" in paths["report"].read_text()
    assert data["final"]["chi2_per_dof"] < data["base"]["chi2_per_dof"]
    z = tifffile.imread(paths["residual_base"])
    assert z.dtype == np.float32 and z.shape == (96, 96)
    np.testing.assert_array_equal(z, glare_result.z_base)
    page = paths["report"].read_text()
    assert "http://" not in page and "https://" not in page  # opens offline
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(images) == 2
    assert all(base64.b64decode(img)[:8] == b"\x89PNG\r\n\x1a\n" for img in images)
    for path in paths.values():
        assert path.with_name(path.name + ".json").is_file()


def test_report_is_deterministic(glare_result, tmp_path):
    a = write_report(glare_result, tmp_path / "a")
    b = write_report(glare_result, tmp_path / "b")
    for key in a:
        assert a[key].read_bytes() == b[key].read_bytes(), key


def test_report_folder_that_is_a_file_is_a_one_line_error(glare_result, tmp_path):
    target = tmp_path / "file"
    target.write_text("x")
    with pytest.raises(OutputError):
        write_report(glare_result, target)


def test_report_names_its_inputs_and_date_and_scales_its_figures(glare_result, tmp_path):
    import html as html_module

    paths = write_report(glare_result, tmp_path / "rep", input_names=["recording layer 'shot 1'", "scene.toml"],
                         created="2026-11-24T17:00:00+00:00")
    page = html_module.unescape(paths["report"].read_text(encoding="utf-8"))
    assert "Inputs: recording layer 'shot 1'; scene.toml" in page
    assert "Created: 2026-11-24T17:00:00+00:00" in page
    assert "img{max-width:100%;height:auto}" in page
    # Without a date the page depends on the inputs only (same bytes twice).
    a = write_report(glare_result, tmp_path / "a", input_names=["x"])["report"].read_bytes()
    b = write_report(glare_result, tmp_path / "b", input_names=["x"])["report"].read_bytes()
    assert a == b and b"Created" not in a
