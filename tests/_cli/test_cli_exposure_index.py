"""Exposure index and deviation index (IEC 62494-1) of ``dslrxr run``, read from its sidecar and DICOM.

The frames come from generators written here, not from the project's phantom: an analytic
object (a soft-tissue ellipse with a bone rod in an open beam) and a real computed radiograph
(the NEMA lower leg) turned into a transmission map. Each is exposed at air kerma K and 2 K,
with Poisson quanta, a camera gain in counts per quantum, a dark offset and read noise; the
calibration given to the run is the generator's counts per µGy, so EI must be 100 x the air
kerma behind the anatomy whatever the gain.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from napari_dslrxr.core.io import write_tiff

QUANTA_PER_UGY = 300.0  # detected quanta per pixel per µGy (RQA5-like)
DARK_OFFSET = 100.0
READ_NOISE = 2.0


def _dslrxr(*args) -> None:
    proc = subprocess.run([sys.executable, "-m", "napari_dslrxr.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"dslrxr {' '.join(map(str, args))} exited {proc.returncode}: {proc.stderr}"


def expose(transmission: np.ndarray, k_ugy: float, counts_per_quantum: float,
            rng: np.random.Generator) -> np.ndarray:
    quanta = rng.poisson(QUANTA_PER_UGY * k_ugy * transmission)
    counts = counts_per_quantum * quanta + DARK_OFFSET + rng.normal(0.0, READ_NOISE, transmission.shape)
    return np.clip(np.round(counts), 0, 65535).astype(np.uint16)


def dark_frame(shape, rng) -> np.ndarray:
    return np.round(DARK_OFFSET + rng.normal(0.0, READ_NOISE, shape)).astype(np.uint16)


def analytic_object(shape=(240, 320)) -> tuple[np.ndarray, np.ndarray]:
    """Transmission of a 6 cm soft-tissue ellipse with a bone rod in an open beam, and the object's mask."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w]
    r2 = ((x - w / 2) / (0.33 * w)) ** 2 + ((y - h / 2) / (0.42 * h)) ** 2
    tissue_mm = np.where(r2 < 1, 60.0 * np.sqrt(np.clip(1 - r2, 0, 1)), 0.0)
    bone = ((x - w / 2) / (0.07 * w)) ** 2 + ((y - h / 2) / (0.38 * h)) ** 2 < 1
    return np.exp(-(0.02 * tissue_mm + 0.8 * bone)), r2 < 1


def _config(folder: Path, name: str, text: str) -> Path:
    path = folder / f"{name}.toml"
    path.write_text(text, encoding="utf-8")
    return path


def _exposure_record(out: Path, stem: str, ext: str = "tif") -> dict:
    side = json.loads((out / f"{stem}_dslrxr.{ext}.json").read_text(encoding="utf-8"))
    return side["results"]["exposure_index"]


def _run_exposures(folder: Path, transmission: np.ndarray, *, counts_per_quantum: float, k_ugy: float,
                   rng: np.random.Generator, extra_toml: str = "", flat_illumination=None) -> dict[float, dict]:
    """Expose at K and 2 K, run them in one process with the matching calibration; return the records."""
    tag = f"g{counts_per_quantum:g}"
    illumination = 1.0 if flat_illumination is None else flat_illumination
    inputs = []
    for k in (k_ugy, 2 * k_ugy):
        inputs.append(write_tiff(folder / f"frame_{tag}_{k:g}.tif",
                                 expose(transmission * illumination, k, counts_per_quantum, rng)))
    dark = write_tiff(folder / f"dark_{tag}.tif", dark_frame(transmission.shape, rng))
    refs = ["--dark", dark]
    if flat_illumination is not None:
        refs += ["--flat", write_tiff(folder / f"flat_{tag}.tif",
                                      expose(np.broadcast_to(illumination, transmission.shape), 20.0,
                                              counts_per_quantum, rng))]
    config = _config(folder, tag, f"[exposure]\ncalibration_dn_per_ugy = {QUANTA_PER_UGY * counts_per_quantum}\n"
                                  f"{extra_toml}")
    out = folder / f"out_{tag}"
    _dslrxr("run", *inputs, *refs, "-c", config, "--dicom", "-o", out)
    return {k: _exposure_record(out, f"frame_{tag}_{k:g}") for k in (k_ugy, 2 * k_ugy)}


def test_ei_is_100_times_the_air_kerma_behind_the_object_and_doubles_with_it(tmp_path, rng):
    transmission, inside = analytic_object()
    k_ugy = 2.0
    expected = {k: 100.0 * k * float(np.median(transmission[inside])) for k in (k_ugy, 2 * k_ugy)}
    by_gain = {g: _run_exposures(tmp_path, transmission, counts_per_quantum=g, k_ugy=k_ugy, rng=rng)
               for g in (1.5, 4.0)}
    for gain, records in by_gain.items():
        for k, record in records.items():
            assert record["computed"] and record["region"] == "anatomy", record
            # the region is the object (the direct beam around it left out): its area, and EI = 100 K T_median
            assert record["region_fraction"] == pytest.approx(inside.mean(), abs=0.02)
            assert record["exposure_index"] == pytest.approx(expected[k], rel=0.03), (gain, k, record)
        ratio = records[2 * k_ugy]["exposure_index"] / records[k_ugy]["exposure_index"]
        assert ratio == pytest.approx(2.0, rel=0.05), (gain, ratio)
    # the calibration absorbs the camera gain: the same exposure gives the same EI at either gain
    assert by_gain[1.5][k_ugy]["exposure_index"] == pytest.approx(by_gain[4.0][k_ugy]["exposure_index"], rel=0.03)


