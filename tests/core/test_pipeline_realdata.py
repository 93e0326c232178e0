"""The whole pipeline on real scintillator + camera frames (shared data)."""

import json

import numpy as np
import pytest

from napari_dslrxr.core.io import read_image
from napari_dslrxr.core.params import PipelineParams
from napari_dslrxr.core.files import run_file
from napari_dslrxr.core.pipeline import process_frame

pytestmark = pytest.mark.realdata


def _row_std(img, rows, cols):
    p = img[rows][:, cols].astype(np.float64).mean(axis=1)
    return p.std()


def test_savu_projection_banding_gone_in_attenuation_and_display(shared_data):
    folder = shared_data / "savu_projections"
    raw = read_image(folder / "raw_00000.tiff").data
    flat = read_image(folder / "flat_00001.tiff").data
    dark = read_image(folder / "dark_00001.tiff").data
    params = PipelineParams()
    params.flatfield.flat_smoothing_px = 0.0  # banding is fine structure of the flat
    params.region.enabled = False  # the whole frame is exposed
    rows, cols = slice(2, -2), np.r_[0:20, 140:160]
    with_flat = process_frame(raw, flats=[flat], darks=[dark], params=params, keep_intermediates=True)
    no_flat = process_frame(raw, darks=[dark], params=params, keep_intermediates=True)
    att_with, att_without = with_flat.intermediates["attenuation"], no_flat.intermediates["attenuation"]
    # in the log domain the banding is additive: its std drops >= 10x with the flat
    assert _row_std(att_without, rows, cols) > 10 * _row_std(att_with, rows, cols)
    assert _row_std(no_flat.display, rows, cols) > 3 * _row_std(with_flat.display, rows, cols)


def test_niqa_frame_through_run_file_with_flat_and_dark(shared_data, tmp_path):
    folder = shared_data / "niqa_edge"
    params = PipelineParams()
    params.flatfield.flat_smoothing_px = 0.0
    params.output.dicom = True
    written = run_file(folder / "edge20mm_0000.tif", tmp_path, params=params,
                       flat_paths=[folder / "ob.tif"], dark_paths=[folder / "dc.tif"])
    assert len(written) == 3
    side = json.loads((tmp_path / "edge20mm_0000_dslrxr.tif.json").read_text())
    assert side["results"]["flatfield"]["applied"] and len(side["inputs"]) == 3
    out = read_image(tmp_path / "edge20mm_0000_dslrxr.tif").data.astype(np.float64) / 65535
    # the Gd edge plate attenuates: it must be brighter (bone-white polarity) than the open beam
    assert out[250:350, 250:350].mean() > out[250:350, 5:45].mean() + 0.2
