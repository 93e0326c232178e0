"""An X-ray → screen → lens → camera recording generator written independently of the project.

Used by the diagnosis study to test the diagnosis on recordings its own forward model did not
make. Only numpy and scipy: nothing of the project's simulator or physics terms is imported.
Differences from the project's forward model, on purpose:

* blur in real space on the fine (supersampled) grid, *then* block-averaged (the project
  blurs in Fourier space on the coarse grid); glare as an explicit exponential kernel
  convolved in real space; the mirror ghost and the focal-spot lobes as spline shifts;
* other functional forms where physics allows: beam hardening as a two-component spectrum,
  heel as a quadratic ramp along a tilted axis, vignetting as cos⁴ of the field angle about an
  off-centre optical axis, inverse square from the geometry in mm, camera non-linearity as a
  soft saturation ``e / (1 + κ e)``;
* noise in another order: read noise, then photon noise (Poisson in electrons), then optional
  spatial smoothing of the noise (demosaicing-like correlation), then the offset, then
  rounding to integer DN;
* nuisances: object shift / magnification / rotation (a spline warp of the blurred image on the
  fine grid), a wrong kVp (other attenuation), large frames;
* effects outside the project's library: row banding, a lens ghost (defocused point-mirrored
  copy), stray light (additive glow), dust (sharp dark spots after the lens), ADC ripple
  (periodic in DN), keystone (projective distortion).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage, signal


@dataclass
class Geometry:
    size_px: int = 128
    supersample: int = 2
    pitch_mm: float = 0.1
    sdd_mm: float = 1200.0
    sod_mm: float = 1000.0
    focal_spot_sigma_mm: float = 0.3
    detector_sigma_mm: float = 0.1
    kvp_stated: float = 60.0

    @property
    def magnification_minus_one(self) -> float:
        return (self.sdd_mm - self.sod_mm) / self.sod_mm


@dataclass
class Camera:
    offset_dn: float = 200.0
    open_dn: float = 3000.0
    electrons_per_dn: float = 1.0 / 1.2  # photon-transfer gain: var = 1.2 DN per DN of signal
    read_noise_dn: float = 6.3
    noise_smoothing_px: float = 0.0      # Gaussian sigma applied to the noise (correlation)


@dataclass
class Recording:
    """Case description: effects and nuisances with their parameters."""

    effects: dict = field(default_factory=dict)
    shift_px: tuple[float, float] = (0.0, 0.0)   # (x, y) object shift on the detector
    scale: float = 0.0                           # magnification error
    rotation_deg: float = 0.0
    kvp_true: float | None = None
    seed: int = 0
    mu_scale: float = 1.0                        # for the base-refit derivative only


def attenuation_per_mm(kvp: float) -> float:
    """Aluminium, rough power law around 30 keV (0.304 /mm at 60 kVp)."""
    return 0.304 * (60.0 / kvp) ** 2.2


def phantom_thickness(geometry: Geometry, shift_px=(0.0, 0.0), scale=0.0, rotation_deg=0.0,
                      supersample: int | None = None) -> np.ndarray:
    """Thickness (mm of aluminium) point-sampled at the centres of the fine pixels.

    Object: a six-step wedge, two discs, a bar tilted by 25°, a near-opaque block; the top band
    and the right strip stay open. The object can be shifted (recording px), scaled and rotated.
    """
    s = supersample or geometry.supersample
    n = geometry.size_px * s
    centre = (n - 1) / 2.0
    rr, cc = np.mgrid[0:n, 0:n].astype(np.float64)
    x = (cc - centre) / s - shift_px[0]
    y = (rr - centre) / s - shift_px[1]
    a = -np.deg2rad(rotation_deg)
    x, y = (x * np.cos(a) - y * np.sin(a)) / (1.0 + scale), (x * np.sin(a) + y * np.cos(a)) / (1.0 + scale)
    u = x / geometry.size_px + 0.5   # column fraction
    v = y / geometry.size_px + 0.5   # row fraction
    t = np.zeros((n, n))
    wedge = (v > 0.6) & (v < 0.86) & (u > 0.08) & (u < 0.68)
    t[wedge] = 1.3 * np.floor((u[wedge] - 0.08) / 0.6 * 6 + 1)
    t[(v - 0.3) ** 2 + (u - 0.28) ** 2 < 0.12**2] = 3.0
    t[(v - 0.22) ** 2 + (u - 0.62) ** 2 < 0.07**2] = 6.0
    b = np.deg2rad(25.0)
    bu = (u - 0.5) * np.cos(b) + (v - 0.5) * np.sin(b)
    bv = -(u - 0.5) * np.sin(b) + (v - 0.5) * np.cos(b)
    t[(np.abs(bu) < 0.04) & (np.abs(bv) < 0.2)] += 2.0
    t[(v > 0.64) & (v < 0.86) & (u > 0.74) & (u < 0.88)] = 25.0
    t[v < 0.08] = 0.0
    t[u > 0.93] = 0.0
    return t


def _block_mean(image: np.ndarray, factor: int) -> np.ndarray:
    if factor == 1:
        return image
    h, w = image.shape
    return image.reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3))


def _unit_coords(n: int):
    """x, y in half-sides from the centre (corners of the square at |x| = |y| = 1)."""
    c = (np.arange(n) - (n - 1) / 2.0) / (n / 2.0)
    return c[None, :], c[:, None]


def render(geometry: Geometry, camera: Camera, case: Recording) -> dict:
    """Noise-free light image and noisy recording of ``case``; returns arrays and truth."""
    s = geometry.supersample
    n_fine = geometry.size_px * s
    kvp = case.kvp_true or geometry.kvp_stated
    mu = attenuation_per_mm(kvp) * case.mu_scale
    t = phantom_thickness(geometry)
    eff = case.effects
    # --- path and transmission (fine grid)
    if "beam_hardening" in eff:
        b = eff["beam_hardening"]["fraction_hard"]
        trans = (1.0 - b) * np.exp(-mu * t) + b * np.exp(-0.55 * mu * t)
    else:
        trans = np.exp(-mu * t)
    # --- incident fluence (fine grid)
    xf, yf = _unit_coords(n_fine)
    fluence = np.ones((n_fine, n_fine))
    if "heel_effect" in eff:
        p = eff["heel_effect"]
        ang = np.deg2rad(p["angle_deg"])
        along = xf * np.cos(ang) + yf * np.sin(ang)
        fluence = fluence * (1.0 + p["slope"] * along * (1.0 + 0.25 * along))
    if "inverse_square" in eff:
        p = eff["inverse_square"]
        half_mm = geometry.size_px * geometry.pitch_mm / 2.0
        r2 = ((xf - p["foot_x"]) ** 2 + (yf - p["foot_y"]) ** 2) * half_mm**2
        fluence = fluence * (geometry.sdd_mm / np.sqrt(geometry.sdd_mm**2 + r2)) ** 3
    screen_in = fluence * trans
    if "scatter" in eff:
        p = eff["scatter"]
        source = fluence * trans * mu * t
        sig_fine = p["sigma_mm"] / geometry.pitch_mm * s
        screen_in = screen_in + p["amplitude"] * ndimage.gaussian_filter(source, sig_fine, mode="nearest")
    # --- blur on the fine grid (real space)
    sigma_mm = np.hypot(geometry.focal_spot_sigma_mm * geometry.magnification_minus_one,
                        geometry.detector_sigma_mm)
    light = ndimage.gaussian_filter(screen_in, sigma_mm / geometry.pitch_mm * s, mode="nearest", truncate=5.0)
    if "focal_spot_shape" in eff:
        p = eff["focal_spot_shape"]
        half_px = p["half_separation_mm"] * geometry.magnification_minus_one / geometry.pitch_mm * s
        ang = np.deg2rad(p["axis_deg"])
        d = (half_px * np.sin(ang), half_px * np.cos(ang))
        light = 0.5 * (ndimage.shift(light, d, order=3, mode="nearest")
                       + ndimage.shift(light, (-d[0], -d[1]), order=3, mode="nearest"))
    if "veiling_glare" in eff:
        p = eff["veiling_glare"]
        w = p["range_mm"] / geometry.pitch_mm * s
        half = int(np.ceil(8 * w))
        ky, kx = np.mgrid[-half:half + 1, -half:half + 1]
        kernel = np.exp(-np.hypot(ky, kx) / w)
        kernel /= kernel.sum()
        padded = np.pad(light, half, mode="edge")
        tail = signal.fftconvolve(padded, kernel, mode="same")[half:-half, half:-half]
        light = (1.0 - p["eta"]) * light + p["eta"] * tail
    if "mirror_ghost" in eff:
        p = eff["mirror_ghost"]
        d = p["shift_mm"] / geometry.pitch_mm * s
        ang = np.deg2rad(p["axis_deg"])
        # O(q) = L(q) + eps L(q + d): sample the light at q + d
        light = light + p["epsilon"] * ndimage.shift(light, (-d * np.sin(ang), -d * np.cos(ang)),
                                                     order=3, mode="nearest")
    if case.shift_px != (0.0, 0.0) or case.scale or case.rotation_deg:
        # the object moved on the detector: warp the blurred (smooth) image with splines;
        # redrawing a point-sampled object would move its edges in whole fine-pixel steps
        a = np.deg2rad(case.rotation_deg)
        inv = np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]]) / (1.0 + case.scale)  # (row, col)
        c = (n_fine - 1) / 2.0
        shift_rc = np.array([case.shift_px[1], case.shift_px[0]]) * s
        offset = c - inv @ (np.array([c, c]) + shift_rc)
        light = ndimage.affine_transform(light, inv, offset=offset, order=3, mode="nearest")
    light = _block_mean(light, s)
    n = geometry.size_px
    x, y = _unit_coords(n)
    rows, cols = np.mgrid[0:n, 0:n].astype(np.float64)
    # --- optics (coarse grid)
    if "lens_distortion" in eff:
        k1 = eff["lens_distortion"]["k1"]
        factor = 1.0 + k1 * (x**2 + y**2) / 2.0
        c = (n - 1) / 2.0
        light = ndimage.map_coordinates(light, [c + (rows - c) * factor, c + (cols - c) * factor],
                                        order=1, mode="nearest")
    if "keystone" in eff:
        p = eff["keystone"]["p"]
        c = (n - 1) / 2.0
        yy = (rows - c) / (n / 2.0)
        light = ndimage.map_coordinates(light, [c + (rows - c) / (1.0 - p * yy), c + (cols - c) / (1.0 - p * yy)],
                                        order=3, mode="nearest")
    if "lens_ghost" in eff:
        p = eff["lens_ghost"]
        ghost = ndimage.gaussian_filter(light[::-1, ::-1], p["blur_px"], mode="nearest")
        light = light + p["epsilon"] * ghost
    if "vignetting" in eff:
        p = eff["vignetting"]
        rho = np.sqrt(((x - p["centre_x"]) ** 2 + (y - p["centre_y"]) ** 2) / 2.0)
        light = light * np.cos(np.arctan(rho * np.tan(np.deg2rad(p["half_field_deg"])))) ** 4
    if "dust" in eff:
        p = eff["dust"]
        rng_d = np.random.default_rng(1000 + case.seed)
        for _ in range(p["count"]):
            r0, c0 = rng_d.uniform(0.1 * n, 0.9 * n, 2)
            light = light * (1.0 - p["depth"] * np.exp(-((rows - r0) ** 2 + (cols - c0) ** 2) / (2 * p["radius_px"] ** 2)))
    if "stray_light" in eff:
        p = eff["stray_light"]
        light = light + p["level"] * np.exp(-((x - 0.9) ** 2 + (y + 0.7) ** 2) / (2 * 0.8**2))
    # --- camera
    if "detector_gamma" in eff:
        k = eff["detector_gamma"]["kappa"]
        light = light / (1.0 + k * light) * (1.0 + k)  # soft saturation, 1 stays 1
    expected = camera.offset_dn + camera.open_dn * light
    rng = np.random.default_rng(case.seed)
    signal_dn = np.clip(expected - camera.offset_dn, 0.0, None)
    read = rng.normal(0.0, camera.read_noise_dn, signal_dn.shape)
    photons = rng.poisson(signal_dn * camera.electrons_per_dn) / camera.electrons_per_dn
    noise = read + (photons - signal_dn)
    sd = np.sqrt(signal_dn / camera.electrons_per_dn + camera.read_noise_dn**2)
    white_z = noise / sd
    if camera.noise_smoothing_px > 0:
        noise = ndimage.gaussian_filter(noise, camera.noise_smoothing_px, mode="reflect")
    recorded = np.round(_banding_and_ripple(camera.offset_dn + signal_dn + noise, case))
    return {"recording": recorded.astype(np.float32), "expected": expected, "sd": sd,
            "white_chi2_per_pixel": float(np.mean(white_z**2)), "mu_per_mm": mu,
            "thickness_scene": phantom_thickness(geometry)}


def _banding_and_ripple(image: np.ndarray, case: Recording) -> np.ndarray:
    """``image`` (DN) with the case's row banding (seeded by the case) and ADC ripple added."""
    if "row_banding" in case.effects:
        rng_b = np.random.default_rng(2000 + case.seed)
        image = image + rng_b.normal(0.0, case.effects["row_banding"]["sigma_dn"], (image.shape[0], 1))
    if "adc_ripple" in case.effects:
        p = case.effects["adc_ripple"]
        image = image + p["amplitude_dn"] * np.sin(2 * np.pi * image / p["period_dn"])
    return image


