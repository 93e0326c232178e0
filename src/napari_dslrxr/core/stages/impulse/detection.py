"""Detection of the impulse stage: candidates from fast medians, the exact posterior test,
the texture guard, patch growth, and the detect-and-replace loop of one channel."""

from __future__ import annotations

import math

import numpy as np

from .neighbourhoods import (
    IQR_TO_SIGMA,
    _Component,
    _detection_components,
    _flat_indices,
    _masked_median_at,
    _ring_median_at,
    _component_values_at,
    _FullMap,
    _REPLACEMENT_WINDOWS_PX,
    _sorted_unique,
    _square_ring_spread,
    _window_flat_indices,
    _window_values,
    _subsample_indices,
    _window_offsets,
)
from ...progress import Steps
from .noise_model import _INFLATION_LIMIT, _fit_mixture, _NoiseModel, _Predictor, _shrink_to_prediction
from .params import _FLOAT, MEDIAN_RESIDUAL_VARIANCE_FACTOR, ImpulseParams

#: Candidates for the exact test are pixels whose residual to the cheap centre-including
#: median, divided by this, passes the test: the centre-excluded residual is usually larger
#: by only half an order-statistic spacing. On a NIQA frame this keeps 99.8 % of the seeds of
#: an exact test of every pixel; the few dropped lie in mixed neighbourhoods (next to other
#: pulses or edges), where the patch growth usually finds them.
_PREFILTER_FRACTION = 0.6

#: Seed test: the spread of the 8 detection samples may exceed the noise by this factor
#: before it raises the residual variance (8 samples estimate a spread only roughly; a
#: factor 2 is rarely reached on a smooth background, always on edges and screen corners).
_SEED_SPREAD_TOLERANCE = 3.0

#: Texture guard. Around a seed, a pixel of the annulus between Chebyshev distances
#: ``_TEXTURE_INNER_PX`` and ``_TEXTURE_OUTER_PX`` is "busy" when its own residual to the
#: fast detection median is at least ``_BUSY_RELATIVE`` of the seed's. A pulse (at most
#: 5x5 px, so never reaching the annulus from any of its pixels) leaves only the noise's
#: tail busy; a track (1-2 px wide) adds the two places where it crosses the annulus. A line
#: pattern, mesh or grid (periodic structure that continues beyond the window) makes a
#: large part of it busy, with residuals of both signs. A seed whose annulus is busier
#: than ``_TEXTURE_BUSY_FRACTION`` is texture, not a pulse. Relative to the seed, not to
#: the noise model: on a frame filled with texture the fitted noise is inflated by it.
#: Measured on line patterns and meshes (2.2-5.3 px period, 60 % modulation) against
#: pulses of every shape (benchmarks/eval_impulse_independent.py): the 1st percentile of
#: texture seeds is at 0.22, the 99th of pulse seeds at 0.14 (tracks 0.24).
#: Weak pulses (4-6 sigma) and texture overlap in that relative measure; the annulus is
#: then also compared with the noise model: more than ``_TEXTURE_NOISY_FRACTION`` of it
#: beyond ``_BUSY_SIGMAS`` noise sigmas is texture too (noise alone: 0.3 %).
_BUSY_RELATIVE = 0.4
_TEXTURE_INNER_PX = 4
_TEXTURE_OUTER_PX = 6
_TEXTURE_BUSY_FRACTION = 0.2
_BUSY_SIGMAS = 3.0
_TEXTURE_NOISY_FRACTION = 0.35
#: ...unless the seed stands out that far: at most ``_TEXTURE_BUSY_FRACTION`` of the annulus
#: above this fraction of the seed's residual (10 times). Texture seeds have residuals like
#: their annulus's; a weak pulse on noise is never 10 times its annulus, so the count holds
#: for it; a strong pulse on a frame filled with a mesh (whose annulus is all beyond 3
#: noise sigmas once the noise is fitted right) is kept.
_STANDOUT_RELATIVE = 0.1

#: Integrated-excess seeds (a matched filter for faint pulses). A pulse a few noise sigmas
#: high in each of several pixels (a flat or Gaussian blob, a cluster, a track) is buried
#: pixel by pixel but not in the mean over its footprint. Footprints (all holding the
#: tested pixel, within its 5x5 window): the 3x3 square, the four 2x2 squares and
#: ``_LINE_PX`` px lines at ``_LINE_ORIENTATIONS`` orientations. The mean of the fast
#: residual over each is compared with its own noise (measured on the EM sample, since
#: neighbouring residuals share median samples, and never below white noise's); a pixel
#: with a footprint above ``_FOOTPRINT_SIGMAS`` is a seed when its own residual carries
#: at least ``_OWN_FRACTION`` of that footprint's mean (not a noise pixel next to a pulse
#: that carries it), and when copies of the footprint shifted to both sides do not hold as
#: much (:func:`_repeats_nearby`). Candidates are pixels beyond ``_FOOTPRINT_OWN_SIGMAS``
#: noise sigmas. Measured on the independent pulse generator (dev seeds): 4 sigma blobs,
#: clusters and tracks found 0.36-0.55 instead of 0.16-0.39. A threshold of 4.5 added
#: false alarms on anatomy edges for 0.01 of recall; candidates down to 0.5 sigma (with a
#: 3x3 mean beyond 3 sigmas: the sparse median of a wide track sits partly on it) added
#: 0.003-0.01 of recall and seeds next to the ridges of a fine line pattern.
_LINE_PX = 5
_LINE_ORIENTATIONS = 8
_FOOTPRINT_SIGMAS = 5.0
_FOOTPRINT_OWN_SIGMAS = 2.0
#: ...and below this: brighter pixels are the exact test's (and, on frames dense with strong
#: pulses, made the footprint test cost a third of the stage).
_FOOTPRINT_MAX_OWN_SIGMAS = 6.0
_OWN_FRACTION = 0.7
#: Candidates must also have a 3x3 mean beyond this many of its noise sigmas (a cheap
#: full-frame filter that every target shape passes: a 1 px track at 4 sigma gives about
#: 5, a 2x2 blob 6.5), so that the footprints are gathered for few pixels.
_FOOTPRINT_PRESCREEN_SIGMAS = 2.5
#: EM samples the footprint noise is measured on (a robust sigma to about 1 %).
_FOOTPRINT_NOISE_SAMPLES = 32768
#: Robust standard deviation of each footprint mean (order of :func:`_footprint_kernels`) of
#: the fast residual on white noise, in units of the model's residual sigma, per detection
#: window: measured on four 1024x1024 Gaussian fields (spread between fields below 0.001).
_WHITE_NOISE_FOOTPRINT_SIGMA = {
    3: np.array([0.201, 0.324, 0.324, 0.324, 0.324, 0.359, 0.351, 0.443, 0.351, 0.359, 0.351, 0.443, 0.351]),
    5: np.array([0.255, 0.441, 0.441, 0.441, 0.441, 0.364, 0.387, 0.474, 0.387, 0.364, 0.387, 0.474, 0.387]),
}
#: Repeat guard of the integrated-excess seeds (:func:`_repeats_nearby`).
_REPEAT_FRACTION = 0.5
#: Integrated-excess seeds are faint, as faint texture is (a pattern a few sigmas deep):
#: their guard is stricter than ``_in_texture``'s. More than ``_FAINT_TEXTURE_FRACTION`` of
#: the annulus beyond ``_FAINT_TEXTURE_SIGMAS`` noise sigmas is texture (noise alone: 4.6 %;
#: a track crossing the annulus adds about 10 %).
_FAINT_TEXTURE_SIGMAS = 2.0
_FAINT_TEXTURE_FRACTION = 0.2
#: Hysteresis growth: the first ring around a seed at least ``_STRONG_SEED_SIGMAS`` above
#: the noise is also tested as the rim of that seed (:func:`_rim_of_strong_seed`: the prior
#: ``_STRONG_RIM_PRIOR``, about 2.4 sigma, and a structure guard that ignores ramps): the
#: rims of strong blobs and tracks (3-4 sigma pixels) were the main loss at 8-20 sigma.
#: Around weak seeds (where false alarms on texture and anatomy sit) and beyond the first
#: ring the growth is unchanged: with the rim test's guard in the ring of every pixel grown
#: from a strong seed, PE on clean pixels rose 0.095 -> 0.113 % for recall +0.002; in
#: every ring around every seed, 0.19 % for +0.016.
_STRONG_SEED_SIGMAS = 6.0
_STRONG_RIM_PRIOR = 0.75
#: ...and its structure guard ignores a ramp whose part of the window's spread is below this
#: many noise sigmas (:func:`_rim_of_strong_seed`). Measured: ignoring ramps of every slope
#: (dev) recall 0.854 -> 0.863, but the DSLR phantom's V precision on the screen 0.957 ->
#: 0.942 (rims grown along its steep edges); below 4 sigmas 0.860 and 0.952; 3: 0.859 and
#: 0.953; 2: 0.857 and 0.955.
_GENTLE_RAMP_SIGMAS = 3.0
#: Sides of the texture guard's annulus (raw CFA planes, :func:`_textured_side`). At the
#: border of a pattern inside a radiograph only one side of the annulus lies on it, and on
#: the dim R and B planes the pattern is aliased at a few noise sigmas, so the whole-annulus
#: fractions stay below their limits: 0.7 % of such patterns' CFA pixels (2 % on a mesh) were
#: flagged, 85-100 % of them within 3 px of the border. A side (three rows or columns,
#: 39 px) is texture when more than ``_SIDE_BUSY_FRACTION`` of it is busy relative to the
#: seed, or more than ``_SIDE_NOISY_FRACTION`` beyond ``_BUSY_SIGMAS`` noise sigmas (noise
#: alone: 0.3 % per pixel; a track through the seed covers 3-8 px of a side). Measured
#: (dev seeds): such patterns 0.68 -> 0.006 % flagged; CFA planes of the tinted pulse
#: frames: recall 0.803 -> 0.798 (pulses next to other pulses), false pixels 438 -> 426.
_SIDE_BUSY_FRACTION = 0.3
_SIDE_NOISY_FRACTION = 0.2
#: Grey and V (``texture_sides="two_signed"``) take the sides too, but a side counts only when
#: its busy pixels have both signs, each at least this share of them: a pattern's residuals
#: alternate, while a pulse next door or a track leaving the seed are one-signed. Measured
#: (session 30): patterns inside a radiograph 0.017 / 0.060 -> 0.001 / 0.014 % flagged (dev,
#: grey, mean / max), held-out 2001-2002 0.064 / 0.67 -> 0.006 / 0.066 %; the pulse sets'
#: recall and residual energy unchanged on dev, -0.001 and +0.004 on 2001-2002. The
#: one-signed rule of the CFA planes cost dev recall 0.858 -> 0.850 there (8-20 sigma single
#: pixels and clusters next to other pulses); on CFA planes the two-signed rule lets the
#: aliased patterns' borders through (dev 0.007 -> 0.079 %).
_SIDE_MIN_SIGN_SHARE = 1.0 / 3.0
#: A side is also texture when more than ``_CURVED_SIDE_FRACTION`` of its pixels have a
#: second difference of the image (along rows or columns, whichever is larger) beyond
#: ``_CURVED_SIGMAS`` of its noise (:func:`_curved_side`). Why: lines within a few degrees of
#: the rows or columns with a period of 2.2-2.5 px are matched by the sparse detection median
#: (samples 2 px apart, nearly a period), so their residual is small inside the pattern and
#: the pattern's border line stood alone (0.3-1.3 % of such patches flagged; CFA planes,
#: whose planes alias finer patterns there, up to 1.6 %). The image's own curvature does not
#: depend on that sampling. Chosen on the development seeds and the NIQA frames (0.5: NIQA
#: spot removal 0.2-0.7 points lower, dense spots filling a side; 0.7: dev patterns inside a
#: radiograph 0.014 % max against 0.006 % at 0.6).
_CURVED_SIGMAS = 3.0
_CURVED_SIDE_FRACTION = 0.6
#: ...and a curved pixel's second difference must be at least this times the seed's own
#: residual, so that a pulse far above the texture's own swing (a strong hit on a mesh)
#: stays a pulse, as ``_STANDOUT_RELATIVE`` keeps it for the whole annulus. Without it,
#: strong pulses on a frame filled with a mesh were all dropped (recall 0).
_CURVED_RELATIVE = 1.0

