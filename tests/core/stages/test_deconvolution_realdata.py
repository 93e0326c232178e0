"""Deconvolution of a real radiograph (NEMA WG04 lower leg, cr_dicom) blurred by a known kernel.

The key comparison of benchmarks/eval_deconvolution.py on a small crop: our default method
with its automatic regularisation (no truth) against scikit-image's Wiener and Richardson-Lucy
at their best parameters chosen with the truth (as called, and given the same replicate
padding, so the comparison is also about the prior and not only about border handling), the
absence of ringing halos, and the GCF of the output against the truth's and the input's.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.signal import fftconvolve
from skimage import restoration

from napari_dslrxr.core.stages import deconvolution as dc
from napari_dslrxr.core.io import read_image
from napari_dslrxr.core.metrics import global_contrast_factor
from napari_dslrxr.core.psf import PSFModel

pytestmark = pytest.mark.realdata

CROP = (1200, 700, 256)  # tibia and fibula cortex: strong bone edges


def psnr(truth, x):
    return float(10 * np.log10(1.0 / np.mean((truth - x) ** 2)))


def display_gcf(x) -> float:
    """GCF of the 8-bit display image (normalised [0, 1] mapped to 0..255), as in the eval script."""
    return global_contrast_factor(np.clip(np.round(np.asarray(x, np.float64) * 255.0), 0, 255).astype(np.uint8))


@pytest.fixture(scope="module")
def leg_blur(shared_data):
    """(truth crop, kernel, noise-free blurred crop): the whole window is blurred, then cropped."""
    full = read_image(shared_data / "cr_dicom" / "RG3_UNCR.dcm").data.astype(np.float64)
    full = (full - full.min()) / (full.max() - full.min())
    kernel = PSFModel(pixel_pitch_mm=0.1, source_fwhm_x_mm=0.6, source_fwhm_y_mm=0.6,
                     detector_fwhm_core_mm=0.25, detector_fwhm_tail_mm=1.0,
                     detector_weight_core=0.9).kernel(900.0, 1000.0)
    r0, c0, n = CROP
    h = kernel.shape[0] // 2
    window = full[r0 - 2 * h:r0 + n + 2 * h, c0 - 2 * h:c0 + n + 2 * h]
    blurred = fftconvolve(window, kernel.astype(np.float64), mode="same")[2 * h:-2 * h, 2 * h:-2 * h]
    return full[r0:r0 + n, c0:c0 + n], kernel, blurred


def add_poisson(blurred, peak_counts: float) -> np.ndarray:
    rng = np.random.default_rng(20261122)
    return (rng.poisson(np.clip(blurred, 0, None) * peak_counts) / peak_counts).astype(np.float32)


@pytest.fixture(scope="module")
def leg_case(leg_blur):
    truth, kernel, blurred = leg_blur
    return truth, kernel, add_poisson(blurred, 5000.0)


def best_skimage_psnr(truth, noisy, kernel, pad_px):
    """Best PSNR of skimage Wiener (balance grid) and Richardson-Lucy (iteration grid), with truth.

    ``pad_px = 0``: called as is (its own circular / zero borders); otherwise the input is
    replicate-padded by ``pad_px`` and the result cropped back (our border handling).
    """
    y = noisy.astype(np.float64)
    if pad_px:
        y = np.pad(y, pad_px, mode="edge")
    crop = (slice(pad_px, -pad_px), slice(pad_px, -pad_px)) if pad_px else (slice(None), slice(None))
    wiener_best = max(psnr(truth, restoration.wiener(y, kernel, b, clip=False)[crop])
                      for b in 10.0 ** np.arange(-3, 1.01, 0.25))
    rl_best = max(psnr(truth, restoration.richardson_lucy(y, kernel, num_iter=n, clip=False)[crop])
                  for n in (5, 10, 20, 40))
    return max(wiener_best, rl_best)


def test_adaptive_auto_against_best_skimage_on_a_real_radiograph(leg_case):
    truth, kernel, noisy = leg_case
    ours = psnr(truth, dc.deconvolve(noisy, kernel))  # adaptive prior, automatic reg: no truth
    as_called = best_skimage_psnr(truth, noisy, kernel, 0)
    padded = best_skimage_psnr(truth, noisy, kernel, kernel.shape[0])
    # The comparison: skimage as called, at its best parameter chosen with the truth.
    assert ours >= as_called + 0.5, (ours, as_called)
    # Given our border handling too, skimage tuned with the truth is matched, not beaten by 0.5 dB
    # (see the report): ours without the truth stays within 0.1 dB or better.
    assert ours >= padded - 0.1, (ours, padded)
    assert ours > psnr(truth, noisy) + 2.0


def test_no_ringing_halo_at_bone_edges(leg_case):
    truth, kernel, noisy = leg_case
    ours = dc.deconvolve(noisy, kernel)
    grad = np.hypot(ndimage.sobel(truth, 0), ndimage.sobel(truth, 1)) / 8.0
    band = ndimage.binary_dilation(grad > 0.25 * np.percentile(grad, 99.9), iterations=10)
    band[:16], band[-16:], band[:, :16], band[:, -16:] = False, False, False, False
    over = np.percentile((ours - ndimage.maximum_filter(truth, size=7))[band], 99.9)
    under = np.percentile((ndimage.minimum_filter(truth, size=7) - ours)[band], 99.9)
    # Overshoot beyond the local truth range stays within the noise (about 4 sigma of the
    # residual noise), and far below the edge height (a ringing halo would be a fraction of it).
    edge_height = np.percentile(truth, 99) - np.percentile(truth, 1)
    sigma = dc.estimate_noise_sigma(noisy)
    assert over < max(4 * sigma, 0.05 * edge_height) and under < max(4 * sigma, 0.05 * edge_height), (over, under, sigma)


@pytest.mark.parametrize("peak_counts", [5000.0, 28000.0])
def test_gcf_follows_the_truth_and_rises_once_blur_outweighs_noise(leg_blur, peak_counts):
    """GCF: the output's tracks the truth's; it exceeds the input's when the truth's does.

    Poisson noise adds pixel-scale contrast and blur removes edge contrast. At 5000 counts
    (about the niqa recording's noise) the noise adds more than this crop's blur removed, so
    even the truth has a lower GCF than the noisy input, and no faithful restoration can
    "raise" it; at 28000 counts (0.6 % noise at white) the truth's GCF is above the input's
    and ours must rise above the input as well. Over-smoothing (GCF well below the truth's)
    or over-sharpening (above it) fails either way.
    """
    truth, kernel, blurred = leg_blur
    noisy = add_poisson(blurred, peak_counts)
    ours = display_gcf(dc.deconvolve(noisy, kernel))
    g_truth, g_noisy = display_gcf(truth), display_gcf(noisy)
    assert 0.93 * g_truth < ours < 1.03 * g_truth, (ours, g_truth)
    if g_truth > g_noisy:
        assert ours > g_noisy, (ours, g_noisy, g_truth)
    if peak_counts >= 28000.0:
        assert g_truth > g_noisy  # the setting where rising is possible is exercised
