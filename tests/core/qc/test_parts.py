"""The pieces of the QC measurement: beam table, conversion-function check, edge-angle rules,
parameter section, spot handling."""

from __future__ import annotations

import numpy as np
import pytest

import detector_truth as dt
from napari_dslrxr.core.errors import InputError, ParameterError
from napari_dslrxr.core.params import load_section, section_class
from napari_dslrxr.core.qc import (NonLinearResponseError, QcParams, conversion_function, dqe,
                                   measure_detector_quality, photon_fluence_per_mm2, slanted_edge_mtf)


def test_beam_table_is_the_2015_edition():
    # IEC 62220-1-1:2015 Table 2 (the 2003 edition had 21 759 for RQA3)
    assert photon_fluence_per_mm2("RQA3", 1.0) == 20673
    assert photon_fluence_per_mm2("RQA5", 2.5) == pytest.approx(2.5 * 29653)
    assert photon_fluence_per_mm2("RQA7", 1.0) == 32490
    assert photon_fluence_per_mm2("RQA9", 1.0) == 31007
    with pytest.raises(ParameterError, match="RQA5"):
        photon_fluence_per_mm2("RQA4", 1.0)


def test_dqe_formula_and_propagated_uncertainty():
    value, unc = dqe(np.array([0.5]), np.array([2e-5]), 1e5, mtf_uncertainty=np.array([0.01]),
                     nnps_uncertainty_mm2=np.array([1e-6]))
    assert value[0] == pytest.approx(0.25 / 2.0)
    assert unc[0] == pytest.approx(0.125 * np.hypot(2 * 0.01 / 0.5, 0.05))


def test_conversion_function_accepts_a_linear_response():
    k = [1.0, 2.0, 4.0]
    conv = conversion_function([101.0, 199.0, 401.0], k)
    assert conv.checked and conv.max_deviation_percent < 1.0
    assert conv.gain_per_ugy == pytest.approx(100.0, rel=0.01)


def test_conversion_function_refuses_a_gamma_response_naming_the_file():
    k = np.array([1.0, 2.0, 4.0, 8.0])
    # the proportional fit is pulled towards the large signals: the lowest air kerma deviates most
    with pytest.raises(NonLinearResponseError, match=r"^f1\.tif: signal is not linear in air kerma"):
        conversion_function(1000 * k ** 0.6, k, names=["f1.tif", "f2.tif", "f4.tif", "f8.tif"])


def test_one_air_kerma_is_reported_as_not_checked():
    conv = conversion_function([100.0, 101.0], [2.0, 2.0])
    assert not conv.checked and "not checked" in conv.warnings[0]


def test_measurement_refuses_non_linear_flats():
    rng = np.random.default_rng(3)
    det = dt.Detector(0.1, 0.5, 2.0)
    flats = [dt.flat_frame(dt.Detector(0.1, 0.5, k), (300, 300), rng) ** 0.7 for k in (1.0, 2.0, 4.0)]
    edge = dt.edge_frame(det, (300, 300), rng)
    with pytest.raises(NonLinearResponseError, match="^flat_a: signal is not linear"):
        measure_detector_quality(flats, [], edge, pixel_pitch_mm=0.1, air_kerma_ugy=[1.0, 2.0, 4.0],
                                 params=QcParams(roi_size_px=128), names={"flats": ["flat_a", "flat_b", "flat_c"]})


def test_edge_outside_the_standard_angles_warns_and_a_square_edge_is_refused():
    rng = np.random.default_rng(4)
    det = dt.Detector(0.1, 0.8, 20.0)
    steep = slanted_edge_mtf(dt.edge_frame(det, (256, 256), rng, angle_deg=6.0), 0.1)
    assert steep.angle_deg == pytest.approx(6.0, abs=0.05)
    assert any("outside the 1.5-3 deg" in w for w in steep.warnings)
    ok = slanted_edge_mtf(dt.edge_frame(det, (256, 256), rng, angle_deg=2.0), 0.1)
    assert not ok.warnings
    with pytest.raises(InputError, match="tilt it by 1.5-3 deg"):
        slanted_edge_mtf(dt.edge_frame(det, (256, 256), rng, angle_deg=0.1), 0.1)


