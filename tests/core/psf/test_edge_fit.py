"""Tests of the joint SABER edge fit (napari_dslrxr.core.psf.edge_fit) on synthetic edges with known blur."""

from __future__ import annotations

import math

import numpy as np
import pytest

from napari_dslrxr.core.psf import edge_fit
from napari_dslrxr.core.psf.edge_fit import EdgeImage, fit_edges, load_edge_config
from napari_dslrxr.core.simulation.edge_synthesis import synthesize_edge_image
from napari_dslrxr.core.errors import InputError, ParameterError
from napari_dslrxr.core.psf import PSFModel

PITCH_MM = 0.01
SDD_MM = 150.0
TRUTH = PSFModel(pixel_pitch_mm=PITCH_MM, source_fwhm_x_mm=0.02, source_fwhm_y_mm=0.03,
                 detector_fwhm_core_mm=0.015, detector_fwhm_tail_mm=0.2, detector_weight_core=0.9)
# Two object heights (ODD/SOD = 2 and 0.5), a vertical and a horizontal edge at each, tilted 2-4 deg.
SPECS = [(50.0, 3.0), (50.0, 92.5), (100.0, -2.0), (100.0, 273.5)]
NOISE = 0.006
#: These tests check the recovery of the SABER parameters: fit the model family the truth is drawn
#: from (the generalised MTF-defined core is checked in test_detector_family.py).
LEGACY = {"detector_core": "exponential_power"}


