"""Raw Bayer path of the impulse stage: pulses removed on the CFA planes before demosaicing."""

from __future__ import annotations

import numpy as np

from ...errors import InputError
from .detection import _clean_channel
from .noise_model import _RAW_INFLATION_LIMIT, _gain
from .params import _FLOAT, _POLARITY_SIGN, ImpulseParams, ImpulseResult, _to_dtype


def remove_impulses_cfa(planes: np.ndarray, params: ImpulseParams | None = None) -> ImpulseResult:
    """Detect and replace zingers on raw Bayer planes, before demosaicing spreads them.

    Parameters
    ----------
    planes : ndarray, float32, shape (4, h, w)
        CFA planes R, G1, G2, B in counts above black (``RawFrame.cfa_planes``).
    params : ImpulseParams, optional
        ``passes_grey`` passes per plane.

    Returns
    -------
    ImpulseResult
        ``image`` float32 (4, h, w); masks, gain and pulse rate keyed R, G1, G2, B.
    """
    params = ImpulseParams() if params is None else params
    arr = np.asarray(planes)
    if arr.ndim != 3 or arr.shape[0] != 4:
        raise InputError("CFA planes", f"expected shape (4, h, w), got {arr.shape}")
    if arr.dtype.kind != "f" and arr.dtype.kind not in "ui":
        raise InputError("CFA planes", f"unsupported dtype {arr.dtype}")
    if min(arr.shape[1:]) < 8:
        raise InputError("CFA planes", f"planes are {arr.shape[1]}x{arr.shape[2]} px; at least 8x8 needed")
    if arr.dtype.kind == "f" and not np.isfinite(arr).all():
        raise InputError("CFA planes", "NaN or infinite values")
    out = arr.copy()
    masks, gain, rate, noise = {}, {}, {}, {}
    for i, name in enumerate(("R", "G1", "G2", "B")):
        plane = arr[i]
        cleaned, mask, model = _clean_channel(plane.astype(_FLOAT), passes=params.passes_grey,
                                              params=params, photon_counting=True,
                                              polarity=_POLARITY_SIGN[params.spots],
                                              faint_pulses=False, texture_sides="one_signed",
                                              inflation_limit=_RAW_INFLATION_LIMIT)
        if mask.any():
            out[i][mask] = _to_dtype(cleaned[mask].astype(np.float64), arr.dtype)
        masks[name] = mask
        gain[name] = _gain(model, params)
        rate[name] = model.pulse_rate if model else float("nan")
        noise[name] = (model.a, model.b) if model else (float("nan"), float("nan"))
    return ImpulseResult(out, masks, gain, rate, noise)


def cfa_mask_to_mosaic(masks: dict[str, np.ndarray], plane_offsets, shape: tuple[int, int]) -> np.ndarray:
    """Place per-plane masks at their Bayer positions in a (H, W) bool mosaic mask."""
    out = np.zeros(shape, bool)
    for (name, mask), (r, c) in zip(masks.items(), plane_offsets, strict=True):
        sub = out[r::2, c::2]
        hh, ww = min(sub.shape[0], mask.shape[0]), min(sub.shape[1], mask.shape[1])
        sub[:hh, :ww] = mask[:hh, :ww]
    return out


def demosaic_cleaned_raw(path, cleaned_planes: np.ndarray, raw_frame) -> np.ndarray:
    """Demosaic a raw file after putting cleaned CFA planes back into its mosaic.

    Opens ``path`` again with rawpy, writes the cleaned values (plus each plane's black
    level, rounded, clipped to [0, white level]) into ``raw_image_visible`` where they
    differ from the original planes, and demosaics with
    :func:`napari_dslrxr.core.io.postprocess_linear`, as :func:`~napari_dslrxr.core.io.read_raw`
    does. With unchanged planes the result equals ``read_image(path).data`` (tested).

    Parameters
    ----------
    path : path-like
        The raw file the planes came from.
    cleaned_planes : ndarray, float32, (4, h, w)
        Counts above black, R, G1, G2, B (from :func:`remove_impulses_cfa`).
    raw_frame : napari_dslrxr.core.io.RawFrame
        The frame read from ``path``: original planes, plane offsets, black and white level.

    Returns
    -------
    ndarray, uint16, (H, W, 3)
        Linear RGB.
    """
    import rawpy

    from ...io import postprocess_linear

    cleaned = np.asarray(cleaned_planes)
    if cleaned.shape != raw_frame.cfa_planes.shape:
        raise InputError(str(path), f"cleaned planes {cleaned.shape} do not match the file's "
                                    f"{raw_frame.cfa_planes.shape}")
    try:
        with rawpy.imread(str(path)) as raw:
            visible = raw.raw_image_visible
            for plane, original, (r, c), black in zip(cleaned, raw_frame.cfa_planes,
                                                       raw_frame.plane_offsets, raw_frame.black_level,
                                                       strict=True):
                changed = plane != original
                if not changed.any():
                    continue
                rows, cols = np.nonzero(changed)
                values = np.clip(np.rint(plane[rows, cols].astype(np.float64) + float(black)), 0,
                                 raw_frame.white_level)
                visible[2 * rows + r, 2 * cols + c] = values.astype(visible.dtype)
            return postprocess_linear(raw)
    except InputError:
        raise
    except Exception as exc:  # rawpy.LibRawError and friends
        raise InputError(str(path), f"cannot demosaic the cleaned raw data ({exc})") from None


def clean_raw_frame(loaded, params: ImpulseParams | None = None) -> tuple[np.ndarray, ImpulseResult]:
    """The camera raw path of stage (i): pulses removed on the CFA planes, then demosaiced.

    The one clean-then-demosaic sequence ``dslrxr run`` and ``dslrxr denoise`` share:
    :func:`remove_impulses_cfa` on ``loaded.raw.cfa_planes``, then :func:`demosaic_cleaned_raw`
    of ``loaded.path`` with the cleaned planes.

    Parameters
    ----------
    loaded : napari_dslrxr.core.io.LoadedImage
        A camera raw file read with its CFA planes (``loaded.raw`` set).
    params : ImpulseParams, optional

    Returns
    -------
    rgb : ndarray, uint16, (H, W, 3)
        The linear RGB, as the reader gives it, with the pulses replaced.
    result : ImpulseResult
        The cleaned planes, and masks, gain and pulse rate keyed R, G1, G2, B.
    """
    if getattr(loaded, "raw", None) is None:
        raise InputError(str(loaded.path), f"the CFA path needs a camera raw file, got {loaded.format}")
    result = remove_impulses_cfa(loaded.raw.cfa_planes, params)
    return demosaic_cleaned_raw(loaded.path, result.image, loaded.raw), result
