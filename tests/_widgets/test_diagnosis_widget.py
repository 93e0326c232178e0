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
    refilled = []
    if result.regions:  # the same regions again: the regions layer is left alone (no refill)
        viewer.layers["mismatch regions"].events.data.connect(refilled.append)
    widget._show(recording, result)
    assert all(a is b for a, b in zip(viewer.layers, shown, strict=True))
    assert not refilled
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


RESULT_LAYERS = ("residual z (base model)", "residual z (final model)", "residual z 4x4 (base model)",
                 "residual z 4x4 (final model)", "residual map labels", "mismatch regions")


def _result_layer_names(viewer) -> list[str]:
    """The diagnosis' result layers in the viewer (duplicates as napari names them: "name [1]")."""
    return [layer.name for layer in viewer.layers if layer.name.split(" [")[0] in RESULT_LAYERS]


@pytest.mark.slow
def test_cancel_while_the_result_is_shown_leaves_no_partial_layers_and_the_re_run_one_set(docked, qtbot, errors_shown):
    """The result is shown over event-loop turns: Cancel in the middle removes the layers it
    added so far (and no later step adds any); Diagnose is disabled while it is shown; the run
    after the cancel shows exactly one set."""
    from qtpy.QtCore import Qt

    viewer, widget, _thickness, _recording = docked
    widget._max_terms.value = 1
    worker = widget.run()
    qtbot.waitUntil(lambda: "residual z (base model)" in viewer.layers, timeout=120_000)
    assert len(_result_layer_names(viewer)) < len(RESULT_LAYERS)  # midway
    assert not widget._run.enabled  # a second run cannot start while it is shown
    qtbot.mouseClick(widget._run.native, Qt.MouseButton.LeftButton)
    assert widget._job.worker is worker
    qtbot.mouseClick(widget._job.cancel_button.native, Qt.MouseButton.LeftButton)
    assert _result_layer_names(viewer) == [] and widget.result is None
    qtbot.waitUntil(lambda: worker.dslrxr_finished, timeout=10_000)
    qtbot.wait(500)  # longer than the steps' timers: none is left to add a layer
    assert _result_layer_names(viewer) == [] and widget.result is None
    assert widget._run.enabled and "cancelled" in widget._job.status.value and not errors_shown
    # run again, Diagnose clicked (it is disabled) while the result is shown: one set
    worker = widget.run()
    qtbot.waitUntil(lambda: "residual z (final model)" in viewer.layers, timeout=120_000)
    qtbot.mouseClick(widget._run.native, Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: worker.dslrxr_finished, timeout=30_000)
    assert widget._job.worker is None and widget.result is not None and not errors_shown
    assert sorted(_result_layer_names(viewer)) == sorted(RESULT_LAYERS)
    assert viewer.layers["residual z 4x4 (final model)"].visible and viewer.layers["mismatch regions"].visible


@pytest.mark.slow
def test_a_re_run_cancelled_while_shown_puts_the_previous_result_back(docked, qtbot, wait_for_worker, errors_shown):
    """Cancel while a re-run updates the result layers in place: every layer shows the
    previous result again (its very arrays), none is removed, ``result`` is the previous one."""
    viewer, widget, _thickness, _recording = docked
    widget._max_terms.value = 1
    wait_for_worker(widget.run(), timeout_ms=120_000)
    previous = widget.result
    layers = {name: viewer.layers[name] for name in RESULT_LAYERS}
    data = {name: layer.data for name, layer in layers.items() if name != "mismatch regions"}
    regions = [np.array(v) for v in layers["mismatch regions"].data]
    labels = list(layers["residual map labels"].features["what"])
    scales = {name: tuple(viewer.layers[name].scale) for name in data}
    widget._binning.value = "2"  # another result: maps of half the size, twice the scale
    worker = widget.run()
    qtbot.waitUntil(lambda: viewer.layers["residual z (final model)"].data is not data["residual z (final model)"],
                    timeout=120_000)
    assert worker.dslrxr_finished is False
    widget.cancel()
    qtbot.waitUntil(lambda: worker.dslrxr_finished, timeout=10_000)
    qtbot.wait(500)
    assert list(viewer.layers)[-len(RESULT_LAYERS):] == list(layers.values()) or all(
        viewer.layers[name] is layer for name, layer in layers.items())
    for name, array in data.items():
        assert viewer.layers[name].data is array and tuple(viewer.layers[name].scale) == scales[name], name
    assert list(viewer.layers["residual map labels"].features["what"]) == labels
    assert len(viewer.layers["mismatch regions"].data) == len(regions)
    assert all(np.allclose(a, b) for a, b in zip(viewer.layers["mismatch regions"].data, regions))
    assert widget.result is previous and not errors_shown


def test_a_failing_display_step_leaves_no_partial_layers(docked, qtbot, wait_for_worker, errors_shown, monkeypatch):
    """A step of the display that raises: a notification, the layers added so far removed,
    the read-out and the status say it failed (not "done")."""
    viewer, widget, _thickness, _recording = docked
    widget._max_terms.value = 1

    def broken(*_args, **_kwargs):
        raise RuntimeError("no labels today")

    monkeypatch.setattr(DiagnosisWidget, "_show_map_labels", broken)
    wait_for_worker(widget.run(), timeout_ms=120_000)
    assert len(errors_shown) == 1 and "no labels today" in errors_shown[0]
    assert _result_layer_names(viewer) == [] and widget.result is None
    assert widget._readout.value.startswith("failed") and widget._job.status.value.startswith("failed")
    assert widget._run.enabled
