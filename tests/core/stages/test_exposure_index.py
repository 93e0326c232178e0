"""Value of interest, exposure index record and DICOM attributes (IEC 62494-1) on known arrays."""

from __future__ import annotations

import math

import numpy as np
import pytest

from napari_dslrxr.core.errors import ParameterError
from napari_dslrxr.core.params import load_params
from napari_dslrxr.core.stages.exposure_index import (ExposureParams, dicom_exposure_tags, exposure_index_record,
                                                      value_of_interest)


def _object_in_open_beam(rng, shape=(200, 300)):
    """Open beam (1000 counts) around a block whose transmission ramps from 0.1 to 0.4."""
    h, w = shape
    linear = np.full(shape, 1000.0)
    block = np.zeros(shape, bool)
    block[40:160, 60:240] = True
    linear[block] = 1000.0 * np.tile(np.linspace(0.1, 0.4, 180), (120, 1)).ravel()
    return linear * rng.normal(1.0, 0.01, shape), block


def test_anatomy_region_leaves_the_open_beam_out(rng):
    linear, block = _object_in_open_beam(rng)
    anatomy = value_of_interest(linear, None, "anatomy")
    assert anatomy["region"] == "anatomy" and "region_note" not in anatomy
    assert anatomy["value_dn"] == pytest.approx(np.median(linear[block]), rel=0.01)  # about 250
    assert anatomy["region_fraction"] == pytest.approx(block.mean(), abs=0.01)
    whole = value_of_interest(linear, None, "field")
    assert whole["value_dn"] == pytest.approx(np.median(linear), rel=1e-9)  # open beam dominates: about 1000
    centre = value_of_interest(linear, None, "centre")
    assert centre["value_dn"] == pytest.approx(np.median(linear[67:133, 100:200]), rel=1e-9)


def test_field_mask_limits_every_region(rng):
    linear, block = _object_in_open_beam(rng)
    field = np.zeros_like(block)
    field[:, :150] = True  # the left half: the block's low-transmission half and the open beam
    result = value_of_interest(linear, field, "anatomy")
    assert result["value_dn"] == pytest.approx(np.median(linear[block & field]), rel=0.01)


def test_uniform_field_has_no_background_and_tiny_regions_fall_back(rng):
    flat = rng.normal(500.0, 5.0, (100, 100))
    result = value_of_interest(flat, None, "anatomy")
    assert "no direct-exposure background" in result["region_note"]
    assert result["value_dn"] == pytest.approx(500.0, rel=0.01)
    field = np.zeros((100, 100), bool)
    field[:6, :6] = True  # its middle third is 2 x 2 pixels
    small = value_of_interest(flat, field, "centre")
    assert small["region"] == "field" and "fewer than" in small["region_note"]
    assert small["value_dn"] == pytest.approx(np.median(flat[field]), rel=1e-9)


def test_record_when_calibrated_and_not(rng):
    linear, _ = _object_in_open_beam(rng)
    record = exposure_index_record(linear, None, ExposureParams(calibration_dn_per_ugy=50.0, target_ei=400.0))
    k_cal = record["value_of_interest_dn"] / 50.0
    assert record["computed"] and record["exposure_index"] == pytest.approx(100 * k_cal, rel=1e-4)
    assert record["deviation_index"] == pytest.approx(10 * math.log10(100 * k_cal / 400.0), abs=1e-3)
    tags = dicom_exposure_tags(record)
    assert set(tags) == {"ExposureIndex", "TargetExposureIndex", "DeviationIndex"}
    assert all(len(v) <= 16 for v in tags.values()) and float(tags["TargetExposureIndex"]) == 400.0
    plain = exposure_index_record(linear, None, ExposureParams())
    assert not plain["computed"] and "not calibrated" in plain["reason"] and dicom_exposure_tags(plain) == {}
    dark = exposure_index_record(np.zeros((50, 50)), None, ExposureParams(calibration_dn_per_ugy=50.0))
    assert not dark["computed"] and "no signal" in dark["reason"]


def test_exposure_section_is_checked_like_every_section(tmp_path):
    path = tmp_path / "p.toml"
    path.write_text("[exposure]\ncalibration_dn_per_ugy = -3.0\n")
    with pytest.raises(ParameterError, match=r"exposure\.calibration_dn_per_ugy"):
        load_params(path)
    path.write_text("[exposure]\nregion = \"anatomie\"\n")
    with pytest.raises(ParameterError, match="did you mean 'anatomy'"):
        load_params(path)


def test_anatomy_found_at_a_few_hundred_quanta_per_pixel(rng):
    """A rod of soft tissue (thickness falling to 0 at its rim) with a dense core at 150 quanta per
    pixel of open beam: the photon noise fills the histogram valley between the open beam and the
    rod unless the split is made on filtered values."""
    shape = (200, 300)
    x = np.arange(shape[1]) - shape[1] / 2
    chord = 2 * np.sqrt(np.clip(90.0 ** 2 - x ** 2, 0, None))  # rod of radius 90 px along the rows
    attenuation = 0.01 * chord + 1.0 * (np.abs(x) < 20)
    transmission = np.broadcast_to(np.exp(-attenuation), shape)
    inside = np.broadcast_to(chord > 0, shape)
    linear = 2.0 * rng.poisson(150.0 * transmission) + rng.normal(0.0, 2.0, shape)
    result = value_of_interest(linear, None, "anatomy")
    assert "region_note" not in result
    assert result["region_fraction"] == pytest.approx(inside.mean(), abs=0.03)
    assert result["value_dn"] == pytest.approx(np.median(linear[inside]), rel=0.03)
