"""The napari readers: claims by extension, never raises, reads raw/TIFF/DICOM, bad files notify."""

from __future__ import annotations

import numpy as np
import pytest
from robustness import synthetic_files

from napari_dslrxr import _reader
from napari_dslrxr._reader import CLAIMED_EXTENSIONS, get_reader, read_cfa_planes, read_radiographs
from napari_dslrxr.core.io import write_tiff

BLACK_COUNTS = 256
WHITE_COUNTS = 4095


def write_dng(path, mosaic: np.ndarray) -> None:
    """Write an RGGB 12-bit DNG (black 256, white 4095) from a uint16 Bayer mosaic."""
    synthetic_files.write_dng(path, mosaic, black_counts=BLACK_COUNTS, white_counts=WHITE_COUNTS, bits=12)


@pytest.fixture
def dng_file(tmp_path, rng):
    mosaic = (BLACK_COUNTS + rng.integers(0, 3000, (64, 96))).astype(np.uint16)
    path = tmp_path / "frame.dng"
    write_dng(path, mosaic)
    return path, mosaic


@pytest.mark.parametrize("name", ["a.CR2", "b.nef", "c.dng", "d.arw", "e.dcm", "f.tif", "g.TIFF"])
def test_get_reader_claims_radiograph_and_raw_extensions(name):
    assert get_reader(name) is read_radiographs
    assert get_reader([name, name]) is read_radiographs


@pytest.mark.parametrize("path", ["a.png", "b.txt", "no_extension", "", [], ["a.tif", "b.png"], None, 3, {"a": 1}])
def test_get_reader_returns_none_when_not_claimed_and_never_raises(path):
    assert get_reader(path) is None


@pytest.mark.parametrize("name", sorted(f"file{ext}" for ext in CLAIMED_EXTENSIONS) + ["FILE.CR2", "x.NEF"])
def test_exactly_one_reader_of_this_plugin_per_extension(name):
    """npe2's reader resolution offers one reader of this plugin (two would make napari ask)."""
    from npe2 import PluginManager

    manager = PluginManager.instance()
    manager.discover()
    ours = [r.command for r in manager.iter_compatible_readers([name]) if r.plugin_name == "napari-dslrxr"]
    assert ours == ["napari-dslrxr.get_reader"]


def test_raw_opens_as_linear_rgb(tmp_path, rng):
    signal = rng.integers(100, 1800, (64, 96))
    write_dng(tmp_path / "once.dng", (BLACK_COUNTS + signal).astype(np.uint16))
    write_dng(tmp_path / "twice.dng", (BLACK_COUNTS + 2 * signal).astype(np.uint16))
    (once,) = read_radiographs(str(tmp_path / "once.dng"))
    (twice,) = read_radiographs([str(tmp_path / "twice.dng")])
    data, kwargs, layer_type = once
    assert layer_type == "image" and kwargs["rgb"] is True
    assert data.shape == (64, 96, 3) and data.dtype == np.uint16
    assert kwargs["name"] == "once" and kwargs["metadata"]["format"] == "raw"
    # Linear (gamma 1) and black-subtracted: twice the counts above black gives twice the
    # value (a gamma-2.2 rendering would give about 1.37 times).
    ratio = twice[0].astype(float).mean() / data.astype(float).mean()
    assert ratio == pytest.approx(2.0, rel=0.03)


def test_cfa_planes_are_the_mosaic_minus_black_and_overlay_the_rgb(dng_file):
    path, mosaic = dng_file
    layers = read_cfa_planes([str(path)])
    assert [kw["name"] for _, kw, _ in layers] == ["frame R", "frame G1", "frame G2", "frame B"]
    offsets = {"R": (0, 0), "G1": (0, 1), "G2": (1, 0), "B": (1, 1)}
    for data, kwargs, layer_type in layers:
        name = kwargs["metadata"]["cfa_plane"]
        r, c = offsets[name]
        assert layer_type == "image" and data.dtype == np.float32 and data.shape == (32, 48)
        np.testing.assert_array_equal(data, mosaic[r::2, c::2].astype(np.float32) - BLACK_COUNTS)
        assert kwargs["scale"] == (2.0, 2.0) and kwargs["translate"] == (float(r), float(c))
        assert kwargs["metadata"]["white_level"] == WHITE_COUNTS