def leg_transmission_map(data_dir: Path) -> np.ndarray:
    """The NEMA computed radiograph of a lower leg (MONOCHROME1, log-exposure values) as a 400 x 400
    transmission map: 3 e-folds of attenuation over its 1-99.5 % range, collimator bands darker still."""
    import cv2
    import pydicom

    values = pydicom.dcmread(data_dir / "cr_dicom" / "RG3_UNCR.dcm").pixel_array.astype(np.float64)
    values = cv2.resize(values, (400, 400), interpolation=cv2.INTER_AREA)
    lo, hi = np.percentile(values, [1, 99.5])
    return np.exp(-3.0 * np.clip((hi - values) / (hi - lo), 0.0, 1.2))


def leg_shaft_median(transmission: np.ndarray) -> float:
    """Median transmission of the leg's shaft: columns 140-240 of 400, between the direct-beam strips
    along its whole length (chosen by eye on the image)."""
    return float(np.median(transmission[:, 140:240]))


def vignetting_of(shape) -> np.ndarray:
    h, w = shape
    y, x = np.mgrid[0:h, 0:w]
    return 1.0 - 0.15 * (((x - w / 2) / (w / 2)) ** 2 + ((y - h / 2) / (h / 2)) ** 2)


@pytest.fixture(scope="module")
def leg_transmission(shared_data):
    return leg_transmission_map(shared_data)


def test_ei_doubles_with_air_kerma_on_real_anatomy_with_flat_field(tmp_path, rng, leg_transmission):
    vignetting = vignetting_of(leg_transmission.shape)
    for gain in (1.0, 3.0):
        records = _run_exposures(tmp_path, leg_transmission, counts_per_quantum=gain, k_ugy=3.0, rng=rng,
                                 flat_illumination=vignetting)
        low, high = records[3.0], records[6.0]
        assert low["computed"] and high["computed"]
        assert high["exposure_index"] / low["exposure_index"] == pytest.approx(2.0, rel=0.05), (gain, records)
        # the anatomy (leg) lies between the direct-beam strips and the collimator bands: not the whole frame
        assert 0.1 < low["region_fraction"] < 0.5, low
        # reference: the shaft's median transmission times the flat's mean level, which the flat field keeps
        reference = 100.0 * 3.0 * float(vignetting.mean()) * leg_shaft_median(leg_transmission)
        assert low["exposure_index"] == pytest.approx(reference, rel=0.15), (low, reference)


def test_di_is_zero_at_the_target_and_dicom_carries_the_three_tags(tmp_path, rng):
    import pydicom
    from pydicom.datadict import dictionary_VR, tag_for_keyword

    # a flat exposure of 2.5 µGy measured over the whole field: EI = 250 = the target
    shape = (160, 200)
    frame = write_tiff(tmp_path / "flat_exposure.tif", expose(np.ones(shape), 2.5, 2.0, rng))
    dark = write_tiff(tmp_path / "dark.tif", dark_frame(shape, rng))
    config = _config(tmp_path, "target", f"[exposure]\ncalibration_dn_per_ugy = {QUANTA_PER_UGY * 2.0}\n"
                                         "target_ei = 250.0\nregion = \"field\"\n")
    out = tmp_path / "out"
    _dslrxr("run", frame, "--dark", dark, "-c", config, "--dicom", "-o", out)
    record = _exposure_record(out, "flat_exposure", "dcm")
    assert record["exposure_index"] == pytest.approx(250.0, rel=0.01)
    assert record["target_exposure_index"] == 250.0
    assert abs(record["deviation_index"]) < 0.05
    assert record["deviation_index"] == pytest.approx(10 * math.log10(record["exposure_index"] / 250.0), abs=2e-3)

    ds = pydicom.dcmread(out / "flat_exposure_dslrxr.dcm")
    for keyword, tag, key in (("ExposureIndex", 0x00181411, "exposure_index"),
                              ("TargetExposureIndex", 0x00181412, "target_exposure_index"),
                              ("DeviationIndex", 0x00181413, "deviation_index")):
        assert tag_for_keyword(keyword) == tag
        element = ds[tag]
        assert element.VR == dictionary_VR(tag) == "DS"
        assert float(element.value) == pytest.approx(record[key], abs=0.051)


def test_uncalibrated_run_says_so_and_writes_no_exposure_tags(tmp_path, rng):
    import pydicom

    transmission, _ = analytic_object((120, 160))
    frame = write_tiff(tmp_path / "shot.tif", expose(transmission, 2.0, 2.0, rng))
    out = tmp_path / "out"
    _dslrxr("run", frame, "--dicom", "-o", out)
    for ext in ("tif", "png", "dcm"):
        record = _exposure_record(out, "shot", ext)
        assert record["computed"] is False and "not calibrated" in record["reason"]
        assert "exposure_index" not in record and record["value_of_interest_dn"] > 0
    ds = pydicom.dcmread(out / "shot_dslrxr.dcm")
    assert not any(tag in ds for tag in (0x00181411, 0x00181412, 0x00181413))


def test_display_radiograph_records_why_no_ei(tmp_path, rng):
    import pydicom

    transmission, _ = analytic_object((120, 160))
    frame = write_tiff(tmp_path / "display.tif", expose(transmission, 2.0, 2.0, rng))
    config = _config(tmp_path, "display", "[input]\ninput_kind = \"display\"\n"
                                          "[exposure]\ncalibration_dn_per_ugy = 600.0\n")
    out = tmp_path / "out"
    _dslrxr("run", frame, "-c", config, "--dicom", "-o", out)
    record = _exposure_record(out, "display", "dcm")
    assert record["computed"] is False and "display radiograph" in record["reason"]
    assert "ExposureIndex" not in pydicom.dcmread(out / "display_dslrxr.dcm")
