"""The npe2 writers: an image layer saved as DICOM DX or 16-bit TIFF, reopened with the same pixels.

Saved through napari's own path (``viewer.layers.save``), reopened with pydicom / tifffile
directly (not the package's reader), and the JSON sidecar checked field by field.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from robustness import synthetic_files

from napari_dslrxr import __version__
from napari_dslrxr.core.io import file_sha256

pytestmark = pytest.mark.gui


def _sidecar(path) -> dict:
    return json.loads(path.with_name(path.name + ".json").read_text())


@pytest.fixture
def viewer(make_napari_viewer):
    return make_napari_viewer()


def test_dicom_from_a_reader_layer_reopens_with_the_same_pixels(viewer, tmp_path):
    pydicom = pytest.importorskip("pydicom")
    grey = (np.arange(48 * 64, dtype=np.uint32).reshape(48, 64) % 4096).astype(np.uint16)
    source = tmp_path / "cr.dcm"
    synthetic_files.write_dicom(source, grey, photometric="MONOCHROME1", bits_stored=12,
                                pixel_spacing_mm=(0.15, 0.15))
    viewer.open(str(source), plugin="napari-dslrxr")
    layer = viewer.layers["cr"]
    out = tmp_path / "saved.dcm"
    viewer.layers.selection = {layer}
    # no plugin named: napari finds the only writer for .dcm, this plugin's
    written = viewer.layers.save(str(out), selected=True)
    assert [str(p) for p in written] == [str(out)]
    ds = pydicom.dcmread(out)
    np.testing.assert_array_equal(ds.pixel_array, layer.data)  # the pixels shown, bit for bit
    np.testing.assert_array_equal(ds.pixel_array, 4095 - grey)  # MONOCHROME1 read bright = bright
    assert ds.Modality == "DX" and ds.PhotometricInterpretation == "MONOCHROME2"
    assert [float(v) for v in ds.ImagerPixelSpacing] == [0.15, 0.15]
    side = _sidecar(out)
    assert side["version"] == __version__ and side["stage"] == "napari-save"
    assert side["inputs"] == [{"path": str(source), "bytes": source.stat().st_size, "sha256": file_sha256(source)}]
    assert side["output"]["sha256"] == file_sha256(out)
    assert set(side["parameters"]) >= {"input", "impulse", "flatfield", "region", "contrast", "output"}
    results = side["results"]
    assert results["value_mapping"]["kind"] == "unchanged (uint16)"
    assert results["source"]["format"] == "dicom" and results["source"]["input_kind"]["kind"] == "display"
    assert source.read_bytes() != out.read_bytes()  # the source was not touched


def test_float_result_and_tuned_parameters_go_into_dicom_and_tiff(viewer, tmp_path):
    pydicom = pytest.importorskip("pydicom")
    import tifffile

    from napari_dslrxr._widgets.contrast import ContrastWidget

    widget = ContrastWidget(viewer)
    viewer.window.add_dock_widget(widget)
    widget._live.value = False
    slider = next(s for (section, name), s in widget._sliders.items() if name == "bone_contrast")
    slider.value = 2.2
    rng = np.random.default_rng(4)
    result = rng.random((40, 56)).astype(np.float32) * 1.2 - 0.1  # a display result, partly out of range
    layer = viewer.add_image(result, name="chest contrast", contrast_limits=(0.0, 1.0))
    viewer.layers.selection = {layer}
    dcm = tmp_path / "tuned.dcm"
    tif = tmp_path / "tuned.tif"
    viewer.layers.save(str(dcm), selected=True, plugin="napari-dslrxr")
    viewer.layers.save(str(tif), selected=True, plugin="napari-dslrxr")
    # independent expectation: the contrast limits [0, 1] onto 0..65535, clipped and rounded
    expected = np.floor(np.clip(result.astype(np.float64), 0, 1) * 65535 + 0.5).astype(np.uint16)
    np.testing.assert_array_equal(pydicom.dcmread(dcm).pixel_array, expected)
    with tifffile.TiffFile(tif) as tf:
        assert tf.pages[0].dtype == np.uint16
        np.testing.assert_array_equal(tf.asarray(), expected)
    for path in (dcm, tif):
        side = _sidecar(path)
        assert side["parameters"]["contrast"]["bone_contrast"] == pytest.approx(2.2)
        assert side["results"]["value_mapping"] == {"kind": "contrast limits to 0..65535",
                                                    "contrast_limits": [0.0, 1.0]}
        assert side["inputs"] == [] and "no source file" in side["results"]["source"]["source"]


def test_colour_layer_to_dicom_is_refused_and_leaves_no_file(viewer, tmp_path):
    layer = viewer.add_image(np.zeros((32, 32, 3), np.uint16), rgb=True, name="colour")
    viewer.layers.selection = {layer}
    out = tmp_path / "colour.dcm"
    with pytest.raises(Exception, match="colour"):
        viewer.layers.save(str(out), selected=True, plugin="napari-dslrxr")
    assert not out.exists() and not out.with_name("colour.dcm.json").exists()
    # as TIFF the colour layer is fine (16-bit RGB)
    viewer.layers.save(str(tmp_path / "colour.tif"), selected=True, plugin="napari-dslrxr")
    assert (tmp_path / "colour.tif.json").exists()


@pytest.mark.realdata
def test_real_cr_dicom_round_trip(viewer, shared_data, tmp_path):
    pydicom = pytest.importorskip("pydicom")
    source = shared_data / "cr_dicom" / "RG3_UNCR.dcm"
    if not source.is_file():
        pytest.skip(f"{source} is absent")
    (layer,) = viewer.open(str(source), plugin="napari-dslrxr")
    viewer.layers.selection = {layer}
    out = tmp_path / "leg.dcm"
    viewer.layers.save(str(out), selected=True)
    original = pydicom.dcmread(source)
    top = (1 << int(original.BitsStored)) - 1
    # MONOCHROME1 inverted once on reading; saved as MONOCHROME2 with the same (bone-bright) values
    np.testing.assert_array_equal(pydicom.dcmread(out).pixel_array, top - original.pixel_array)
    assert _sidecar(out)["inputs"][0]["sha256"] == file_sha256(source)


def test_saved_dicom_reads_back_as_the_kind_it_was(viewer, tmp_path):
    """A camera frame saved as DICOM is marked linear (LIN) and reads back as a camera frame."""
    from napari_dslrxr.core.io.input_kind import input_kind_of
    from napari_dslrxr.core.io import read_image, write_tiff

    counts = (np.arange(40 * 60, dtype=np.uint32).reshape(40, 60) % 3000 + 200).astype(np.uint16)
    (frame,) = viewer.open(str(write_tiff(tmp_path / "counts.tif", counts)), plugin="napari-dslrxr")
    assert frame.metadata["input_kind"]["kind"] == "camera"
    result = viewer.add_image(np.linspace(0, 1, 40 * 60, dtype=np.float32).reshape(40, 60), name="result",
                              contrast_limits=(0.0, 1.0))
    kinds = {}
    for layer in (frame, result):
        viewer.layers.selection = {layer}
        out = tmp_path / f"{layer.name}.dcm"
        viewer.layers.save(str(out), selected=True)
        kinds[layer.name] = input_kind_of(read_image(out))
        assert _sidecar(out)["results"]["pixel_intensity_relationship"] == (
            "LIN" if layer is frame else "LOG")
        tif = tmp_path / f"{layer.name}_saved.tif"
        viewer.layers.save(str(tif), selected=True, plugin="napari-dslrxr")
        kinds[f"{layer.name} tif"] = input_kind_of(read_image(tif))
    for name in ("counts", "counts tif"):
        assert kinds[name].kind == "camera" and kinds[name].certain, kinds[name]
    for name in ("result", "result tif"):
        assert kinds[name].kind == "display" and kinds[name].certain, kinds[name]
    np.testing.assert_array_equal(read_image(tmp_path / "counts.dcm").data, counts)
