"""The automatic regularisation keeps flat-region noise at most 2x the input's, and says when it guessed.

Images: the plugin's own edge samples (step-like: the spectral model alone raised flat-region
noise 19-37x there), a plain step and a flat field, real CR crops and the SABER resolution
target at several noise levels. The noise gain is measured, not predicted: in a flat patch of
the sample (std ratio after removing a plane), or as the std of deconvolve(noisy) -
deconvolve(clean) over the flat part of a truth image, over the noise's std.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from napari_dslrxr._sample_data import EDGE_SOURCE_TO_DETECTOR_MM, EDGE_TRUTH, _edge_images
from napari_dslrxr.core.stages import deconvolution as dc
from napari_dslrxr.core.stages import regularisation as rg
from napari_dslrxr.core.psf import PSFModel

METHODS = ("adaptive", "rls", "wiener")


def _plane_removed_std(patch: np.ndarray) -> float:
    p = patch.astype(np.float64)
    yy, xx = np.mgrid[0:p.shape[0], 0:p.shape[1]]
    design = np.column_stack([yy.ravel(), xx.ravel(), np.ones(p.size)])
    coef, *_ = np.linalg.lstsq(design, p.ravel(), rcond=None)
    return float((p.ravel() - design @ coef).std())


def _gaussian_kernel(sigma_px: float) -> np.ndarray:
    r = np.arange(-int(4 * sigma_px), int(4 * sigma_px) + 1)
    g = np.exp(-0.5 * (r / sigma_px) ** 2)
    k = np.outer(g, g)
    return (k / k.sum()).astype(np.float32)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("sample", [0, 1])
def test_edge_samples_flat_noise_gain_at_most_two(sample, method):
    sod, image = _edge_images()[sample]
    kernel = PSFModel(**EDGE_TRUTH).kernel(sod, EDGE_SOURCE_TO_DETECTOR_MM)
    choice = rg.choose_regularisation(image, kernel, method)
    out = dc.deconvolve(image, kernel, method=method, reg=choice.reg)
    # the bright, flat side of the near-vertical edge (edge near x = 64 of the left half)
    rows, cols = slice(8, 120), slice(84, 108)
    gain = _plane_removed_std(out[rows, cols]) / _plane_removed_std(image[rows, cols])
    assert gain <= 2.0, (gain, choice)  # 1.96-2.14 before the 10 % margin, 19-37x uncapped at SOD 500
    assert choice.noise_gain <= rg.AUTO_MAX_NOISE_GAIN + 0.01
    # the edge rings little: over- and undershoot within 5 % of the step (10.6-13 % uncapped)
    profile = out[20:108, 40:90].mean(axis=0)
    high, low = np.median(image[20:108, 84:108]), np.median(image[20:108, 4:28])
    assert profile.max() - high < 0.05 * (high - low) and low - profile.min() < 0.05 * (high - low)
    assert not choice.reliable and any("step-like" in w for w in choice.warnings)
    if sample == 0:  # magnification 2: the model alone would have amplified the noise many times
        assert choice.capped and choice.model_noise_gain > 10 and choice.reg > 10 * choice.model_reg
        assert any("raised to" in w for w in choice.warnings)


def test_flat_and_step_images_fall_back_gracefully(rng):
    kernel = _gaussian_kernel(2.0)
    flat = rng.poisson(np.full((160, 160), 3000.0)).astype(np.float32)
    step = np.full((160, 160), 1000.0)
    step[:, 80:] = 4000.0
    step = rng.poisson(ndimage.convolve(step, kernel, mode="nearest")).astype(np.float32)
    for image, patch in ((flat, (slice(40, 120), slice(40, 120))), (step, (slice(20, 140), slice(100, 150)))):
        choice = rg.choose_regularisation(image, kernel, "adaptive")
        out = dc.deconvolve(image, kernel, reg=choice.reg)
        assert np.isfinite(out).all()
        gain = _plane_removed_std(out[patch]) / _plane_removed_std(image[patch])
        assert gain <= 2.0, (gain, choice)
        assert not choice.reliable and choice.warnings  # it says it had little to go on


def test_texture_is_left_alone(rng):
    """On a textured image the model's choice stands when it already keeps the noise gain."""
    kernel = _gaussian_kernel(1.5)
    texture = ndimage.gaussian_filter(rng.normal(0, 1, (192, 192)), 2.0)
    texture = 2000 + 800 * texture / texture.std()
    image = rng.poisson(np.clip(ndimage.convolve(texture, kernel, mode="nearest"), 1, None)).astype(np.float32)
    choice = rg.choose_regularisation(image, kernel, "adaptive")
    # the model's own choice keeps the noise gain here (1.71 against the cap of 1.8), so it
    # must stand; either branch of an if on that number would pass whatever the cap did
    assert choice.model_noise_gain <= rg.AUTO_MAX_NOISE_GAIN, choice
    assert not choice.capped and choice.reg == choice.model_reg, choice