def _relative_l2(a, b):
    n = max(a.shape[0], b.shape[0])
    pad = lambda k: np.pad(k.astype(float), ((n - k.shape[0]) // 2,) * 2)  # noqa: E731
    return float(np.linalg.norm(pad(a) - pad(b)) / np.linalg.norm(pad(b)))


def _edges(rng, size=96, noise=NOISE, specs=SPECS):
    out = []
    for sod, angle in specs:
        img = synthesize_edge_image(TRUTH, sod, SDD_MM, (size, size), angle, offset_px=rng.uniform(-3, 3),
                                    low=0.02, high=0.97)
        out.append(EdgeImage(img + rng.normal(0, noise, img.shape), sod, SDD_MM, name=f"sod{sod:g}_{angle:g}"))
    return out


@pytest.fixture(scope="module")
def fitted():
    rng = np.random.default_rng(20261122)
    edges = _edges(rng)
    return edges, fit_edges(edges, PITCH_MM, **LEGACY)


def test_synthesis_matches_independent_2d_kernel_projection():
    # The synthetic ESF (spatial |t| K1 projections) must agree with the 2-D kernel sampler:
    # differences of a point-sampled vertical edge half a pixel off the grid are pixel integrals
    # of the LSF, i.e. the column sums of the area-integrated kernel.
    model = PSFModel(PITCH_MM, 0.02, 0.03, 0.015, 0.1, 0.9)
    img = synthesize_edge_image(model, 50.0, SDD_MM, (9, 301), 0.0, offset_px=0.5, supersample=1)
    lsf_from_image = np.diff(img[4])
    kernel = model.kernel(50.0, SDD_MM).astype(float)
    lsf_from_kernel = kernel.sum(axis=0)
    r = kernel.shape[1] // 2
    centre = 150   # pixel boundary at the edge: image column 150 | 151 straddles d = 0
    window = lsf_from_image[centre - 40:centre + 41]
    np.testing.assert_allclose(window, lsf_from_kernel[r - 40:r + 41], atol=3e-3 * lsf_from_kernel.max())  # kernel support cut at 5 FWHM


def _assert_gradient_exact(problem, theta):
    """The objective's gradient against central finite differences."""
    _, grad = problem.cost_and_gradient(theta)
    numeric = np.zeros_like(theta)
    for k in range(theta.size):
        h = 1e-6 * max(1.0, abs(theta[k]))
        up, down = theta.copy(), theta.copy()
        up[k] += h
        down[k] -= h
        numeric[k] = (problem.cost_and_gradient(up)[0] - problem.cost_and_gradient(down)[0]) / (2 * h)
    np.testing.assert_allclose(grad, numeric, rtol=1e-5, atol=1e-7 * np.abs(numeric).max())


def test_gradient_is_exact_against_finite_differences(rng):
    edges = _edges(rng, size=64)
    prepared = [edge_fit._prepare(e, i, True) for i, e in enumerate(edges)]
    for p in prepared:   # noise-model weights and masked pixels enter the gradient too
        p.weight = rng.uniform(0.3, 3.0, p.values.size)
        p.keep = rng.random(p.values.size) > 0.05
    problem = edge_fit._JointProblem(prepared, 1.0, True, False, 256.0, 1 / 16, NOISE, 16.0)
    theta = np.array([math.log(2.2), math.log(2.8), math.log(1.3), math.log(25.0), 0.87]
                     + sum([[p.offset_px + 0.2, 0.4] for p in prepared], []))
    _assert_gradient_exact(problem, theta)


@pytest.mark.parametrize("with_tail", [False, True])
def test_gradient_is_exact_for_the_generalised_core(rng, with_tail):
    edges = _edges(rng, size=64)
    prepared = [edge_fit._prepare(e, i, True) for i, e in enumerate(edges)]
    for p in prepared:
        p.weight = rng.uniform(0.3, 3.0, p.values.size)
    problem = edge_fit._JointProblem(prepared, 2.0, True, False, 256.0, 1 / 16, NOISE, 16.0,
                                     generalised_core=True, with_tail=with_tail)
    assert problem.global_free == ["sx", "sy", "core", "power", "linnik"] + (["tail", "w"] if with_tail else [])
    theta = np.array([math.log(2.2), math.log(2.8), math.log(3.0), 1.3, 0.4] + ([math.log(25.0), 0.9] if with_tail else [])
                     + sum([[p.offset_px + 0.2, 0.4] for p in prepared], []))
    _assert_gradient_exact(problem, theta)


def test_joint_fit_recovers_parameters_and_heldout_kernel(fitted):
    edges, model = fitted
    assert model.source_fwhm_x_mm == pytest.approx(TRUTH.source_fwhm_x_mm, rel=0.03)
    assert model.source_fwhm_y_mm == pytest.approx(TRUTH.source_fwhm_y_mm, rel=0.03)
    assert model.detector_fwhm_core_mm == pytest.approx(TRUTH.detector_fwhm_core_mm, rel=0.03)
    assert model.detector_fwhm_tail_mm == pytest.approx(TRUTH.detector_fwhm_tail_mm, rel=0.15)
    assert model.detector_weight_core == pytest.approx(TRUTH.detector_weight_core, abs=0.02)
    # Held-out distance (ODD/SOD = 1), never seen by the fit.
    error = _relative_l2(model.kernel(75.0, SDD_MM), TRUTH.kernel(75.0, SDD_MM))
    assert error <= 0.05
    report = model.fit_report
    assert report["source_fitted"] and not report["source_axes_tied"] and report["n_images"] == 4
    assert report["residual_rms"] == pytest.approx(NOISE, rel=0.05)
    assert report["noise_rms_estimate"] == pytest.approx(NOISE, rel=0.1)


def test_uncertainties_cover_the_error(fitted):
    _, model = fitted
    for name in ("source_fwhm_x_mm", "source_fwhm_y_mm", "detector_fwhm_core_mm", "detector_weight_core"):
        sigma = model.uncertainty[name]
        assert 0 < sigma < 0.05 * max(getattr(TRUTH, name), 0.1)
        assert abs(getattr(model, name) - getattr(TRUTH, name)) < 5 * sigma


def test_edge_geometry_and_profiles(fitted):
    edges, model = fitted
    for spec, report in zip(SPECS, model.fit_report["edges"]):
        expected = (spec[1] + 180) % 360 - 180
        assert (report["edge_normal_angle_deg"] - expected + 180) % 360 - 180 == pytest.approx(0, abs=0.1)
        assert report["low_level"] == pytest.approx(0.02, abs=0.005)
        assert report["high_level"] == pytest.approx(0.97, abs=0.005)
        prof = report["profile"]
        esf_m, esf_f = np.array(prof["esf_measured"]), np.array(prof["esf_fitted"])
        assert esf_f[0] < 0.05 and esf_f[-1] > 0.95
        assert np.sqrt(np.mean((esf_m - esf_f) ** 2)) < 0.01
        lsf_f = np.array(prof["lsf_fitted"])
        assert abs(prof["distance_px"][int(np.argmax(lsf_f))]) < 1.0


def test_flat_dark_normalisation_and_impulses(rng):
    # Counts with an open-beam and dark frame, plus bright gamma hits: same blur recovered.
    edges = _edges(rng)
    dark = np.full((96, 96), 100.0)
    bright = np.repeat(100.0 + 3000.0 * (1 + 0.1 * np.linspace(-1, 1, 96))[None, :], 96, axis=0)
    counted = []
    for e in edges:
        counts = dark + (bright - dark) * e.image
        hits = rng.random(counts.shape) < 0.005
        counts[hits] += 2000.0
        counted.append(EdgeImage(counts, e.source_to_object_mm, e.source_to_detector_mm, bright=bright, dark=dark))
    model = fit_edges(counted, PITCH_MM, **LEGACY)
    assert model.detector_fwhm_core_mm == pytest.approx(TRUTH.detector_fwhm_core_mm, rel=0.05)
    assert model.source_fwhm_y_mm == pytest.approx(TRUTH.source_fwhm_y_mm, rel=0.05)
    assert sum(e["n_impulses_masked"] for e in model.fit_report["edges"]) > 4 * 0.004 * 96 * 96
    assert model.fit_report["residual_rms"] < 1.2 * NOISE


def test_single_distance_fits_detector_only(rng):
    # Contact radiographs (object on the detector): no source blur, one geometry.
    edges = _edges(rng, specs=[(SDD_MM, 3.0), (SDD_MM, 92.5)])
    model = fit_edges(edges, PITCH_MM, **LEGACY)
    assert not model.fit_report["source_fitted"] and "not separable" in model.fit_report["note"]
    assert model.source_fwhm_x_mm == 0.0 and model.source_fwhm_y_mm == 0.0
    assert model.detector_fwhm_core_mm == pytest.approx(TRUTH.detector_fwhm_core_mm, rel=0.03)
    assert model.detector_fwhm_tail_mm == pytest.approx(TRUTH.detector_fwhm_tail_mm, rel=0.2)
    assert model.detector_weight_core == pytest.approx(TRUTH.detector_weight_core, abs=0.02)
    assert model.fit_report["residual_rms"] < 1.02 * NOISE
    with pytest.raises(ParameterError, match="two or more"):
        fit_edges(edges, PITCH_MM, fit_source=True, **LEGACY)


def test_one_orientation_ties_source_axes(rng):
    edges = [e for e in _edges(rng, specs=[(50.0, 3.0), (100.0, -2.0)])]
    model = fit_edges(edges, PITCH_MM, **LEGACY)
    assert model.fit_report["source_axes_tied"]
    assert model.source_fwhm_x_mm == model.source_fwhm_y_mm
    assert model.source_fwhm_x_mm == pytest.approx(TRUTH.source_fwhm_x_mm, rel=0.05)


def test_bad_inputs_raise_one_line_errors(rng):
    with pytest.raises(ParameterError, match="no edge images"):
        fit_edges([], PITCH_MM)
    flat = EdgeImage(np.full((64, 64), 0.5) + rng.normal(0, 1e-3, (64, 64)) * 0, 50.0, SDD_MM, name="flat.tif")
    with pytest.raises(InputError, match="flat.tif"):
        fit_edges([flat], PITCH_MM)
    edge = _edges(rng, size=64)[0]
    with pytest.raises(ParameterError, match="outside"):
        fit_edges([EdgeImage(edge.image, 50.0, SDD_MM, roi=(0, 0, 80, 80), name="e.tif")], PITCH_MM)
    with pytest.raises(ParameterError, match="pixel_pitch_mm"):
        fit_edges([edge], 0.0)
    with pytest.raises(ParameterError, match="source_to_detector_mm"):
        fit_edges([EdgeImage(edge.image, 200.0, SDD_MM)], PITCH_MM)
    with pytest.raises(InputError, match="shape"):
        fit_edges([EdgeImage(edge.image, 50.0, SDD_MM, bright=np.ones((10, 10)))], PITCH_MM)


def test_roi_selects_one_edge(rng):
    # Two edges in one image; the ROI keeps the vertical one.
    img = synthesize_edge_image(TRUTH, 100.0, SDD_MM, (96, 160), 2.0, offset_px=-40, low=0.02, high=0.97)
    img = np.minimum(img, synthesize_edge_image(TRUTH, 100.0, SDD_MM, (96, 160), 180.0, offset_px=-40,
                                                low=0.02, high=0.97))
    img += rng.normal(0, NOISE, img.shape)
    model = fit_edges([EdgeImage(img, 100.0, SDD_MM, roi=(0, 0, 96, 80))], PITCH_MM, **LEGACY)
    report = model.fit_report["edges"][0]
    assert report["edge_normal_angle_deg"] == pytest.approx(2.0, abs=0.3)
    assert report["residual_rms"] < 1.1 * NOISE


def test_load_edge_config(tmp_path, rng):
    from napari_dslrxr.core.io import write_tiff

    img = np.asarray(_edges(rng, size=64)[0].image, np.float32)
    write_tiff(tmp_path / "e.tif", img)
    write_tiff(tmp_path / "flat.tif", np.ones_like(img))
    cfg_path = tmp_path / "cfg.toml"
    cfg_path.write_text('pixel_pitch_mm = 0.01\n[[edges]]\nimage = "e.tif"\nsource_to_object_mm = 50\n'
                        'source_to_detector_mm = 150.0\nbright = "flat.tif"\nroi = [0, 0, 64, 60]\n')
    cfg = load_edge_config(cfg_path)
    assert cfg.pixel_pitch_mm == 0.01 and len(cfg.edges) == 1
    assert cfg.edges[0].roi == (0, 0, 64, 60) and cfg.edges[0].bright is not None
    np.testing.assert_array_equal(cfg.edges[0].image, img)
    assert {p.name for p in cfg.input_files} == {"e.tif", "flat.tif"}
    bad_cases = {
        'pixel_pitch_mm = "x"\n[[edges]]\nimage = "e.tif"\nsource_to_object_mm = 1\nsource_to_detector_mm = 2\n':
            "pixel_pitch_mm",
        'pixel_pitch_mm = 0.01\n[[edges]]\nimage = "e.tif"\nsource_to_detector_mm = 2\n': "source_to_object_mm",
        'pixel_pitch_mm = 0.01\n[[edges]]\nimage = "missing.tif"\nsource_to_object_mm = 1\n'
        'source_to_detector_mm = 2\n': "missing.tif",
        'pixel_pitch_mm = 0.01\n[[edges]]\nimage = "e.tif"\nsource_to_object_mm = 1\n'
        'source_to_detector_mm = 2\nroi = [0, 0, 10]\n': "roi",
        'pixel_pitch_mm = 0.01\n': "edges",
        'pixel_pitch_mm = 0.01\n[[edges]\n': "not valid TOML",
        'pixel_pitch_mm = 0.01\npixel_pich = 2\n[[edges]]\nimage = "e.tif"\nsource_to_object_mm = 1\n'
        'source_to_detector_mm = 2\n': "pixel_pich",
        'pixel_pitch_mm = 0.01\n[[edges]]\nimage = "e.tif"\nsource_to_object_mm = 1\n'
        'source_to_detector_mm = 2\nbrigth = "flat.tif"\n': "brigth",
    }
    for text, key in bad_cases.items():
        cfg_path.write_text(text)
        with pytest.raises(InputError, match=key) as info:
            load_edge_config(cfg_path)
        assert str(cfg_path) in str(info.value)


def test_poisson_noise_is_weighted(rng):
    # Photon noise: 4x larger on the bright side than under the plate. The weighted refit uses
    # the level-dependent noise model and is more precise than the unweighted fit.
    counts = 2000.0
    edges = []
    for sod, angle in SPECS:
        t = synthesize_edge_image(TRUTH, sod, SDD_MM, (96, 96), angle, offset_px=rng.uniform(-3, 3),
                                  low=0.05, high=0.97)
        edges.append(EdgeImage(rng.poisson(t * counts) / counts, sod, SDD_MM))
    weighted = fit_edges(edges, PITCH_MM, **LEGACY)
    plain = fit_edges(edges, PITCH_MM, weight_by_noise=False, **LEGACY)
    assert weighted.fit_report["noise_weighted"] and not plain.fit_report["noise_weighted"]
    for name in ("source_fwhm_x_mm", "source_fwhm_y_mm", "detector_fwhm_core_mm"):
        assert getattr(weighted, name) == pytest.approx(getattr(TRUTH, name), rel=0.05)
        assert abs(getattr(weighted, name) - getattr(TRUTH, name)) < 4 * weighted.uncertainty[name]
    assert weighted.uncertainty["detector_fwhm_core_mm"] < 0.9 * plain.uncertainty["detector_fwhm_core_mm"]


def test_sub_step_core_keeps_its_weight_against_the_tail():
    # A core far narrower than the synthesis grid must act as a delta of weight w, not be
    # over-weighted by its under-sampled peak (was 10x at 0.0014 px FWHM).
    tiny = PSFModel(1.0, 0.0, 0.0, 0.0014, 10.0, 0.5)
    delta = PSFModel(1.0, 0.0, 0.0, 0.0, 10.0, 0.5)
    a = synthesize_edge_image(tiny, 100.0, 200.0, (3, 201), 0.0, supersample=1)
    b = synthesize_edge_image(delta, 100.0, 200.0, (3, 201), 0.0, supersample=1)
    np.testing.assert_allclose(a, b, atol=1e-6)


def test_roi_without_an_edge_is_named_not_an_internal_error():
    """Noise alone (no edge) is refused with the ROI's name, before the fit."""
    rng = np.random.default_rng(5)
    truth = PSFModel(pixel_pitch_mm=0.1, source_fwhm_x_mm=0.4, source_fwhm_y_mm=0.4, detector_fwhm_core_mm=0.15,
                     detector_fwhm_tail_mm=1.0, detector_weight_core=0.9)
    edge = rng.poisson(synthesize_edge_image(truth, 500.0, 1000.0, (64, 64), 3.0) * 4000.0).astype(np.float32)
    flat = rng.poisson(np.full((64, 64), 4000.0)).astype(np.float32)
    edges = [EdgeImage(image=edge, source_to_object_mm=500.0, source_to_detector_mm=1000.0, name="ROI 1"),
             EdgeImage(image=flat, source_to_object_mm=900.0, source_to_detector_mm=1000.0, name="ROI 2")]
    with pytest.raises(InputError, match=r"^ROI 2: no edge found"):
        fit_edges(edges, 0.1)