_FOOTPRINTS = None  # set below, once the helpers are defined

#: Progress steps of one pass of :func:`_clean_channel`: candidates and exact test, texture
#: guard, patch growth and replacement.
_STEPS_PER_PASS = 3


def channel_steps(passes: int) -> int:
    """Progress steps :func:`_clean_channel` reports for ``passes`` passes (the noise-model fit
    first, then :data:`_STEPS_PER_PASS` per pass)."""
    return 0 if passes <= 0 else 1 + _STEPS_PER_PASS * passes


#: EM samples are left out where the image is this many times busier than usual (texture).
#: A tighter cut (at the median) also removed noise-only samples selectively and biased
#: the fitted gain by up to 20 %.
_BUSY_SAMPLE_FACTOR = 1.5

#: Pixels whose neighbourhoods are gathered at once (the (N, K) index and value arrays of
#: the exact test and the texture guard stay at a few MB; a later pass on a frame with 1 %
#: of pulses re-tests millions of pixels, and whole-set arrays held the peak memory).
_CHUNK_PX = 8192


def _clean_channel(x: np.ndarray, *, passes: int, params: ImpulseParams, photon_counting: bool,
                   polarity: int, valid: np.ndarray | None = None, circular: bool = False,
                   value_range: float | None = None, residual_weight: np.ndarray | None = None,
                   in_place: bool = False, fit_region: np.ndarray | None = None,
                   steps: Steps | None = None, faint_pulses: bool = True,
                   channels: np.ndarray | None = None, texture_sides: str | None = None,
                   inflation_limit: float = _INFLATION_LIMIT):
    """Detect and replace pulses in one float32 channel (``in_place``: in ``x`` itself).

    ``fit_region`` (bool, optional): the noise model is fitted on these pixels only (and
    within ``valid``); detection still covers every valid pixel.

    ``residual_weight`` (constant-variance channels): residuals are multiplied by it before
    the Gaussian model is fitted and applied, so that a channel whose noise is known to
    scale as 1/weight gets a constant variance (H and S: see :func:`_remove_hsv`).

    Only the first pass looks at the whole image. A later pass can only find pulses where
    the previous one changed a detection median, so it re-tests just the pixels within the
    detection window of the pixels replaced before (the same result as a full pass).

    ``faint_pulses`` (photon-counting channels): also seed faint pulses by their integrated
    excess over a footprint (``_FOOTPRINT_SIGMAS``) and grow strong seeds' first ring at a
    lower significance (``_STRONG_RIM_PRIOR``). Off on raw CFA planes, where a hit stays
    one pixel and a fine pattern lands aliased at a few noise sigmas (measured: line
    patterns flagged 0.18 % instead of 0.006 %).

    ``texture_sides``: a seed is also texture when one side of its annulus is
    (:func:`_textured_side`): a pattern's border. ``"one_signed"`` (raw CFA planes, whose dim
    planes hold patterns aliased at a few noise sigmas): any busy side; ``"two_signed"``
    (grey and V): a side busy with residuals of both signs (``_SIDE_MIN_SIGN_SHARE``); None:
    the whole annulus only.

    ``inflation_limit``: how many times too wide (in variance) the fitted noise may be, by
    the texture predictor's residual, before it is shrunk (:func:`_shrink_to_prediction`;
    raw CFA planes, whose noise is independent between pixels, take a tighter limit).

    ``channels`` (V of the colour path): the (H, W, 3) image ``x`` is the maximum of; the
    noise model is widened to the tail of that maximum (:func:`_match_channel_tail`).

    ``steps``: advanced by :func:`channel_steps` ``(passes)`` in all (the fit, then each
    pass's steps; passes not needed are skipped at once), so a caller's progress callback
    runs between them and can stop the channel by raising.

    Returns (cleaned float32 channel, mask, model of the first pass or None). Pulse pixels
    get the median of their non-pulse neighbours; others are untouched.
    """
    steps = Steps(None, 0) if steps is None else steps
    channel_end = steps.done + channel_steps(passes)
    if not (in_place and x.dtype == _FLOAT and x.flags.c_contiguous):
        x = np.array(x, dtype=_FLOAT, copy=True)
    h, w = x.shape
    mask_total = np.zeros((h, w), bool)
    if passes == 0:
        return x, mask_total, None
    if value_range is None:
        value_range = float(x.max() - x.min())
    value_range = max(value_range, 1e-12)
    x_span = float(x.max()) - float(x.min())  # bounds the structure guard's spread (_exact_test)
    components, fast_residual = _fast_residual(x, params.window_px, circular, residual_weight)
    steps.check()
    fit_valid = valid if fit_region is None else (fit_region if valid is None else valid & fit_region)
    pick = _flat_area_sample(components, fit_valid, params.em_samples, photon_counting, x, fast_residual)
    if pick.size < 16 and fit_region is not None:  # too few: fit on every valid pixel
        pick = _flat_area_sample(components, valid, params.em_samples, photon_counting, x, fast_residual)
    median_max = max(float(comp.median.max()) for comp in components)
    del components  # the prefilter reads the median as x - residual (memory: 24 Mpx frames)
    if pick.size < 16:
        steps.to(channel_end)
        return x, mask_total, None
    d_fit, m_fit = _exact_residual(x, *np.divmod(pick, w), params.window_px, circular, residual_weight)
    steps.check()
    # Dark spots are sought in frames that still hold bright ones (direct hits): a dark-only
    # mixture would take those for noise and inflate its variance, so the fit is two-sided.
    model = _fit_mixture(d_fit, m_fit, photon_counting=photon_counting, polarity=max(polarity, 0),
                         value_range=value_range, iterations=params.em_iterations)
    # A fit on fine texture that fills the frame (no flat area to fit on) is shrunk; seeds
    # must then also stand out from the texture's own prediction.
    residual_factor = MEDIAN_RESIDUAL_VARIANCE_FACTOR[params.window_px]
    predictor = None if circular else _shrink_to_prediction(model, x, pick, m_fit, residual_factor,
                                                            residual_weight, inflation_limit)
    if polarity < 0:
        model.polarity, model.pulse_density = -1, 1.0 / value_range
    if channels is not None and photon_counting:
        _match_channel_tail(model, channels, pick, d_fit, m_fit, params.window_px)
    del d_fit
    footprint_noise = None  # a frame filled with texture (predictor) gets no faint seeds
    # Two-sided searches (spots = "both") get none either: on frames with dark spots they
    # cost precision 0.98 -> 0.95 (anatomy on both sides of the noise) for recall +0.03.
    if photon_counting and faint_pulses and predictor is None and polarity != 0:
        footprint_noise = _footprint_noise(fast_residual, pick, m_fit, model)
    del pick, m_fit
    if photon_counting:
        model.min_contrast = float(params.min_contrast)
    steps.advance()
    valid_flat = None if valid is None else valid.ravel()
    scratch = np.zeros((h, w), np.uint8)  # 1: pulse of this pass, 2: ring under test
    near_scratch = np.zeros((h, w), np.uint8)  # within 2 px of a pulse (growth's texture guard)
    reach = 1 if params.window_px == 3 else 2
    to_check = None
    for _ in range(passes):
        if to_check is None:
            candidates = _prefilter(x, median_max, model, params, fast_residual)
        else:
            candidates = to_check
        if valid_flat is not None:
            candidates = candidates[valid_flat[candidates]]
        seeds = _exact_test(x, candidates, model, params, circular, residual_weight, x_span)
        if footprint_noise is not None and to_check is None:
            seeds = _sorted_unique(np.concatenate([seeds, _footprint_seeds(x, fast_residual, model, params,
                                                                           footprint_noise, valid_flat)]), h * w)
        if predictor is not None:
            seeds = seeds[_unpredicted(x, seeds, predictor, model, params, fast_residual, residual_weight,
                                       residual_factor)]
        steps.advance()
        seeds = seeds[~_in_texture(fast_residual, seeds, x, model, check=steps.check, sides=texture_sides,
                                   residual_factor=residual_factor)]
        steps.advance()
        pulses = _grow_patches(x, seeds, model, params, valid_flat, circular, residual_weight, scratch,
                               fast_residual, near_scratch, check=steps.check, strong_rims=faint_pulses)
        if photon_counting and faint_pulses and residual_weight is None:  # grey and V (CFA: no faint rims)
            pulses = _without_broad_patches(x, pulses, model, scratch, channels, params.min_object_sigma_px)
        if pulses.size == 0:
            break
        rows, cols = np.divmod(pulses, w)
        # Replacement values come from outside the detected patches. (Leaving out their 1-px
        # rim as well changed the residual pulse energy by 1 % and doubled the damage of
        # false alarms on thin anatomy: measured, not kept.)
        scratch.ravel()[pulses] = 1
        repl = _masked_median_at(x, scratch, rows, cols, marked_px=pulses)
        scratch.ravel()[pulses] = 0
        keep = np.isfinite(repl)
        x.ravel()[pulses[keep]] = repl[keep].astype(_FLOAT)
        fast_residual.flat[pulses] = 0.0  # replaced: no longer busy (texture guard)
        mask_total.ravel()[pulses] = True
        dr, dc = _window_offsets(2 * reach + 1)
        to_check = _sorted_unique(_flat_indices(rows, cols, dr, dc, (h, w)), h * w)
        steps.advance()
    steps.to(channel_end)
    return x, mask_total, model


