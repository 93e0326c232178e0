"""Entry point of the impulse stage for grey and RGB images (grey, grey-of-RGB and HSV paths)."""

from __future__ import annotations

import numpy as np

from ...errors import InputError, ParameterError
from ...progress import ProgressCallback, Steps
from .colour import _remove_hsv, hsv_steps
from .detection import _clean_channel, channel_steps
from .neighbourhoods import _masked_median_at
from .noise_model import _gain
from .params import _FLOAT, _POLARITY_SIGN, ImpulseParams, ImpulseResult, _to_dtype


def remove_impulses(image: np.ndarray, params: ImpulseParams | None = None, *,
                    space: str | None = None, progress: ProgressCallback | None = None) -> ImpulseResult:
    """Detect and replace impulse noise (zingers) in a grey or RGB image.

    Parameters
    ----------
    image : ndarray
        ``(H, W)`` grey or ``(H, W, 3)`` RGB; uint8, uint16, float32 or float64, **linear**
        values (counts; never gamma-encoded), at least 8x8 px.
    params : ImpulseParams, optional
        Defaults: H 3 passes, S 1, V 1, grey 1; 5x5 detection median; bright-only pulses.
    space : {"auto", "grey", "hsv"}, optional
        Default ``params.space``. ``"auto"``: grey for 2-D input, HSV for RGB. ``"grey"`` on RGB detects on R+G+B
        and replaces all three channels at the detected pixels. ``"hsv"``: H, S and V
        separately (H circular, rotated so the dominant hue sits at 0.5; pixels with small S
        or V are left out of hue filtering).
    progress : callable, optional
        Called as ``progress(done, total)`` between the steps of each channel's passes (and
        between chunks of the longer steps). To stop the stage, raise from it (e.g.
        :class:`~napari_dslrxr.core.errors.WorkCancelled`): the exception propagates and
        nothing is returned.

    Returns
    -------
    ImpulseResult
        Cleaned image (same shape and dtype), per-channel masks, gain and pulse rate.

    Raises
    ------
    InputError
        Wrong shape, dtype, NaN values or a too small image.
    ParameterError
        Unknown ``space`` or ``space="hsv"`` on a grey image.
    """
    from ...io import validate_image

    params = ImpulseParams() if params is None else params
    if not isinstance(params, ImpulseParams):
        raise ParameterError(f"impulse: params must be ImpulseParams, got {type(params).__name__}")
    space = params.space if space is None else space
    if space == "cfa":
        raise ParameterError("impulse: space 'cfa' needs the raw Bayer planes of a camera raw file "
                             "(remove_impulses_cfa); this image is already demosaiced")
    if space not in ("auto", "grey", "hsv"):
        raise ParameterError(f"impulse: space must be auto, grey or hsv, got {space!r}")
    arr = np.asarray(image)
    checked = validate_image(arr, "image")
    if checked.shape != arr.shape or checked.dtype != arr.dtype:
        raise InputError("image", f"expected (H, W) or (H, W, 3) uint8/uint16/float32/float64, "
                                  f"got shape {arr.shape} dtype {arr.dtype}")
    if arr.ndim == 2:
        if space == "hsv":
            raise ParameterError("impulse: space 'hsv' needs an RGB image, got a grey one")
        return _remove_grey(arr, params, Steps(progress, channel_steps(params.passes_grey)))
    if space == "grey":
        return _remove_grey_of_rgb(arr, params, Steps(progress, channel_steps(params.passes_grey) + 1))
    return _remove_hsv(arr, params, Steps(progress, hsv_steps(params)))


def _remove_grey(image: np.ndarray, params: ImpulseParams, steps: Steps) -> ImpulseResult:
    x = image.astype(_FLOAT)
    cleaned, mask, model = _clean_channel(x, passes=params.passes_grey, params=params,
                                          photon_counting=True, polarity=_POLARITY_SIGN[params.spots],
                                          texture_sides="two_signed", steps=steps)
    out = image.copy()
    if mask.any():
        # Only pulse pixels are written: medians computed in float32 (exact for integer
        # counts below 2**24), rounded for integer images.
        out[mask] = _to_dtype(cleaned[mask].astype(np.float64), image.dtype)
    return ImpulseResult(out, {"grey": mask}, {"grey": _gain(model, params)},
                         {"grey": model.pulse_rate if model else float("nan")},
                         {"grey": (model.a, model.b) if model else (float("nan"), float("nan"))})


def _remove_grey_of_rgb(image: np.ndarray, params: ImpulseParams, steps: Steps) -> ImpulseResult:
    """Detect on the channel sum (still photon counting) and replace R, G, B at the pulses."""
    grey = image.astype(_FLOAT).sum(axis=2)
    _, mask, model = _clean_channel(grey, passes=params.passes_grey, params=params,
                                    photon_counting=True, polarity=_POLARITY_SIGN[params.spots],
                                    texture_sides="two_signed", steps=steps)
    out = image.copy()
    if mask.any():
        rows, cols = np.nonzero(mask)
        for c in range(3):
            chan = image[..., c].astype(_FLOAT)
            repl = _masked_median_at(chan, mask, rows, cols)
            out[rows, cols, c] = _to_dtype(repl, image.dtype)
    steps.advance()
    return ImpulseResult(out, {"grey": mask}, {"grey": _gain(model, params)},
                         {"grey": model.pulse_rate if model else float("nan")},
                         {"grey": (model.a, model.b) if model else (float("nan"), float("nan"))})