def _without_effects(case: Recording) -> Recording:
    return Recording(seed=case.seed, shift_px=case.shift_px, scale=case.scale, rotation_deg=case.rotation_deg,
                     kvp_true=case.kvp_true)


def _residual_after_refit(columns: list[np.ndarray], with_effect: np.ndarray, sd: np.ndarray) -> tuple[float, float]:
    """Integrated SNR and max |residual| (in sigma) of ``with_effect`` after the weighted
    least-squares fit of a constant and ``columns``."""
    sd = sd.ravel()
    design = np.stack([np.ones(sd.size), *(c.ravel() for c in columns)], 1) / sd[:, None]
    coef, *_ = np.linalg.lstsq(design, with_effect.ravel() / sd, rcond=None)
    resid = with_effect.ravel() / sd - design @ coef
    return float(np.sqrt(np.sum(resid**2))), float(np.abs(resid).max())


def effect_signal(geometry: Geometry, camera: Camera, case: Recording) -> tuple[float, float]:
    """Integrated SNR and max per-pixel |Δ|/σ of the case's effects after the best gain/offset
    refit (what a base model could absorb): Δ = with effects − without, σ = per-pixel noise."""
    base = render(geometry, camera, _without_effects(case))
    with_effect = _banding_and_ripple(render(geometry, camera, case)["expected"], case)
    return _residual_after_refit([base["expected"]], with_effect, base["sd"])


