"""The whole chain, from a camera frame to a display-ready radiograph.

Stages follow the target paper's order: on the colour image (i) impulse removal, (ii) flat
field per channel, (iii) screen region and value-of-interest scaling, (iv) optional
deblurring (only with a PSF kernel); then on grey, in the log (attenuation) domain, (v)
dynamic-range / latitude reduction and (vi) multiscale contrast, finished by the sigmoid
display curve.

:func:`run_pipeline` is a generator: it yields ``(done, total)`` after each stage (the name of
stage ``done`` is ``PIPELINE_STAGES[done - 1]``) and returns a :class:`PipelineResult`.
:func:`process_frame` runs it to completion. :func:`run_display_pipeline` is the shorter path for a
radiograph already in display form. Files (reading an input, writing the outputs and their
sidecars) are :mod:`.files`'s: :func:`~.files.run_file` calls :func:`process_frame`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from .display import display_steps, scale_display_field, scale_to_voi_window
from .params import PipelineParams
from .stages.collimation import detect_collimation
from .stages.exposure_index import exposure_index_record, not_linear_record
from .stages.flatfield import FlatReference, apply_flat_field, prepare_flat_reference, saturated_flat_message
from .stages.region import Region, polygon_mask, rectify
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
    results["impulse"] = impulse_record(res)
    return res.image


def impulse_record(res, **where) -> dict:
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


def _half_plane(shape: tuple[int, int], a: np.ndarray, b: np.ndarray, towards: np.ndarray) -> np.ndarray:
    """The pixels on the side of the line through ``a`` and ``b`` (x, y) where ``towards`` lies."""
    h, w = shape
    direction = (b - a) / max(float(np.hypot(*(b - a))), 1e-9)
    normal = np.array([-direction[1], direction[0]])
    if normal @ (towards - a) < 0:
        normal = -normal
    far = 2.0 * float(np.hypot(h, w))  # beyond the frame on every side
    return polygon_mask(shape, np.array([a - far * direction, b + far * direction,
                                         b + far * direction + far * normal, a - far * direction + far * normal]))


def _outward(a: np.ndarray, b: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The unit normal of the line through ``a`` and ``b`` pointing away from ``centre``."""
    direction = (b - a) / max(float(np.hypot(*(b - a))), 1e-9)
    normal = np.array([-direction[1], direction[0]])
    return -normal if normal @ (centre - a) > 0 else normal


def _beyond_side(shape: tuple[int, int], a: np.ndarray, b: np.ndarray, outward: np.ndarray) -> np.ndarray:
    """The pixels beyond the segment a-b (x, y), within its extent, to the frame's border."""
    far = 2.0 * float(np.hypot(*shape))
    return polygon_mask(shape, np.array([a, b, b + far * outward, a + far * outward]))


def _blade_sides(sub: np.ndarray, inside: np.ndarray, beyond: np.ndarray, polygon: np.ndarray, step: int,
                 dense_share: float, gap_px: float = 0.0, extent_only: bool = False) -> tuple[list, int]:
    """The sides (a, b) of a field polygon (full-resolution x, y) whose band is a blade's shadow,
    and how many sides with a band were refused.

    Judged on the subsample ``sub`` (every ``step``-th pixel, bone white) with the field's
    pixels ``inside`` and the bands' ``beyond``; each side's band (the part of ``beyond``
    outside its line) on its own: at least ``dense_share`` of it attenuates more than 95 % of
    the field, and its median gets less than e^-1 (37 %) of the field's median light. A side
    with (almost) no band lies on the frame's border: no blade, neither kept nor refused. The
    band starts ``gap_px`` (subsample pixels) beyond the line (the blade's penumbra); with
    ``extent_only`` it is only what lies beyond the side itself, not beyond its extension.
    """
    field_mid, field_top = (float(v) for v in np.percentile(sub[inside], [50, 95]))
    centre = polygon.mean(axis=0) / step
    blades, refused = [], 0
    for a, b in zip(polygon, np.roll(polygon, -1, axis=0), strict=True):
        a_sub, b_sub = a / step, b / step
        outward = _outward(a_sub, b_sub, centre)
        a_sub, b_sub = a_sub + gap_px * outward, b_sub + gap_px * outward
        side_band = beyond & (_beyond_side(beyond.shape, a_sub, b_sub, outward) if extent_only
                              else ~_half_plane(beyond.shape, a_sub, b_sub, centre))
        if np.count_nonzero(side_band) < 16:
            continue
        values = sub[side_band]
        dense = float(np.percentile(values, 100.0 * (1.0 - dense_share)))
        if dense < field_top or abs(float(np.median(values)) - field_mid) < 1.0:
            refused += 1
        else:
            blades.append((a, b))
    return blades, refused


