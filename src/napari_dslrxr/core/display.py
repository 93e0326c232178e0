"""The display end of the chain: value-of-interest scaling, dynamic range, contrast, display curve.

Shared by the camera-frame pipeline (:func:`~.pipeline.run_pipeline`, after the grey/log step),
the display-radiograph path (:func:`~.pipeline.run_display_pipeline`: CR/DX DICOM already in
display form) and the napari contrast widget:

* :func:`scale_to_voi_window` - the value-of-interest window mapped to [0, 1];
* :func:`scale_display_radiograph` - that scaling for a display radiograph, inside its
  collimated field;
* :func:`display_steps` / :func:`apply_display_stages` - stages (v) and (vi) and the sigmoid
  display curve, one stage at a time or in one call.
"""

from __future__ import annotations

from collections.abc import Generator

import cv2
import numpy as np

from .params import PipelineParams
from .stages.collimation import detect_collimation
from .stages.contrast import enhance_contrast
from .stages.dynamic_range import (CLIPPED_HIGH, CLIPPED_LOW, add_toe, fit_to_display, foot_toe,
                                   reduce_dynamic_range, sigmoid_lut)
from .stages.region import direct_exposure_masks, voi_window


def scale_to_voi_window(x: np.ndarray, mask: np.ndarray | None, params: PipelineParams) -> tuple[float, float]:
    """Map the VOI window of the region's anatomy to [0, 1], in place on float32 ``x``; return the window.

    The window's percentiles are taken over the region (``mask``; None = all pixels) without
    its direct exposure (:func:`anatomy_grid`), on a regular subsample.
    """
    step, anatomy = anatomy_grid(x, mask, params, at_foot=False)
    lo, hi = voi_window(x[::step, ::step][anatomy], low_percentile=params.region.voi_low_percentile,
                        high_percentile=params.region.voi_high_percentile, exclude_direct_exposure=False)
    x -= np.float32(lo)
    x *= np.float32(1.0 / (hi - lo))
    return lo, hi


def anatomy_grid(image: np.ndarray, mask: np.ndarray | None, params: PipelineParams,
                 at_foot: bool = True) -> tuple[int, np.ndarray]:
    """Regular subsample step and its anatomy mask: inside ``mask``, outside direct exposure.

    ``image`` is attenuation-like (high = more attenuation). Direct exposure is the beam that
    reached the detector without passing the patient (:func:`~.stages.region.direct_exposure_mask`: a narrow
    low-attenuation mode outside the body's outline); lungs and other lucent parts enclosed by
    the body are anatomy. ``at_foot`` (the display's check) takes the conservative level, so
    thin tissue beside the direct exposure counts as anatomy and must not burn out; the
    value-of-interest window takes the valley above the mode.
    """
    step, region, direct = direct_exposure_grid(image, mask, params, (at_foot,))
    return step, without_direct_exposure(region, None if direct is None else direct[0])


def direct_exposure_grid(image: np.ndarray, mask: np.ndarray | None, params: PipelineParams,
                         at_foot: tuple[bool, ...]) -> tuple[int, np.ndarray, tuple[np.ndarray, ...] | None]:
    """Regular subsample step, the region on it, and its direct exposure at each level of ``at_foot``.

    The direct exposure is None when there is none or ``params.region.exclude_direct_exposure``
    is off (:func:`~.stages.region.direct_exposure_masks`: one smoothing and one histogram for
    all levels).
    """
    step = max(1, int(np.sqrt(image.size / 1_000_000)))
    region = np.ones(image[::step, ::step].shape, bool) if mask is None else mask[::step, ::step].copy()
    if not region.any():
        region[...] = True
    direct = None
    if params.region.exclude_direct_exposure:
        direct = direct_exposure_masks(image[::step, ::step], region, at_foot=at_foot)
    return step, region, direct


def without_direct_exposure(region: np.ndarray, direct: np.ndarray | None) -> np.ndarray:
    """The anatomy: ``region`` less ``direct`` (the whole region when that would leave nothing)."""
    if direct is not None and (region & ~direct).any():
        return region & ~direct
    return region