def effect_signal_after_base_refit(geometry: Geometry, camera: Camera, case: Recording) -> tuple[float, float]:
    """As :func:`effect_signal`, but after the best *linearised* refit of every base-model
    parameter the diagnosis fits (offset, gain, attenuation, blur width, and the registration:
    shift, magnification, rotation): what is left for a library term to explain. Attenuation
    and blur absorb much of beam hardening, scatter and glare, the magnification much of a lens
    distortion, so this SNR is the one that sets their detectability."""
    from dataclasses import replace as _replace

    null = _without_effects(case)
    base = render(geometry, camera, null)
    e0 = base["expected"]
    d_mu = render(geometry, camera, _replace(null, mu_scale=1.001))["expected"] - e0
    d_blur = render(_replace(geometry, detector_sigma_mm=geometry.detector_sigma_mm * 1.01), camera,
                    null)["expected"] - e0
    registration = [render(geometry, camera, _replace(null, **change))["expected"] - e0
                    for change in ({"shift_px": (null.shift_px[0] + 0.01, null.shift_px[1])},
                                   {"shift_px": (null.shift_px[0], null.shift_px[1] + 0.01)},
                                   {"scale": null.scale + 1e-4},
                                   {"rotation_deg": null.rotation_deg + 0.01})]
    with_effect = _banding_and_ripple(render(geometry, camera, case)["expected"], case)
    return _residual_after_refit([e0, d_mu, d_blur, *registration], with_effect, base["sd"])
