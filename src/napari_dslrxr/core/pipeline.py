"""The whole chain, from a camera frame to a display-ready radiograph.

Stages follow the target paper's order: on the colour image (i) impulse removal, (ii) flat
field per channel, (iii) screen region and value-of-interest scaling, (iv) optional
deblurring (only with a PSF kernel); then on grey, in the log (attenuation) domain, (v)
dynamic-range / latitude reduction and (vi) multiscale contrast, finished by the sigmoid
display curve.

:func:`run_pipeline` is a generator: it yields ``(done, total)`` after each stage (the name of
stage ``done`` is ``PIPELINE_STAGES[done - 1]``) and returns a :class:`PipelineResult`.
:func:`process_frame` runs it to completion. :func:`run_file` reads a file, runs the chain
and writes the outputs (16-bit TIFF, PNG preview, optional DICOM DX), each with a JSON
sidecar (parameters, version, input checksums, stage timings).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .stages.contrast import enhance_contrast
from .stages.dynamic_range import CLIPPED_HIGH, CLIPPED_LOW, fit_to_display, reduce_dynamic_range, \
    sigmoid_lut
from .errors import InputError, OutputError, ParameterError
from .stages.flatfield import FlatReference, apply_flat_field, prepare_flat_reference
from .params import PipelineParams, params_to_dict, params_to_toml, validate_params
from .stages.collimation import detect_collimation
from .stages.exposure_index import dicom_exposure_tags, exposure_index_record, not_linear_record
from .stages.region import Region, direct_exposure_level, polygon_mask, rectify, voi_window
from .stages.screen import detect_screen

#: Stage names, in the order their progress steps are yielded.
PIPELINE_STAGES = ("impulse", "flatfield", "region", "deblur", "grey_log", "dynamic_range", "contrast", "display")


@dataclass
class PipelineResult:
    """What a pipeline run produced.

    Attributes
    ----------
    display : ndarray, float32, (H, W)
        Display-ready radiograph in [0, 1] (after the sigmoid curve).
    region : Region
        Screen mask and corners (in the input frame's coordinates).
    voi_window : (float, float)
        Attenuation (log) values mapped to 0 and 1.
    timings_s : dict
        Wall time of each stage, seconds.
    results : dict
        Numbers worth keeping (pulse rate, gain, flat-field statistics, stage notes);
        ``results["warnings"]`` lists, one line each, the stages that were skipped or had to
        guess (no flat, no PSF, no screen found, ...): the CLI prints them, the widgets show them.
    intermediates : dict
        Named intermediate images when ``keep_intermediates=True`` (``"impulse"``,
        ``"flatfield"``, ``"attenuation"``, ``"dynamic_range"``, ``"contrast"``).
    params : PipelineParams
    """

    display: np.ndarray
    region: Region
    voi_window: tuple[float, float]
    timings_s: dict = field(default_factory=dict)
    results: dict = field(default_factory=dict)
    intermediates: dict = field(default_factory=dict)
    params: PipelineParams | None = None

    def display_uint16(self) -> np.ndarray:
        """The display image scaled to 0..65535 (uint16)."""
        return to_uint16(self.display)


def to_uint16(display: np.ndarray) -> np.ndarray:
    """[0, 1] float -> uint16 with rounding."""
    out = np.clip(display, 0.0, 1.0) * np.float32(65535.0)
    out += 0.5
    return out.astype(np.uint16)


def _impulse_stage(image: np.ndarray, params: PipelineParams, results: dict) -> np.ndarray:
    from .stages.impulse import remove_impulses

    impulse = params.impulse
    if not any((impulse.passes_h, impulse.passes_s, impulse.passes_v, impulse.passes_grey)):
        results["impulse"] = "skipped (all passes 0)"
        return image
    res = remove_impulses(image, impulse)
    results["impulse"] = _impulse_record(res)
    return res.image


def _impulse_record(res, **where) -> dict:
    """What the sidecar keeps of an impulse removal: pulse pixels per channel, gain, pulse rate."""
    return {**where, "pulse_pixels": {k: int(np.count_nonzero(v)) for k, v in res.masks.items()},
            "gain": res.gain, "pulse_rate": res.pulse_rate}


def _deblur_stage(colour: np.ndarray, mask: np.ndarray, kernel: np.ndarray, params: PipelineParams,
                  results: dict) -> np.ndarray:
    from .stages.deconvolution import check_reg, deconvolve
    from .stages.regularisation import choose_regularisation

    # scale each channel to about [0, 1] over the region (the solver's expected range)
    chans = colour if colour.ndim == 3 else colour[..., None]
    scales = []
    for c in range(chans.shape[2]):
        sample = chans[..., c][mask] if mask.any() else chans[..., c].ravel()
        scales.append(max(float(np.percentile(sample, 99.5)), 1e-6))
    scale = np.asarray(scales, np.float32)
    normalised = chans / scale
    solver_input = normalised if colour.ndim == 3 else normalised[..., 0]
    reg_used = check_reg(params.deblur.reg)
    auto = None
    if reg_used == "auto":  # estimate here (once) so the sidecar records the number the solver used
        auto = choose_regularisation(solver_input, kernel, params.deblur.method)
        reg_used = auto.reg
        results["warnings"].extend(f"deblurring: automatic regularisation unreliable: {text}"
                                   for text in auto.warnings)
    out = deconvolve(solver_input, kernel, method=params.deblur.method, reg=reg_used)
    out = (out if out.ndim == 3 else out[..., None]) * scale
    results["deblur"] = {"kernel_shape": list(kernel.shape), "method": params.deblur.method,
                         "reg": params.deblur.reg, "reg_used": reg_used}
    if auto is not None:
        results["deblur"]["auto"] = auto.as_dict()
    return out if colour.ndim == 3 else out[..., 0]


def _scale_to_voi_window(x: np.ndarray, sample: np.ndarray, params: PipelineParams) -> tuple[float, float]:
    """Map the VOI window found on ``sample`` to [0, 1], in place on float32 ``x``; return the window."""
    lo, hi = voi_window(sample, low_percentile=params.region.voi_low_percentile,
                        high_percentile=params.region.voi_high_percentile,
                        exclude_direct_exposure=params.region.exclude_direct_exposure)
    x -= np.float32(lo)
    x *= np.float32(1.0 / (hi - lo))
    return lo, hi


def _may_hold_blades(display_oriented: np.ndarray, mask: np.ndarray, factor: float) -> bool:
    """Cheap test before the blade search: does a side strip of the region attenuate like a blade?

    A blade's band lies along a side of the region (the screen or the frame): the outer 5 %
    strip of the region's bounding box on that side is then at least as dense as 95 % of the
    region's middle (the box without its outer 20 %). When no side is, the search (and its
    imports) is skipped.
    """
    sh, sw = display_oriented.shape
    small_mask = cv2.resize(mask.astype(np.uint8), (sw, sh), interpolation=cv2.INTER_NEAREST).astype(bool) \
        if factor > 1 else mask
    rows, cols = np.nonzero(small_mask.any(axis=1))[0], np.nonzero(small_mask.any(axis=0))[0]
    if rows.size < 16 or cols.size < 16:
        return False
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    dr, dc = max(2, (r1 - r0) // 20), max(2, (c1 - c0) // 20)
    # the density to beat: 95 % of the region's middle (bands may cover much of its outer part)
    middle = (slice(r0 + 4 * dr, r1 - 4 * dr), slice(c0 + 4 * dc, c1 - 4 * dc))
    values = display_oriented[middle][small_mask[middle]]
    if values.size < 16:
        return True
    top = float(np.percentile(values[:: max(1, values.size // 200_000)], 95))
    for strip in ((slice(r0, r0 + dr), slice(c0, c1)), (slice(r1 - dr, r1), slice(c0, c1)),
                  (slice(r0, r1), slice(c0, c0 + dc)), (slice(r0, r1), slice(c1 - dc, c1))):
        inside = small_mask[strip]
        if np.count_nonzero(inside) >= 32 and float(np.median(display_oriented[strip][inside])) >= top:
            return True
    return False


def _collimated_field(attenuation: np.ndarray, mask: np.ndarray, region: Region, params: PipelineParams,
                      results: dict) -> tuple[np.ndarray, Region]:
    """Collimator blades on a camera frame: leave the unexposed bands out of the region.

    Blades shade straight bands of the screen that got (almost) no X-rays; in the
    bone-white attenuation image they are bright and uniform, as on a CR plate, so
    :func:`~napari_dslrxr.core.stages.collimation.detect_collimation` finds them. The inset scales with
    the frame (``collimation_inset_px`` is for a 2000 px radiograph).
    """
    h, w = attenuation.shape
    # a copy of at most 2000 px a side is plenty for blades (and costs little on 24 Mpx frames)
    factor = max(1.0, max(h, w) / 2000.0)
    small = cv2.resize(attenuation, (max(16, round(w / factor)), max(16, round(h / factor))),
                       interpolation=cv2.INTER_AREA) if factor > 1 else attenuation
    display_oriented = small if params.output.polarity == "bone_white" else -small
    # Behind a blade a camera frame gets a few counts at most: its log is noise, wider than the
    # field's anatomy, and fails the blade test's uniformity (a starved blade went undetected
    # and its band took the value-of-interest window). A 1 px Gaussian averages that noise down.
    display_oriented = cv2.GaussianBlur(display_oriented, (0, 0), 1.0)
    results["collimation"] = {"detected": False}
    if not _may_hold_blades(display_oriented, mask, factor):
        return mask, region
    inset = params.region.collimation_inset_px * min(1.0, max(h, w) / 2000.0) / factor
    found = detect_collimation(display_oriented, inset_px=inset)
    if not found.detected:
        return mask, region
    polygon = (found.polygon_xy + 0.5) * np.array([w / small.shape[1], h / small.shape[0]]) - 0.5
    field = Region(polygon_mask((h, w), polygon), polygon) if factor > 1 else found
    combined = mask & field.mask
    band = mask & ~field.mask
    step = max(1, int(np.sqrt(attenuation.size / 1_000_000)))
    inside, beyond = combined[::step, ::step], band[::step, ::step]
    if not inside.any() or not beyond.any():
        return mask, region
    # Behind a blade the screen gets scatter only: the band must attenuate more than almost all
    # of the field, and get less than e^-1 (37 %) of the field's median light (a uniform stretch
    # of soft tissue at the frame's side, or the vignetting of a frame without a flat, does not)
    sub = attenuation[::step, ::step] if params.output.polarity == "bone_white" else -attenuation[::step, ::step]
    band_level = float(np.median(sub[beyond]))
    field_mid, field_top = (float(v) for v in np.percentile(sub[inside], [50, 95]))
    if band_level < field_top or abs(band_level - field_mid) < 1.0:
        results["collimation"]["rejected"] = ("the band beyond the edges is not darker than 95 % of the field "
                                              "or gets more than 37 % of its median light")
        return mask, region
    results["collimation"] = {"detected": True, "polygon_xy": field.polygon_xy.round(2).tolist()}
    region = Region(combined, region.polygon_xy, region.detected, {**region.evidence, "collimation": True})
    results["region"]["area_fraction"] = float(combined.mean())
    return combined, region


def run_pipeline(image: np.ndarray, *, flats: Sequence[np.ndarray] = (), darks: Sequence[np.ndarray] = (),
                 black_level=None, psf_kernel: np.ndarray | None = None,
                 params: PipelineParams | None = None, reference: FlatReference | None = None,
                 keep_intermediates: bool = False,
                 impulses_removed: dict | None = None) -> Generator[tuple[int, int], None, PipelineResult]:
    """Run the six stages on one frame, yielding ``(done, total)`` after each stage.

    Parameters
    ----------
    image : ndarray, (H, W, 3) or (H, W)
        Linear camera frame in counts (uint16 or float); never gamma-encoded.
    flats, darks : sequence of ndarray
        Open-beam and dark frames of the same shape (counts). Optional.
    black_level : float or sequence, optional
        Offset per channel when no dark frame is given (default ``params.flatfield.black_level_counts``).
    psf_kernel : ndarray, optional
        Blur kernel on the frame's pixel grid; deblurring (stage iv) runs only when given.
    params : PipelineParams, optional
    reference : FlatReference, optional
        A prepared flat-field reference (reuse across a batch); overrides flats/darks.
    keep_intermediates : bool
        Keep the intermediate images in the result (memory: several full-size copies).
    impulses_removed : dict, optional
        Set when stage (i) already ran on the raw CFA planes (:func:`run_file` does this for
        camera raw input); its statistics are recorded and the stage is skipped.

    Returns
    -------
    PipelineResult
        Via ``StopIteration.value``; use :func:`process_frame` for a plain call.

    Raises
    ------
    InputError
        Wrong shape or dtype, NaN values, or flats/darks not matching the frame.
    """
    from .io import validate_image

    params = params or PipelineParams()
    image = validate_image(image, "image")
    total = len(PIPELINE_STAGES)
    timings: dict[str, float] = {}
    results: dict = {}
    warnings: list[str] = results.setdefault("warnings", [])  # stages skipped or guessed, one line each
    inter: dict = {}
    clock = time.perf_counter

    # (i) impulse removal on the colour image (linear counts)
    t0 = clock()
    if impulses_removed is not None:
        results["impulse"] = impulses_removed
        cleaned = image
    else:
        cleaned = _impulse_stage(image, params, results)
    if keep_intermediates:
        inter["impulse"] = cleaned
    timings["impulse"] = clock() - t0
    yield 1, total

    # (ii) flat field per colour channel
    t0 = clock()
    if reference is None:
        offset = black_level if black_level is not None else params.flatfield.black_level_counts
        reference = prepare_flat_reference(image.shape, flats=flats, darks=darks, black_level=offset,
                                           params=params.flatfield)
    corrected = apply_flat_field(cleaned, reference)
    del cleaned
    results["flatfield"] = {"n_flats": reference.n_flats, "reference_pulses_cleaned": reference.cleaned_pulses,
                            "applied": reference.denominator is not None}
    if reference.denominator is None:
        warnings.append("no flat frame given: flat field not corrected (uneven illumination stays in the image)")
    if keep_intermediates:
        inter["flatfield"] = corrected
    timings["flatfield"] = clock() - t0
    yield 2, total

    # (iii) screen region (values of interest come after the grey/log conversion)
    t0 = clock()
    region = detect_screen(corrected, params.region, illumination=reference.denominator)
    results["region"] = {"polygon_xy": region.polygon_xy.round(2).tolist(), "detected": region.detected,
                         "area_fraction": float(region.mask.mean()), "evidence": region.evidence}
    if not region.detected and "reason" in region.evidence:
        used = ("the area the flat frame saw exposed is used" if "flat_exposed_fraction" in region.evidence
                else "the whole frame is used")
        warnings.append(f"region: no screen found ({region.evidence['reason']}); {used}")
    timings["region"] = clock() - t0
    yield 3, total

    # (iv) optional deblurring, per channel, in linear intensity
    t0 = clock()
    if psf_kernel is not None:
        corrected = _deblur_stage(corrected, region.mask, np.asarray(psf_kernel, np.float32), params, results)
    else:
        results["deblur"] = "skipped (no PSF model given)"
        warnings.append("no PSF model given: not deblurred")
    timings["deblur"] = clock() - t0
    yield 4, total

    # grey (sum of channels = photon-count weighting), log domain, VOI scaling
    t0 = clock()
    grey = corrected.sum(axis=2, dtype=np.float32) if corrected.ndim == 3 else corrected.astype(np.float32)
    del corrected
    mask = region.mask
    if params.region.rectify and (region.detected or params.region.polygon_xy):
        grey = rectify(grey, region.polygon_xy)
        mask = np.ones(grey.shape, bool)
    step = max(1, int(np.sqrt(grey.size / 1_000_000)))  # statistics from a regular subsample
    sub_mask = mask[::step, ::step]
    sample = grey[::step, ::step][sub_mask] if sub_mask.any() else grey[::step, ::step].ravel()
    floor = max(float(np.percentile(sample, 99.5)) * 1e-3, 1e-6)
    np.maximum(grey, floor, out=grey)
    attenuation = np.log(grey, out=grey)  # in place: grey is not needed any more
    if params.output.polarity == "bone_white":
        np.negative(attenuation, out=attenuation)
    if params.region.detect_collimation:
        mask, region = _collimated_field(attenuation, mask, region, params, results)
        sub_mask = mask[::step, ::step]
    sub_att = attenuation[::step, ::step]
    # exposure index: on the linear signal (the logarithm undone on the subsample), before any display mapping
    linear_sample = np.exp(-sub_att if params.output.polarity == "bone_white" else sub_att)
    results["exposure_index"] = exposure_index_record(linear_sample, sub_mask if sub_mask.any() else None,
                                                      params.exposure)
    lo, hi = _scale_to_voi_window(attenuation, sub_att[sub_mask] if sub_mask.any() else sub_att, params)
    results["voi_window"] = [lo, hi]
    if keep_intermediates:
        inter["attenuation"] = attenuation.copy()
    timings["grey_log"] = clock() - t0
    yield 5, total

    # (v) dynamic-range / latitude reduction, (vi) multiscale contrast, display curve: the
    # same steps as apply_display_stages, one at a time for the progress and the timings
    display_report: dict = {}
    display_steps = _display_steps(attenuation, mask, params, report=display_report)
    del attenuation  # the steps' generator holds it until stage (v) is done
    for step, stage in ((6, "dynamic_range"), (7, "contrast")):
        t0 = clock()
        stage_output = next(display_steps)
        if keep_intermediates:
            inter[stage] = stage_output.copy()
        del stage_output
        timings[stage] = clock() - t0
        yield step, total

    t0 = clock()
    display = next(display_steps)
    results["display"] = display_report
    timings["display"] = clock() - t0
    yield 8, total
    return PipelineResult(display=display, region=region, voi_window=(lo, hi), timings_s=timings,
                          results=results, intermediates=inter, params=params)


def _anatomy_grid(image: np.ndarray, mask: np.ndarray | None, params: PipelineParams) -> tuple[int, np.ndarray]:
    """Regular subsample step and its anatomy mask: inside ``mask``, outside direct exposure.

    ``image`` is the value-of-interest scaled attenuation; the direct-exposure level is the
    one the value-of-interest window leaves out (:func:`direct_exposure_level`).
    """
    step = max(1, int(np.sqrt(image.size / 1_000_000)))
    sub = image[::step, ::step]
    anatomy = np.ones(sub.shape, bool) if mask is None else mask[::step, ::step].copy()
    if not anatomy.any():
        anatomy[...] = True
    if params.region.exclude_direct_exposure:
        # the conservative level: thin tissue beside the direct exposure must not burn out
        low = direct_exposure_level(sub[anatomy], at_foot=True)
        if low is not None:
            anatomy &= sub >= low
    return step, anatomy


def _display_steps(image: np.ndarray, mask: np.ndarray | None, params: PipelineParams,
                   fill_outside: bool = True, report: dict | None = None) -> Generator[np.ndarray, None, None]:
    """Yield the image after dynamic-range reduction, after contrast, and the display image.

    The body of :func:`apply_display_stages`, one stage per ``next`` so that
    :func:`run_pipeline` can report progress and time each stage. The generator releases
    ``image`` once the first stage is done and each stage's result once the next is done.
    Before the display curve the anatomy is kept off the display's ends
    (:func:`~napari_dslrxr.core.dynamic_range.fit_to_display`); ``report`` (when given) gets
    the adjustment (``display_fit``) and the share of the anatomy still clipped
    (``clipped_fraction``).
    """
    step, anatomy = _anatomy_grid(image, mask, params)
    x = reduce_dynamic_range(image, mask, params.dynamic_range)
    del image
    yield x
    x = enhance_contrast(x, params.contrast, mask)
    yield x
    fit = fit_to_display(x, x[::step, ::step][anatomy], params.dynamic_range)
    x = sigmoid_lut(x, params.dynamic_range)
    if report is not None:
        shown = x[::step, ::step][anatomy]
        report["display_fit"] = fit
        report["clipped_fraction"] = round(float(np.mean((shown <= CLIPPED_LOW) | (shown >= CLIPPED_HIGH))), 5) \
            if shown.size else 0.0
    if fill_outside and mask is not None and not mask.all():
        x[~mask] = 0.0 if params.output.outside_region == "black" else 1.0
    yield x


def apply_display_stages(image: np.ndarray, mask: np.ndarray | None = None,
                         params: PipelineParams | None = None, *, fill_outside: bool = True,
                         report: dict | None = None) -> np.ndarray:
    """Stages v-vi and the display curve on a value-of-interest scaled attenuation image.

    The display end of the chain, shared by :func:`run_pipeline`, :func:`enhance_radiograph`
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
    for display in _display_steps(image, mask, params, fill_outside, report):
        pass  # rebinding drops each intermediate as soon as the next stage is done
    return display