def anatomy_foot_weight(region: np.ndarray, direct: np.ndarray | None) -> np.ndarray | None:
    """Where the display lifts the anatomy's foot: the body as opposed to direct exposure.

    ``region`` and ``direct`` are on the statistics grid (:func:`direct_exposure_grid`), the
    direct exposure taken at the value-of-interest window's level (not at the mode's foot): the
    beam's glow near the field's edge then stays black, and the body's outline lies on the
    skin's steep rise. Returns a float32 weight on that grid (1 = anatomy, 0 = direct exposure,
    feathered by a Gaussian of 1 grid pixel), or None when there is no direct exposure. An
    opening by a disc of 1 % of the short side drops strips narrower than that (the penumbra
    along a collimator blade), which are not anatomy.
    """
    if direct is None or not direct.any():
        return None
    size = max(5, (min(region.shape) // 100) | 1)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    body = cv2.morphologyEx((region & ~direct).astype(np.uint8), cv2.MORPH_OPEN, disc)
    if not body.any():
        return None
    return cv2.GaussianBlur(body.astype(np.float32), (0, 0), 1.0)


def apply_anatomy_foot(display: np.ndarray, step: int, weight: np.ndarray, floor: float, rows: int = 512) -> None:
    """:func:`~.stages.dynamic_range.lift_anatomy_foot` in place, ``weight`` on the grid of ``step``.

    The weight is brought to full size in blocks of ``rows`` (pixel ``(r, c)`` reads the grid
    at ``(r / step, c / step)``, bilinear), so no full-size weight is held; only the columns
    with anatomy are touched.
    """
    top, scale = foot_toe(floor)
    scaled = weight * scale
    h, w = display.shape
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        cols = np.flatnonzero(scaled[r0 // step: (r1 - 1) // step + 2].any(axis=0))
        if cols.size == 0:
            continue
        c0, c1 = max(0, (cols[0] - 1) * step), min(w, (cols[-1] + 2) * step)  # the columns with anatomy
        to_grid = np.float32([[1.0 / step, 0.0, c0 / step], [0.0, 1.0 / step, r0 / step]])
        block = scaled[r0:r1, c0:c1] if step == 1 else cv2.warpAffine(
            scaled, to_grid, (c1 - c0, r1 - r0), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE)
        add_toe(display[r0:r1, c0:c1], block, top)


#: Self-check bounds of a display image: the anatomy's share at pure black or white, and the
#: least correlation of the displayed anatomy with its (value-of-interest scaled) attenuation.
MAX_PLAUSIBLE_CLIPPED = 0.01
MIN_POLARITY_EVIDENCE = 0.5


def display_self_check(shown: np.ndarray, attenuation: np.ndarray, clipped_fraction: float) -> dict:
    """Is the display of the anatomy plausible? ``polarity_evidence`` and, when not, ``warning``.

    ``shown`` are the displayed anatomy values, ``attenuation`` the same pixels' value-of-interest
    scaled attenuation (bone white). Enhancement changes local contrast but keeps the display
    increasing with attenuation over the anatomy: measured r 0.8-0.99 on the real CR chest and
    leg, their camera frames and the demo. A burned-out or inverted anatomy (its values at one
    end of the display, or darker where it attenuates more) gives r near 0 or below, and a
    clipped share beyond the display's own 0.5 % bound means the anatomy was mis-identified
    (its "direct exposure" was part of it) or the settings burn it out.
    """
    out: dict = {}
    r = 0.0
    if shown.size >= 16 and float(np.std(shown)) > 0 and float(np.std(attenuation)) > 0:
        r = float(np.corrcoef(shown.astype(np.float64), attenuation.astype(np.float64))[0, 1])
    out["polarity_evidence"] = round(r, 4)
    problems = []
    if clipped_fraction > MAX_PLAUSIBLE_CLIPPED:
        problems.append(f"{100 * clipped_fraction:.1f} % of the anatomy is shown pure black or white "
                        f"(more than {100 * MAX_PLAUSIBLE_CLIPPED:.0f} %)")
    if r < MIN_POLARITY_EVIDENCE:
        problems.append(f"the displayed anatomy does not follow its attenuation (r = {r:.2f}, "
                        f"expected >= {MIN_POLARITY_EVIDENCE}): inverted or burned out")
    if problems:
        out["warning"] = "display implausible: " + "; ".join(problems) + "; check the region and display settings"
    return out


def display_steps(image: np.ndarray, mask: np.ndarray | None, params: PipelineParams,
                   fill_outside: bool = True, report: dict | None = None) -> Generator[np.ndarray, None, None]:
    """Yield the image after dynamic-range reduction, after contrast, and the display image.

    The body of :func:`apply_display_stages`, one stage per ``next`` so that
    :func:`~.pipeline.run_pipeline` can report progress and time each stage. The generator releases
    ``image`` once the first stage is done and each stage's result once the next is done.
    Before the display curve the anatomy is kept off the display's ends
    (:func:`~napari_dslrxr.core.dynamic_range.fit_to_display`); after it, beside direct exposure,
    the anatomy's darkest values are lifted off black (:func:`anatomy_foot_weight`,
    ``dynamic_range.anatomy_floor``). ``report`` (when given) gets
    the adjustment (``display_fit``) and the share of the anatomy still clipped
    (``clipped_fraction``).
    """
    step, region, direct = direct_exposure_grid(image, mask, params, (True, False))
    anatomy = without_direct_exposure(region, None if direct is None else direct[0])
    scaled_anatomy = image[::step, ::step][anatomy].copy() if report is not None else None
    floor = params.dynamic_range.anatomy_floor
    foot = anatomy_foot_weight(region, direct[1]) if direct is not None and floor > 0 else None
    x = reduce_dynamic_range(image, mask, params.dynamic_range)
    del image
    yield x
    x = enhance_contrast(x, params.contrast, mask)
    yield x
    fit = fit_to_display(x, x[::step, ::step][anatomy], params.dynamic_range)
    x = sigmoid_lut(x, params.dynamic_range)
    if foot is not None:
        apply_anatomy_foot(x, step, foot, floor)
    if report is not None:
        shown = x[::step, ::step][anatomy]
        report["display_fit"] = fit
        report["clipped_fraction"] = round(float(np.mean((shown <= CLIPPED_LOW) | (shown >= CLIPPED_HIGH))), 5) \
            if shown.size else 0.0
        report.update(display_self_check(shown, scaled_anatomy, report["clipped_fraction"]))
    if fill_outside and mask is not None and not mask.all():
        x[~mask] = 0.0 if params.output.outside_region == "black" else 1.0
    yield x


def apply_display_stages(image: np.ndarray, mask: np.ndarray | None = None,
                         params: PipelineParams | None = None, *, fill_outside: bool = True,
                         report: dict | None = None) -> np.ndarray:
    """Stages v-vi and the display curve on a value-of-interest scaled attenuation image.

    The display end of the chain, shared by :func:`~.pipeline.run_pipeline`, :func:`~.pipeline.enhance_radiograph`
    and the napari contrast widget: dynamic-range / latitude reduction
    (:func:`~napari_dslrxr.core.stages.dynamic_range.reduce_dynamic_range`), multiscale contrast
    (:func:`~napari_dslrxr.core.stages.contrast.enhance_contrast`), the sigmoid display curve
    (:func:`~napari_dslrxr.core.stages.dynamic_range.sigmoid_lut`), then the pixels outside the
    region set to black (0) or white (1) as ``params.output.outside_region`` says.

    Parameters
    ----------
    image : ndarray, float32, (H, W)
        Value-of-interest scaled attenuation, dimensionless: the VOI window maps to 0..1
        (values outside it are kept). Not modified.
    mask : ndarray, bool, (H, W), optional
        Screen region: the stages' statistics and low-passes use only these pixels.
        None = all pixels.
    params : PipelineParams, optional
        Uses ``dynamic_range``, ``contrast`` and ``output.outside_region``.
    fill_outside : bool
        Set the pixels outside ``mask`` to the ``outside_region`` value (as the pipeline's
        output does); False leaves them processed like the rest.
    report : dict, optional
        Receives ``display_fit`` (the compression that kept the anatomy off the display's
        ends) and ``clipped_fraction`` (the share of the anatomy still at pure black or
        white), as the pipeline's sidecar records them.

    Returns
    -------
    ndarray, float32, (H, W)
        Display values in [0, 1] (a new array).
    """
    params = params or PipelineParams()
    for display in display_steps(image, mask, params, fill_outside, report):
        pass  # rebinding drops each intermediate as soon as the next stage is done
    return display


def scale_display_radiograph(image: np.ndarray, params: PipelineParams | None = None,
                             mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None, bool]:
    """Value-of-interest scaling of a grey display radiograph, inside its collimated field.

    The step before :func:`apply_display_stages` for radiographs that are already log-scaled
    and bone-bright (CR/DR DICOM after MONOCHROME1 inversion), shared by
    :func:`~.pipeline.enhance_radiograph` and the napari contrast widget.

    Parameters
    ----------
    image : ndarray, (H, W)
        Grey radiograph (any real dtype), higher = brighter on display. Not modified.
    params : PipelineParams, optional
        Uses ``region`` (VOI percentiles, ``detect_collimation``, ``collimation_inset_px``).
    mask : ndarray, bool, optional
        Region of interest for the statistics. Default: when ``params.region.detect_collimation``
        is true, the exposed field found by :func:`~napari_dslrxr.core.stages.collimation.detect_collimation`;
        None (all pixels) when no collimation is found or detection is off.

    Returns
    -------
    scaled : ndarray, float32, (H, W)
        The VOI window mapped to 0..1 (values outside it kept).
    mask : ndarray, bool, (H, W) or None
        The region used.
    fill_outside : bool
        True when ``mask`` is a detected collimated field, whose outside the display should
        shutter (a caller's own mask only restricts the statistics).
    """
    x, mask, field, _ = scale_display_field(image, params or PipelineParams(), mask)
    return x, mask, field is not None


def scale_display_field(image: np.ndarray, params: PipelineParams, mask: np.ndarray | None):
    """:func:`scale_display_radiograph`, also giving the collimated field found (a
    :class:`~.region.Region`, or None) and the VOI window."""
    x = np.asarray(image, np.float32).copy()
    field = None
    if mask is None and params.region.detect_collimation:
        found = detect_collimation(x, inset_px=params.region.collimation_inset_px, drop_penumbra=True)
        if found.detected:
            field, mask = found, found.mask
    window = scale_to_voi_window(x, mask, params)
    return x, mask, field, window
