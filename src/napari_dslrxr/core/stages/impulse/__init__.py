"""Impulse-noise (zinger) removal: the statistical switching median of Frosio and Borghese.

A DSLR photographing an X-ray scintillator records, besides the screen light, direct X-ray
hits on its sensor: bright spots of one pixel on the raw mosaic that demosaicing spreads into
2x2 to 4x4 coloured patches. This module detects them with a statistical test and replaces
only the detected pixels; every other pixel is returned bit-for-bit unchanged.
The other pulse detectors of the package (reference frames, diagnosis, repeated exposures) and
why each differs from this one: ``docs/architecture.md``, section 'Pulse detectors'.

Model (Frosio & Borghese, IEEE TMI 28(1), 2009; Frosio, Abati & Borghese, IJCARS 2008;
``docs/algorithms/impulse.md``; issue 13's additions and limits in ``docs/impulse.md``). For a pixel value ``x`` and the median ``m``
of the 8 detection samples around it (centre excluded, so ``d`` is Gaussian) the residual
``d = x - m`` is a mixture

    p(d | m) = (1 - P) N(d; 0, s^2(m)) + P u(d)

The samples are the 8 neighbours (``window_px`` 3) or, by default, the 8 pixels two steps
away (``window_px`` 5, a sparse 5x5 window: a patch of up to 3x3 px holds none of them).

* photon-counting channels (grey images, V, raw CFA planes):
  ``s^2(m) = max(a m + b, floor)`` with ``a = k G`` (``G`` the Poisson gain in counts per
  photon-electron, ``k`` the variance of ``x - median`` relative to that of ``x``), ``b``
  absorbing the offset and read noise (``b = k (sigma_e^2 - G o)``), and ``floor`` the
  residual variance measured where the image is darkest: ``k (G (m - o) + sigma_e^2)`` never
  falls below the read-noise term, while the line crosses zero near the black level;
* ratio channels (H, S): a constant variance ``s^2 = b`` of the residual weighted by the
  inverse of the channel's noise, propagated from the count variance of V's model at the
  3x3 medians of S and V (S: ``sqrt(Var[min] + (1-S)^2 Var[max]) / V``, H:
  ``sqrt(Var[V]) / (V S)``); S's variance is fitted where S is defined (S >= min_saturation);
* pulses: uniform over the channel's value range ``V`` (``u = 1/V`` for bright-only pulses,
  ``1/(2V)`` for pulses of either sign).

``a``, ``b`` and the pulse rate ``P`` are fitted by expectation-maximisation on a regular
subsample of the flatter half of the image itself. A pixel is a pulse where the posterior
probability of the pulse component exceeds one half (and, on photon-counting channels, its
Weber contrast exceeds ``min_contrast``). Patches: pixels next to detected pulses are
re-tested, with a higher prior ``neighbour_prior``, against the median of their non-pulse
neighbours in a 7x7 or larger window, repeatedly, so larger patches and tracks are grown
from their rim inward. Detected pixels are replaced by the median of the non-pulse pixels of
the smallest window (3x3 up to 9x9) that holds enough of them.

Structure guards (edges and corners of the screen are not pulses): a seed's residual
variance is at least (spread / 3)^2, the spread being that of the means of point-symmetric
pixel pairs on the square ring at ``max_patch_px`` from it (outside any patch; a linear
ramp does not spread them, an edge's shoulder or a corner does); a grown pixel's is at
least the spread of its window's background, whose exclusions are made point-symmetric so
that the median stays unbiased on a ramp. Hue pixels are tested only where the whole
detection window has a defined hue.

Faint pulses (a few sigmas in each pixel of a blob or track) are seeded by the mean of the
residual over small footprints (squares and short lines) against its own noise, and the
first ring around strong seeds is grown at a lower significance (hysteresis); see
``detection._footprint_seeds`` and ``docs/impulse.md``.

Texture guard (line patterns, meshes, grids are not pulses): around a seed or a grown
pixel, the annulus 4 to 6 px away must not be busy, busy meaning residuals to the fast
median of at least 0.4 of the pixel's own (or beyond 3 noise sigmas). A pulse of up to
5x5 px never reaches the annulus and a track crosses it in two places; periodic structure
fills it. The EM sample avoids busy areas too, since a median flattens fine texture.
One busy side of the annulus is enough (a pattern's border): on raw CFA planes any busy
side (a dim plane holds patterns aliased at a few noise sigmas), in grey and V a side busy
with residuals of both signs (a neighbouring pulse's are one-signed); on both, also a side
whose image is curved throughout (a pattern the sparse median matches); see
``detection._textured_side`` and ``detection._curved_side``.

Polarity (``spots``): bright pulses (direct hits), dark ones (a hit in the open beam turned
dark by normalisation) or both, on the photon-counting channels.

Speed: a full-image prefilter with OpenCV medians (centre included) picks candidates; the
exact test runs on them only; later passes re-test only the neighbourhood of replaced
pixels. See benchmarks/bench_impulse.py for the 6000x4000 RGB timings.

Modules: ``params`` (parameters, result), ``neighbourhoods`` (polyphase components,
ring and window medians), ``noise_model`` (mixture and EM fit),
``detection`` (candidates, exact test, texture guard, growth, one channel's passes),
``colour`` (HSV path), ``removal`` (:func:`remove_impulses`), ``cfa`` (raw Bayer planes).
"""

from .cfa import cfa_mask_to_mosaic, clean_raw_frame, demosaic_cleaned_raw, remove_impulses_cfa
from .colour import dominant_hue, hsv_counts_to_rgb, rgb_to_hsv_counts
from .params import MEDIAN_RESIDUAL_VARIANCE_FACTOR, SPACES, SPOT_POLARITIES, ImpulseParams, ImpulseResult
from .removal import remove_impulses

__all__ = [
    "ImpulseParams",
    "ImpulseResult",
    "remove_impulses",
    "remove_impulses_cfa",
    "clean_raw_frame",
    "cfa_mask_to_mosaic",
    "demosaic_cleaned_raw",
    "rgb_to_hsv_counts",
    "hsv_counts_to_rgb",
    "dominant_hue",
    "SPOT_POLARITIES",
    "SPACES",
    "MEDIAN_RESIDUAL_VARIANCE_FACTOR",
]