def _flat_area_sample(components: list[_Component], valid: np.ndarray | None, count: int,
                      photon_counting: bool, x: np.ndarray, fast_residual: "_FullMap") -> np.ndarray:
    """Flat indices of about ``count`` pixels in the flattest half of the image.

    Texture and edges inflate the residual and would bias the noise fit
    (docs/algorithms/impulse.md, section 'Pitfalls'); the fit therefore uses pixels whose local slope of the detection median (between
    the direct neighbours, whose medians use other samples than the pixel's own) is at most
    the median slope, the slope being divided by sqrt(m) for photon-counting channels so
    that bright areas are not excluded just for their larger noise. A median flattens fine
    texture (line patterns, meshes), so its slope does not see it; the pixels must also be
    at most ``_BUSY_SAMPLE_FACTOR`` times as busy as the median pixel (a mean of 8
    absolute noise residuals rarely is; texture far more), busy meaning the mean absolute residual to the
    fast median of the 8 pixels three steps away (scaled like the slope; those pixels and
    their median samples all have an odd offset, so they share no pixel with the residual
    the fit uses, and selecting on them does not bias the fitted noise). Regular subsample
    (deterministic).
    """
    h, w = x.shape
    candidates = _subsample_indices(h * w, 2 * count)
    if valid is not None:
        candidates = candidates[valid.ravel()[candidates]]
    if candidates.size < 32:
        return candidates
    rows, cols = np.divmod(candidates, w)
    ring_dr = np.array([-3, -3, -3, 0, 0, 3, 3, 3])
    ring_dc = np.array([-3, 0, 3, -3, 3, -3, 0, 3])
    slope = np.empty(candidates.size, _FLOAT)
    busy = np.empty(candidates.size, _FLOAT)
    for start in range(0, candidates.size, 8 * _CHUNK_PX):  # bounded (N, 8) temporaries
        part = slice(start, start + 8 * _CHUNK_PX)
        around = _component_values_at(components, rows[part, None] + np.array([0, 0, 1, -1]),
                                      cols[part, None] + np.array([1, -1, 0, 0]))
        slope[part] = np.abs(around[:, 0] - around[:, 1]) + np.abs(around[:, 2] - around[:, 3])
        busy[part] = np.abs(fast_residual.around(rows[part], cols[part], ring_dr, ring_dc)).mean(axis=1)
    if photon_counting:
        scale = np.sqrt(np.abs(x.ravel()[candidates] - fast_residual.at(candidates)) + 1.0)
        slope = slope / scale
        busy = busy / scale
    return candidates[(slope <= np.median(slope)) & (busy <= _BUSY_SAMPLE_FACTOR * np.median(busy))]


#: Variance of the Gaussian whose tail matches that of the residual of V = max(R, G, B) where
#: the three channels are equal (grey), relative to one channel's variance. The maximum of
#: three equal noisy channels has a narrow body (0.45-0.55 of one channel's variance: what
#: V's fit sees) but its upper tail is that of a single channel, three times as likely:
#: P(V - mean > u) ~ 3 Q(u/s + 0.85) (s one channel's sigma, 0.85 s the mean excess of the
#: maximum), which a Gaussian of sigma 0.84-0.86 s matches at u = 3-4 s.
_MAX_TAIL_VARIANCE = 0.75


def _match_channel_tail(model: _NoiseModel, channels: np.ndarray, pick: np.ndarray, d_v: np.ndarray,
                        m_v: np.ndarray, window_px: int) -> None:
    """Widen V's fitted noise to the tail of a maximum of channels (in place).

    On the brighter half of the EM sample, the residual of the brightest channel (by its
    detection median) to its own median is compared with V's (robust sigmas, relative to
    the fitted noise): their
    variance ratio is about 1 where one channel dominates (a tinted screen) and 1.8-2.2 on a
    grey frame. Where ``_MAX_TAIL_VARIANCE`` times it exceeds 1, ``a``, ``b`` and the floor
    are scaled by that, so that V's bright noise tail (false pulses on grey frames) is
    tested against a Gaussian as wide; ``count_variance_scale`` keeps the channel's count
    variance (the reported gain) apart from that widening.
    """
    from ...robust import robust_sigma

    rows, cols = np.divmod(pick, channels.shape[1])
    residuals = []
    for c in range(channels.shape[2]):
        med = _ring_median_at(channels, rows, cols, window_px, channel=c)
        residuals.append((channels[rows, cols, c].astype(np.float64) - med, med))
    top = np.argmax(np.stack([med for _, med in residuals]), axis=0)
    d_top = np.stack([d for d, _ in residuals])[top, np.arange(pick.size)]
    # The brighter half of the sample: a dark surround (read noise of three channels over a
    # black level, a maximum even on a tinted frame) must not set a screen's ratio.
    bright = m_v >= np.median(m_v)
    sigma = np.sqrt(model.variance(m_v[bright]))
    ratio = (robust_sigma(d_top[bright] / sigma, center=0.0)
             / max(robust_sigma(d_v[bright] / sigma, center=0.0), 1e-12)) ** 2
    scale = max(_MAX_TAIL_VARIANCE * ratio, 1.0)
    model.a *= scale
    model.b *= scale
    model.var_floor *= scale
    model.count_variance_scale = ratio / scale


def _exact_residual(x: np.ndarray, rows: np.ndarray, cols: np.ndarray, size_px: int,
                    circular: bool, residual_weight: np.ndarray | None):
    """Residual to the centre-excluded detection median, and that median (float64)."""
    med = _ring_median_at(x, rows, cols, size_px)
    d = x[rows, cols].astype(np.float64) - med
    if circular:
        d -= np.rint(d)  # into [-0.5, 0.5]: the short way round the hue circle
    if residual_weight is not None:
        d *= residual_weight[rows, cols]
    return d, med


def _fast_residual(x: np.ndarray, size_px: int, circular: bool,
                   residual_weight: np.ndarray | None) -> tuple[list[_Component], _FullMap]:
    """The fast detection medians (components) and the residual of every pixel to its own
    (float32, weighted like the test)."""
    components = []
    residual = None
    for comp, values in _detection_components(x, size_px):
        if residual is None:
            residual = _FullMap(x.shape, comp.step)
        # Contiguous work, one strided copy; in the component's own buffer unless that is x
        # itself (a 3x3 window on a contiguous float32 channel).
        d = np.subtract(values, comp.median, out=None if np.may_share_memory(values, x) else values)
        if circular:
            d -= np.rint(d)
        if residual_weight is not None:
            d *= residual_weight[comp.r0::comp.step, comp.c0::comp.step]
        residual.part(comp)[...] = d
        del values, d
        components.append(comp)
    return components, residual