def test_spots_on_the_edge_are_left_out():
    """Direct hits (bright spots of 40 sigma) on an edge image: the MTF stays that of the clean image."""
    rng = np.random.default_rng(5)
    det = dt.Detector(0.1, 0.6, 20.0)
    clean = dt.edge_frame(det, (512, 512), rng)
    spotted = clean.copy()
    rr, cc = rng.integers(0, 512, 400), 256 + rng.integers(-30, 30, 400)  # within the ESF window
    spotted[rr, cc] += 40 * np.sqrt(det.mean_dn)
    a = slanted_edge_mtf(clean, 0.1)
    b = slanted_edge_mtf(spotted, 0.1)
    assert b.n_outliers >= 380
    assert np.max(np.abs(a.mtf - b.mtf)) < 0.02
    c = slanted_edge_mtf(spotted, 0.1, outlier_sigma=0.0)  # without the rejection the spots do harm
    assert np.max(np.abs(a.mtf - c.mtf)) > np.max(np.abs(a.mtf - b.mtf))


def test_qc_section_is_a_parameter_section(tmp_path):
    assert section_class("qc") is QcParams
    path = tmp_path / "p.toml"
    path.write_text("[qc]\nbeam = \"RQA7\"\nroi_size_px = 128\n")
    got = load_section(path, "qc", pixel_pitch_mm=0.2)
    assert (got.beam, got.roi_size_px, got.pixel_pitch_mm) == ("RQA7", 128, 0.2)
    path.write_text("[qc]\nbeam = \"RQA6\"\n")
    with pytest.raises(ParameterError, match="qc.beam: must be one of RQA3, RQA5, RQA7, RQA9"):
        load_section(path, "qc")
    with pytest.raises(ParameterError, match="nnps_cut_half_width"):
        QcParams(roi_size_px=32, nnps_cut_half_width=20)


def test_missing_pitch_or_air_kerma_is_a_parameter_error():
    flats = [np.ones((300, 300))]
    with pytest.raises(ParameterError, match="pixel pitch is required"):
        measure_detector_quality(flats, [], flats[0], air_kerma_ugy=1.0)
    with pytest.raises(ParameterError, match="air kerma at the detector is required"):
        measure_detector_quality(flats, [], flats[0], pixel_pitch_mm=0.1)


def test_progress_is_reported_up_to_the_total():
    rng = np.random.default_rng(6)
    det = dt.Detector(0.1, 0.5, 5.0)
    flats = [dt.flat_frame(det, (300, 300), rng) for _ in range(3)]
    edge = dt.edge_frame(det, (300, 300), rng)
    steps = []
    measure_detector_quality(flats, [], edge, pixel_pitch_mm=0.1, air_kerma_ugy=5.0, params=QcParams(roi_size_px=128),
                             progress=lambda done, total: steps.append((done, total)))
    assert steps == [(i, 5) for i in range(1, 6)]  # three flats, one edge, the DQE


@pytest.mark.parametrize("mirrored", [False, True])
def test_report_draws_the_esf_rising_and_the_lsf_positive(mirrored):
    """Dark-to-bright and bright-to-dark edges both give the report a rising ESF and a positive
    LSF peak at the edge (the LSF of a bright-to-dark edge was drawn negative)."""
    from napari_dslrxr.core.qc.report import esf_lsf_dark_to_bright

    frame = dt.edge_frame(dt.Detector(0.1, 0.8, 20.0), (256, 256), np.random.default_rng(6), angle_deg=2.0)
    edge = slanted_edge_mtf(frame[:, ::-1] if mirrored else frame, 0.1)
    assert (edge.lsf.sum() < 0) == mirrored
    distance, esf, lsf = esf_lsf_dark_to_bright(edge)
    order = np.argsort(distance)
    esf, lsf, distance = esf[order], lsf[order], distance[order]
    assert esf[:20].mean() < 0.1 and esf[-20:].mean() > 0.9
    assert lsf.max() == pytest.approx(1.0) and abs(distance[np.argmax(lsf)]) < 0.1
