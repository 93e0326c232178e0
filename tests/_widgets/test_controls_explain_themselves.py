"""Every control has a tooltip; parameter controls take meaning, unit, range and default from
the parameter dataclasses' metadata (the same text as the TOML comments); nothing is cut at
the dock width ``dslrxr view`` gives."""

from __future__ import annotations

import pytest
from magicgui.widgets import Container, FloatSlider, PushButton
from magicgui.widgets.bases import ValueWidget

from napari_dslrxr._cli.view import DOCK_WIDTH_PX, plugin_widget_names, populate_viewer
from napari_dslrxr._widgets._controls import param_tooltip
from napari_dslrxr.core.stages.contrast import ContrastParams
from napari_dslrxr.core.stages.dynamic_range import DynamicRangeParams
from napari_dslrxr.core.stages.impulse import ImpulseParams
from napari_dslrxr.core.param_fields import field_info
from napari_dslrxr.core.params import params_to_toml

pytestmark = pytest.mark.gui


def controls(container: Container):
    for widget in container:
        if isinstance(widget, Container):
            yield from controls(widget)
        else:
            yield widget


@pytest.fixture
def docked(make_napari_viewer, qtbot):
    viewer = make_napari_viewer(show=True)
    widgets = dict(zip(plugin_widget_names(), populate_viewer(viewer, []), strict=True))
    qtbot.wait(100)  # the deferred dock arrangement
    return viewer, widgets


def test_every_control_has_a_tooltip(docked):
    _, widgets = docked
    missing = [f"{name}: {w.label or getattr(w, 'text', '')}" for name, container in widgets.items()
               for w in controls(container)
               if isinstance(w, (ValueWidget, PushButton)) and type(w).__name__ != "Label" and not w.tooltip]
    assert not missing, missing


def test_parameter_tooltips_and_ranges_come_from_the_metadata(docked):
    _, widgets = docked
    contrast = widgets["Contrast"]
    width = contrast._sliders[("dynamic_range", "lut_width")]
    info = field_info(DynamicRangeParams, "lut_width")
    # Radiologist's word as the label, the technical term and the metadata in the tooltip.
    assert width.label == "window width"
    assert info["help"] in width.tooltip and "range 0.05 to 2" in width.tooltip and "lut_width" in width.tooltip
    assert (width.min, width.max, width.value) == (info["min"], info["max"], info["default"])
    edge = contrast._sliders[("contrast", "edge_sharpness")]
    assert edge.label == "edge enhancement" and "Laplacian-pyramid" in edge.tooltip
    assert edge.max == field_info(ContrastParams, "edge_sharpness")["max"]
    passes = widgets["Impulse removal"]._passes["H"]
    assert (passes.min, passes.max) == (0, 10) and "passes on hue" in passes.tooltip
    assert passes.tooltip == param_tooltip(ImpulseParams, "passes_h", label="passes on hue", section="impulse")
    # The TOML file documents the same field with the same text.
    assert f"# {field_info(ImpulseParams, 'passes_h')['help']}" in params_to_toml()


def test_nothing_is_cut_at_the_dock_width(docked, qtbot):
    from qtpy.QtCore import Qt
    from qtpy.QtWidgets import QLabel, QTabBar

    viewer, widgets = docked
    window = viewer.window._qt_window
    bars = [bar for bar in window.findChildren(QTabBar) if bar.parent() is window and bar.count() >= 7]
    assert bars, "the widgets are tabbed"
    for bar in bars:
        assert bar.elideMode() == Qt.TextElideMode.ElideNone
        titles = [bar.tabText(i) for i in range(bar.count())]
        assert "Flat field" in titles and "Contrast" in titles, titles
    for name, container in widgets.items():
        container.native.window().raise_()
        for i in range(bars[0].count()):
            if bars[0].tabText(i) == name:
                bars[0].setCurrentIndex(i)
        qtbot.wait(30)
        assert container.native.width() <= DOCK_WIDTH_PX + 40, (name, container.native.width())
        for label in container.native.findChildren(QLabel):
            if label.isVisible() and label.text() and not label.wordWrap():
                assert label.width() >= label.sizeHint().width() - 1, (name, label.text(), label.width())
        for w in controls(container):
            if isinstance(w, FloatSlider) and w.native.isVisible():
                assert w.native.width() >= 150, (name, w.label, w.native.width())


def test_a_long_read_out_scrolls_and_the_window_keeps_its_size(docked, qtbot):
    """A result's read-out of many lines (detector quality, diagnosis, PSF fit) grew the
    widget's minimum height past the window's: Qt made the main window taller than the
    screen (1000 to 1112 px here) and resized the canvas, whose full redraw froze the viewer
    in the turn that showed the result. The read-out scrolls instead; the last line is still
    there to read."""
    from qtpy.QtWidgets import QScrollArea

    viewer, widgets = docked
    window, canvas = viewer.window._qt_window, viewer.window._qt_viewer.canvas.native
    text = "\n".join(f"line {k}: MTF 0.123 ± 0.004, NNPS 1.2e-05 ± 3e-07 mm², DQE 0.45 ± 0.02"
                     for k in range(20))
    for name in ("Detector quality", "Diagnosis", "PSF from edges", "Flat field"):
        container = widgets[name]
        container.native.window().raise_()
        qtbot.wait(30)
        before = (window.size(), canvas.size())
        container._readout.value = text
        qtbot.wait(100)
        after = (window.size(), canvas.size())
        assert after == before, (name, before, after)
        scroll = container._readout.native.parentWidget().parentWidget()
        assert isinstance(scroll, QScrollArea), name
        assert scroll.height() < container._readout.native.height(), name  # it scrolls
        assert container._readout.value.endswith("line 19: MTF 0.123 ± 0.004, NNPS 1.2e-05 ± 3e-07 mm², DQE 0.45 ± 0.02")