def _with_light_beyond_blades(kept: np.ndarray, shadow: np.ndarray, oriented: np.ndarray,
                              field: np.ndarray) -> np.ndarray:
    """``kept`` with the part of a blade's ``shadow`` that is as light as the field and joins it.

    A blade's band is accepted when nearly all of it is denser than the field, and its line is a
    four-corner fit's straight side: where the real edge curves (a keystoned or partly framed
    screen), the line cuts a sliver of the field off with it (corpus seed 3020 of the dense-area
    family: 1.1 % of the anatomy). A collimator's shadow is dense; what lies beyond the line at
    the field's levels (below halfway from the field's 95th percentile to the band's median, on
    a 1 px Gaussian against the noise) and is connected to the field is the field.
    """
    smooth = cv2.GaussianBlur(oriented.astype(np.float32), (0, 0), 1.0)
    if not np.any(field & kept) or not shadow.any():
        return kept
    # halfway between the field's dense end and the band's own level
    level = 0.5 * (float(np.percentile(smooth[field & kept], 95)) + float(np.median(smooth[shadow])))
    light = shadow & (smooth < level)
    if not light.any():
        return kept
    count, labels = cv2.connectedComponents((kept | light).astype(np.uint8), connectivity=8)
    joined = np.zeros(count, bool)
    joined[labels[kept]] = True
    joined[0] = False
    return kept | (light & joined[labels])