def scale_display_radiograph(image: np.ndarray, params: PipelineParams | None = None,
                             mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None, bool]:
    """Value-of-interest scaling of a grey display radiograph, inside its collimated field.

    The step before :func:`apply_display_stages` for radiographs that are already log-scaled
    and bone-bright (CR/DR DICOM after MONOCHROME1 inversion), shared by
    :func:`enhance_radiograph` and the napari contrast widget.

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
    x, mask, field, _ = _scale_display(image, params or PipelineParams(), mask)
    return x, mask, field is not None


def _scale_display(image: np.ndarray, params: PipelineParams, mask: np.ndarray | None):
    """:func:`scale_display_radiograph`, also giving the collimated field found (a
    :class:`~.region.Region`, or None) and the VOI window."""
    x = np.asarray(image, np.float32).copy()
    field = None
    if mask is None and params.region.detect_collimation:
        found = detect_collimation(x, inset_px=params.region.collimation_inset_px)
        if found.detected:
            field, mask = found, found.mask
    window = _scale_to_voi_window(x, x[mask] if mask is not None else x, params)
    return x, mask, field, window


def enhance_radiograph(image: np.ndarray, params: PipelineParams | None = None,
                       mask: np.ndarray | None = None) -> np.ndarray:
    """Stages v-vi and the display curve on a grey radiograph already in display orientation.

    :func:`scale_display_radiograph` (value-of-interest scaling inside the collimated field),
    then :func:`apply_display_stages` (dynamic-range reduction, multiscale contrast, sigmoid
    curve; a detected collimator band is set to ``params.output.outside_region``).

    Parameters
    ----------
    image : ndarray, (H, W)
        Grey radiograph (any real dtype), higher = brighter on display.
    params : PipelineParams, optional
        Uses ``region`` (VOI percentiles, collimation), ``dynamic_range``, ``contrast``,
        ``output.outside_region`` and ``output.polarity`` (as :func:`run_display_pipeline`).
    mask : ndarray, bool, optional
        Region of interest for the statistics (pixels outside are processed, not filled);
        default: the detected collimated field, see :func:`scale_display_radiograph`.

    Returns
    -------
    ndarray, float32, (H, W)
        Display values in [0, 1].
    """
    return process_display_radiograph(image, params=params, mask=mask).display


#: Stage names of the display-radiograph path, in the order their progress steps are yielded.
DISPLAY_STAGES = ("region", "dynamic_range", "contrast", "display")


def run_display_pipeline(image: np.ndarray, *, params: PipelineParams | None = None,
                         mask: np.ndarray | None = None,
                         keep_intermediates: bool = False) -> Generator[tuple[int, int], None, PipelineResult]:
    """The display path for a radiograph already in display form, yielding ``(done, total)``.

    What ``dslrxr run`` does with a display radiograph (a CR/DX DICOM, bone bright after
    MONOCHROME1 inversion): :func:`scale_display_radiograph` (collimated field, value-of-interest
    window), then the stages of :func:`apply_display_stages` (dynamic range, contrast, display
    curve; the collimator band set to ``params.output.outside_region``). No impulse removal,
    flat field or logarithm: the image is not linear light. ``params.output.polarity =
    "as_captured"`` inverts the scaled image (more exposure brighter).

    Parameters
    ----------
    image : ndarray, (H, W) or (H, W, 3)
        Display radiograph, higher = brighter on display (colour is averaged).
    params : PipelineParams, optional
    mask : ndarray, bool, optional
        Region for the statistics (default: the detected collimated field).
    keep_intermediates : bool
        Keep ``"attenuation"`` (the VOI-scaled input), ``"dynamic_range"`` and ``"contrast"``.

    Returns
    -------
    PipelineResult
        Via ``StopIteration.value``; use :func:`process_display_radiograph` for a plain call.
    """
    from .io import validate_image

    params = params or PipelineParams()
    image = validate_image(image, "image")
    grey = image.mean(axis=2, dtype=np.float32) if image.ndim == 3 else image
    total = len(DISPLAY_STAGES)
    clock = time.perf_counter
    timings: dict[str, float] = {}
    inter: dict = {}
    t0 = clock()
    x, mask, field, (lo, hi) = _scale_display(grey, params, mask)
    if params.output.polarity == "as_captured":
        np.subtract(np.float32(1.0), x, out=x)
    h, w = x.shape
    if field is not None:
        region = field
    else:
        whole = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float64)
        region = Region(np.ones((h, w), bool) if mask is None else mask, whole, detected=False)
    results = {"region": {"kind": "collimated field" if field is not None else "whole frame (no collimator found)",
                          "polygon_xy": region.polygon_xy.round(2).tolist(), "detected": field is not None,
                          "area_fraction": float(region.mask.mean())},
               "voi_window": [lo, hi],
               "exposure_index": not_linear_record("display radiograph: its values are display-mapped, not linear "
                                                   "in air kerma, so no detector calibration applies")}
    if keep_intermediates:
        inter["attenuation"] = x.copy()
    timings["region"] = clock() - t0
    yield 1, total
    steps = _display_steps(x, mask, params, fill_outside=field is not None, report=results.setdefault("display", {}))
    del x
    for step, stage in ((2, "dynamic_range"), (3, "contrast"), (4, "display")):
        t0 = clock()
        output = next(steps)
        if keep_intermediates and stage != "display":
            inter[stage] = output.copy()
        timings[stage] = clock() - t0
        yield step, total
    return PipelineResult(display=output, region=region, voi_window=(lo, hi), timings_s=timings,
                          results=results, intermediates=inter, params=params)


def process_display_radiograph(image: np.ndarray, *, progress: Callable[[int, int], object] | None = None,
                               **kwargs) -> PipelineResult:
    """Plain-function form of :func:`run_display_pipeline` (same keyword arguments)."""
    return drive(run_display_pipeline(image, **kwargs), progress)


def drive(gen: Generator, progress: Callable[[int, int], object] | None = None):
    """Run a progress generator to completion; call ``progress(done, total)`` on each step."""
    while True:
        try:
            step = next(gen)
        except StopIteration as stop:
            return stop.value
        if progress is not None:
            progress(*step)


def process_frame(image: np.ndarray, *, progress: Callable[[int, int], object] | None = None,
                  **kwargs) -> PipelineResult:
    """Plain-function form of :func:`run_pipeline` (same keyword arguments)."""
    return drive(run_pipeline(image, **kwargs), progress)


# --------------------------------------------------------------------------- files


def output_paths(input_path: str | os.PathLike, out_dir: str | os.PathLike,
                 params: PipelineParams) -> dict[str, Path]:
    """The files :func:`run_file` writes for one input (``<stem>_dslrxr.tif`` etc.)."""
    stem = Path(input_path).stem + "_dslrxr"
    out_dir = Path(out_dir)
    paths = {}
    if params.output.tiff:
        paths["tiff"] = out_dir / f"{stem}.tif"
    if params.output.png_preview:
        paths["png"] = out_dir / f"{stem}.png"
    if params.output.dicom:
        paths["dicom"] = out_dir / f"{stem}.dcm"
    return paths


def run_identity(input_files: Sequence[str | os.PathLike], params: PipelineParams, extra: str = "") -> str:
    """A hex digest of the input files' contents and every parameter (seeds DICOM UIDs)."""
    from .io import file_sha256

    digest = hashlib.sha256()
    for path in input_files:
        digest.update(file_sha256(path).encode())
    # how the batch was spread (the [batch] section) never changes an output; nor does the
    # [exposure] section of an uncalibrated detector (the files of earlier versions keep their UIDs)
    omit = () if params.exposure.calibrated else ("exposure",)
    digest.update(params_to_toml(params, comments=False, run_sections=False, omit=omit).encode())
    digest.update(extra.encode())
    return digest.hexdigest()