def _prefilter(x: np.ndarray, median_max: float, model: _NoiseModel, params: ImpulseParams,
               residual: _FullMap) -> np.ndarray:
    """Flat indices of pulse candidates from the residuals to the cheap centre-including medians.

    Nearly a superset of the pulses of the exact test (see ``_PREFILTER_FRACTION``): the
    residual to the fast median must exceed
    ``_PREFILTER_FRACTION`` of the smallest threshold the exact test can use at that level
    (the log term of the threshold is bounded by its value at the largest variance, that
    at ``median_max``, the largest fast median), so the full-image work is a handful of
    array operations without logarithms, in blocks of rows (bounded temporaries). Where
    the variance depends on the level (photon-counting channels: never weighted or
    circular), the fast median is ``x - residual``.
    """
    height, width = x.shape
    const = model.log_odds_constant(params.posterior_threshold, model.pulse_rate)
    fraction2 = _PREFILTER_FRACTION ** 2
    if model.a > 0:
        factor = const - math.log(max(model.a * median_max + model.b, model.var_floor))
    else:
        s2 = max(model.b, model.var_floor)
        factor = const - math.log(s2)
    found = []
    rows_per_block = max(1, (1 << 20) // max(width, 1))
    for r0 in range(0, height, rows_per_block):
        d = residual.data[r0:r0 + rows_per_block].copy()
        if factor <= 0:  # degenerate fit: test every pixel exactly
            candidates = d * model.polarity > 0 if model.polarity else d != 0
        elif model.a > 0:
            s2 = np.subtract(x[r0:r0 + rows_per_block], d, dtype=_FLOAT)
            s2 *= _FLOAT(model.a * fraction2 * factor)
            s2 += _FLOAT(model.b * fraction2 * factor)
            np.maximum(s2, _FLOAT(model.var_floor * fraction2 * factor), out=s2)
            candidates = d * _FLOAT(model.polarity) > 0 if model.polarity else None
            d *= d
            candidates = d > s2 if candidates is None else candidates & (d > s2)
        else:
            threshold = _FLOAT(_PREFILTER_FRACTION * math.sqrt(s2 * factor))
            candidates = d * _FLOAT(model.polarity) > threshold if model.polarity else np.abs(d) > threshold
        found.append(np.flatnonzero(candidates) + r0 * width)
    return np.concatenate(found)


def _footprint_kernels() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The footprints of the integrated-excess test, as averaging weights on the 5x5 window.

    Returns (row offsets, column offsets) of the 25 window pixels and a (25, K) matrix
    whose columns average the residual over one footprint holding the centre: the 3x3
    square, the four 2x2 squares, and 5 px lines through the centre at 8 orientations
    (0 to 157.5 degrees, pixel positions rounded).
    """
    dr, dc = _window_offsets(5)
    index = {(int(r), int(c)): k for k, (r, c) in enumerate(zip(dr, dc))}
    footprints = [[(r, c) for r in (-1, 0, 1) for c in (-1, 0, 1)]]
    footprints += [[(r0 + r, c0 + c) for r in (0, 1) for c in (0, 1)] for r0 in (-1, 0) for c0 in (-1, 0)]
    for step in range(_LINE_ORIENTATIONS):
        angle = math.pi * step / _LINE_ORIENTATIONS
        footprints.append(sorted({(round(t * math.sin(angle)), round(t * math.cos(angle)))
                                  for t in range(-(_LINE_PX // 2), _LINE_PX // 2 + 1)}))
    weights = np.zeros((dr.size, len(footprints)))
    for k, fp in enumerate(footprints):
        for pos in fp:
            weights[index[pos], k] = 1.0 / len(fp)
    return dr, dc, weights


def _repeat_shifts() -> list[np.ndarray]:
    """Per footprint of :func:`_footprint_kernels`, the (S, 2) shifts (row, column) at which a
    copy of it is compared (see :func:`_repeats_nearby`); opposite shifts are adjacent
    (rows 2i and 2i + 1). Squares: 3 to 5 px in the 8 directions; lines: 2 to 5 px
    perpendicular to the line (along it, a track repeats itself)."""
    out = []
    squares = 5
    for k in range(squares + _LINE_ORIENTATIONS):
        shifts = []
        if k < squares:
            for dist in (3, 4, 5):
                for dr_, dc_ in ((0, 1), (1, 0), (1, 1), (1, -1)):
                    shifts += [(dist * dr_, dist * dc_), (-dist * dr_, -dist * dc_)]
        else:
            angle = math.pi * (k - squares) / _LINE_ORIENTATIONS
            for dist in (2, 3, 4, 5):
                r_, c_ = round(dist * math.cos(angle)), round(-dist * math.sin(angle))
                shifts += [(r_, c_), (-r_, -c_)]
        out.append(np.array(shifts))
    return out


def _footprint_means(residual: _FullMap, pixels: np.ndarray) -> np.ndarray:
    """(N, K) means of the fast residual over each footprint of :func:`_footprint_kernels`."""
    dr, dc, weights = _FOOTPRINTS
    out = np.empty((pixels.size, weights.shape[1]))
    for start in range(0, pixels.size, _CHUNK_PX):
        part = pixels[start:start + _CHUNK_PX]
        around = residual.around(*np.divmod(part, residual.width), dr, dc).astype(np.float64)
        out[start:start + _CHUNK_PX] = around @ weights
    return out


def _footprint_noise(residual: _FullMap, pick: np.ndarray, level: np.ndarray,
                     model: _NoiseModel) -> np.ndarray | None:
    """Noise of each footprint mean (:func:`_footprint_means`) relative to the model's
    sigma, measured robustly on the EM sample (neighbouring residuals share median samples,
    so it is not 1/sqrt(n)); None when there are too few samples."""
    from ...robust import robust_sigma

    if pick.size < 256:
        return None
    at = _subsample_indices(pick.size, _FOOTPRINT_NOISE_SAMPLES)
    pick, level = pick[at], level[at]
    means = _footprint_means(residual, pick) / np.sqrt(model.variance(level))[:, None]
    factor = np.array([robust_sigma(means[:, k], center=0.0) for k in range(means.shape[1])])
    # Never below white noise's: on a steep ramp most residuals to a median that holds the
    # centre are exactly zero, and the measured spread with them.
    return np.maximum(factor, _WHITE_NOISE_FOOTPRINT_SIGMA[3 if residual.step == 1 else 5])


def _footprint_seeds(x: np.ndarray, residual: _FullMap, model: _NoiseModel, params: ImpulseParams,
                     footprint_noise: np.ndarray, valid_flat: np.ndarray | None) -> np.ndarray:
    """Flat indices of the integrated-excess seeds (see ``_FOOTPRINT_SIGMAS``).

    Candidates (blocks of rows, with the pulse's polarity and the Weber contrast rule): a
    residual between ``_FOOTPRINT_OWN_SIGMAS`` and ``_FOOTPRINT_MAX_OWN_SIGMAS`` pixel noise
    sigmas and a 3x3 mean beyond
    ``_FOOTPRINT_PRESCREEN_SIGMAS`` of its noise. A candidate is a seed when its best footprint's mean exceeds
    ``_FOOTPRINT_SIGMAS`` of that mean's noise, the noise being at least the structure
    guard's (``_square_ring_spread`` at ``max_patch_px``, as for the exact test), when its
    own residual is at least ``_OWN_FRACTION`` of that mean, and when its annulus is quiet
    (:func:`_noisy_annulus`).
    """
    import cv2

    height, width = x.shape
    sign = _FLOAT(model.polarity if model.polarity else 1)
    own2 = _FLOAT(_FOOTPRINT_OWN_SIGMAS ** 2)
    faint2 = _FLOAT(_FOOTPRINT_MAX_OWN_SIGMAS ** 2)
    found = []
    rows_per_block = max(1, (1 << 20) // max(width, 1))
    square2 = _FLOAT((_FOOTPRINT_PRESCREEN_SIGMAS * footprint_noise[0]) ** 2)
    for r0 in range(0, height, rows_per_block):
        lo, hi = max(0, r0 - 1), min(height, r0 + rows_per_block + 1)
        square = cv2.blur(residual.data[lo:hi], (3, 3), borderType=cv2.BORDER_REPLICATE)
        square = square[r0 - lo:r0 - lo + rows_per_block]
        d = residual.data[r0:r0 + rows_per_block]
        var = model.variance(np.subtract(x[r0:r0 + rows_per_block], d, dtype=_FLOAT))
        # The 3x3 mean first (the most selective test); the rest on its few pixels.
        if model.polarity:
            square *= sign
            np.maximum(square, _FLOAT(0.0), out=square)
        square *= square
        var *= square2
        at = np.flatnonzero(square > var)
        d_at = d.ravel()[at]
        var_at = var.ravel()[at] * _FLOAT(1.0 / square2)
        d2 = d_at * d_at
        hit = (d2 > own2 * var_at) & (d2 < faint2 * var_at)
        hit &= (d_at * sign > 0) if model.polarity else (d_at != 0)
        if model.min_contrast > 0:
            level_at = x.ravel()[r0 * width + at] - d_at
            hit &= np.abs(d_at) > _FLOAT(model.min_contrast) * np.abs(level_at)
        found.append(at[hit] + r0 * width)
    candidates = np.concatenate(found)
    if valid_flat is not None:
        candidates = candidates[valid_flat[candidates]]
    rows, cols = np.divmod(candidates, width)
    # Footprints must lie inside the frame: a replicated border repeats one residual and
    # breaks the measured noise of the mean.
    inside = (rows >= 2) & (rows < height - 2) & (cols >= 2) & (cols < width - 2)
    candidates, rows, cols = candidates[inside], rows[inside], cols[inside]
    if candidates.size == 0:
        return candidates
    raw = _footprint_means(residual, candidates)
    own = residual.at(candidates).astype(np.float64)
    if model.polarity:
        raw, own = raw * model.polarity, own * model.polarity
    else:
        raw, own = np.abs(raw), np.abs(own)
    means = raw / footprint_noise[None, :]
    pick = means.argmax(axis=1)
    best = means[np.arange(pick.size), pick]
    level = x.ravel()[candidates].astype(np.float64) - residual.at(candidates)
    var = model.variance(level)
    # The pixel itself must carry the footprint's excess, not sit next to a pulse that does.
    pre = (best * best > _FOOTPRINT_SIGMAS ** 2 * var) & (own >= _OWN_FRACTION * raw[np.arange(pick.size), pick])
    candidates, best, var, rows, cols = candidates[pre], best[pre], var[pre], rows[pre], cols[pre]
    # Structure guard: on an edge or a corner the footprint's mean is the structure's.
    # The ring's spread is noise plus structure. Structure is correlated between neighbours
    # and does not average down over the footprint as noise does: beyond the pixel noise
    # it bounds the footprint mean's own variance (var is in units of the pixel's, the
    # footprint factor^2 below, hence the division by it).
    spread = _square_ring_spread(x, rows, cols, params.max_patch_px)
    structure2 = np.maximum(spread * spread - var, 0.0) / footprint_noise[pick[pre]] ** 2
    var = np.maximum(var, np.maximum(spread * spread, structure2) / _SEED_SPREAD_TOLERANCE ** 2)
    # The posterior test of the mixture on the footprint's mean (variance: footprint factor^2
    # times the pixel's), never below _FOOTPRINT_SIGMAS: a frame with few pulses (a small
    # fitted pulse rate) gets a higher threshold, as in the exact test.
    fp_var = var * footprint_noise[pick[pre]] ** 2
    limit = np.maximum(model.log_odds_constant(params.posterior_threshold, model.pulse_rate) - np.log(fp_var),
                       _FOOTPRINT_SIGMAS ** 2)
    keep = best * best > limit * var
    seeds = candidates[keep]
    kernel = pick[pre][keep]
    signed_mean = _footprint_means(residual, seeds)[np.arange(seeds.size), kernel]
    seeds = seeds[~_repeats_nearby(residual, seeds, kernel, signed_mean)]
    return seeds[~_noisy_annulus(residual, seeds, x, model)]


def _repeats_nearby(residual: _FullMap, pixels: np.ndarray, kernel: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """True where a copy of a pixel's best footprint, shifted to both sides by the same
    amount (:func:`_repeat_shifts`), holds on average at least ``_REPEAT_FRACTION`` of the
    footprint's own mean (signed like it): structure that continues beyond the pulse's
    extent (a line pattern's next line, a mesh's next node), not a pulse or a track, whose
    surroundings are background. ``kernel``: index of the best footprint per pixel;
    ``mean``: its signed mean."""
    dr, dc, weights = _FOOTPRINTS
    out = np.zeros(pixels.size, bool)
    for k in np.unique(kernel):
        sel = np.flatnonzero(kernel == k)
        on = weights[:, k] > 0
        rows, cols = np.divmod(pixels[sel], residual.width)
        shifts = _REPEAT_SHIFTS[k]
        sums = np.empty((sel.size, shifts.shape[0]))
        for j, (sr, sc) in enumerate(shifts):
            sums[:, j] = residual.around(rows + sr, cols + sc, dr[on], dc[on]).astype(np.float64).mean(axis=1)
        pair = 0.5 * (sums[:, 0::2] + sums[:, 1::2]) * np.sign(mean[sel])[:, None]
        out[sel] = pair.max(axis=1) >= _REPEAT_FRACTION * np.abs(mean[sel])
    return out


def _noisy_annulus(residual: _FullMap, pixels: np.ndarray, x: np.ndarray, model: _NoiseModel) -> np.ndarray:
    """True where more than ``_FAINT_TEXTURE_FRACTION`` of the texture guard's annulus lies
    beyond ``_FAINT_TEXTURE_SIGMAS`` noise sigmas (noise alone: 4.6 % at 2 sigmas; a track
    crossing it adds about 10 %): the stricter guard of the integrated-excess seeds, whose
    pixels are faint, as faint texture is (a pattern a few sigmas deep, or aliased onto
    a CFA plane)."""
    out = np.zeros(pixels.size, bool)
    dr, dc = _ANNULUS_DR, _ANNULUS_DC
    flat_x = x.ravel()
    for start in range(0, pixels.size, _CHUNK_PX):
        part = pixels[start:start + _CHUNK_PX]
        idx = _flat_indices(*np.divmod(part, x.shape[1]), dr, dc, x.shape)
        around = residual.flat[idx]
        noise2 = model.variance(flat_x[idx] - around).astype(_FLOAT)
        beyond = around * around > _FLOAT(_FAINT_TEXTURE_SIGMAS ** 2) * noise2
        out[start:start + _CHUNK_PX] = np.count_nonzero(beyond, axis=1) > _FAINT_TEXTURE_FRACTION * dr.size
    return out


def _in_texture(residual: _FullMap, pixels: np.ndarray, x: np.ndarray, model: "_NoiseModel",
                reference: np.ndarray | None = None, ignore: np.ndarray | None = None,
                chunk: int = _CHUNK_PX, check=None, sides: str | None = None,
                residual_factor: float = MEDIAN_RESIDUAL_VARIANCE_FACTOR[3]) -> np.ndarray:
    """True where the annulus around a pixel is busier than a pulse's can be (texture guard).

    ``residual``: the fast-median residual map of :func:`_prefilter`; ``pixels``: flat
    indices; ``reference``: the residual busy pixels are compared with (default: each
    pixel's own to the fast median; a patch rim uses its excess over its background),
    never less than ``_BUSY_SIGMAS`` noise sigmas; ``x`` and ``model``: the
    channel and its noise model (for the noise-relative count); ``ignore`` (flat uint8,
    optional): pixels left out of the annulus (next to detected pulses, whose fast median
    the pulse pulls up). Fewer than a third of the annulus left: not texture. ``check``
    (optional) is called between chunks (a progress report that may stop the stage).
    ``sides``: also one busy side of the annulus (:func:`_textured_side`; ``"one_signed"``
    or ``"two_signed"``) or one curved side (:func:`_curved_side`; ``residual_factor``: the
    model's variance over a pixel's), or None.
    """
    out = np.zeros(pixels.size, bool)
    if pixels.size == 0:
        return out
    dr, dc = _ANNULUS_DR, _ANNULUS_DC
    flat_x = x.ravel()

    for start in range(0, pixels.size, chunk):
        if check is not None and start:
            check()
        part = pixels[start:start + chunk]
        rows, cols = np.divmod(part, x.shape[1])
        own_residual = residual.at(part)
        own = own_residual if reference is None else reference[start:start + chunk]
        if model.a > 0:
            own_noise2 = model.variance(flat_x[part] - own_residual)
        else:
            own_noise2 = max(model.b, model.var_floor)
        # At least the noise-relative level: a weak pulse or rim is not texture for noise.
        level = np.maximum(np.abs(own) * _BUSY_RELATIVE, _BUSY_SIGMAS * np.sqrt(own_noise2)).astype(_FLOAT)
        idx = _flat_indices(rows, cols, dr, dc, x.shape)
        around_signed = residual.flat[idx]
        around = np.abs(around_signed)
        counted = np.ones(idx.shape, bool) if ignore is None else ignore[idx] == 0
        n_counted = np.count_nonzero(counted, axis=1)
        busy_px = (around > level[:, None]) & counted
        busy = np.count_nonzero(busy_px, axis=1) > _TEXTURE_BUSY_FRACTION * n_counted
        around *= around
        # A seed far above the texture around it (a strong pulse on a mesh) is a pulse
        # however noisy that texture is; the noise-relative count is for weak seeds.
        far_above = _FLOAT(_STANDOUT_RELATIVE * _STANDOUT_RELATIVE) * (own * own).astype(_FLOAT)
        standout = (np.count_nonzero((around > far_above[:, None]) & counted, axis=1)
                    <= _TEXTURE_BUSY_FRACTION * n_counted)
        # The noise-relative count decides only pixels neither busy yet nor standing out
        # (few on frames dense with strong pulses): computed for those alone.
        undecided = np.flatnonzero(~busy & ~standout)
        noisy = np.zeros(idx.shape, bool)
        if undecided.size:
            if model.a > 0:  # photon counting: variance at the fast median x - residual
                noise2 = model.variance(flat_x[idx[undecided]] - around_signed[undecided]).astype(_FLOAT)
            else:
                noise2 = _FLOAT(max(model.b, model.var_floor))
            noisy[undecided] = (around[undecided] > _FLOAT(_BUSY_SIGMAS ** 2) * noise2) & counted[undecided]
        busy |= (np.count_nonzero(noisy, axis=1) > _TEXTURE_NOISY_FRACTION * n_counted) & ~standout
        busy &= n_counted * 3 >= dr.size
        if sides is not None:
            positive = around_signed > 0 if sides == "two_signed" else None
            busy |= _textured_side(busy_px, noisy, counted, standout, positive)
            rest = np.flatnonzero(~busy)
            if rest.size:
                busy[rest] = _curved_side(x, rows[rest], cols[rest], own[rest], model, residual_factor)
        out[start:start + chunk] = busy
    return out


def _textured_side(busy_px: np.ndarray, noisy_px: np.ndarray, counted: np.ndarray,
                   standout: np.ndarray, positive: np.ndarray | None = None) -> np.ndarray:
    """True where one side of the texture guard's annulus (its upper, lower, left or right
    three rows or columns) is as busy as texture: the pixel lies at the border of a
    textured area, whose half of the annulus the whole-annulus fractions dilute.

    ``positive`` (bool, like ``busy_px``; optional): the sign of each annulus residual; a
    side then counts only when each sign holds at least ``_SIDE_MIN_SIGN_SHARE`` of its busy
    (or noisy) pixels, as a pattern's alternating residuals do and a neighbouring pulse's
    do not."""

    def two_signed(px: np.ndarray, side: np.ndarray) -> np.ndarray:
        on_side = px[:, side]
        pos = np.count_nonzero(on_side & positive[:, side], axis=1)
        neg = np.count_nonzero(on_side, axis=1) - pos
        return np.minimum(pos, neg) >= _SIDE_MIN_SIGN_SHARE * (pos + neg)

    out = np.zeros(busy_px.shape[0], bool)
    for side in _ANNULUS_SIDES:
        n = np.count_nonzero(counted[:, side], axis=1)
        enough = n * 2 >= np.count_nonzero(side)
        rel = np.count_nonzero(busy_px[:, side], axis=1) > _SIDE_BUSY_FRACTION * n
        noisy = (np.count_nonzero(noisy_px[:, side], axis=1) > _SIDE_NOISY_FRACTION * n) & ~standout
        if positive is not None:
            rel &= two_signed(busy_px, side)
            noisy &= two_signed(noisy_px, side)
        out |= enough & (rel | noisy)
    return out


def _curved_side(x: np.ndarray, rows: np.ndarray, cols: np.ndarray, own: np.ndarray, model: _NoiseModel,
                 residual_factor: float) -> np.ndarray:
    """True where one side of the texture guard's annulus around (``rows``, ``cols``) is
    mostly curved: more than ``_CURVED_SIDE_FRACTION`` of its pixels have a second
    difference of ``x`` beyond ``_CURVED_SIGMAS`` of its noise (6 pixel variances, the
    pixel's variance read from ``model`` at its own value) and of at least
    ``_CURVED_RELATIVE`` times the pixel's own residual ``own`` (a strong pulse on texture
    stands above the texture's curvature). Fine periodic texture is curved everywhere; a
    pulse of up to 5x5 px covers at most 15 of a side's 39 pixels."""
    size = 2 * _TEXTURE_OUTER_PX + 3  # the annulus's window and a 1-px margin
    win = _window_values(x, rows, cols, size).reshape(rows.size, size, size)
    centre = win[:, 1:-1, 1:-1]
    across_rows = win[:, :-2, 1:-1] + win[:, 2:, 1:-1]
    across_rows -= 2 * centre
    across_cols = win[:, 1:-1, :-2] + win[:, 1:-1, 2:]
    across_cols -= 2 * centre
    np.multiply(across_rows, across_rows, out=across_rows)
    np.multiply(across_cols, across_cols, out=across_cols)
    np.maximum(across_rows, across_cols, out=across_rows)
    curvature2 = across_rows.reshape(rows.size, -1)[:, _ANNULUS_ON]
    centre = centre.reshape(rows.size, -1)[:, _ANNULUS_ON]
    noise2 = model.variance(centre) if model.a > 0 else max(model.b, model.var_floor)
    curved = curvature2 > _FLOAT(_CURVED_SIGMAS ** 2 * 6.0 / residual_factor) * noise2
    own_part = (_FLOAT(_CURVED_RELATIVE) * own.astype(_FLOAT)) ** 2
    curved &= curvature2 > own_part[:, None]
    out = np.zeros(rows.size, bool)
    for side in _ANNULUS_SIDES:
        out |= np.count_nonzero(curved[:, side], axis=1) > _CURVED_SIDE_FRACTION * np.count_nonzero(side)
    return out


def _unpredicted(x: np.ndarray, seeds: np.ndarray, predictor: "_Predictor", model: _NoiseModel,
                 params: ImpulseParams, fast_residual: _FullMap, residual_weight: np.ndarray | None,
                 residual_factor: float) -> np.ndarray:
    """True for seeds that are pulses by their residual to the texture's linear prediction.

    On a frame filled with fine texture the median residual holds texture and noise
    together; where the texture's amplitude is a few noise sigmas (a dim channel, or a CFA
    plane on which the scene's pattern lands aliased) their sum passes the test at many
    places, in neighbourhoods the texture guard cannot tell from noise. The predictor
    removes the texture: its residual, rescaled to the variance of the median residual the
    model describes, takes the same posterior test (at the predicted level).
    """
    d = predictor.residual_at(x, seeds)
    level = x.ravel()[seeds].astype(np.float64) - d  # the prediction: the texture's level there
    d *= math.sqrt(residual_factor / predictor.noise_gain)
    if residual_weight is not None:
        d *= residual_weight.ravel()[seeds]
    return model.is_pulse(d, level, params.posterior_threshold)


def _exact_test(x: np.ndarray, candidates: np.ndarray, model: _NoiseModel, params: ImpulseParams,
                circular: bool, residual_weight: np.ndarray | None,
                x_span: float | None = None) -> np.ndarray:
    """The candidates (flat indices) that are pulses by the posterior test.

    ``x_span`` (optional): ``x.max() - x.min()``. The structure guard's spread (32 ring
    pixels gathered and sorted per candidate) is then computed only where it can change
    the result: for candidates that fail the test without it, a floor between their
    variance and the largest the span allows, all below the peak of the test's bound
    (:meth:`_NoiseModel.test_limit`, rising there), can only raise the bound, so they fail
    with it too. Most candidates of a later pass (the pixels around the previous pass's
    pulses) are such noise; the result is the same.
    """
    if candidates.size == 0:
        return candidates
    pulse = np.zeros(candidates.size, bool)
    if x_span is not None:
        const = model.log_odds_constant(params.posterior_threshold, model.pulse_rate)
        # Below the peak with a margin for rounding; the spread's largest value: the ring's
        # quartile difference of pair means is at most the span.
        below_peak = math.exp(min(const - 1.0, 700.0)) * (1.0 - 1e-9)
        largest_floor = math.sqrt(2.0) * IQR_TO_SIGMA * x_span * (1.0 + 1e-6) / _SEED_SPREAD_TOLERANCE
    for start in range(0, candidates.size, _CHUNK_PX):  # bounded temporaries (later passes test many)
        part = slice(start, start + _CHUNK_PX)
        rows, cols = np.divmod(candidates[part], x.shape[1])
        d, med = _exact_residual(x, rows, cols, params.window_px, circular, None)
        weight = None
        if residual_weight is not None:
            weight = residual_weight[rows, cols]
            d *= weight
        need = slice(None)
        if x_span is not None:
            s2 = model.variance(med)
            floor2 = largest_floor * largest_floor if weight is None else (largest_floor * weight.astype(np.float64)) ** 2
            unchanged = ((d * d <= model.test_limit(s2, params.posterior_threshold) * (1.0 - 1e-12))
                         & (np.maximum(s2, floor2) <= below_peak))
            need = np.flatnonzero(~unchanged)
            rows, cols, d, med = rows[need], cols[need], d[need], med[need]
            weight = None if weight is None else weight[need]
        spread = _square_ring_spread(x, rows, cols, params.max_patch_px)
        if weight is not None:
            spread *= weight
        # Structure guard: where the background around the candidate spreads far more than the
        # noise (an edge, the corner of the screen), the residual is not Gaussian around the
        # median; the variance is then at least (spread / _SEED_SPREAD_TOLERANCE)^2. The spread
        # is taken just outside the largest patch, so the patch itself never inflates it.
        spread /= _SEED_SPREAD_TOLERANCE
        pulse[start:start + _CHUNK_PX][need] = model.is_pulse(d, med, params.posterior_threshold,
                                                               min_variance=spread * spread)
    return candidates[pulse]


def _grow_patches(x: np.ndarray, seeds: np.ndarray, model: _NoiseModel, params: ImpulseParams,
                  valid_flat: np.ndarray | None, circular: bool,
                  residual_weight: np.ndarray | None, scratch: np.ndarray,
                  fast_residual: _FullMap, near_scratch: np.ndarray, check=None,
                  strong_rims: bool = False) -> np.ndarray:
    """Add neighbours of detected pulses that are pulses against their background.

    Each round tests the ring of pixels next to the pulses against the median of the
    pixels of a 7x7 (or larger) window that are neither pulses nor in the ring, so the
    still undetected core of a large patch does not pull the background up; a patch is
    peeled from its rim inward. The window is large enough to surround the pixel on an edge
    (a 3x3 window minus the patch would hold only pixels on one side). Ring pixels get the
    prior pulse probability ``params.neighbour_prior``: pulses come as patches and tracks,
    so their fainter rims are accepted at a lower significance.

    ``strong_rims``: a pixel of the first ring around seeds at least
    ``_STRONG_SEED_SIGMAS`` above the noise is also a pulse by :func:`_rim_of_strong_seed`
    (hysteresis; photon-counting channels).

    Grown pixels also pass the texture guard (:func:`_in_texture`), relative to their
    excess over the background and ignoring pixels within 2 px of the pulses found so far.

    ``seeds`` and the result are flat indices; ``scratch`` and ``near_scratch`` (uint8,
    zero) mark pulses and ring, and the neighbourhood of pulses; both are zero on return.
    ``check`` (optional) is called between growth rounds (a progress report that may stop
    the stage; the scratch arrays are then left marked, so the stage must not go on).
    """
    if seeds.size == 0:
        return seeds
    h, w = x.shape
    marks = scratch.ravel()
    prior = max(params.neighbour_prior, model.pulse_rate)
    dr8 = np.array([-1, -1, -1, 0, 0, 1, 1, 1])
    dc8 = np.array([-1, 0, 1, -1, 1, -1, 0, 1])
    pulses = seeds
    marks[pulses] = 1
    strong_ring = None  # hysteresis (photon-counting channels): the ring around strong seeds
    if strong_rims and model.a > 0:
        own = fast_residual.at(seeds).astype(np.float64)
        strong = seeds[own * own > _STRONG_SEED_SIGMAS ** 2 * model.variance(x.ravel()[seeds] - own)]
        strong_ring = _sorted_unique(_flat_indices(*np.divmod(strong, w), dr8, dc8, (h, w)), h * w)
    near_flat = near_scratch.ravel()
    dr5, dc5 = _window_offsets(5)
    near_marked = [_flat_indices(*np.divmod(seeds, w), dr5, dc5, (h, w))]
    near_flat[near_marked[0]] = 1
    # Each round re-tests the whole ring, but a ring pixel the test rejected keeps its result
    # while no mark of its window changes: marks change only within 1 px of the pixels grown
    # last round and the window reaches at most 4 px (9x9), so only rejected pixels within
    # 5 px of them are tested again (same result; most of a 1 % pulse frame's ring is stale
    # after the first round). The ring itself is updated from the pixels grown.
    ring = _sorted_unique(_flat_indices(*np.divmod(pulses, w), dr8, dc8, (h, w)), h * w)
    stale = None  # ring pixels rejected by the test and not re-testable yet (sorted)
    for round_ in range(params.max_patch_px):
        if check is not None and round_:
            check()
        ring = ring[marks[ring] == 0]
        if valid_flat is not None:
            ring = ring[valid_flat[ring]]
        if ring.size == 0:
            break
        marks[ring] = 2
        rejected = np.zeros(ring.shape, bool)  # rejected by the test (skipped ones included)
        if stale is None:
            tested_at = np.arange(ring.size)
        else:
            skip = _in_sorted(ring, stale)
            skip[skip] = ~_near(ring[skip], grown, _STALE_REACH_PX, (h, w), near_flat)
            rejected[skip] = True
            tested_at = np.flatnonzero(~skip)
        tested = ring[tested_at]
        marked = np.concatenate([pulses, ring])  # the nonzero marks
        med, spread = _masked_median_at(x, scratch, *np.divmod(tested, w), smallest_px=7,
                                        symmetric=True, with_spread=True, marked_px=marked)
        d = x.ravel()[tested].astype(np.float64) - med
        if circular:
            d -= np.rint(d)
        if residual_weight is not None:
            weight = residual_weight.ravel()[tested]
            d *= weight
            spread *= weight
        ok = np.isfinite(d)
        new = np.zeros(tested.shape, bool)
        new[ok] = model.is_pulse(d[ok], med[ok], params.posterior_threshold, prior=prior,
                                 min_variance=spread[ok] ** 2)
        if round_ == 0 and strong_ring is not None:
            rim = np.flatnonzero(ok & ~new & _in_sorted(tested, strong_ring))
            new[rim] = _rim_of_strong_seed(x, scratch, tested[rim], d[rim], med[rim], spread[rim], model, params,
                                           marked)
        # A rejected pixel failed the plain test (the strong rims' test only adds pulses),
        # which later rounds repeat while its window is unchanged.
        rejected[tested_at] = ~new
        marks[ring] = 0
        if new.any():
            # Texture guard as for seeds, relative to the pixel's excess over its background.
            texture = _in_texture(fast_residual, tested[new], x, model, d[new], near_flat)
            new[np.flatnonzero(new)[texture]] = False
        if not new.any():
            break
        grown = tested[new]
        stale = ring[rejected]
        marks[grown] = 1
        near_marked.append(_flat_indices(*np.divmod(grown, w), dr5, dc5, (h, w)))
        near_flat[near_marked[-1]] = 1
        pulses = np.concatenate([pulses, grown])
        # The next ring: this one without the grown pixels, and the grown pixels' neighbours.
        ring = _sorted_unique(np.concatenate([ring, _flat_indices(*np.divmod(grown, w), dr8, dc8, (h, w)).ravel()]),
                              h * w)
    marks[pulses] = 0
    for marked in near_marked:
        near_flat[marked] = 0
    return pulses


#: A grown patch of V is broad structure, not a pulse, when it is compact (its coordinates' smaller
#: spread at least this, px: a 3x3 square spreads 0.82 px, a 2 px track less) ...
_BROAD_MIN_SPREAD_PX = 0.9
#: ... and not elongated: its coordinates' larger spread at most this many times the smaller (a
#: track with soft edges, 3 px wide, also spreads 0.9 px across and its rims go on beyond it; with
#: no such bound, 2 of the 20-sigma tracks of held-out seed 6002 were dropped whole) ...
_BROAD_MAX_ELONGATION = 3.0
#: ... and the ring just outside it stands, by its median, at least this many noise sigmas (per
#: pixel; the median, because a pulse the growth has not peeled to its end has the rest of
#: itself in part of its ring, where a blob's whole ring stands up) ...
_BROAD_RING_SIGMAS = 2.0
#: ... and at least this share of the patch's own border excess above the background 2-3 px out:
#: a pulse ends within its footprint (81 % of dev pulse patches' rings under 0.1 of the border's
#: excess), a blob blurred by the screen goes on down its flanks (0.2-0.6).
_BROAD_RING_SHARE = 0.25
#: ... and its excess has the scintillator's colour: chi-square (2 degrees of freedom) of the
#: patch's mean excess per channel about the background's colour, scaled, at most this (p 0.001).
_TINT_CHI2 = 13.8
#: Relative colour mismatch each channel's excess is allowed besides the noise (a pulse in a subset
#: of the channels misses by 100 % in the others).
_TINT_TOLERANCE = 0.05


# A grown patch is also broad structure when its excess, with the 2 px around it, is a smooth
# Gaussian hill (a small dense object, a calcification or a marker, blurred by the screen) at
# least ``ImpulseParams.min_object_sigma_px`` wide: the growth climbs such a hill down to the
# noise, so its ring no longer stands up, and the replacement would flatten it. The independent
# pulses' Gaussians have sigma 0.5-1.1 px and end within their footprints; flat pulses and
# clusters end abruptly and fit no Gaussian that also fits their ring.

#: Gaussian widths tried for the hill (sigma, px); a best fit at the widest is no hill (a flat top).
_HILL_SIGMAS_PX = np.arange(0.5, 4.01, 0.1)
#: The hill fits when its chi-square is within this many standard deviations of its degrees of
#: freedom (the pixels less 7: the plane's 3, height, width and centre) ...
_HILL_CHI2_SDS = 3.0
#: ... and beats a pulse's shape, one flat level over the patch and none in its ring, by at
#: least this much chi-square: at a few noise sigmas a small flat pulse fits a wide Gaussian as
#: well (dev pulse frames, grey, the test's first form: 4-sigma flat pulses' recall 0.51 -> 0.44
#: without this condition).
_HILL_MIN_CHI2_GAIN = 25.0
#: Relative mismatch a hill's profile is allowed besides the noise, of its excess.
_HILL_TOLERANCE = 0.05
#: Only a patch whose border excess is at most this share of its peak excess is fitted as a hill.
_HILL_MAX_BORDER_SHARE = 0.75
#: The hill's background plane is also fitted on the outline of the patch's bounding box grown
#: by this, px (besides the 2 px around the patch).
_HILL_BACKGROUND_PX = 5


def _box_outline(shape, labels: np.ndarray, rows: np.ndarray, cols: np.ndarray, margin_px: int,
                 count: int) -> tuple[np.ndarray, np.ndarray]:
    """(labels, flat indices) of the outline of each label's bounding box (its pixels
    ``labels``, ``rows``, ``cols``) grown by ``margin_px``, clipped to the image."""
    h, w = shape
    r0 = np.full(count, h, np.int64)
    c0 = np.full(count, w, np.int64)
    r1 = np.full(count, -1, np.int64)
    c1 = np.full(count, -1, np.int64)
    np.minimum.at(r0, labels, rows)
    np.minimum.at(c0, labels, cols)
    np.maximum.at(r1, labels, rows)
    np.maximum.at(c1, labels, cols)
    used = np.flatnonzero(r1 >= 0)
    r0, c0 = np.maximum(r0[used] - margin_px, 0), np.maximum(c0[used] - margin_px, 0)
    r1, c1 = np.minimum(r1[used] + margin_px, h - 1), np.minimum(c1[used] + margin_px, w - 1)
    lab_parts, pix_parts = [], []
    for fixed, lo, hi, along_rows in ((r0, c0, c1, False), (r1, c0, c1, False), (c0, r0 + 1, r1 - 1, True),
                                      (c1, r0 + 1, r1 - 1, True)):
        n = np.maximum(hi - lo + 1, 0)
        moving = np.repeat(lo, n) + np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        fixed_rep = np.repeat(fixed, n)
        lab_parts.append(np.repeat(used, n))
        pix_parts.append(moving * w + fixed_rep if along_rows else fixed_rep * w + moving)
    return np.concatenate(lab_parts), np.concatenate(pix_parts)


def _gaussian_hills(values: np.ndarray, width: int, sign: np.ndarray, background: np.ndarray,
                    model: _NoiseModel, patch: tuple[np.ndarray, np.ndarray],
                    around: tuple[np.ndarray, np.ndarray], min_sigma_px: float) -> np.ndarray:
    """Per label (``sign``'s length), whether the patch, with the pixels ``around`` it, is a
    Gaussian hill of sigma ``min_sigma_px`` or wider on a sloping background.

    ``patch``, ``around``: (labels, flat indices) of their pixels in ``values`` (the channel,
    flat, ``width`` px per row); ``sign``: +1 for a bright patch, -1 for a dark one;
    ``background``: a level near each patch, for the model's tolerance. The model,
    fitted by weighted least squares (each pixel by its noise), is a plane plus ``sign`` times a
    Gaussian at the patch's excess-weighted centroid, on a grid of widths
    (:data:`_HILL_SIGMAS_PX`); the pulse's alternative is the plane plus one level over the patch.
    """
    n_labels = sign.size
    # on the labels present only (a frame's patches number in the ten thousands)
    used, lab = np.unique(np.concatenate([patch[0], around[0]]), return_inverse=True)
    count, n_patch = used.size, patch[0].size
    sign, background = sign[used], background[used]
    patch_lab = lab[:n_patch]
    pix = np.concatenate([patch[1], around[1]])
    rows, cols = np.divmod(pix, width)
    y = values[pix].astype(np.float64)
    # each pixel's noise, and a tolerance for a real object's profile (not quite Gaussian,
    # centre and width on a grid) in proportion to its excess
    excess = y - np.nan_to_num(background)[lab]
    wt = 1.0 / (np.maximum(model.variance(np.maximum(y, 0.0)), 1e-12) + (_HILL_TOLERANCE * excess) ** 2)
    # centre: the patch pixels' positive excess as weights (the hill's top)
    top = np.maximum(sign[patch_lab] * excess[:n_patch], 0.0)
    total = np.maximum(np.bincount(patch_lab, top, count), 1e-12)
    centre_r = np.bincount(patch_lab, top * rows[:n_patch], count) / total
    centre_c = np.bincount(patch_lab, top * cols[:n_patch], count) / total
    dr, dc = rows - centre_r[lab], cols - centre_c[lab]
    d2 = dr * dr + dc * dc

    # the background's columns [1, dr, dc] do not depend on the shape: their sums once
    base_columns = (np.ones_like(y), dr, dc)
    base_normal = np.empty((count, 3, 3))
    base_rhs = np.empty((count, 3))
    for i in range(3):
        base_rhs[:, i] = np.bincount(lab, wt * base_columns[i] * y, count)
        for j in range(i, 3):
            base_normal[:, i, j] = base_normal[:, j, i] = np.bincount(
                lab, wt * base_columns[i] * base_columns[j], count)
    sum_wyy = np.bincount(lab, wt * y * y, count)

    def chi2_of(shape_col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # least squares of y on [1, dr, dc, shape] per label: (chi-square, shape's coefficient)
        normal = np.empty((count, 4, 4))
        rhs = np.empty((count, 4))
        normal[:, :3, :3], rhs[:, :3] = base_normal, base_rhs
        w_shape = wt * shape_col
        rhs[:, 3] = np.bincount(lab, w_shape * y, count)
        for i in range(3):
            normal[:, i, 3] = normal[:, 3, i] = np.bincount(lab, w_shape * base_columns[i], count)
        normal[:, 3, 3] = np.bincount(lab, w_shape * shape_col, count)
        normal[:, range(4), range(4)] += 1e-9
        beta = np.linalg.solve(normal, rhs[..., None])[..., 0]
        return sum_wyy - np.einsum("ki,ki->k", beta, rhs), beta[:, 3]

    best_chi2, best_sigma, best_height = np.full(count, np.inf), np.zeros(count), np.zeros(count)
    for sigma in _HILL_SIGMAS_PX:
        chi2, height = chi2_of(np.exp(-d2 / (2.0 * sigma * sigma)))
        better = chi2 < best_chi2
        best_chi2[better], best_sigma[better], best_height[better] = chi2[better], sigma, height[better]
    flat_chi2, _ = chi2_of((np.arange(lab.size) < n_patch).astype(np.float64))
    dof = np.maximum(np.bincount(lab, minlength=count) - 7, 1).astype(np.float64)
    hill = np.zeros(n_labels, bool)
    hill[used] = ((best_sigma >= min_sigma_px) & (best_sigma < _HILL_SIGMAS_PX[-1])
                  & (sign * best_height > 0) & (best_chi2 <= dof + _HILL_CHI2_SDS * np.sqrt(2.0 * dof))
                  & (best_chi2 + _HILL_MIN_CHI2_GAIN <= flat_chi2))
    return hill


def _scintillator_tint(channels: np.ndarray, block_px: int = 8) -> np.ndarray:
    """The colour (unit RGB vector) in which the frame's light varies: the first principal axis
    of the differences between neighbouring ``block_px`` blocks' mean colours (the largest 1 %
    left out), less what the pixel noise puts there.

    Offsets (black level, room light) drop out of differences; across a radiograph the
    scintillator's light varies in its own colour. The noise (larger in the brightest channel)
    would pull the axis toward that channel: its part of the differences' covariance, from each
    channel's robust spread between neighbouring pixels, is taken off first.
    """
    import cv2

    h, w = channels.shape[:2]
    image = np.asarray(channels, dtype=np.float32)  # no copy of a float32 frame (24 Mpx: 288 MB)
    small = cv2.resize(image, (max(w // block_px, 2), max(h // block_px, 2)),
                       interpolation=cv2.INTER_AREA).astype(np.float64)
    diffs = np.concatenate([(small[:, 1:] - small[:, :-1]).reshape(-1, 3),
                            (small[1:] - small[:-1]).reshape(-1, 3)])
    fine = (image[::4, 1:] - image[::4, :-1]).reshape(-1, 3)
    pixel_var = (1.4826 * np.median(np.abs(fine - np.median(fine, axis=0)), axis=0)) ** 2 / 2.0
    # the largest 1 % left out: blocks holding a strong pulse (one channel's light)
    size = np.linalg.norm(diffs, axis=1)
    diffs = diffs[size <= np.percentile(size, 99)]
    covariance = diffs.T @ diffs / max(len(diffs), 1) - np.diag(2.0 * pixel_var / block_px ** 2)
    _, vectors = np.linalg.eigh(covariance)
    tint = vectors[:, -1]
    return tint if tint.sum() >= 0 else -tint


def _without_broad_patches(x: np.ndarray, pulses: np.ndarray, model: _NoiseModel,
                           scratch: np.ndarray, channels: np.ndarray | None,
                           min_object_sigma_px: float) -> np.ndarray:
    """``pulses`` (flat indices) without the patches whose excess goes on beyond them.

    The growth climbs down a smooth blob (anatomy blurred by the screen, 6-8 px across and
    10-16 noise sigmas high, whose top the exact test seeds) ring by ring: every ring of it
    stands above the window with the patch left out. What tells it from a pulse is outside
    the patch: a pulse's excess ends within its footprint, a blob's goes on. So a compact,
    not elongated patch whose outer ring (the pixels touching it) still stands out, by its
    median, from the background 2-3 px out, by :data:`_BROAD_RING_SIGMAS` noise sigmas and
    :data:`_BROAD_RING_SHARE` of the patch's own border excess, is dropped, if its light is the
    scintillator's: its excess in the three ``channels`` (the (H, W, 3) image ``x``, V, is the
    maximum of) is proportional to the background's colour within the noise (:data:`_TINT_CHI2`).
    A hit on the sensor lands in one colour's pixels, so a pulse in a subset of channels is kept
    however its ring looks: by shape alone a weak Gaussian pulse whose growth stopped early
    looks like a blob, and dev and held-out pulse frames had 20-sigma flat pulses and tracks on
    anatomy edges dropped without the colour test. Single-channel frames (``channels`` None:
    grey) give no such evidence and get no ring rule.

    A patch the growth has climbed down to the noise (its ring no longer stands up) is also
    dropped when it is a Gaussian hill at least ``min_object_sigma_px`` wide
    (:func:`_gaussian_hills`: a small dense object blurred by the screen); on V it still has to
    have the scintillator's colour, on grey frames the shape is all the evidence. Other pulses
    are left out of the ring and the background. ``scratch`` (uint8, zero) is used and left zero.
    """
    import cv2

    min_area = 9  # below it no patch spreads 0.9 px along both axes
    if pulses.size < min_area:
        return pulses
    h, w = x.shape
    marks = scratch.ravel()
    marks[pulses] = 1
    count, labels = cv2.connectedComponents(scratch, connectivity=8, ltype=cv2.CV_32S)
    marks[pulses] = 0
    label = labels.ravel()[pulses]
    del labels
    area = np.bincount(label, minlength=count)
    big = area >= min_area
    big[0] = False
    if not big.any():
        return pulses
    member = big[label]
    sub, sub_label = pulses[member], label[member]
    rows, cols = np.divmod(sub, w)
    n = area[sub_label].astype(np.float64)
    mean_r = np.bincount(sub_label, rows, count)[sub_label] / n
    mean_c = np.bincount(sub_label, cols, count)[sub_label] / n
    dr, dc = rows - mean_r, cols - mean_c
    n_l = np.maximum(area, 1).astype(np.float64)
    crr = np.bincount(sub_label, dr * dr, count) / n_l
    ccc = np.bincount(sub_label, dc * dc, count) / n_l
    crc = np.bincount(sub_label, dr * dc, count) / n_l
    half_gap = np.sqrt(0.25 * (crr - ccc) ** 2 + crc ** 2)
    minor_var, major_var = 0.5 * (crr + ccc) - half_gap, 0.5 * (crr + ccc) + half_gap
    compact = big & (minor_var >= _BROAD_MIN_SPREAD_PX ** 2) & (major_var <= _BROAD_MAX_ELONGATION ** 2 * minor_var)
    if not compact.any():
        return pulses
    keep_px = compact[sub_label]
    sub, sub_label, rows, cols = sub[keep_px], sub_label[keep_px], rows[keep_px], cols[keep_px]
    pulse_set = np.sort(pulses)
    size = h * w
    values = x.ravel()

    def around(reach_px: int, of: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        # (label, pixel) pairs within reach of each compact patch (``of``: only the patch
        # pixels selected), other pulses left out
        ddr, ddc = _window_offsets(2 * reach_px + 1)
        pick = slice(None) if of is None else of
        near = _flat_indices(rows[pick], cols[pick], ddr, ddc, (h, w))
        pairs = _sorted_unique(sub_label[pick][:, None].astype(np.int64) * size + near)
        pix = pairs % size
        outside = ~_in_sorted(pix, pulse_set)
        return pairs[outside] // size, pix[outside]

    def per_label_stat(lab: np.ndarray, val: np.ndarray, median: bool) -> np.ndarray:
        out = np.full(count, np.nan)
        if lab.size == 0:
            return out
        if not median:
            cnt = np.bincount(lab, minlength=count)
            with np.errstate(invalid="ignore", divide="ignore"):
                return np.bincount(lab, val, count) / cnt
        order = np.lexsort((val, lab))
        lab_s, val_s = lab[order], val[order]
        starts = np.flatnonzero(np.r_[True, lab_s[1:] != lab_s[:-1]])
        ends = np.r_[starts[1:], lab_s.size]
        lo, hi = (starts + ends - 1) // 2, (starts + ends) // 2
        out[lab_s[starts]] = 0.5 * (val_s[lo] + val_s[hi])
        return out

    ring_lab, ring_pix = around(1)
    far_lab, far_pix = around(3)
    in_ring = _in_sorted(far_lab * size + far_pix, ring_lab * size + ring_pix)  # both sorted pairs
    far_lab, far_pix = far_lab[~in_ring], far_pix[~in_ring]
    background = per_label_stat(far_lab, values[far_pix].astype(np.float64), median=True)
    ring_level = per_label_stat(ring_lab, values[ring_pix].astype(np.float64), median=True)
    # the patch's border: its pixels with a neighbour outside every pulse
    d8r = np.array([-1, -1, -1, 0, 0, 1, 1, 1])
    d8c = np.array([-1, 0, 1, -1, 1, -1, 0, 1])
    neighbours = _flat_indices(rows, cols, d8r, d8c, (h, w))
    border = (~_in_sorted(neighbours.ravel(), pulse_set)).reshape(neighbours.shape).any(axis=1)
    border_mean = per_label_stat(sub_label[border], values[sub[border]].astype(np.float64), median=False)
    with np.errstate(invalid="ignore"):
        sign = np.sign(border_mean - background)
        ring_excess = sign * (ring_level - background)
        border_excess = sign * (border_mean - background)
        sigma = np.sqrt(np.maximum(model.variance(np.nan_to_num(background)), 0.0))
        broad = compact & (ring_excess >= _BROAD_RING_SIGMAS * sigma) & (ring_excess >= _BROAD_RING_SHARE * border_excess)
    broad &= np.isfinite(ring_excess) & np.isfinite(border_excess) & (border_excess > 0)
    # a hill the growth has climbed down to the noise: its ring no longer stands up, but the
    # patch with the 2 px around it is a wide Gaussian on the background's plane (fitted with
    # the outline 5 px out too). Only patches whose border has come down from their peak (a
    # flat pulse's has not) are fitted.
    excess_px = sign[sub_label] * (values[sub].astype(np.float64) - background[sub_label])
    peak_excess = np.full(count, -np.inf)
    np.maximum.at(peak_excess, sub_label, np.nan_to_num(excess_px, nan=-np.inf))
    with np.errstate(invalid="ignore"):
        # (on V the ring's patches go to the colour test anyway)
        hill = (compact & (~broad if channels is not None else True) & (border_excess > 0)
                & (border_excess <= _HILL_MAX_BORDER_SHARE * peak_excess))
    if hill.any():
        fit_px = hill[sub_label]
        near_lab, near_pix = around(2, fit_px)
        out_lab, out_pix = _box_outline((h, w), sub_label[fit_px], rows[fit_px], cols[fit_px],
                                        _HILL_BACKGROUND_PX, count)
        out_keep = ~_in_sorted(out_pix, pulse_set)
        hill &= _gaussian_hills(values, w, np.nan_to_num(sign), background, model,
                                (sub_label[fit_px], sub[fit_px]),
                                (np.concatenate([near_lab, out_lab[out_keep]]),
                                 np.concatenate([near_pix, out_pix[out_keep]])), min_object_sigma_px)
    if channels is None:  # one channel: the shape is all the evidence, and a ring alone drops pulses
        return pulses[~hill[label]] if hill.any() else pulses
    broad |= hill
    if not broad.any():
        return pulses
    # the scintillator's colour: excess per channel against the background's colour
    keep_px = broad[sub_label]
    sub, sub_label = sub[keep_px], sub_label[keep_px]
    far_keep = broad[far_lab]
    far_lab, far_pix = far_lab[far_keep], far_pix[far_keep]
    n_patch = np.maximum(np.bincount(sub_label, minlength=count), 1).astype(np.float64)
    rgb = channels.reshape(-1, channels.shape[-1])
    excess, level = [], []
    for k in range(rgb.shape[1]):
        level.append(per_label_stat(far_lab, rgb[far_pix, k].astype(np.float64), median=True))
        excess.append(np.bincount(sub_label, rgb[sub, k].astype(np.float64), count) / n_patch - level[-1])
    excess, level = np.array(excess), np.maximum(np.array(level), 0.0)
    tint = _scintillator_tint(channels)[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        # a patch mean's noise, and a colour tolerance (the tint's estimate, demosaicing's mixing)
        var = (np.maximum(model.variance(np.nan_to_num(level)), 1e-12) / n_patch
               + (_TINT_TOLERANCE * np.abs(excess)) ** 2)
        alpha = np.sum(excess * tint / var, axis=0) / np.sum(tint * tint / var, axis=0)
        chi2 = np.sum((excess - alpha * tint) ** 2 / var, axis=0)
    broad &= np.isfinite(chi2) & (chi2 <= _TINT_CHI2) & (alpha > 0)
    if not broad.any():
        return pulses
    return pulses[~broad[label]]


#: Reach of a grown pixel's change of marks on the growth windows: its own mark and its
#: neighbours' ring marks (1 px) plus the largest window's half-width (9x9: 4 px).
_STALE_REACH_PX = 1 + _REPLACEMENT_WINDOWS_PX[-1] // 2


def _near(pixels: np.ndarray, others: np.ndarray, radius_px: int, shape, flags: np.ndarray) -> np.ndarray:
    """True for ``pixels`` (flat indices, sorted and distinct) within Chebyshev distance
    ``radius_px`` of one of ``others``.

    Few others (the usual case: the pixels grown in the last round): their square
    neighbourhoods (border replicated, which keeps every pixel within the distance) are
    looked up among the sorted ``pixels``. Many: the others' row segments of
    ``2 radius_px + 1`` px are marked in ``flags`` (flat uint8, bit ``_NEAR_BIT`` clear;
    cleared again on return) and looked up from each pixel's column in the rows within
    ``radius_px`` (a row outside the image has a flat index outside it, and no segment).
    Both give the same set; the binary search of every pixel's rows in a sorted set of
    segments had taken a fifth of the growth on 24 Mpx frames with 1 % of their pixels in
    pulses (280 000 ring pixels, 11 rows each, against a few thousand grown pixels)."""
    height, width = shape
    side = 2 * radius_px + 1
    out = np.zeros(pixels.shape, bool)
    if others.size == 0 or pixels.size == 0:
        return out
    if others.size * side <= 2 * pixels.size:
        around = _window_flat_indices(*np.divmod(others, width), side, shape).ravel()
        at = np.searchsorted(pixels, around)
        inside = at < pixels.size
        at, around = at[inside], around[inside]
        hit = at[pixels[at] == around]
        out[hit] = True
        return out
    offsets = np.arange(-radius_px, radius_px + 1)
    segments = _flat_indices(*np.divmod(others, width), np.zeros_like(offsets), offsets, shape).ravel()
    flags[segments] |= _NEAR_BIT
    for dr in offsets:
        at = pixels + dr * width
        if at.min() < 0 or at.max() >= flags.size:
            inside = (at >= 0) & (at < flags.size)
            out[inside] |= (flags[at[inside]] & _NEAR_BIT) != 0
        else:
            out |= (flags[at] & _NEAR_BIT) != 0
    flags[segments] &= ~_NEAR_BIT
    return out


#: The bit :func:`_near` marks its segments with in the growth's ``near_scratch`` (which
#: holds 0 or 1 otherwise).
_NEAR_BIT = np.uint8(2)


def _rim_of_strong_seed(x: np.ndarray, scratch: np.ndarray, pixels: np.ndarray, d: np.ndarray,
                        med: np.ndarray, spread: np.ndarray, model: _NoiseModel,
                        params: ImpulseParams, marked: np.ndarray | None = None) -> np.ndarray:
    """True for pixels of the first ring around strong seeds that are pulses as their rims.

    The prior is ``_STRONG_RIM_PRIOR`` (about 2.4 noise sigmas instead of 2.7) and Weber's
    visibility rule is not applied: the rule is the seed's (is the pulse visible?), and a
    strong pulse's 3-4 sigma rim on a bright area (1500-5000 counts: 3-4 sigma is 4-7 %)
    is part of it. Measured (dev seeds): recall +0.007; on the real NIQA repeats the pixels
    it adds were 2.9-3.1 sigma above the repeats' median and are left within about 1 sigma
    of it. Beyond the first ring, or around weaker seeds, the rule stays (a NIQA frame's PE
    on spot-free pixels past 0.2 % otherwise).

    The structure guard is the spread of the window about its least-squares plane, not
    about its median (:func:`_masked_median_at`, ``spread_about="plane"``): the window of
    a rim pixel often lies on a ramp (an anatomy edge, the screen's fall-off), whose
    linear part the point-symmetric median already cancels, while the raw spread took it
    for structure and kept 3-5 sigma rims (measured on the rims the growth had missed on
    grey frames: the spread was 1.1 noise sigmas at the median, 5.4 at the 90th
    percentile; about the plane 0.7 and 1.3). Curved structure (a bump, a ridge) still
    spreads about a plane. Where the ramp is gentle (its part of the spread below
    ``_GENTLE_RAMP_SIGMAS`` noise sigmas: a slope of about 1.5 sigma per px) the smaller of
    the two spreads is used (``spread``: the plain test's, about the median), elsewhere the
    plain test's.
    """
    prior = max(params.neighbour_prior, model.pulse_rate, _STRONG_RIM_PRIOR)
    out = model.is_pulse(d, med, params.posterior_threshold, prior=prior, min_variance=spread ** 2,
                         min_contrast=0.0)
    # The plane's spread can only lower the floor: it is needed only where the floor made
    # the difference (most rejected ring pixels are noise that fails without any floor;
    # 24 Mpx frames with 1 % of their pixels in strong pulses have millions of them).
    todo = np.flatnonzero(~out & model.is_pulse(d, med, params.posterior_threshold, prior=prior,
                                                min_contrast=0.0))
    if todo.size == 0:
        return out
    _, about_plane = _masked_median_at(x, scratch, *np.divmod(pixels[todo], x.shape[1]), smallest_px=7,
                                       symmetric=True, with_spread=True, spread_about="plane", marked_px=marked)
    # The ramp's part of the spread (what the plane explains): only a gentle ramp is
    # ignored. On a steep edge (the phantom's screen and anatomy edges, 5-8 noise sigmas
    # per px) a point-symmetric median cancels the ramp only as far as the edge is linear
    # over the window, and rims grew along such edges from false seeds on them.
    spread, d, med = spread[todo], d[todo], med[todo]
    ramp2 = np.maximum(spread * spread - about_plane * about_plane, 0.0)
    gentle = ramp2 < _GENTLE_RAMP_SIGMAS ** 2 * model.variance(med)
    floor = np.where(gentle, np.minimum(spread, about_plane), spread)
    out[todo] = model.is_pulse(d, med, params.posterior_threshold, prior=prior, min_variance=floor ** 2,
                               min_contrast=0.0)
    return out


def _in_sorted(values: np.ndarray, sorted_set: np.ndarray) -> np.ndarray:
    """``np.isin(values, sorted_set)`` for a sorted, duplicate-free ``sorted_set``, by binary
    search (numpy 2's hash-based ``isin`` took most of a growth round on 24 Mpx frames)."""
    if sorted_set.size == 0:
        return np.zeros(values.shape, bool)
    at = np.minimum(np.searchsorted(sorted_set, values), sorted_set.size - 1)
    return sorted_set[at] == values


def _annulus() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texture guard's annulus (_TEXTURE_INNER_PX to _TEXTURE_OUTER_PX, Chebyshev):
    its positions in the (2 _TEXTURE_OUTER_PX + 1)^2 window (row-major, the order of
    ``_window_offsets``) and their row and column offsets."""
    dr, dc = _window_offsets(2 * _TEXTURE_OUTER_PX + 1)
    on = np.flatnonzero(np.maximum(np.abs(dr), np.abs(dc)) >= _TEXTURE_INNER_PX)
    return on, dr[on], dc[on]


_ANNULUS_ON, _ANNULUS_DR, _ANNULUS_DC = _annulus()
#: Masks over the annulus's offsets: its upper, lower, left and right bands.
_ANNULUS_SIDES = [_ANNULUS_DR <= -_TEXTURE_INNER_PX, _ANNULUS_DR >= _TEXTURE_INNER_PX,
                  _ANNULUS_DC <= -_TEXTURE_INNER_PX, _ANNULUS_DC >= _TEXTURE_INNER_PX]
_FOOTPRINTS = _footprint_kernels()
_REPEAT_SHIFTS = _repeat_shifts()
