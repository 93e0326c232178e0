"""The contrast widget picks the input kind by the core rule when a layer is chosen (and at start)."""

from __future__ import annotations

import numpy as np
import pytest
from robustness import synthetic_files

from napari_dslrxr._widgets.contrast import DISPLAY, LINEAR, ContrastWidget
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph

pytestmark = pytest.mark.gui


def _cr_radiograph(shape=(160, 200)) -> np.ndarray:
    """Stored MONOCHROME1 values of a bone-bright band on soft tissue (bright = low on disk)."""
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    display = 1200 + 800 * np.exp(-((xx - shape[1] / 2) / 18.0) ** 2) + 3 * yy  # bone bright
    return (4095 - display).astype(np.uint16)


def test_dicom_opened_before_the_widget_is_a_display_radiograph(make_napari_viewer, tmp_path, wait_for_worker,
                                                                 errors_shown):
    viewer = make_napari_viewer()
    stored = _cr_radiograph()
    synthetic_files.write_dicom(tmp_path / "chest.dcm", stored, photometric="MONOCHROME1", bits_stored=12)
    (layer,) = viewer.open(str(tmp_path / "chest.dcm"), plugin="napari-dslrxr")
    widget = ContrastWidget(viewer)  # the DICOM layer is preselected: no change event
    viewer.window.add_dock_widget(widget)
    widget._live.value = False
    assert widget._image.value is layer
    assert widget._kind.value == DISPLAY
    assert "display" in widget._readout.value and "CR" in widget._readout.value
    wait_for_worker(widget.run())
    assert not errors_shown, errors_shown
    shown = np.asarray(layer.data, np.float64)
    # bone white: the result follows the radiograph as displayed, nowhere blanked to a trapezoid
    assert np.corrcoef(shown.ravel(), widget.result.ravel())[0, 1] > 0.8
    assert np.mean(widget.result == 0.0) < 0.001


def test_choosing_layers_switches_the_kind(make_napari_viewer, tmp_path):
    viewer = make_napari_viewer()
    frame = make_dslr_radiograph((96, 128), seed=1).raw_rgb  # a tinted camera frame
    camera = viewer.add_image(frame, rgb=True, name="camera frame")
    synthetic_files.write_dicom(tmp_path / "leg.dcm", _cr_radiograph(), photometric="MONOCHROME1", bits_stored=12)
    (dicom,) = viewer.open(str(tmp_path / "leg.dcm"), plugin="napari-dslrxr")
    widget = ContrastWidget(viewer)
    widget._live.value = False
    widget._image.value = camera
    assert widget._kind.value == LINEAR and "tint" in widget._readout.value
    widget._image.value = dicom
    assert widget._kind.value == DISPLAY
    grey = viewer.add_image(frame[..., 1].astype(np.float32), name="grey counts")
    widget._image.reset_choices()
    widget._image.value = grey
    assert widget._kind.value == LINEAR and "a guess" in widget._readout.value  # said, not hidden


@pytest.mark.realdata
def test_real_chest_dicom_in_the_widget_is_bone_white_and_whole(make_napari_viewer, shared_data, wait_for_worker,
                                                                 errors_shown):
    """The case from the report: the chest CR was taken as camera counts (inverted, cut to a trapezoid)."""
    source = shared_data / "cr_dicom" / "RG1_UNCR.dcm"
    if not source.is_file():
        pytest.skip(f"{source} is absent")
    viewer = make_napari_viewer()
    (layer,) = viewer.open(str(source), plugin="napari-dslrxr")
    widget = ContrastWidget(viewer)
    viewer.window.add_dock_widget(widget)
    widget._live.value = False
    assert widget._kind.value == DISPLAY
    wait_for_worker(widget.run())
    assert not errors_shown, errors_shown
    shown = np.asarray(layer.data, np.float64)[::4, ::4]
    result = widget.result[::4, ::4]
    assert np.corrcoef(shown.ravel(), result.ravel())[0, 1] > 0.85
    # No blanking (the bug cut 21 % to black); the display fit may clip up to its budget,
    # max_clipped_percent split between black and white.
    from napari_dslrxr.core.stages.dynamic_range import DynamicRangeParams

    assert np.mean(result == 0.0) <= DynamicRangeParams().max_clipped_percent / 100.0