def preview_uint8(display: np.ndarray, max_side_px: int = 2048) -> np.ndarray:
    """8-bit preview of a [0, 1] image, area-downsampled so its longest side <= ``max_side_px``."""
    img = np.clip(display, 0, 1)
    h, w = img.shape[:2]
    if max_side_px and max(h, w) > max_side_px:
        f = max_side_px / max(h, w)
        img = cv2.resize(img, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA)
    return np.round(img * 255).astype(np.uint8)


def write_outputs(result: PipelineResult, paths: dict[str, Path], *, inputs: Sequence[str | os.PathLike],
                  params: PipelineParams, pixel_spacing_mm: float | None = None,
                  patient: dict | None = None, uid_seed: str | None = None,
                  run_options: dict | None = None) -> list[Path]:
    """Write the TIFF / PNG / DICOM outputs of a run, each with a JSON sidecar.

    ``run_options`` (for example the deblurring geometry in mm) are recorded in each sidecar
    beside the parameters, so an output can be reproduced from its sidecar alone.

    Returns
    -------
    list of Path
        The image files written (sidecars are ``<file>.json``).
    """
    from .. import __version__
    from .io import write_png, write_tiff
    from .io.provenance import write_sidecar

    written = []
    sidecar_results = {**result.results, "voi_window": list(result.voi_window)}
    if run_options:
        sidecar_results["run_options"] = dict(run_options)
    if params.batch.scheduler:  # where it ran; the [batch] section never changes the bytes
        sidecar_results["batch"] = {"scheduler": params.batch.scheduler}
    description = json.dumps({"software": "napari-dslrxr", "version": __version__, "stage": "run",
                              "polarity": params.output.polarity}, sort_keys=True)
    spacing = pixel_spacing_mm or (params.output.pixel_spacing_mm or None)
    for kind, path in paths.items():
        if kind == "tiff":
            write_tiff(path, result.display_uint16(), description=description, inputs=inputs,
                       resolution_px_per_mm=(1.0 / spacing) if spacing else None)
        elif kind == "png":
            write_png(path, preview_uint8(result.display, params.output.preview_max_side_px), inputs=inputs)
        elif kind == "dicom":
            from .io.dicom import write_dicom_dx

            write_dicom_dx(path, result.display_uint16(), pixel_spacing_mm=spacing,
                           uid_seed=uid_seed or run_identity(inputs, params), patient=patient,
                           series_description="napari-dslrxr processed radiograph", inputs=inputs,
                           attributes=dicom_exposure_tags(result.results.get("exposure_index")))
        else:  # pragma: no cover
            raise OutputError(f"{path}: unknown output kind {kind!r}")
        write_sidecar(path, stage="run", parameters=params_to_dict(params, run_sections=False), inputs=inputs,
                      timings_s=result.timings_s,
                      results=sidecar_results)
        written.append(path)
    return written