def test_tiff_and_dicom_radiographs(tmp_path, rng):
    grey = rng.integers(0, 4000, (40, 50)).astype(np.uint16)
    tif = write_tiff(tmp_path / "radiograph.tif", grey)
    ((data, kwargs, kind),) = read_radiographs(str(tif))
    np.testing.assert_array_equal(data, grey)
    assert kind == "image" and "rgb" not in kwargs

    synthetic_files.write_dicom(tmp_path / "r.dcm", grey, photometric="MONOCHROME1", bits_stored=12,
                                pixel_spacing_mm=(0.15, 0.2))
    ((data, kwargs, _),) = read_radiographs(str(tmp_path / "r.dcm"))
    np.testing.assert_array_equal(data, 4095 - grey)  # MONOCHROME1 shown as bright = bright
    assert kwargs["scale"] == (0.15, 0.2)


def test_bad_file_becomes_a_notification_not_an_exception(tmp_path, monkeypatch):
    shown = []
    monkeypatch.setattr(_reader, "_notify_error", shown.append)
    bad = tmp_path / "broken.tif"
    bad.write_bytes(b"II*\x00" + b"\x00" * 20)
    good = write_tiff(tmp_path / "good.tif", np.full((16, 16), 7, np.uint16))
    layers = read_radiographs([str(bad), str(good)])
    assert [kw["name"] for _, kw, _ in layers] == ["good"]
    assert len(shown) == 1 and "broken.tif" in shown[0]
    # Nothing readable: claimed, nothing added (napari's null-layer sentinel), still no raise.
    assert read_radiographs(str(bad)) == [(None,)]
    assert read_cfa_planes(str(tmp_path / "missing.nef")) == [(None,)]
    assert len(shown) == 3


def test_layers_carry_the_input_kind(tmp_path, dng_file):
    path, _ = dng_file
    ((_, raw_kwargs, _),) = read_radiographs(str(path))
    assert raw_kwargs["metadata"]["input_kind"]["kind"] == "camera"
    grey = np.arange(40 * 50, dtype=np.uint16).reshape(40, 50)
    synthetic_files.write_dicom(tmp_path / "cr.dcm", grey, photometric="MONOCHROME1", bits_stored=12)
    ((_, dicom_kwargs, _),) = read_radiographs(str(tmp_path / "cr.dcm"))
    kind = dicom_kwargs["metadata"]["input_kind"]
    assert kind["kind"] == "display" and kind["certain"] and "MONOCHROME1" in kind["evidence"]


def _menu_action(viewer, *titles: str):
    """The QAction reached by following menu titles from the menu bar (ampersands and the
    plugin name napari appends to plugin actions ignored)."""
    menu = viewer.window._qt_window.menuBar()
    for i, title in enumerate(titles):
        matches = [a for a in menu.actions()
                   if a.text().replace("&", "").removesuffix(" (DSLR Radiography)") == title]
        assert matches, (title, [a.text() for a in menu.actions()])
        if i == len(titles) - 1:
            return matches[0]
        menu = matches[0].menu()


@pytest.mark.gui
def test_bayer_planes_from_the_layers_menu(make_napari_viewer, dng_file, monkeypatch):
    path, _ = dng_file
    viewer = make_napari_viewer()
    shown = []
    monkeypatch.setattr(_reader, "_notify_error", shown.append)
    action = _menu_action(viewer, "Layers", "Data", "Show Bayer (CFA) planes of the selected raw layer")
    viewer.add_image(np.zeros((16, 16)), name="not raw")
    action.trigger()  # a layer made in napari: refused with a message, nothing added
    assert len(shown) == 1 and "'not raw' was not opened from a camera raw file" in shown[0]
    viewer.layers.clear()
    viewer.open(str(path), plugin="napari-dslrxr")
    assert [layer.name for layer in viewer.layers] == ["frame"] and viewer.layers["frame"].rgb
    viewer.layers.selection.active = viewer.layers["frame"]
    action.trigger()
    assert [layer.name for layer in viewer.layers][1:] == ["frame R", "frame G1", "frame G2", "frame B"]
    # The planes overlay the RGB: plane pixel (0, 0) of B sits at mosaic pixel (1, 1).
    assert tuple(viewer.layers["frame B"].data_to_world((0, 0))) == (1.0, 1.0)
    assert len(shown) == 1


