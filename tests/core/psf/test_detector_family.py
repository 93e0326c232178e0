"""The generalised detector core against an independent edge generator, and the per-pixel
impulse mask of the edge fit.

Edges are rendered by ``independent_edge_generator`` (2-D supersampled FFT blur with an analytic
radial MTF, block-averaged pixels, Poisson + read noise): none of the project's simulation or
fit code. Detector MTFs of three shapes (stretched exponential with p = 1.2, Lorentzian,
Gaussian), a Gaussian focal spot; fitted at two object distances, predicted at a third.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import independent_edge_generator as gen
from napari_dslrxr.core.psf.edge_fit import EdgeImage, fit_edges
from napari_dslrxr.core.psf.edge_images import _impulse_mask

PITCH_MM = 0.194                      # Nyquist 2.58 cycles/mm
SDD_MM = 1000.0
SPOT_MM = (0.3, 0.4)                  # Gaussian focal spot FWHM x, y (source plane)
FIT_SODS = (500.0, 750.0)             # ODD/SOD 1 and 1/3
HELD_OUT_SOD = 600.0                  # ODD/SOD 2/3, never seen by the fit
BAND = np.linspace(0.5, 0.9 * 0.5 / PITCH_MM, 40)   # cycles/mm: 0.5 c/mm to 0.9 Nyquist
TRUTHS = {
    "stretched p=1.2": gen.stretched_mtf(1.575, 1.2),
    "lorentzian": gen.lorentzian_mtf(1.0),
    "gaussian": gen.gaussian_mtf(1.5),
}


def _m1(sod):
    return (SDD_MM - sod) / sod


@pytest.fixture(scope="module", params=list(TRUTHS))
def fitted(request):
    mtf = TRUTHS[request.param]
    rng = np.random.default_rng(sorted(TRUTHS).index(request.param) + 11)
    edges = []
    for sod in FIT_SODS:
        for angle in (3.0, 93.0):
            t = gen.render_edge((256, 256), PITCH_MM, angle, mtf, spot=gen.gaussian_spot_mtf(*SPOT_MM, _m1(sod)),
                                offset_px=rng.uniform(-3, 3))
            edges.append(EdgeImage(gen.add_counting_noise(t, rng), sod, SDD_MM, name=f"{sod:g}mm_{angle:g}deg"))
    # shape_power 2: the focal spot is Gaussian (the detector core's shape is fitted).
    return request.param, mtf, fit_edges(edges, PITCH_MM, shape_power=2.0)


@pytest.mark.slow
def test_detector_mtf_follows_the_true_shape(fitted):
    name, mtf, model = fitted
    assert model.core_from_mtf
    error = np.abs(model.detector_mtf(BAND) - mtf(BAND)).max()
    assert error < 0.03, f"{name}: detector MTF off by {error:.3f}"
    # The family's named members are found: Lorentzian u ~ 1, q ~ 2; stretched u ~ 0, q ~ 1.2.
    if name == "lorentzian":
        assert model.detector_core_mtf_power > 1.8 and 0.8 < model.detector_core_mtf_linnik < 1.2
    elif name.startswith("stretched"):
        assert abs(model.detector_core_mtf_power - 1.2) < 0.1 and model.detector_core_mtf_linnik < 0.15
    assert model.detector_weight_core == 1.0          # no tail was asked for


@pytest.mark.slow
def test_focal_spot_and_held_out_distance(fitted):
    name, mtf, model = fitted
    assert model.source_fitted
    assert model.source_fwhm_x_mm == pytest.approx(SPOT_MM[0], rel=0.1)
    assert model.source_fwhm_y_mm == pytest.approx(SPOT_MM[1], rel=0.1)
    m1 = _m1(HELD_OUT_SOD)
    for angle in (3.0, 93.0):
        phi = math.radians(angle)
        # Presampling MTF along the edge normal at the held-out distance.
        truth = (mtf(BAND) * gen.gaussian_spot_mtf(*SPOT_MM, m1)(BAND * math.cos(phi), BAND * math.sin(phi))
                 * np.abs(np.sinc(BAND * PITCH_MM * math.cos(phi)) * np.sinc(BAND * PITCH_MM * math.sin(phi))))
        predicted = model.presampling_mtf(BAND, HELD_OUT_SOD, SDD_MM, phi)
        assert np.abs(predicted - truth).max() < 0.03, name
        # Edge profile: the true noise-free edge against the same renderer driven by the fitted
        # model's transfer functions (its focal spot is Gaussian: shape_power 2).
        true_edge = gen.render_edge((96, 96), PITCH_MM, angle, mtf, spot=gen.gaussian_spot_mtf(*SPOT_MM, m1))
        predicted_edge = gen.render_edge((96, 96), PITCH_MM, angle, model.detector_mtf,
                                         spot=gen.gaussian_spot_mtf(model.source_fwhm_x_mm,
                                                                    model.source_fwhm_y_mm, m1))
        assert np.abs(predicted_edge - true_edge).max() < 0.01, name


@pytest.mark.slow
def test_kernel_mtf_matches_the_model(fitted):
    # The sampled 2-D kernel carries the model: the DFT of its column sums is the presampling
    # MTF (detector x pixel aperture) aliased onto the pixel grid.
    name, _, model = fitted
    kernel = model.detector_kernel().astype(float)
    line = kernel.sum(axis=0)
    f_px = np.fft.rfftfreq(line.size)
    dft = np.real(np.fft.rfft(np.fft.ifftshift(line)))
    expected = sum(model.detector_mtf((f_px + k) / PITCH_MM) * np.sinc(f_px + k) for k in range(-6, 7))
    assert np.abs(dft - expected).max() < 0.005, name


def test_impulse_mask_uses_per_pixel_noise():
    # Dark side 2 % of the open beam: its photon noise is 7x smaller than the bright side's. One
    # sigma for the region masked 5 % of ordinary bright-side pixels; the per-pixel model none,
    # while it still finds gamma hits on both sides.
    rng = np.random.default_rng(3)
    t = gen.render_edge((256, 256), PITCH_MM, 3.0, gen.stretched_mtf(1.575, 1.2), low=0.02)
    counts = gen.add_counting_noise(t, rng, open_counts=4000.0, read_noise_counts=3.0)
    hits = np.zeros(counts.shape, bool)
    hits[rng.integers(2, 254, 60), rng.integers(2, 254, 60)] = True
    counts[hits] += 1500.0
    mask = _impulse_mask(counts)
    bright, dark = t > 0.9, t < 0.05
    near_hit = np.zeros_like(mask)
    for r, c in zip(*np.nonzero(hits)):
        near_hit[r - 1:r + 2, c - 1:c + 2] = True
    assert mask[bright & ~near_hit].mean() < 0.001
    assert mask[dark & ~near_hit].mean() < 0.001
    assert mask[hits].mean() > 0.95


def test_project_simulator_renders_the_generalised_core_like_the_independent_generator():
    # The project's edge synthesis (spatial line spreads) with an MTF-defined core, against the
    # independent 2-D FFT renderer of the same detector: a stretched exponential, p = 1.2.
    from napari_dslrxr.core.psf import PSFModel
    from napari_dslrxr.core.simulation.edge_synthesis import synthesize_edge_image

    model = PSFModel(PITCH_MM, 0.0, 0.0, 0.0, 0.0, 1.0, shape_power=2.0, detector_core_mtf_scale_mm=1 / 1.575,
                     detector_core_mtf_power=1.2, source_fitted=False)
    ours = synthesize_edge_image(model, 100.0, 100.0, (64, 64), 3.0)
    independent = gen.render_edge((64, 64), PITCH_MM, 3.0, gen.stretched_mtf(1.575, 1.2), low=0.0, high=1.0)
    assert np.abs(ours - independent).max() < 0.003
