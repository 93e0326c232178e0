"""The Fourier-domain pieces of the deconvolution: padding, kernel OTF, derivative spectra."""

from __future__ import annotations

import numpy as np

from napari_dslrxr.core.stages import fourier


def test_pad_and_taper_keeps_the_image_and_is_periodic():
    img = np.arange(20 * 30, dtype=np.float32).reshape(20, 30)
    padded, (r0, c0) = fourier.pad_and_taper(img, (32, 48), fill=-5.0)
    np.testing.assert_array_equal(padded[r0:r0 + 20, c0:c0 + 30], img)
    # Both ends of each axis approach the fill value, so the periodic seam is smooth.
    assert np.max(np.abs(padded[0] - padded[-1])) < 0.05 * np.ptp(img)
    assert np.max(np.abs(padded[:, 0] - padded[:, -1])) < 0.05 * np.ptp(img)


def test_kernel_otf_matches_numpy_fft_of_the_centred_kernel():
    """Independent reference: numpy's full FFT of the kernel zero-padded and rolled so its centre is at (0, 0)."""
    rng = np.random.default_rng(3)
    kernel = rng.random((5, 7)).astype(np.float32)
    kernel /= kernel.sum()
    shape = (24, 30)
    padded = np.zeros(shape, np.float64)
    padded[:5, :7] = kernel
    padded = np.roll(padded, (-2, -3), axis=(0, 1))
    expected = np.fft.rfft2(padded)
    np.testing.assert_allclose(fourier.kernel_otf(kernel, shape), expected, atol=1e-5)


def test_gradient_spectrum_is_the_forward_difference_power():
    shape = (16, 20)
    dx = np.zeros(shape)
    dx[0, 0], dx[0, 1] = -1.0, 1.0
    dy = np.zeros(shape)
    dy[0, 0], dy[1, 0] = -1.0, 1.0
    expected = np.abs(np.fft.rfft2(dx)) ** 2 + np.abs(np.fft.rfft2(dy)) ** 2
    np.testing.assert_allclose(fourier.gradient_spectrum(shape), expected, atol=1e-5)