def load_frames(paths: Sequence[str | os.PathLike]) -> list[np.ndarray]:
    """Read reference frames (flats, darks) as arrays in counts."""
    from .io import read_image

    return [read_image(p).data for p in paths]


def input_black_level(input_path: str | os.PathLike, params: PipelineParams):
    """The dark offset :func:`run_file` uses without dark frames (0 for camera raw, whose
    decoded RGB has the black level subtracted already; else the parameter)."""
    from .io import RAW_EXTENSIONS

    return 0.0 if Path(input_path).suffix.lower() in RAW_EXTENSIONS else params.flatfield.black_level_counts


def flat_reference_key(flat_paths: Sequence[str | os.PathLike], dark_paths: Sequence[str | os.PathLike],
                       shape: tuple[int, ...], offset, params: PipelineParams) -> tuple:
    """Key of a prepared :class:`FlatReference` in a ``reference_cache`` (see :func:`run_file`)."""
    return (tuple(map(str, flat_paths)), tuple(map(str, dark_paths)), tuple(shape), repr(offset),
            repr(params.flatfield))


def psf_kernel_key(psf_path: str | os.PathLike, source_to_object_mm: float, source_to_detector_mm: float) -> tuple:
    """Key of a PSF kernel in a ``reference_cache`` (see :func:`run_file`)."""
    return ("psf", str(psf_path), float(source_to_object_mm), float(source_to_detector_mm))


