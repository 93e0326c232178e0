"""The input-kind rule: camera frame (linear light) or display radiograph (bone bright)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from napari_dslrxr.core.errors import ParameterError
from napari_dslrxr.core.io.input_kind import CAMERA, DISPLAY, decide_input_kind, input_kind_of
from napari_dslrxr.core.io import read_image, write_png, write_tiff
from napari_dslrxr.core.params import PipelineParams, load_params
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph


def _dicom_meta(modality="CR", photometric="MONOCHROME1", relationship=None):
    meta = {"modality": modality, "photometric_original": photometric, "bits_stored": 12}
    if relationship:
        meta["pixel_intensity_relationship"] = relationship
    return meta


@pytest.mark.parametrize("modality", ["CR", "DX", "MG"])
@pytest.mark.parametrize("photometric", ["MONOCHROME1", "MONOCHROME2"])
def test_projection_radiograph_dicom_is_display_whatever_the_parameter(modality, photometric):
    for requested in ("auto", "display", "camera"):
        kind = decide_input_kind("dicom", _dicom_meta(modality, photometric), None, requested)
        assert kind.kind == DISPLAY and kind.certain
        assert modality in kind.evidence and photometric in kind.evidence
        # An explicit "camera" is overruled by the header, and the user is told.
        assert kind.overridden == (requested == "camera")
        assert (kind.message() is not None) == (requested == "camera")


def test_linear_dicom_and_camera_raw_are_camera_frames():
    lin = decide_input_kind("dicom", _dicom_meta("DX", "MONOCHROME2", "LIN"))
    assert lin.kind == CAMERA and lin.certain and "LIN" in lin.evidence
    raw = decide_input_kind("raw", {}, np.zeros((16, 16, 3), np.uint16), "display")
    assert raw.kind == CAMERA and raw.overridden and "display" in raw.message()


def test_other_dicom_modality_follows_the_parameter_or_the_evidence():
    meta = _dicom_meta("OT", "MONOCHROME2")
    assert decide_input_kind("dicom", meta, None, "display").kind == DISPLAY
    assert decide_input_kind("dicom", meta, None, "camera").kind == CAMERA
    guess = decide_input_kind("dicom", meta, np.zeros((16, 16), np.uint16))
    assert guess.kind == DISPLAY and not guess.certain and "OT" in guess.evidence


def test_parameter_decides_for_tiff_and_png():
    grey16 = np.zeros((16, 16), np.uint16)
    for requested in (CAMERA, DISPLAY):
        kind = decide_input_kind("tiff", {}, grey16, requested)
        assert kind.kind == requested and kind.certain and kind.message() is None


def test_auto_on_tiff_png_is_certain_only_with_evidence(tmp_path):
    tinted = make_dslr_radiograph((96, 128), seed=2).raw_rgb  # a scintillator photo: green tint
    camera = input_kind_of(read_image(write_tiff(tmp_path / "frame.tif", tinted)))
    assert camera.kind == CAMERA and camera.certain and "tint" in camera.evidence
    assert camera.message() is None

    grey16 = input_kind_of(read_image(write_tiff(tmp_path / "grey.tif", tinted[..., 1])))
    assert grey16.kind == CAMERA and not grey16.certain
    line = grey16.message()
    assert "not certain" in line and 'input_kind = "display"' in line and "\n" not in line

    grey8 = (tinted[..., 1] >> 8).astype(np.uint8)
    display = input_kind_of(read_image(write_png(tmp_path / "grey.png", grey8)))
    assert display.kind == DISPLAY and not display.certain and "8-bit" in display.evidence
    # grey stored as RGB is no evidence of a camera frame
    as_rgb = decide_input_kind("png", {}, np.repeat(grey8[..., None], 3, axis=2))
    assert as_rgb.kind == DISPLAY and not as_rgb.certain


def test_own_run_output_is_a_display_radiograph(tmp_path):
    description = json.dumps({"software": "napari-dslrxr", "version": "0", "stage": "run"})
    path = write_tiff(tmp_path / "out.tif", np.zeros((16, 16), np.uint16), description=description)
    kind = input_kind_of(read_image(path))
    assert kind.kind == DISPLAY and kind.certain


def test_parameter_file_section_and_validation(tmp_path):
    assert PipelineParams().input.input_kind == "auto"
    cfg = tmp_path / "p.toml"
    cfg.write_text('[input]\ninput_kind = "display"\n')
    assert load_params(cfg).input.input_kind == "display"
    cfg.write_text('[input]\ninput_kind = "displya"\n')
    with pytest.raises(ParameterError, match="did you mean 'display'"):
        load_params(cfg)
    with pytest.raises(ParameterError):
        decide_input_kind("tiff", {}, None, "xray")


def test_record_round_trip():
    kind = decide_input_kind("dicom", _dicom_meta())
    assert type(kind).from_record(kind.as_record()) == kind


def test_an_unknown_requested_kind_is_refused_as_in_the_parameter_file():
    with pytest.raises(ParameterError, match=r"input\.input_kind: must be one of auto, camera, display, "
                                             r"got 'dispaly'; did you mean 'display'\?"):
        decide_input_kind("tiff", {}, None, requested="dispaly")
