"""Parameter TOML: the widgets' values round-trip through the file the CLI reads."""

from __future__ import annotations

import pytest

from napari_dslrxr._widgets.contrast import ContrastWidget
from napari_dslrxr._widgets.deconvolution import DeconvolutionWidget
from napari_dslrxr._widgets.flatfield import FlatFieldWidget
from napari_dslrxr._widgets.impulse import ImpulseWidget
from napari_dslrxr._widgets.params_file import ParamsFileWidget
from napari_dslrxr.cli import main
from napari_dslrxr.core.params import load_params

pytestmark = pytest.mark.gui


def test_save_then_load_restores_every_stage_widget(make_napari_viewer, tmp_path, errors_shown, capsys):
    viewer = make_napari_viewer()
    impulse, flat, deconv, contrast = (cls(viewer) for cls in (ImpulseWidget, FlatFieldWidget,
                                                               DeconvolutionWidget, ContrastWidget))
    contrast._live.value = False
    params_widget = ParamsFileWidget(viewer)
    for w in (impulse, flat, deconv, contrast, params_widget):
        viewer.window.add_dock_widget(w)
    impulse._passes["H"].value = 5
    flat._smoothing.value = 7.5
    deconv._method.value = "wiener"
    deconv._reg.value = 1000.0
    contrast._sliders[("contrast", "bone_contrast")].value = 2.7
    contrast._sliders[("dynamic_range", "latitude")].value = 0.35
    path = tmp_path / "session.toml"
    params_widget._path.value = path
    assert params_widget.save() == path and not errors_shown

    # The file is the CLI's: it validates with `dslrxr params --check` and holds the values.
    assert main(["params", "--check", str(path)]) == 0
    saved = load_params(path)
    assert saved.impulse.passes_h == 5 and saved.flatfield.flat_smoothing_px == 7.5
    assert saved.deblur.method == "wiener" and saved.deblur.reg == pytest.approx(1000.0, rel=0.02)
    assert saved.contrast.bone_contrast == pytest.approx(2.7) and saved.dynamic_range.latitude == pytest.approx(0.35)

    impulse._passes["H"].value = 0
    flat._smoothing.value = 0.0
    deconv._method.value = "rls"
    contrast._sliders[("contrast", "bone_contrast")].value = 1.0
    params_widget.load()
    assert impulse._passes["H"].value == 5 and flat._smoothing.value == 7.5
    assert deconv._method.value == "wiener"
    assert contrast._sliders[("contrast", "bone_contrast")].value == pytest.approx(2.7)
    assert "loaded session.toml" in params_widget._readout.value


def test_bad_parameter_file_is_a_notification(make_napari_viewer, tmp_path, errors_shown):
    viewer = make_napari_viewer()
    impulse = ImpulseWidget(viewer)
    params_widget = ParamsFileWidget(viewer)
    bad = tmp_path / "bad.toml"
    bad.write_text("[impulse]\npasses_hh = 2\n")
    params_widget._path.value = bad
    assert params_widget.load() is None
    assert "passes_hh" in errors_shown[-1] and "passes_h" in errors_shown[-1]
    assert impulse._passes["H"].value == 3  # unchanged