def _psf_kernel(psf_path: str | os.PathLike, source_to_object_mm: float | None,
                source_to_detector_mm: float | None, cache: dict | None) -> np.ndarray:
    """The PSF kernel at this geometry: from ``cache`` (keyed by :func:`psf_kernel_key`), or
    read from the model file and stored there."""
    if source_to_object_mm is None or source_to_detector_mm is None:
        raise ParameterError("--psf needs --source-to-object-mm and --source-to-detector-mm")
    key = psf_kernel_key(psf_path, source_to_object_mm, source_to_detector_mm)
    kernel = cache.get(key) if cache is not None else None
    if kernel is None:
        from .psf import load_psf

        kernel = load_psf(psf_path).kernel(source_to_object_mm, source_to_detector_mm)
        if cache is not None:
            cache[key] = kernel
    return kernel


def _reference_frames(flat_paths: Sequence[str | os.PathLike], dark_paths: Sequence[str | os.PathLike],
                      shape: tuple[int, ...] | None = None, shape_of: str | None = None):
    """Read the flats and darks, which must all have ``shape`` (``shape_of`` says whose, for
    the message); without ``shape``, the first frame's. Returns ``(flats, darks, shape)``."""
    flats, darks = load_frames(flat_paths), load_frames(dark_paths)
    if shape is None:
        shape = (flats or darks)[0].shape
        shape_of = f"the other reference frames' {shape}"
    for name, frame_paths, frames in (("flat", flat_paths, flats), ("dark", dark_paths, darks)):
        for p, f in zip(frame_paths, frames, strict=True):
            if f.shape != shape:
                raise InputError(p, f"{name} frame shape {f.shape} differs from {shape_of}")
    return flats, darks, shape