@pytest.mark.gui
def test_bayer_planes_from_the_file_menu(make_napari_viewer, dng_file, monkeypatch):
    from qtpy.QtWidgets import QFileDialog

    path, _ = dng_file
    viewer = make_napari_viewer()
    asked = []

    def choose(parent, caption, folder, filters):
        asked.append(filters)
        return [str(path)], filters

    monkeypatch.setattr(QFileDialog, "getOpenFileNames", staticmethod(choose))
    _menu_action(viewer, "File", "IO Utilities", "Open camera raw as Bayer (CFA) planes...").trigger()
    assert [layer.name for layer in viewer.layers] == ["frame R", "frame G1", "frame G2", "frame B"]
    assert "*.cr2" in asked[0] and "*.nef" in asked[0] and "*.dng" in asked[0]


@pytest.mark.gui
def test_dropped_files_open_without_a_reader_dialog(make_napari_viewer, tmp_path, dng_file, monkeypatch):
    """As ``dslrxr view`` sets napari up, opening .tif/.dcm/raw by drop or File > Open asks nothing."""
    from napari._qt import qt_viewer as qt_viewer_module
    from napari.plugins.utils import get_preferred_reader
    from napari.settings import get_settings

    from napari_dslrxr._cli.view import prefer_plugin_reader, restore_reader_preferences

    viewer = make_napari_viewer()
    dialogs = []
    monkeypatch.setattr(qt_viewer_module, "handle_gui_reading", lambda paths, *a, **k: dialogs.append(list(paths)))
    grey = np.arange(40 * 50, dtype=np.uint16).reshape(40, 50)
    tif = write_tiff(tmp_path / "plain.tif", grey)
    synthetic_files.write_dicom(tmp_path / "cr.dcm", grey, photometric="MONOCHROME1", bits_stored=12)
    get_settings().plugins.extension2reader = {"*.tiff": "napari"}  # a choice the user made
    # Without the preference napari's own reader competes for every one of these files.
    viewer.window._qt_viewer._qt_open([str(tif)], stack=False)
    assert len(dialogs) == 1 and len(viewer.layers) == 0
    added = prefer_plugin_reader()
    for name in ("a.tif", "b.dcm", "c.cr2", "d.nef", "e.dng", "F.CR2"):
        assert get_preferred_reader(tmp_path / name) == "napari-dslrxr", name
    assert get_preferred_reader(tmp_path / "x.tiff") == "napari"  # the user's choice is kept
    paths = [tif, tmp_path / "cr.dcm", dng_file[0]]
    for path in paths:
        viewer.window._qt_viewer._qt_open([str(path)], stack=False)
    assert len(dialogs) == 1, "a reader dialog was shown"
    assert [layer.name for layer in viewer.layers] == ["plain", "cr", "frame"]
    assert viewer.layers["cr"].metadata["input_kind"]["kind"] == "display"
    restore_reader_preferences(added)
    assert get_settings().plugins.extension2reader == {"*.tiff": "napari"}


@pytest.mark.gui
def test_viewer_survives_a_corrupt_file(make_napari_viewer, tmp_path):
    bad = tmp_path / "corrupt.dng"
    bad.write_bytes(b"not a raw file at all" * 10)
    viewer = make_napari_viewer()
    viewer.open(str(bad), plugin="napari-dslrxr")
    assert len(viewer.layers) == 0


@pytest.mark.gui
def test_view_cfa_planes_option_shows_the_planes(make_napari_viewer, dng_file):
    from napari_dslrxr._cli.view import populate_viewer

    path, mosaic = dng_file
    viewer = make_napari_viewer()
    populate_viewer(viewer, [path], cfa_planes=True, widgets=[])
    assert [layer.name for layer in viewer.layers] == ["frame R", "frame G1", "frame G2", "frame B"]
    np.testing.assert_array_equal(viewer.layers["frame B"].data, mosaic[1::2, 1::2].astype(np.float32) - BLACK_COUNTS)