def _noise_gain_on_truth(truth: np.ndarray, kernel: np.ndarray, counts: float, method: str, seed: int) -> tuple:
    """Flat-part noise gain of the automatic choice on a blurred truth at a photon level."""
    rng = np.random.default_rng(seed)
    clean = ndimage.convolve(truth * counts, kernel, mode="nearest").astype(np.float32)
    noisy = rng.poisson(np.clip(clean, 0, None)).astype(np.float32)
    choice = rg.choose_regularisation(noisy, kernel, method)
    propagated = dc.deconvolve(noisy, kernel, method=method, reg=choice.reg) - \
        dc.deconvolve(clean, kernel, method=method, reg=choice.reg)
    smooth = ndimage.gaussian_filter(truth, 2.0)  # the target image carries its own microscope noise
    edges = np.hypot(ndimage.sobel(smooth, 0), ndimage.sobel(smooth, 1))
    flat = ndimage.uniform_filter(edges, 9) < 0.05 * np.percentile(edges, 99)
    flat[:16], flat[-16:], flat[:, :16], flat[:, -16:] = False, False, False, False
    noise = noisy - clean
    return float(propagated[flat].std() / noise[flat].std()), choice, int(flat.sum())


@pytest.mark.realdata
@pytest.mark.parametrize("counts", [200.0, 2000.0, 20000.0])
def test_saber_target_noise_gain_at_several_noise_levels(shared_data, counts):
    import tifffile

    target = tifffile.imread(shared_data / "resolution_target" / "artifact_ground_truth.tif").astype(np.float64)
    truth = 0.2 + 0.8 * target[340:724, 280:664] / 65535.0  # the star's bars on a flat background
    for method in ("adaptive", "wiener"):
        gain, choice, n_flat = _noise_gain_on_truth(truth, _gaussian_kernel(2.0), counts, method, seed=int(counts))
        assert n_flat > 2000
        assert gain <= 2.0, (counts, method, gain, choice)


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["RG1_UNCR", "RG3_UNCR"])
def test_real_cr_crop_noise_gain(shared_data, name):
    from napari_dslrxr.core.io import read_image

    data = read_image(shared_data / "cr_dicom" / f"{name}.dcm").data.astype(np.float64)
    h, w = data.shape
    crop = data[h // 2 - 128:h // 2 + 128, w // 2 - 128:w // 2 + 128]
    # display value as attenuation -> transmission, as a camera would see the plate
    a = (crop - crop.min()) / max(np.ptp(crop), 1.0)
    truth = np.exp(-2.5 * a)
    kernel = _gaussian_kernel(1.5)
    rng = np.random.default_rng(7)
    clean = ndimage.convolve(truth * 3000.0, kernel, mode="nearest").astype(np.float32)
    noisy = rng.poisson(clean).astype(np.float32)
    choice = rg.choose_regularisation(noisy, kernel, "adaptive")
    propagated = dc.deconvolve(noisy, kernel, reg=choice.reg) - dc.deconvolve(clean, kernel, reg=choice.reg)
    inner = (slice(16, -16), slice(16, -16))
    gain = propagated[inner].std() / (noisy - clean)[inner].std()
    assert gain <= 2.0, (gain, choice)