def prepare_batch_references(input_paths: Sequence[str | os.PathLike], *, params: PipelineParams,
                             flat_paths: Sequence[str | os.PathLike] = (),
                             dark_paths: Sequence[str | os.PathLike] = (),
                             psf_path: str | os.PathLike | None = None,
                             source_to_object_mm: float | None = None,
                             source_to_detector_mm: float | None = None) -> dict:
    """Flat references and the PSF kernel of a batch, prepared once, keyed as :func:`run_file`
    looks them up in its ``reference_cache`` (a cluster run sends this dict to every worker).

    The frame shape is the reference frames' own (a radiograph of another shape fails in
    :func:`run_file` with its usual message); one reference is prepared per dark offset the
    inputs need (:func:`input_black_level`). Without flats and darks nothing heavy is
    prepared (the offset-only reference is trivial) and no flat entry is made.

    Raises
    ------
    InputError
        An unreadable reference frame, or flats and darks of different shapes.
    """
    params = validate_params(params)
    cache: dict = {}
    if psf_path is not None:
        _psf_kernel(psf_path, source_to_object_mm, source_to_detector_mm, cache)
    if not flat_paths and not dark_paths:
        return cache
    flats, darks, shape = _reference_frames(flat_paths, dark_paths)
    for offset in {repr(input_black_level(p, params)): input_black_level(p, params) for p in input_paths}.values():
        cache[flat_reference_key(flat_paths, dark_paths, shape, offset, params)] = prepare_flat_reference(
            shape, flats=flats, darks=darks, black_level=offset, params=params.flatfield)
    return cache


