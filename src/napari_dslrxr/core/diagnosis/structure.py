"""Is anything left after the last term? Tests of the final (prewhitened) residual.

Under the fitted model the prewhitened residual ``z`` is white with unit variance, so every
statistic below has a known null distribution. Each test runs at ``alpha / n_tests``
(Bonferroni); any failure makes the result *unexplained*, with the failing tests' signatures
and locations — the diagnosis never calls a residual "consistent with noise" while one fails.

============  =======================================================  =====================
test          statistic                                                signature
============  =======================================================  =====================
global        ``(χ²/n - 1) / se`` (se includes the noise estimate)  excess variance
rows/columns  ``Σ_b (Σz/√n)_b² ~ χ²(B)`` per row / column              banding, or a smooth
                                                                       variation when the
                                                                       line-to-line part passes
radius        same, 32 radial bins                                     radial
intensity     same, 48 quantile bins of the expected intensity         intensity structure
ripple        max over trial periods P of the LS sin/cos fit of ``z`` intensity ripple
              on the expected intensity ``μ`` (DN), each ``χ²(2)``;   (period ~P DN)
              columns weighted by the noise's attenuation of a ripple
              in the recorded value, ``exp(-2π²σ²/P²)/σ``; a smooth
              trend in ``μ`` projected out; Bonferroni over the periods
edge          same, signed distance to edges (±30 px)                  edge-distance
tiles         per-tile mean ``Σz/√n`` (:func:`flagged_regions`)       localised
periodic      max periodogram ordinate / local level (> 3 cycles)  periodic
ghost         max residual autocorrelation at lags 3-32 px ~ N(0, 1/n)  ghost-like offset copy
spots         max matched filter (Gaussian σ 1.5, 3 px) ~ N(0, 1)        localised spot (dust)
              per pixel, Bonferroni over pixels × scales
============  =======================================================  =====================
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .locating import _quantile_edges

N_TESTS = 11
#: Intensity-ripple test: slowest trial period as a fraction of the expected-intensity span,
#: frequency-grid oversampling relative to 1 / span, and cosines of the smooth trend in the
#: expected intensity projected out first (periods down to about span / 4: the binned
#: intensity test's business, and a detector non-linearity's).
RIPPLE_MAX_PERIOD_FRACTION = 0.25
RIPPLE_OVERSAMPLE = 4.0
RIPPLE_SMOOTH_COSINES = 8
#: Gaussian widths (fitted-grid pixels) of the spot test's matched filters.
SPOT_SIGMAS_PX = (1.5, 3.0)


def _profile_test(values: np.ndarray, z: np.ndarray, edges: np.ndarray) -> tuple[float, float, float]:
    """(p-value, χ² statistic, centre of the largest bin) of ``Σ_b (Σz/√n)_b²`` over the bins."""
    from scipy import special

    which = np.searchsorted(edges, values, side="right") - 1
    ok = (which >= 0) & (which < len(edges) - 1)
    which, zz, vv = which[ok], z[ok], values[ok]
    n_bins = len(edges) - 1
    counts = np.bincount(which, minlength=n_bins).astype(float)
    sums = np.bincount(which, weights=zz, minlength=n_bins)
    centres = np.bincount(which, weights=vv, minlength=n_bins) / np.maximum(counts, 1)
    use = counts >= 10
    if use.sum() < 2:
        return 1.0, 0.0, float("nan")
    bin_z = sums[use] / np.sqrt(counts[use])
    stat = float(np.sum(bin_z**2))
    return float(special.chdtrc(int(use.sum()), stat)), stat, float(centres[use][np.argmax(np.abs(bin_z))])


def _line_profile(values: np.ndarray, z: np.ndarray, n_lines: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-line ``Σz/√n`` (lines with at least 10 pixels) and the lines' indices."""
    which = values.astype(np.intp)
    counts = np.bincount(which, minlength=n_lines).astype(float)
    sums = np.bincount(which, weights=z, minlength=n_lines)
    use = counts >= 10
    return sums[use] / np.sqrt(np.maximum(counts[use], 1)), np.flatnonzero(use)