def _between(blades: list, centre: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The pixels on the field's side of every blade line (a, b)."""
    return np.logical_and.reduce([_half_plane(shape, a, b, centre) for a, b in blades])


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
    step = max(1, int(np.sqrt(attenuation.size / 1_000_000)))
    sub = attenuation[::step, ::step] if params.output.polarity == "bone_white" else -attenuation[::step, ::step]
    if region.evidence.get("field_edge") and "candidate_xy" in region.evidence:
        # the screen step found a strong straight edge inside the exposed screen: a blade's only
        # when nearly all of the band beyond it (98 %) is denser than 95 % of the field, so at
        # most a trace of anatomy cut by the edge goes with it
        polygon = np.asarray(region.evidence["candidate_xy"], np.float64)  # the edge's 50 % points
        field_mask = polygon_mask((h, w), polygon)
        inside, beyond = (mask & field_mask)[::step, ::step], (mask & ~field_mask)[::step, ::step]
        # away from the region's own edge (the screen's soft rim and the room beyond it)
        rim = max(2, round(0.015 * min(beyond.shape)))
        beyond &= cv2.erode(mask[::step, ::step].astype(np.uint8), np.ones((2 * rim + 1,) * 2, np.uint8)).astype(bool)
        if inside.any() and beyond.any():
            # on the noise averaged down (1 px Gaussian, as for the search below): a starved
            # band's log is noise, and its lowest 2 % would reach into the field's levels
            blades, refused = _blade_sides(cv2.GaussianBlur(sub, (0, 0), 1.0), inside, beyond, polygon, step,
                                           dense_share=0.98, gap_px=rim, extent_only=True)
            if blades:
                # what lies beyond each blade's own side, and beyond the corner two blades share
                # (a side's extension may run into the anatomy: a four-corner fit of a field
                # with a cut corner has a short side)
                centre = polygon.mean(axis=0)
                outward = [_outward(a, b, centre) for a, b in blades]
                shadow = np.zeros((h, w), bool)
                for (a, b), o in zip(blades, outward, strict=True):
                    shadow |= _beyond_side((h, w), a, b, o)
                for (_, b1), o1, (a2, _), o2 in zip(blades, outward, blades[1:] + blades[:1], outward[1:] + outward[:1],
                                                     strict=True):
                    if len(blades) > 1 and np.allclose(b1, a2):
                        shadow |= _beyond_side((h, w), b1, b1 + 2.0 * float(np.hypot(h, w)) * o1, o2)
                combined = _with_light_beyond_blades(
                    mask & ~shadow, mask & shadow,
                    attenuation if params.output.polarity == "bone_white" else -attenuation, mask & field_mask)
                results["collimation"] = {"detected": True, "source": "screen candidate",
                                          "polygon_xy": polygon.round(2).tolist(), "blades": len(blades),
                                          "refused_edges": refused}
                region = Region(combined, region.polygon_xy, region.detected, {**region.evidence, "collimation": True})
                results["region"]["area_fraction"] = float(combined.mean())
                return combined, region
    if not _may_hold_blades(display_oriented, mask, factor):
        return mask, region
    inset = params.region.collimation_inset_px * min(1.0, max(h, w) / 2000.0) / factor
    found = detect_collimation(display_oriented, inset_px=inset, drop_penumbra=True)
    if not found.detected:
        return mask, region
    polygon = (found.polygon_xy + 0.5) * np.array([w / small.shape[1], h / small.shape[0]]) - 0.5
    field = Region(polygon_mask((h, w), polygon), polygon) if factor > 1 else found
    combined = mask & field.mask
    band = mask & ~field.mask
    inside, beyond = combined[::step, ::step], band[::step, ::step]
    if not inside.any() or not beyond.any():
        return mask, region
    # Behind a blade the screen gets scatter only: the band must attenuate more than almost all
    # of the field, and get less than e^-1 (37 %) of the field's median light (a uniform stretch
    # of soft tissue at the frame's side, or the vignetting of a frame without a flat, does not)
    blades, refused = _blade_sides(sub, inside, beyond, polygon, step, dense_share=0.5)
    if not blades:
        results["collimation"]["rejected"] = ("the band beyond the edges is not darker than 95 % of the field "
                                              "or gets more than 37 % of its median light")
        return mask, region
    if refused:
        # the field between the blades that passed (a half-plane per blade, the others left open)
        combined = mask & _between(blades, polygon.mean(axis=0), (h, w))
    results["collimation"] = {"detected": True, "polygon_xy": field.polygon_xy.round(2).tolist(),
                              "blades": len(blades), "refused_edges": refused}
    region = Region(combined, region.polygon_xy, region.detected, {**region.evidence, "collimation": True})
    results["region"]["area_fraction"] = float(combined.mean())
    return combined, region


def _flatfield_stage(cleaned: np.ndarray, reference: FlatReference, results: dict) -> np.ndarray:
    """Stage (ii): the flat-field correction, and what the sidecar keeps of it."""
    corrected = apply_flat_field(cleaned, reference)
    results["flatfield"] = {"n_flats": reference.n_flats, "reference_pulses_cleaned": reference.cleaned_pulses,
                            "applied": reference.denominator is not None}
    if reference.denominator is None:
        results["warnings"].append(
            "no flat frame given: flat field not corrected (uneven illumination stays in the image)")
    elif reference.saturated_fraction > 0:
        results["flatfield"]["saturated_fraction"] = reference.saturated_fraction
        results["warnings"].append(saturated_flat_message(reference))
    return corrected


def _region_stage(corrected: np.ndarray, reference: FlatReference, params: PipelineParams, results: dict) -> Region:
    """Stage (iii): the screen in the frame (values of interest come after the grey/log step)."""
    region = detect_screen(corrected, params.region, illumination=reference.denominator)
    results["region"] = {"polygon_xy": region.polygon_xy.round(2).tolist(), "detected": region.detected,
                         "area_fraction": float(region.mask.mean()), "evidence": region.evidence}
    if not region.detected and "reason" in region.evidence:
        used = ("the area the flat frame saw exposed is used" if "flat_exposed_fraction" in region.evidence
                else "the whole frame is used")
        results["warnings"].append(f"region: no screen found ({region.evidence['reason']}); {used}")
    return region


def _attenuation_stage(grey: np.ndarray, region: Region, params: PipelineParams,
                       results: dict) -> tuple[np.ndarray, np.ndarray, Region, tuple[float, float]]:
    """The grey/log step: the grey image (sum of channels, photon-count weighting; float32, may
    be overwritten) rectified when asked, to attenuation (log domain, bone white unless
    ``as_captured``), the collimated field left out, the VOI window mapped to [0, 1].

    Returns the attenuation, the region mask it uses, the region and the VOI window.
    """
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
    lo, hi = scale_to_voi_window(attenuation, mask if sub_mask.any() else None, params)
    results["voi_window"] = [lo, hi]
    return attenuation, mask, region, (lo, hi)


def run_pipeline(image: np.ndarray, *, flats: Sequence[np.ndarray] = (), darks: Sequence[np.ndarray] = (),
                 black_level=None, psf_kernel: np.ndarray | None = None,
                 params: PipelineParams | None = None,
                 reference: FlatReference | Callable[[], FlatReference] | None = None,
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
    reference : FlatReference or callable, optional
        A prepared flat-field reference (reuse across a batch); overrides flats/darks. A
        function returning it is called when stage (ii) starts (stage (i) does not need it).
    keep_intermediates : bool
        Keep the intermediate images in the result (memory: several full-size copies).
    impulses_removed : dict, optional
        Set when stage (i) already ran on the raw CFA planes (:func:`~.files.run_file` does this for
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
    results: dict = {"warnings": []}  # stages skipped or guessed, one line each
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
    if callable(reference):  # prepared (or waited for) now, outside the stage's timing as a given one
        reference = reference()
    t0 = clock()
    if reference is None:
        offset = black_level if black_level is not None else params.flatfield.black_level_counts
        reference = prepare_flat_reference(image.shape, flats=flats, darks=darks, black_level=offset,
                                           params=params.flatfield)
    corrected = _flatfield_stage(cleaned, reference, results)
    del cleaned
    if keep_intermediates:
        inter["flatfield"] = corrected
    timings["flatfield"] = clock() - t0
    yield 2, total

    # (iii) screen region (values of interest come after the grey/log conversion)
    t0 = clock()
    region = _region_stage(corrected, reference, params, results)
    timings["region"] = clock() - t0
    yield 3, total

    # (iv) optional deblurring, per channel, in linear intensity
    t0 = clock()
    if psf_kernel is not None:
        corrected = _deblur_stage(corrected, region.mask, np.asarray(psf_kernel, np.float32), params, results)
    else:
        results["deblur"] = "skipped (no PSF model given)"
        results["warnings"].append("no PSF model given: not deblurred")
    timings["deblur"] = clock() - t0
    yield 4, total

    # grey (sum of channels = photon-count weighting), log domain, VOI scaling
    t0 = clock()
    grey = corrected.sum(axis=2, dtype=np.float32) if corrected.ndim == 3 else corrected.astype(np.float32)
    del corrected
    attenuation, mask, region, (lo, hi) = _attenuation_stage(grey, region, params, results)
    del grey  # the attenuation was computed in its place
    if keep_intermediates:
        inter["attenuation"] = attenuation.copy()
    timings["grey_log"] = clock() - t0
    yield 5, total

    # (v) dynamic-range / latitude reduction, (vi) multiscale contrast, display curve: the
    # same steps as apply_display_stages, one at a time for the progress and the timings
    display_report: dict = {}
    remaining = display_steps(attenuation, mask, params, report=display_report)
    del attenuation  # the steps' generator holds it until stage (v) is done
    for step, stage in ((6, "dynamic_range"), (7, "contrast")):
        t0 = clock()
        stage_output = next(remaining)
        if keep_intermediates:
            inter[stage] = stage_output.copy()
        del stage_output
        timings[stage] = clock() - t0
        yield step, total

    t0 = clock()
    display = next(remaining)
    results["display"] = display_report
    if "warning" in display_report:
        results["warnings"].append(display_report["warning"])
    timings["display"] = clock() - t0
    yield 8, total
    return PipelineResult(display=display, region=region, voi_window=(lo, hi), timings_s=timings,
                          results=results, intermediates=inter, params=params)


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
    x, mask, field, (lo, hi) = scale_display_field(grey, params, mask)
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
    steps = display_steps(x, mask, params, fill_outside=field is not None, report=results.setdefault("display", {}))
    del x
    for step, stage in ((2, "dynamic_range"), (3, "contrast"), (4, "display")):
        t0 = clock()
        output = next(steps)
        if keep_intermediates and stage != "display":
            inter[stage] = output.copy()
        timings[stage] = clock() - t0
        yield step, total
    results["warnings"] = [results["display"]["warning"]] if "warning" in results["display"] else []
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