def run_file(input_path: str | os.PathLike, out_dir: str | os.PathLike, *,
             params: PipelineParams | None = None, flat_paths: Sequence[str | os.PathLike] = (),
             dark_paths: Sequence[str | os.PathLike] = (), psf_path: str | os.PathLike | None = None,
             source_to_object_mm: float | None = None, source_to_detector_mm: float | None = None,
             reference: FlatReference | None = None, patient: dict | None = None,
             progress: Callable[[int, int], object] | None = None,
             reference_cache: dict | None = None,
             warn: Callable[[str], object] | None = None) -> list[Path]:
    """Read one frame, run the pipeline and write its outputs (with sidecars).

    The input's kind (:func:`~napari_dslrxr.core.io.input_kind.decide_input_kind` under
    ``params.input.input_kind``) picks the path: a camera frame goes through the whole chain,
    a display radiograph (a CR/DX DICOM...) through :func:`run_display_pipeline` only. The
    decision is recorded in the sidecar (``results.input_kind``).

    Parameters
    ----------
    input_path : path-like
        Camera raw, TIFF, PNG or DICOM.
    out_dir : path-like
        Existing output folder.
    params : PipelineParams, optional
    flat_paths, dark_paths : sequence of path-like
        Reference frames; ignored when ``reference`` is given.
    psf_path : path-like, optional
        PSF model JSON (:func:`napari_dslrxr.core.psf.load_psf`); with the two distances it
        turns on deblurring.
    source_to_object_mm, source_to_detector_mm : float, optional
    reference : FlatReference, optional
        Prepared flat reference (a batch prepares it once).
    patient : dict, optional
        DICOM patient fields supplied by the user (``PatientName``, ``PatientID``...).
    reference_cache : dict, optional
        References prepared by earlier calls (or by :func:`prepare_batch_references`): flat
        references keyed by :func:`flat_reference_key`, PSF kernels by
        :func:`psf_kernel_key`; a batch passes one dict so its flats, darks and PSF model are
        read and prepared once, not once per file.
    warn : callable, optional
        Receives one line (without the file name) when the input kind was guessed or a given
        reference frame or PSF does not apply to the input's kind.

    Returns
    -------
    list of Path
        Files written.
    """
    from .io.input_kind import DISPLAY, input_kind_of
    from .io import read_image

    params = validate_params(params or PipelineParams())
    loaded = read_image(input_path)
    kind = input_kind_of(loaded, params.input.input_kind)
    if warn is not None and kind.message():
        warn(kind.message())
    if kind.kind == DISPLAY:
        return _run_display_file(loaded, out_dir, kind, params=params, flat_paths=flat_paths,
                                 dark_paths=dark_paths, psf_path=psf_path, patient=patient,
                                 progress=progress, warn=warn, source_to_object_mm=source_to_object_mm,
                                 source_to_detector_mm=source_to_detector_mm)
    black = None
    image = loaded.data
    impulses_removed = None
    t_cfa = time.perf_counter()
    if loaded.format == "raw":
        black = 0.0  # rawpy's linear RGB has the black level subtracted already
        if loaded.raw is not None and params.impulse.passes_grey > 0 and params.impulse.space in ("auto", "cfa"):
            # stage (i) on the Bayer planes, before demosaicing spreads each zinger
            from .stages.impulse import demosaic_cleaned_raw, remove_impulses_cfa

            cfa = remove_impulses_cfa(loaded.raw.cfa_planes, params.impulse)
            image = demosaic_cleaned_raw(input_path, cfa.image, loaded.raw)
            impulses_removed = _impulse_record(cfa, space="cfa")
    t_cfa = time.perf_counter() - t_cfa
    kernel = None
    if psf_path is not None:
        kernel = _psf_kernel(psf_path, source_to_object_mm, source_to_detector_mm, reference_cache)
    offset = black if black is not None else params.flatfield.black_level_counts
    cache_key = flat_reference_key(flat_paths, dark_paths, image.shape, offset, params)
    if reference is None and reference_cache is not None:
        reference = reference_cache.get(cache_key)
    if reference is None:
        flats, darks, _ = _reference_frames(flat_paths, dark_paths, image.shape, f"{input_path}'s {image.shape}")
        reference = prepare_flat_reference(image.shape, flats=flats, darks=darks, black_level=offset,
                                           params=params.flatfield)
        if reference_cache is not None:
            reference_cache[cache_key] = reference
    result = process_frame(image, params=params, reference=reference, psf_kernel=kernel, progress=progress,
                           impulses_removed=impulses_removed)
    result.results["input_kind"] = kind.as_record()
    if impulses_removed is not None:
        result.timings_s["impulse"] = t_cfa
    extra = f"{source_to_object_mm}|{source_to_detector_mm}|{json.dumps(patient or {}, sort_keys=True)}"
    return _write_file_outputs(result, loaded, out_dir, extra, params=params, flat_paths=flat_paths,
                               dark_paths=dark_paths, psf_path=psf_path, patient=patient,
                               source_to_object_mm=source_to_object_mm,
                               source_to_detector_mm=source_to_detector_mm)