def _line_to_line_p(values: np.ndarray, z: np.ndarray, n_lines: int, smooth_lines: int = 8) -> float:
    """p-value of the per-line profile's part that varies from line to line.

    The profile ``Σz/√n`` is white N(0, 1) per line under the model; its projection off the
    span of the cosines slower than one cycle per ``2 * smooth_lines`` lines is χ²(B - K)
    exactly. A smooth trend across the image (stray light, a ghost) fails the whole profile test
    but not this one, and must not be called banding, which is offsets from line to line.
    """
    from scipy import special

    profile, lines = _line_profile(values, z, n_lines)
    n_used = len(profile)
    n_smooth = max(2, n_lines // (2 * smooth_lines))
    if n_used <= n_smooth + 2:
        return 1.0
    position = (lines + 0.5) / n_lines
    basis = np.cos(np.pi * np.outer(position, np.arange(n_smooth)))
    q, _ = np.linalg.qr(basis)
    high = profile - q @ (q.T @ profile)
    return float(special.chdtrc(n_used - n_smooth, float(np.sum(high**2))))


def flagged_regions(z: np.ndarray, mask: np.ndarray, tile: int, binning: int, alpha: float = 0.01,
                    scale: float = 1.0, variance_test: bool = True) -> list[list[int]]:
    """Bounding boxes (recording pixels, end exclusive) of connected tiles with excess residual:
    tile mean ``Σz/√n`` or (``variance_test``) excess ``(Σz²/scale - n)/√(2n)`` beyond the
    Bonferroni threshold."""
    from scipy import ndimage, special

    h, w = z.shape
    stats_list = []
    for r0 in range(0, h - tile // 2, tile):
        for c0 in range(0, w - tile // 2, tile):
            r1, c1 = min(h, r0 + tile), min(w, c0 + tile)
            m = mask[r0:r1, c0:c1]
            n = int(m.sum())
            if n < 16:
                continue
            zz = z[r0:r1, c0:c1][m]
            stats_list.append((r0, c0, zz.sum() / np.sqrt(n), (np.sum(zz**2) / scale - n) / np.sqrt(2 * n)))
    if not stats_list:
        return []
    threshold = -special.ndtri(alpha / (2 * len(stats_list)))  # normal isf
    grid = np.zeros((int(np.ceil(h / tile)), int(np.ceil(w / tile))), dtype=bool)
    for r0, c0, mean_stat, chi_stat in stats_list:
        if abs(mean_stat) > threshold or (variance_test and chi_stat > threshold):
            grid[r0 // tile, c0 // tile] = True
    labels, _ = ndimage.label(grid)
    regions = []
    for sl in ndimage.find_objects(labels):
        r0, c0 = sl[0].start * tile, sl[1].start * tile
        r1, c1 = min(h, sl[0].stop * tile), min(w, sl[1].stop * tile)
        regions.append([int(r0 * binning), int(c0 * binning), int(r1 * binning), int(c1 * binning)])
    return regions


def _periodogram_test(z: np.ndarray, mask: np.ndarray, min_cycles: float = 3.0):
    from scipy import ndimage

    n = int(mask.sum())
    spec = np.abs(np.fft.rfft2(np.where(mask, z, 0.0))) ** 2 / max(n, 1)
    # relative to the local spectral level (median of Exp(1) = ln 2): a periodic pattern is a
    # peak, not a band where the noise spectrum was slightly misestimated
    # (periodic along fy; along fx the rfft half-plane ends: fx = 0 must not see the Nyquist column)
    padded = np.pad(np.pad(spec, ((4, 4), (0, 0)), mode="wrap"), ((0, 0), (4, 4)), mode="reflect")
    local = ndimage.median_filter(padded, size=9)[4:-4, 4:-4]
    spec = spec / np.maximum(local / np.log(2.0), 1e-12)
    h, w = z.shape
    fy = np.fft.fftfreq(h)[:, None] * h
    fx = np.fft.rfftfreq(w)[None, :] * w
    far = np.hypot(fy, fx) > min_cycles
    # rfft: the fx = 0 and Nyquist columns are mirrored; count each ordinate once
    count = int(far.sum())
    peak = float(spec[far].max()) if count else 0.0
    p = min(1.0, count * np.exp(-peak))  # max of `count` Exp(1) ordinates
    iy, ix = np.unravel_index(np.argmax(np.where(far, spec, 0.0)), spec.shape)
    return p, peak, (float(fy[iy, 0]), float(fx[0, ix]))


def ripple_visibility(frequency_per_dn, noise_sd_dn):
    """The share of a ripple of the recorded value (frequency in cycles per DN) left in its mean
    at one expected intensity, under Gaussian noise of ``noise_sd_dn`` (recording DN):
    ``exp(-2π² f² σ²)``."""
    return np.exp(-2.0 * np.pi**2 * frequency_per_dn**2 * noise_sd_dn**2)


def ripple_phase_profile(z: np.ndarray, expected_dn: np.ndarray, noise_sd_dn: np.ndarray, binning: int,
                         period_dn: float, n_bins: int = 16) -> dict:
    """The residual folded on the phase of the expected intensity at ``period_dn`` (a profile
    as :func:`~.locating.residual_profiles` gives), over the pixels where a ripple of that period
    keeps at least ``e^-1`` of itself (elsewhere the noise has averaged it out and the pixels
    only add noise): the evidence the report shows for an intensity ripple."""
    from .locating import _binned_profile

    visible = ripple_visibility(1.0 / period_dn, noise_sd_dn * binning) >= np.exp(-1.0)
    phase = np.mod(expected_dn[visible], period_dn) / period_dn
    return _binned_profile(phase, z[visible], np.linspace(0.0, 1.0, n_bins + 1))


def _intensity_ripple_test(z: np.ndarray, expected_dn: np.ndarray, noise_sd_dn: np.ndarray | None,
                           binning: int = 1, chunk: int = 64):
    """Periodogram of the residual against the expected intensity (an ADC ripple, a periodic
    differential non-linearity of the read-out).

    A ripple ``A sin(2π x / P)`` of the *recorded* value ``x`` acts after the noise: its mean at
    expected intensity ``μ`` is the ripple smoothed by the noise, ``A exp(-2π²σ²/P²) sin(2πμ/P)``
    (σ the per-pixel noise, recording DN), i.e. ``A exp(-2π²σ²/P²) / σ_fit`` in prewhitened
    units — a 97 DN ripple survives only where the noise is below ~30 DN (dark regions). For
    each trial frequency the two columns ``g(μ) cos(2πμ/P)``, ``g(μ) sin(2πμ/P)`` with that
    weight ``g`` are fitted to ``z`` by least squares after projecting out a smooth trend in
    ``μ`` (:data:`RIPPLE_SMOOTH_COSINES` cosines over the span); the explained sum of squares is
    exactly χ²(2) for white unit-variance ``z`` (any fixed design), whatever the weights. The
    p-value is the Bonferroni bound over every trial frequency (oversampled, so conservative).
    Trial periods run from where the attenuation at the least noisy pixels (0.5 % quantile)
    reaches ``e^-2`` (never below 4 DN) to :data:`RIPPLE_MAX_PERIOD_FRACTION` of the span.

    Everything is a function of ``μ`` alone, so the sums are taken once per fine intensity bin
    (width 1/16 of the shortest period: a phase error below π/16).
    Returns (p, max statistic, period at the maximum in DN, number of trial frequencies).
    """
    from scipy import special

    mu = np.asarray(expected_dn, dtype=float)
    lo, hi = float(mu.min()), float(mu.max())
    span = hi - lo
    if noise_sd_dn is None:
        sd_fit = np.ones_like(mu)
        f_max = 0.25
    else:
        sd_fit = np.maximum(np.asarray(noise_sd_dn, dtype=float), 1e-12)
        sd_min = float(np.quantile(sd_fit, 0.005)) * binning
        f_max = min(0.25, 1.0 / (np.pi * max(sd_min, 1e-12)))  # exp(-2π² f² σ²) = e^-2
    f_min = 1.0 / (RIPPLE_MAX_PERIOD_FRACTION * span) if span > 0 else np.inf
    if not f_max > 2.0 * f_min:
        return 1.0, 0.0, float("nan"), 0
    freqs = np.arange(f_min, f_max, 1.0 / (RIPPLE_OVERSAMPLE * span))
    width = 1.0 / (16.0 * f_max)
    k = ((mu - lo) / width).astype(np.intp)
    # the occupied bins, numbered in order (numpy 2's hash-based np.unique: 15x the time)
    per_bin = np.bincount(k)
    occupied = np.flatnonzero(per_bin)
    k = (np.cumsum(per_bin > 0) - 1)[k]
    counts = per_bin[occupied].astype(float)
    sums = np.bincount(k, weights=z)
    sd_bin = np.bincount(k, weights=sd_fit) / counts
    level = lo + (occupied + 0.5) * width
    smooth = np.cos(np.pi * np.outer((level - lo) / span, np.arange(RIPPLE_SMOOTH_COSINES)))
    q, _ = np.linalg.qr(smooth * np.sqrt(counts)[:, None])  # orthonormal under the pixel counts
    z_bins = sums / np.sqrt(counts)  # pixel-space inner products with bin-constant columns
    stats = np.empty(len(freqs))
    for i0 in range(0, len(freqs), chunk):
        f = freqs[i0:i0 + chunk, None]
        gain = (ripple_visibility(f, sd_bin * binning) if noise_sd_dn is not None
                else np.ones((len(f), 1))) / sd_bin
        phase = 2.0 * np.pi * f * level
        cols = np.stack([gain * np.cos(phase), gain * np.sin(phase)], axis=1)  # (chunk, 2, bins)
        # the columns off the smooth trend, as pixel-count-weighted bin values
        root = cols * np.sqrt(counts)
        root = root - (root @ q) @ q.T
        b = root @ z_bins
        gram = root @ root.transpose(0, 2, 1)
        det = gram[:, 0, 0] * gram[:, 1, 1] - gram[:, 0, 1] ** 2
        ok = det > 1e-9 * gram[:, 0, 0] * gram[:, 1, 1]
        quad = (gram[:, 1, 1] * b[:, 0] ** 2 - 2 * gram[:, 0, 1] * b[:, 0] * b[:, 1]
                + gram[:, 0, 0] * b[:, 1] ** 2)
        stats[i0:i0 + chunk] = np.where(ok, quad / np.where(ok, det, 1.0), 0.0)
    i = int(np.argmax(stats))
    p = min(1.0, len(freqs) * float(special.chdtrc(2, stats[i])))
    return p, float(stats[i]), float(1.0 / freqs[i]), len(freqs)


def _autocorrelation_test(z: np.ndarray, mask: np.ndarray, min_lag: int = 3, max_lag: int = 32):
    from scipy import special

    zz = np.where(mask, z, 0.0)
    h, w = zz.shape
    padded = np.zeros((h + max_lag, w + max_lag))
    padded[:h, :w] = zz
    f = np.fft.rfft2(padded)
    acf = np.fft.irfft2(np.abs(f) ** 2, s=padded.shape)
    mf = np.fft.rfft2(np.pad(mask.astype(float), ((0, max_lag), (0, max_lag))))
    pairs = np.fft.irfft2(np.abs(mf) ** 2, s=padded.shape)
    lags_y = np.r_[0:max_lag + 1, -max_lag:0]
    lags_x = np.r_[0:max_lag + 1, -max_lag:0]
    sub = acf[np.ix_(lags_y % padded.shape[0], lags_x % padded.shape[1])]
    npairs = np.maximum(pairs[np.ix_(lags_y % padded.shape[0], lags_x % padded.shape[1])], 1.0)
    stat = sub / np.sqrt(npairs)  # ~ N(0, 1) per lag under white unit-variance noise
    ly, lx = np.meshgrid(lags_y, lags_x, indexing="ij")
    use = (np.maximum(np.abs(ly), np.abs(lx)) >= min_lag) & ((ly > 0) | ((ly == 0) & (lx > 0)))
    count = int(use.sum())
    k = np.argmax(np.where(use, np.abs(stat), 0.0))
    peak = float(np.abs(stat).ravel()[k])
    p = min(1.0, count * 2.0 * special.ndtr(-peak))  # normal sf
    return p, peak, (int(ly.ravel()[k]), int(lx.ravel()[k]))


def _spot_filters(mask: np.ndarray, sigmas_px) -> tuple[list, list, list]:
    """Per width: the 1-D Gaussian and its radius, the null variance ``Σk²`` of the matched
    filter over unmasked pixels, and where it is tested: at least half the kernel's weight on
    unmasked pixels, and not within the kernel's reach of the frame border (there the
    prewhitening of correlated noise is inexact: a false spot at column 0 of a correlated-noise
    null)."""
    from scipy import ndimage

    m = mask.astype(float)
    kernels, dens, uses = [], [], []
    for sigma in sigmas_px:
        radius = int(np.ceil(4.0 * sigma))
        k = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
        k2 = k**2
        den = ndimage.correlate1d(ndimage.correlate1d(m, k2, axis=0, mode="constant"), k2, axis=1, mode="constant")
        use = mask & (den > 0.5 * k2.sum() ** 2)
        use[:radius], use[-radius:], use[:, :radius], use[:, -radius:] = False, False, False, False
        kernels.append((k, radius))
        dens.append(den)
        uses.append(use)
    return kernels, dens, uses


def _spot_test(z: np.ndarray, mask: np.ndarray, sigmas_px=SPOT_SIGMAS_PX):
    """Small localised spots (dust on the lens or screen, a defect): the prewhitened residual
    correlated with a Gaussian of each width, normalised by its standard deviation under the null
    (``Σk·z / √Σk²`` over unmasked pixels: N(0, 1) per pixel for white unit-variance ``z``). A tile
    mean dilutes a 3 px spot 30-fold in area; the matched filter does not. Pixels within the
    kernel's reach of the frame border are not tested. The p-value is the
    Bonferroni bound over every pixel and width (conservative: neighbouring values correlate).
    Returns (p, max |statistic|, (row, column), width)."""
    from scipy import ndimage, special

    zz = np.where(mask, z, 0.0)
    best = (0.0, (0, 0), sigmas_px[0])
    count = 0
    for sigma, (k, _), den, use in zip(sigmas_px, *_spot_filters(mask, sigmas_px)):
        num = ndimage.correlate1d(ndimage.correlate1d(zz, k, axis=0, mode="constant"), k, axis=1, mode="constant")
        count += int(use.sum())
        stat = np.where(use, np.abs(num) / np.sqrt(np.maximum(den, 1e-30)), 0.0)
        i = int(np.argmax(stat))
        if stat.flat[i] > best[0]:
            best = (float(stat.flat[i]), np.unravel_index(i, stat.shape), sigma)
    peak, (r, c), sigma = best
    p = min(1.0, max(count, 1) * 2.0 * special.ndtr(-peak))  # two-sided normal tail
    return p, peak, (int(r), int(c)), sigma


#: Most spots the out-of-library spot alternative fits, one after the other.
MAX_ALTERNATIVE_SPOTS = 16


@dataclass
class OutOfLibraryAlternative:
    """An out-of-library explanation of the current residual, from the structure tests' own
    statistics: its ``delta_bic`` (Δχ² of its fit minus ``k ln n`` for its ``k`` parameters,
    its positions and periods included), what it is, and where."""

    name: str
    delta_bic: float
    signature: str


def out_of_library_alternatives(z: np.ndarray, mask: np.ndarray, expected_dn: np.ndarray,
                                noise_sd_dn: np.ndarray, binning: int, log_n: float,
                                accept_delta_bic: float) -> list[OutOfLibraryAlternative]:
    """What an intensity ripple and a set of localised spots, neither in the library, explain of
    the prewhitened residual ``z`` (2-D, zero outside ``mask``) of the current model.

    A library term that passes the acceptance threshold only by absorbing a part of such a
    structure (a mirror ghost fitted to an ADC ripple, a camera gamma to dust spots) explains
    less than these; the caller rejects it then. Ripple: the largest χ²(2) of
    :func:`_intensity_ripple_test` (beyond a smooth trend in the expected intensity), for 3
    parameters (two amplitudes and the period). Spots: Gaussian spots fitted one after the other
    at the matched filter's maximum (:func:`_spot_test`'s widths), each subtracted before the
    next, each kept while it gains ΔBIC > ``accept_delta_bic`` for 4 parameters (amplitude, row,
    column, width); under the null neither gains (the maximum of ~n null statistics is about
    ``2 ln n``, below ``3 ln n`` and ``4 ln n``)."""
    out = []
    zm = z[mask]
    _, stat, period, n_freq = _intensity_ripple_test(zm, expected_dn[mask], noise_sd_dn[mask], binning)
    if n_freq:
        out.append(OutOfLibraryAlternative("intensity_ripple", stat - 3.0 * log_n,
                                           f"intensity ripple (period ~{period:.0f} DN)"))
    spots, gain = _greedy_spots(z, mask, 4.0 * log_n + accept_delta_bic)
    if spots:
        where = ", ".join(f"row {r * binning}, column {c * binning}" for r, c in spots[:3])
        more = f" and {len(spots) - 3} more" if len(spots) > 3 else ""
        out.append(OutOfLibraryAlternative("spots", gain - 4.0 * log_n * len(spots),
                                           f"{len(spots)} localised spot(s) (dust, a defect) at {where}{more}"))
    return out


def _greedy_spots(z: np.ndarray, mask: np.ndarray, min_chi2: float,
                  sigmas_px=SPOT_SIGMAS_PX) -> tuple[list[tuple[int, int]], float]:
    """Gaussian spots fitted one after the other to ``z``: each at the largest matched-filter
    statistic ``s`` over positions and widths (its fit's Δχ² is ``s²``), subtracted before the
    next; while ``s² > min_chi2``. Returns their positions (fitted grid) and summed Δχ²."""
    from scipy import ndimage

    m = mask.astype(float)
    zz = np.where(mask, z, 0.0)
    kernels, dens, uses = _spot_filters(mask, sigmas_px)
    dens = [np.maximum(den, 1e-30) for den in dens]
    spots, total = [], 0.0
    while len(spots) < MAX_ALTERNATIVE_SPOTS:
        best = None
        for (k, radius), den, use in zip(kernels, dens, uses):
            num = ndimage.correlate1d(ndimage.correlate1d(zz, k, axis=0, mode="constant"), k, axis=1, mode="constant")
            chi2 = np.where(use, num**2 / den, 0.0)
            i = int(np.argmax(chi2))
            if best is None or chi2.flat[i] > best[0]:
                best = (float(chi2.flat[i]), np.unravel_index(i, chi2.shape), num.flat[i] / den.flat[i], k, radius)
        chi2, (r, c), amplitude, k, radius = best
        if not chi2 > min_chi2:
            break
        # tested positions lie at least a radius from the border: the whole kernel fits
        rows, cols = slice(r - radius, r + radius + 1), slice(c - radius, c + radius + 1)
        zz[rows, cols] -= amplitude * np.outer(k, k) * m[rows, cols]
        spots.append((int(r), int(c)))
        total += chi2
    return spots, total


def structure_tests(z: np.ndarray, mask: np.ndarray, chi2: float, n_effective: float,
                    expected_dn: np.ndarray, signed_edge_px: np.ndarray, radius: np.ndarray,
                    tile: int, binning: int, alpha: float = 1e-3, noise_samples: int = 0,
                    min_ghost_lag: int = 3, noise_sd_dn: np.ndarray | None = None) -> dict:
    """Run every test on the prewhitened residual; return per-test results and signatures.

    Positions in the output (rows, columns, edge distance, regions, lags, periods) are in
    recording pixels (fitted-grid pixels × ``binning``). ``noise_sd_dn``: the noise model's
    standard deviation per fitted-grid pixel (DN), for the intensity-ripple test's attenuation
    weights (without it the test is unweighted).
    """
    h, w = z.shape
    rows, cols = np.broadcast_arrays(np.arange(h)[:, None], np.arange(w)[None, :])
    zm = z[mask]
    level = alpha / N_TESTS
    tests: dict[str, dict] = {}

    from scipy import special

    # The noise level was itself estimated (from ``noise_samples`` flat pixels or repeats): its
    # relative error sqrt(2 / noise_samples) adds to that of χ²/dof.
    se = np.sqrt(2.0 / n_effective + (2.0 / noise_samples if noise_samples else 0.0))
    global_stat = (chi2 / n_effective - 1.0) / se
    tests["global"] = {"p": float(special.ndtr(-global_stat)), "stat": float(global_stat),
                       "signature": "excess residual variance"}
    for name, values, edges, signature in (
            ("rows", rows[mask].astype(float), np.arange(h + 1) - 0.5, "row banding"),
            ("columns", cols[mask].astype(float), np.arange(w + 1) - 0.5, "column banding"),
            ("radius", radius[mask], np.linspace(0, radius.max() + 1e-9, 33), "radial structure"),
            ("intensity", expected_dn[mask], _quantile_edges(expected_dn[mask], 48),
             "structure in the expected intensity"),
            ("edge_distance", signed_edge_px[mask], np.arange(-30.5, 31.5, max(2.0, binning)) / binning,
             "structure at a fixed distance from edges")):
        p, stat, where = _profile_test(values, zm, edges)
        if name in ("rows", "columns", "edge_distance"):
            where = where * binning
        tests[name] = {"p": p, "stat": stat, "where": where, "signature": signature}
    p, stat, period, n_freq = _intensity_ripple_test(
        zm, expected_dn[mask], None if noise_sd_dn is None else noise_sd_dn[mask], binning)
    tests["intensity_ripple"] = {"p": p, "stat": stat, "period_dn": period, "n_periods": n_freq,
                                 "signature": "intensity ripple"}
    # mean test only: a small dark region's variance rests on few flat pixels, and a noise
    # level misestimated there is not a missing physical effect
    regions = flagged_regions(z, mask, tile, binning, alpha=level, variance_test=False)
    tests["tiles"] = {"p": 0.0 if regions else 1.0, "regions": regions, "signature": "localised"}
    p, peak, (fy, fx) = _periodogram_test(z, mask)
    period = float(1.0 / np.hypot(fy / h, fx / w)) * binning if (fy or fx) else float("inf")
    tests["periodic"] = {"p": p, "stat": peak, "cycles_per_image": [fy, fx], "period_px": period,
                         "signature": "periodic pattern"}
    p, peak, lag = _autocorrelation_test(z, mask, min_lag=min_ghost_lag)
    tests["ghost"] = {"p": p, "stat": peak, "lag_px": [lag[0] * binning, lag[1] * binning],
                      "signature": "ghost-like offset copy"}
    p, peak, (r, c), sigma = _spot_test(z, mask)
    tests["spots"] = {"p": p, "stat": peak, "where": [r * binning, c * binning], "sigma_px": sigma * binning,
                      "signature": "localised spot (dust, a defect)"}
    failed = [name for name, t in tests.items() if t["p"] < level]
    signatures = []
    for name in failed:
        t = tests[name]
        text = t["signature"]
        if name in ("rows", "columns"):
            line_values = rows[mask] if name == "rows" else cols[mask]
            if _line_to_line_p(line_values, zm, h if name == "rows" else w) >= level:
                text = f"smooth variation across the {name} (no line-to-line banding)"
            text += f" (strongest at {name[:-1]} {t['where']:.0f})"
        elif name == "intensity":
            text += f" (strongest at {t['where']:.0f} DN)"
        elif name == "intensity_ripple":
            text += f" (period ~{t['period_dn']:.0f} DN)"
        elif name == "edge_distance":
            text += f" (strongest {t['where']:+.0f} px from edges)"
        elif name == "tiles":
            text += f" at {t['regions']}"
        elif name == "periodic":
            text += f" (period {t['period_px']:.1f} px)"
        elif name == "spots":
            text += f" (strongest at row {t['where'][0]}, column {t['where'][1]}, σ {t['sigma_px']:.1f} px)"
        elif name == "ghost":
            text += f" (lag {t['lag_px']} px)"
        signatures.append(text)
    return {"tests": tests, "failed": failed, "signatures": signatures, "alpha": alpha}
