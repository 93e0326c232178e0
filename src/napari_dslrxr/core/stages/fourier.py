"""The Fourier-domain pieces the deconvolution solvers and the regularisation estimate share.

Everything works on ``scipy.fft`` real-transform (``rfft2``) grids: the padded FFT size of an
image and kernel (:func:`padded_shape`), the closed-form spectra of the derivative filters
(:func:`gradient_spectrum` for the gradient prior of ``"rls"``, :func:`fo_derivative_spectrum`
for the five Fortunato-Oliveira filters of ``"adaptive"``), the kernel's OTF (:func:`kernel_otf`)
and the replicate padding blended towards the mean so the FFT's periodic model holds without a
seam (:func:`pad_and_taper`). See :mod:`.deconvolution` for the solvers built on them.
"""

from __future__ import annotations

import numpy as np

from ..errors import ParameterError


def padded_shape(shape: tuple[int, int], kernel_shape: tuple[int, int]) -> tuple[int, int]:
    """FFT-friendly size with >= 2 kernel radii (and >= 4 px) of padding on each side."""
    import scipy.fft as sfft  # not at module level: the command line imports this module to start

    out = []
    for n, k in zip(shape, kernel_shape):
        pad = max(2 * ((k - 1) // 2), 4)
        out.append(sfft.next_fast_len(n + 2 * pad, real=True))
    return out[0], out[1]


def _frequency_cosines(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``cos(omega)`` along rows (column vector, full) and columns (row vector, half) for rfft2."""
    wy = 2 * np.pi * np.fft.fftfreq(shape[0])
    wx = 2 * np.pi * np.fft.rfftfreq(shape[1])
    return np.cos(wy).astype(np.float32)[:, None], np.cos(wx).astype(np.float32)[None, :]


def gradient_spectrum(shape: tuple[int, int]) -> np.ndarray:
    """``|Dx|^2 + |Dy|^2`` of forward differences on an rfft2 grid of ``shape`` (float32).

    Closed form ``(2 - 2 cos wx) + (2 - 2 cos wy)``.
    """
    cy, cx = _frequency_cosines(shape)
    return (2.0 - 2.0 * cy) + (2.0 - 2.0 * cx)


def fo_derivative_spectrum(shape: tuple[int, int]) -> np.ndarray:
    """``A1 = sum_d |F_d|^2`` of the five Fortunato-Oliveira filters on an rfft2 grid (float32).

    f_x = [-1/2, 0, 1/2] -> sin^2 w; f_xx = [-1, 2, -1]/sqrt 2 -> (2 - 2 cos w)^2 / 2;
    f_xy = sqrt 2 [[-1, 1], [1, -1]] -> 2 (2 - 2 cos wx)(2 - 2 cos wy).
    """
    cy, cx = _frequency_cosines(shape)
    ux, uy = 2.0 - 2.0 * cx, 2.0 - 2.0 * cy
    sx, sy = 1.0 - cx * cx, 1.0 - cy * cy  # sin^2
    row = (sx + 0.5 * ux * ux).astype(np.float32)
    col = (sy + 0.5 * uy * uy).astype(np.float32)
    out = (2.0 * uy) * ux
    out += col
    out += row
    return out.astype(np.float32, copy=False)


def kernel_otf(kernel: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """rfft2 of ``kernel`` zero-padded to ``shape`` with its centre moved to the origin (complex64).

    Two stages: the row transforms of the kernel's few non-zero rows, then a column FFT.
    """
    import scipy.fft as sfft

    kh, kw = kernel.shape
    if kh > shape[0] or kw > shape[1]:
        raise ParameterError(f"blur kernel {kh}x{kw} is larger than the padded image {shape[0]}x{shape[1]}")
    rows = np.zeros((kh, shape[1]), dtype=np.float32)
    rows[:, :kw] = kernel
    rows = np.roll(rows, -(kw // 2), axis=1)
    row_spectra = sfft.rfft(rows, axis=1, workers=-1).astype(np.complex64)
    full = np.zeros((shape[0], shape[1] // 2 + 1), dtype=np.complex64)
    full[(np.arange(kh) - kh // 2) % shape[0]] = row_spectra
    return sfft.fft(full, axis=0, workers=-1, overwrite_x=True).astype(np.complex64, copy=False)


def _cosine_ramp(n_pad: int, towards_image: bool) -> np.ndarray:
    """Raised-cosine weights over ``n_pad`` samples: ~1 next to the image, 0 at the far end."""
    d = np.arange(1, n_pad + 1, dtype=np.float32)  # distance from the image edge
    w = 0.5 * (1.0 + np.cos(np.pi * d / (n_pad + 1)))
    return w[::-1].copy() if towards_image else w


def pad_and_taper(channel: np.ndarray, shape: tuple[int, int], fill: float) -> tuple[np.ndarray, tuple[int, int]]:
    """Replicate-pad a 2-D float32 channel to ``shape`` and fade the padding towards ``fill``.

    The padding is split between both sides of each axis; a raised cosine blends the
    replicated border values into ``fill`` so the padded image is smooth and periodic.

    Returns
    -------
    padded : ndarray of float32, ``shape``
    offset : (int, int)
        Row and column of the image's first pixel inside ``padded``.
    """
    h, w = channel.shape
    top = (shape[0] - h) // 2
    left = (shape[1] - w) // 2
    bottom, right = shape[0] - h - top, shape[1] - w - left
    out = np.pad(channel, ((top, bottom), (left, right)), mode="edge")
    # Rows first (full width), then columns (full height): corners get both weights.
    for sl, n_pad, towards in ((slice(0, top), top, True), (slice(top + h, None), bottom, False)):
        if n_pad:
            ramp = _cosine_ramp(n_pad, towards)[:, None]
            block = out[sl]
            block -= fill
            block *= ramp
            block += fill
    for sl, n_pad, towards in ((slice(0, left), left, True), (slice(left + w, None), right, False)):
        if n_pad:
            ramp = _cosine_ramp(n_pad, towards)[None, :]
            block = out[:, sl]
            block -= fill
            block *= ramp
            block += fill
    return out, (top, left)