def _run_display_file(loaded, out_dir: str | os.PathLike, kind, *, params: PipelineParams,
                      flat_paths: Sequence[str | os.PathLike], dark_paths: Sequence[str | os.PathLike],
                      psf_path: str | os.PathLike | None, patient: dict | None,
                      progress: Callable[[int, int], object] | None,
                      warn: Callable[[str], object] | None, source_to_object_mm: float | None = None,
                      source_to_detector_mm: float | None = None) -> list[Path]:
    """:func:`run_file` for a display radiograph: the display path, then the same outputs.

    References given for the batch are checksummed and recorded (with their roles and the
    deblurring geometry) like a camera frame's, so a rerun compares them the same way."""
    ignored = [what for what, given in (("flat/dark frames", flat_paths or dark_paths), ("the PSF", psf_path))
               if given]
    if ignored and warn is not None:
        warn(f"{' and '.join(ignored)} not applied: a display radiograph is not linear light")
    result = process_display_radiograph(loaded.data, params=params, progress=progress)
    result.results["input_kind"] = kind.as_record()
    result.results.update({"impulse": "skipped (display radiograph)", "flatfield": "skipped (display radiograph)",
                           "deblur": "skipped (display radiograph)"})
    extra = f"display|{json.dumps(patient or {}, sort_keys=True)}"
    return _write_file_outputs(result, loaded, out_dir, extra, params=params, flat_paths=flat_paths,
                               dark_paths=dark_paths, psf_path=psf_path, patient=patient,
                               source_to_object_mm=source_to_object_mm,
                               source_to_detector_mm=source_to_detector_mm)


def _write_file_outputs(result: PipelineResult, loaded, out_dir: str | os.PathLike, extra: str, *,
                        params: PipelineParams, flat_paths: Sequence[str | os.PathLike],
                        dark_paths: Sequence[str | os.PathLike], psf_path: str | os.PathLike | None,
                        patient: dict | None, source_to_object_mm: float | None,
                        source_to_detector_mm: float | None) -> list[Path]:
    """The outputs of :func:`run_file` (either path): the references by role and the
    deblurring geometry go into the sidecars; ``extra`` seeds the DICOM UIDs with the inputs'
    checksums and the parameters."""
    # which of the checksummed inputs are flats and darks (a rerun compares them by role)
    result.results["reference_frames"] = {"flat": len(flat_paths), "dark": len(dark_paths)}
    inputs = [loaded.path, *map(Path, flat_paths), *map(Path, dark_paths), *([Path(psf_path)] if psf_path else [])]
    spacing = loaded.metadata.get("pixel_spacing_mm")
    spacing = float(spacing[0]) if spacing else None
    run_options = None
    if psf_path is not None and source_to_object_mm is not None and source_to_detector_mm is not None:
        run_options = {"source_to_object_mm": float(source_to_object_mm),
                       "source_to_detector_mm": float(source_to_detector_mm)}
    return write_outputs(result, output_paths(loaded.path, out_dir, params), inputs=inputs, params=params,
                         pixel_spacing_mm=spacing, patient=patient, uid_seed=run_identity(inputs, params, extra),
                         run_options=run_options)
