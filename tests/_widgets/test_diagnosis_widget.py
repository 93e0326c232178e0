"""Diagnosis widget on the sample scene: the hidden veiling glare is named, residuals shown, report opens."""

from __future__ import annotations

import numpy as np
import pytest
import tomli_w
from napari.layers import Layer

from napari_dslrxr import _sample_data as samples
from napari_dslrxr._widgets.diagnosis import DiagnosisWidget
from napari_dslrxr.core.io import write_tiff

pytestmark = pytest.mark.gui


@pytest.fixture
def docked(make_napari_viewer):
    viewer = make_napari_viewer()
    thickness, recording = (viewer.add_layer(Layer.create(*t)) for t in samples.make_sample_scene())
    widget = DiagnosisWidget(viewer)
    viewer.window.add_dock_widget(widget)
    widget._recording.value = recording
    return viewer, widget, thickness, recording


@pytest.mark.slow
def test_hidden_glare_is_named_with_residual_layers_and_report(docked, wait_for_worker, tmp_path, monkeypatch,
                                                               errors_shown):
    viewer, widget, thickness, recording = docked
    assert widget._thickness.value is thickness  # found through the recording's metadata
    widget._max_terms.value = 2
    wait_for_worker(widget.run(), timeout_ms=120_000)
    assert not errors_shown
    result = widget.result
    (term,) = result.added
    truth = samples.SCENE_HIDDEN_EFFECTS["veiling_glare"]
    assert term.effect == "veiling_glare"
    assert abs(term.params["eta"] - truth["eta"]) <= 3 * term.uncertainty["eta"]
    assert "+ veiling_glare: eta = " in widget._readout.value
    # Residual maps before/after: structured before, noise after.
    before = viewer.layers["residual z (base model)"].data
    after = viewer.layers["residual z (final model)"].data
    assert before.shape == after.shape == (128 // result.binning, 128 // result.binning)
    assert np.mean(before[result.mask] ** 2) > np.mean(after[result.mask] ** 2)
    assert np.mean(after[result.mask] ** 2) == pytest.approx(1.0, abs=0.1)
    assert tuple(viewer.layers["residual z (final model)"].scale) == tuple(recording.scale * result.binning)
    # 4x4-binned maps (unit variance under the null): excess before (1.41 here), noise after.
    binned_before = viewer.layers["residual z 4x4 (base model)"].data
    binned_after = viewer.layers["residual z 4x4 (final model)"].data
    assert binned_before.shape == (32 // result.binning, 32 // result.binning)
    assert np.mean(binned_before**2) > 1.25 and np.mean(binned_after**2) < 1.2
    if result.regions:
        assert len(viewer.layers["mismatch regions"].data) == len(result.regions)
    # Shown again (a re-run): every layer updated in place, none removed and re-added.
    shown = list(viewer.layers)
    widget._show(recording, result)
    assert all(a is b for a, b in zip(viewer.layers, shown, strict=True))
    assert list(viewer.layers["residual map labels"].features["what"]) == [
        "before (scene as given)", "after (+ veiling glare)"]
    if result.regions:
        assert len(viewer.layers["mismatch regions"].data) == len(result.regions)

    opened = []
    monkeypatch.setattr("webbrowser.open", lambda url: opened.append(url) or True)
    widget._report_dir.value = tmp_path / "report"
    wait_for_worker(widget.write())
    paths = widget.report_paths
    assert (tmp_path / "report" / "report.html").is_file() and "veiling_glare" in paths["report"].read_text()
    assert widget.open_report() and opened == [(tmp_path / "report" / "report.html").resolve().as_uri()]


def test_scene_file_input_and_errors(docked, tmp_path, errors_shown, wait_for_worker):
    viewer, widget, thickness, recording = docked
    widget._thickness.value = None
    assert widget.run() is None and "thickness layer" in errors_shown[-1]
    write_tiff(tmp_path / "thickness.tif", np.asarray(thickness.data, np.float32))
    table = {**samples.SCENE_TABLE, "object": {**samples.SCENE_TABLE["object"], "thickness_mm": "thickness.tif"}}
    (tmp_path / "scene.toml").write_text(tomli_w.dumps(table))
    widget._scene_file.value = tmp_path / "scene.toml"
    scene = widget.scene()
    assert scene.shape == (128, 128) and scene.source_to_object_mm == 1000.0
    np.testing.assert_allclose(scene.thickness_mm, thickness.data)
    widget._recording.value = viewer.add_image(np.zeros((64, 64), np.float32), name="wrong size")
    # Shape mismatch: raised by the core inside the worker, shown as a notification.
    wait_for_worker(widget.run())
    assert "does not match" in errors_shown[-1] and widget.result is None
    assert widget._run.enabled
