"""Forward model of the X-ray imaging chain and the scene file that drives it.

Chain (docs/algorithms/simulation.md, section 'Forward model'; mono effective energy; every library term of
:mod:`.physics_terms` hooks in at its stage)::

    p(u)    = mu_eff · t(u)                         line integral, fine grid   [path]
    T       = block_mean(exp(-p))                   Beer–Lambert              
    F(u)    = 1 × heel × inverse square             relative fluence          [fluence]
    X       = F·T (+ scatter)                       screen input              [primary]
    L       = X ⊛ G(sqrt((s_fs (M-1))² + s_det²))   focal-spot + screen blur  [psf]
    O       = L (distortion, vignetting)                                     [optics]
    DN      = b + g · O (camera non-linearity)                               [camera]
    record  = b + K·Poisson((DN - b)/K) + N(0, s_r²) + impulsive pulses (+ RGGB gains)

``mu_eff`` comes from a table of mass attenuation coefficients at an effective energy
``E_eff = 0.5 kVp`` (a filtered tungsten spectrum at 60 kVp, 2.5 mm Al has HVL 2.03 mm Al,
i.e. mu = 0.341 /mm = aluminium at ≈ 29 keV; docs/algorithms/simulation.md, section 'Effective
energy and attenuation'). Spectral hardening is the
``beam_hardening`` term.

Scene file (TOML)::

    [geometry]
    source_to_detector_mm = 1200.0
    source_to_object_mm = 1150.0
    pixel_pitch_mm = 0.1
    [object]
    thickness_mm = "thickness.tif"   # float32, relative to the scene file
    material = "aluminium"           # aluminium, copper, water, pmma, bone
    # supersample = 1                # thickness map is this many times finer per axis
    # mu_per_mm = 0.3                # overrides the material table
    [source]
    kvp = 60
    # focal_spot_sigma_mm = 0.3      # Gaussian sigma of the focal spot
    [detector]
    # sigma_mm = 0.1                 # Gaussian screen blur sigma
    [camera]
    # offset_dn = 200.0, gain_dn = 3000.0 (open field above offset), cfa = false
    [noise]
    # poisson_gain_dn = 1.0 (var = K (mu - b) + s_r^2), read_noise_dn = 5.0,
    # pulse_rate_per_px = 0.0, pulse_amplitude_dn = 2000.0
    [effects.veiling_glare]          # any library term with its parameters
    eta = 0.02
    range_mm = 1.0
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from difflib import get_close_matches
from pathlib import Path

import numpy as np

from ..errors import InputError, ParameterError
from .physics_terms import LIBRARY, ChainGrid, ChainState, PhysicsTerm, _gauss_transfer, image_gradient, \
    _inverse_spectrum, _padded_spectrum, get_term, validate_params

# Mass attenuation coefficients mu/rho (cm^2/g, with coherent scattering) at 20..100 keV, from the
# NIST XCOM / Hubbell & Seltzer tables (NISTIR 5632), rounded; densities in g/cm^3. Checked against
# xraylib 4.3 (elements; NIST compositions by the mixture rule): aluminium, copper and water agree
# to 0.1 %; PMMA is the mixture-rule value for C5H8O2; bone is NIST's cortical bone (ICRU-44).
_ENERGIES_KEV = np.array([20.0, 30.0, 40.0, 50.0, 60.0, 80.0, 100.0])
MATERIALS: dict[str, tuple[float, tuple[float, ...]]] = {
    "aluminium": (2.699, (3.441, 1.128, 0.5685, 0.3681, 0.2778, 0.2018, 0.1704)),
    "copper": (8.96, (33.79, 10.92, 4.862, 2.613, 1.593, 0.7630, 0.4584)),
    "water": (1.0, (0.8096, 0.3756, 0.2683, 0.2269, 0.2059, 0.1837, 0.1707)),
    "pmma": (1.19, (0.5714, 0.3032, 0.2350, 0.2074, 0.1924, 0.1751, 0.1641)),
    "bone": (1.92, (4.001, 1.331, 0.6655, 0.4242, 0.3148, 0.2229, 0.1855)),
}
_MATERIAL_ALIASES = {"aluminum": "aluminium", "al": "aluminium", "cu": "copper", "acrylic": "pmma",
                     "perspex": "pmma", "cortical_bone": "bone"}


def effective_attenuation_per_mm(material: str, kvp: float, *, source: str = "scene") -> float:
    """Linear attenuation coefficient (1/mm) of ``material`` at ``E_eff = 0.5 kVp``.

    Log-log interpolation of the NIST table; ``kvp`` must lie in 40–200 (E_eff 20–100 keV).
    """
    key = _MATERIAL_ALIASES.get(material.lower(), material.lower())
    if key not in MATERIALS:
        close = get_close_matches(key, list(MATERIALS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ParameterError(f"{source}: unknown material {material!r}{hint}; known: {', '.join(MATERIALS)}")
    if not 40.0 <= kvp <= 200.0:
        raise ParameterError(f"{source}: [source] kvp={kvp} outside 40–200")
    density, mass_mu = MATERIALS[key]
    e_eff = 0.5 * kvp
    log_mu = np.interp(np.log(e_eff), np.log(_ENERGIES_KEV), np.log(mass_mu))
    return float(np.exp(log_mu) * density / 10.0)


@dataclass
class Scene:
    """A parsed and validated scene.

    Attributes
    ----------
    thickness_mm : ndarray, float64, (H*s, W*s)
        Path length of the material per (fine) detector pixel in mm.
    supersample : int
        ``s``: how many fine pixels per recording pixel along each axis.
    mu_per_mm : float
        Effective linear attenuation coefficient.
    effects : dict
        Library terms switched on in the scene, ``{name: full params}``.
    """

    path: Path | None
    source_to_detector_mm: float
    source_to_object_mm: float
    pixel_pitch_mm: float
    thickness_mm: np.ndarray
    material: str
    kvp: float
    mu_per_mm: float
    supersample: int = 1
    focal_spot_sigma_mm: float = 0.3
    detector_sigma_mm: float = 0.1
    offset_dn: float = 200.0
    gain_dn: float = 3000.0
    cfa: bool = False
    poisson_gain_dn: float = 1.0
    read_noise_dn: float = 5.0
    pulse_rate_per_px: float = 0.0
    pulse_amplitude_dn: float = 2000.0
    effects: dict[str, dict[str, float]] = field(default_factory=dict)
    thickness_path: Path | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """Shape of the recording (thickness shape / supersample)."""
        h, w = self.thickness_mm.shape
        return h // self.supersample, w // self.supersample

    @property
    def magnification_minus_one(self) -> float:
        return (self.source_to_detector_mm - self.source_to_object_mm) / self.source_to_object_mm

    def base_params(self) -> dict[str, float]:
        """The base-model parameters the scene states (starting point of a diagnosis)."""
        return {"offset_dn": self.offset_dn, "gain_dn": self.gain_dn, "mu_per_mm": self.mu_per_mm,
                "detector_sigma_mm": self.detector_sigma_mm,
                "focal_spot_sigma_mm": self.focal_spot_sigma_mm}

    def grid(self, binning: int = 1) -> ChainGrid:
        """The chain grid for this scene, optionally for a recording binned ``binning``×."""
        h, w = self.shape
        return ChainGrid((h // binning, w // binning), self.supersample * binning,
                         self.pixel_pitch_mm * binning, self.magnification_minus_one,
                         self.source_to_detector_mm)


def _get(table: dict, section: str, key: str, source, *, default=None, kind=float, positive=False):
    sec = table.get(section, {})
    if not isinstance(sec, dict):
        raise ParameterError(f"{source}: [{section}] must be a table")
    if key not in sec:
        if default is None:
            raise ParameterError(f"{source}: [{section}] is missing {key}")
        return default
    value = sec[key]
    try:
        value = kind(value)
    except (TypeError, ValueError, OverflowError):  # OverflowError: int(inf)
        raise ParameterError(f"{source}: [{section}] {key} must be a {kind.__name__}, got {value!r}") from None
    if kind is float and not np.isfinite(value):
        raise ParameterError(f"{source}: [{section}] {key} must be finite, got {value!r}")
    if positive and value <= 0:
        raise ParameterError(f"{source}: [{section}] {key} must be > 0, got {value!r}")
    return value


def parse_scene(table: dict, *, source: str = "scene", base_dir: str | os.PathLike = ".",
                thickness: np.ndarray | None = None) -> Scene:
    """Validate a scene dictionary (as read from TOML) and load its thickness map.

    Parameters
    ----------
    table : dict
        The TOML content.
    source : str
        Name used in error messages (the scene file).
    base_dir : path-like
        Folder the thickness path is relative to.
    thickness : ndarray, optional
        Use this thickness map (mm) instead of reading ``[object] thickness_mm``.
    """
    from .. import io

    known = {"geometry", "object", "source", "detector", "camera", "noise", "effects"}
    for section in table:
        if section not in known:
            close = get_close_matches(section, sorted(known), n=1)
            hint = f" (did you mean [{close[0]}]?)" if close else ""
            raise ParameterError(f"{source}: unknown section [{section}]{hint}")
    for section in ("geometry", "object", "source"):
        if section not in table:
            raise ParameterError(f"{source}: missing section [{section}]")
    sdd = _get(table, "geometry", "source_to_detector_mm", source, positive=True)
    sod = _get(table, "geometry", "source_to_object_mm", source, positive=True)
    pitch = _get(table, "geometry", "pixel_pitch_mm", source, positive=True)
    if sod > sdd:
        raise ParameterError(f"{source}: source_to_object_mm={sod} exceeds source_to_detector_mm={sdd}")
    material = _get(table, "object", "material", source, kind=str)
    kvp = _get(table, "source", "kvp", source, positive=True)
    mu_default = effective_attenuation_per_mm(material, kvp, source=source)
    mu = _get(table, "object", "mu_per_mm", source, default=mu_default, positive=True)
    supersample = _get(table, "object", "supersample", source, default=1, kind=int, positive=True)
    thickness_path = None
    if thickness is None:
        rel = _get(table, "object", "thickness_mm", source, kind=str)
        thickness_path = Path(base_dir) / rel
        if not thickness_path.is_file():
            raise InputError(source, f"[object] thickness_mm file {str(thickness_path)!r} not found")
        loaded = io.read_image(thickness_path)
        thickness = loaded.data
    thickness = np.asarray(thickness)
    if thickness.ndim != 2:
        raise InputError(thickness_path or source, f"thickness map must be 2-D, got shape {thickness.shape}")
    thickness = thickness.astype(np.float64)
    if not np.all(np.isfinite(thickness)) or thickness.min() < 0:
        raise InputError(thickness_path or source, "thickness map must be finite and >= 0 mm")
    if thickness.shape[0] % supersample or thickness.shape[1] % supersample:
        raise InputError(thickness_path or source,
                         f"thickness shape {thickness.shape} not divisible by supersample={supersample}")
    if min(thickness.shape) // supersample < 16:
        raise InputError(thickness_path or source, f"thickness map {thickness.shape} too small (min 16 px)")
    cam = dict(
        focal_spot_sigma_mm=_get(table, "source", "focal_spot_sigma_mm", source, default=0.3),
        detector_sigma_mm=_get(table, "detector", "sigma_mm", source, default=0.1),
        offset_dn=_get(table, "camera", "offset_dn", source, default=200.0),
        gain_dn=_get(table, "camera", "gain_dn", source, default=3000.0, positive=True),
        cfa=bool(table.get("camera", {}).get("cfa", False)),
        poisson_gain_dn=_get(table, "noise", "poisson_gain_dn", source, default=1.0),
        read_noise_dn=_get(table, "noise", "read_noise_dn", source, default=5.0),
        pulse_rate_per_px=_get(table, "noise", "pulse_rate_per_px", source, default=0.0),
        pulse_amplitude_dn=_get(table, "noise", "pulse_amplitude_dn", source, default=2000.0),
    )
    for key in ("focal_spot_sigma_mm", "detector_sigma_mm", "poisson_gain_dn", "read_noise_dn",
                "pulse_rate_per_px", "pulse_amplitude_dn"):
        if cam[key] < 0:
            raise ParameterError(f"{source}: {key} must be >= 0, got {cam[key]}")
    effects: dict[str, dict[str, float]] = {}
    eff_table = table.get("effects", {})
    if not isinstance(eff_table, dict):
        raise ParameterError(f"{source}: [effects] must be a table of [effects.NAME] tables")
    for name, params in eff_table.items():
        if not isinstance(params, dict):
            raise ParameterError(f"{source}: [effects.{name}] must be a table of parameters")
        try:
            effects[name] = validate_params(get_term(name), params)
        except ParameterError as exc:  # name the scene file, as every other scene error does
            raise ParameterError(f"{source}: [effects.{name}]: {exc}") from None
    return Scene(path=None, source_to_detector_mm=sdd, source_to_object_mm=sod, pixel_pitch_mm=pitch,
                 thickness_mm=thickness, material=material, kvp=kvp, mu_per_mm=mu,
                 supersample=supersample, effects=effects, thickness_path=thickness_path, **cam)


def load_scene(path: str | os.PathLike) -> Scene:
    """Read and validate a scene TOML file (thickness path relative to the file)."""
    from ..io import read_structured_file

    path = Path(path)
    table = read_structured_file(path, what="scene file")
    scene = parse_scene(table, source=str(path), base_dir=path.parent)
    scene.path = path
    return scene


def block_mean(image: np.ndarray, factor: int) -> np.ndarray:
    """Mean over ``factor × factor`` blocks (shape must be divisible)."""
    if factor == 1:
        return image
    h, w = image.shape
    return image.reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3))


def _ordered(terms: list[tuple[PhysicsTerm, dict]]) -> list[tuple[PhysicsTerm, dict]]:
    order = {t.name: i for i, t in enumerate(LIBRARY)}
    return sorted(terms, key=lambda tp: order.get(tp[0].name, 99))


class _TransmissionExpansion:
    """The coarse transmission ``C[exp(-mu t)]`` and scatter source ``C[mu t exp(-mu t)]`` for
    any ``mu`` near a centre ``mu0``, where ``C`` is the linear fine-to-coarse operator.

    With ``s = t / t_max`` and ``d = (mu - mu0) t_max``,
    ``exp(-mu t) = exp(-mu0 t) sum_n (-d)^n s^n / n!``, so
    ``C[exp(-mu t)] = sum_n (-d)^n / n! B_n`` with ``B_n = C[s^n exp(-mu0 t)]``, made once
    (``TERMS + 2`` applications of ``C``), and each ``mu`` costs ``TERMS + 1`` multiply-adds on
    the coarse grid. ``|d| <= RADIUS`` keeps the omitted tail below ``RADIUS^(TERMS+1) /
    (TERMS+1)!`` (7e-19) of the value: the same numbers as the direct computation to rounding.
    """

    RADIUS = 0.5
    TERMS = 15

    def __init__(self, thickness_mm: np.ndarray, mu0: float, to_coarse) -> None:
        self.mu0 = float(mu0)
        self.t_max_mm = max(float(np.abs(thickness_mm).max()), 1e-300)
        fine = np.exp(-self.mu0 * thickness_mm)
        scaled = thickness_mm / self.t_max_mm
        self.basis = [to_coarse(fine)]
        for _ in range(self.TERMS + 1):  # one more than the series: the scatter source's s·exp
            np.multiply(fine, scaled, out=fine)
            self.basis.append(to_coarse(fine))

    def covers(self, mu: float) -> bool:
        return abs(mu - self.mu0) * self.t_max_mm <= self.RADIUS

    def _series(self, d: float, first: int) -> np.ndarray:
        out = self.basis[first].copy()
        coefficient = 1.0
        for n in range(1, self.TERMS + 1):
            coefficient *= -d / n
            out += coefficient * self.basis[first + n]
        return out

    def at(self, mu: float):
        d = (mu - self.mu0) * self.t_max_mm
        memo: dict = {}

        def scatter_source() -> np.ndarray:
            if "tp" not in memo:
                memo["tp"] = (mu * self.t_max_mm) * self._series(d, 1)
            return memo["tp"]

        return self._series(d, 0), scatter_source


class ChainModel:
    """Noise-free expected recording (DN) of a scene as a function of base and term parameters.

    Keeps the last transmission (the only fine-grid step) and the Gaussian transfer function so
    that Jacobian columns of later stages do not recompute them.

    Parameters
    ----------
    thickness_mm : ndarray, (H*s, W*s)
        Fine-grid path length in mm.
    grid : ChainGrid
        Coarse grid (``grid.fine_factor == s``).
    pre_blur_px : float
        Gaussian sigma (coarse pixels) applied on the fine grid before block averaging (for
        binned fits); the total blur must stay at least this large.
    """

    def __init__(self, thickness_mm: np.ndarray, grid: ChainGrid, pre_blur_px: float = 0.0):
        self.thickness_mm = np.asarray(thickness_mm, dtype=np.float64)
        self.grid = grid
        # Part of the Gaussian blur (sigma in *coarse* pixels) applied on the fine grid before
        # block averaging: binning a sharp-edged image and blurring afterwards aliases; blurring
        # first does not. The rest of the blur is applied on the coarse grid.
        self.pre_blur_px = float(pre_blur_px)
        self._path_cache: tuple | None = None
        self._expansion: _TransmissionExpansion | None = None
        self._direct_mu: float | None = None
        self._spectrum_cache: tuple | None = None
        self._light_cache: tuple | None = None
        self._transfer_cache: tuple | None = None

    def _transmission(self, mu: float, path_terms: list[tuple[PhysicsTerm, dict]]):
        key = (mu, tuple((t.name, tuple(sorted(p.items()))) for t, p in path_terms))
        if self._path_cache is not None and self._path_cache[0] == key:
            return self._path_cache[1]
        if not path_terms and self.grid.fine_factor > 1:
            # A binned (or supersampled) fit asks for many attenuations mu, each a blur and
            # block average of a fine-grid image (the costliest step at 2048²): from the second
            # mu on, the coarse transmission comes from a series in mu about a centre, whose
            # coarse terms are made once (docs/algorithms/simulation.md, 'Transmission series').
            if self._expansion is not None or (self._direct_mu is not None and mu != self._direct_mu):
                if self._expansion is None or not self._expansion.covers(mu):
                    self._expansion = _TransmissionExpansion(self.thickness_mm, mu, self._to_coarse)
                out = self._expansion.at(mu)
                self._path_cache = (key, out)
                return out
            self._direct_mu = mu
        path_terms = [(t, dict(p)) for t, p in path_terms]  # kept by the closures below

        def fine_path() -> np.ndarray:
            state = ChainState(self.grid, path=mu * self.thickness_mm)
            for term, params in path_terms:
                term.apply(state, params)
            return state.path

        path = fine_path()
        fine_t = np.exp(-path)
        del path
        memo: dict = {}

        def scatter_source() -> np.ndarray:
            # only the scatter term reads T·p: its fine-grid blur (the costly step of a binned
            # fit) is done when first asked for, once per transmission; the fine arrays are
            # recomputed then rather than kept (a full-resolution array held per cached
            # transmission raised the peak memory of the 2048² benchmark from 0.86 to 1.1 GB)
            if "tp" not in memo:
                p_fine = fine_path()
                memo["tp"] = self._to_coarse(np.exp(-p_fine) * p_fine)
            return memo["tp"]

        out = (self._to_coarse(fine_t), scatter_source)
        self._path_cache = (key, out)
        return out

    def _to_coarse(self, fine: np.ndarray) -> np.ndarray:
        """Pre-blur on the fine grid (binned or supersampled fits), then block-average."""
        f = self.grid.fine_factor
        if self.pre_blur_px > 0 and f > 1:
            from scipy import ndimage

            # The Gaussian is separable, and blur and block averaging along different axes
            # commute: blur along each row, average column blocks, then blur and average
            # along the columns of the f× narrower image — the same linear operator as the
            # full 2-D blur followed by block averaging (equal to rounding), in half the time
            # (the strided column pass runs on 1/f of the pixels).
            sigma_fine = self.pre_blur_px * f
            h, w = fine.shape
            along_rows = ndimage.gaussian_filter1d(fine, sigma_fine, axis=1, mode="reflect", truncate=3.5)
            narrow = np.einsum("ijk->ij", along_rows.reshape(h, w // f, f)) / f
            both = ndimage.gaussian_filter1d(narrow, sigma_fine, axis=0, mode="reflect", truncate=3.5)
            return both.reshape(h // f, f, w // f).mean(axis=1)
        return block_mean(fine, f)

    def expected(self, base: dict[str, float], terms: list[tuple[PhysicsTerm, dict]] = ()) -> np.ndarray:
        """Expected recording in DN (float64, coarse shape).

        Parameters
        ----------
        base : dict
            ``offset_dn``, ``gain_dn``, ``mu_per_mm``, ``detector_sigma_mm``,
            ``focal_spot_sigma_mm``.
        terms : list of (PhysicsTerm, dict)
            Active terms with full parameter dicts.
        """
        g = self.grid
        terms = _ordered(list(terms))
        by_stage: dict[str, list] = {}
        for term, params in terms:
            by_stage.setdefault(term.stage, []).append((term, params))
        def stage_key(stages):
            return tuple((t.name, tuple(sorted(p.items()))) for st in stages for t, p in by_stage.get(st, []))

        # Caches: the spectrum of the screen input (reused when only PSF, optics or camera
        # parameters change) and the light image after the PSF (reused when only optics/camera
        # parameters change) — the bulk of the Jacobian columns.
        signal_key = (float(base["mu_per_mm"]), stage_key(("path", "fluence", "primary")))
        sigma_px = np.hypot(base["focal_spot_sigma_mm"] * g.magnification_minus_one,
                            base["detector_sigma_mm"]) / g.pitch_mm
        sigma_px = float(np.sqrt(max(sigma_px**2 - self.pre_blur_px**2, 0.0)))
        light_key = (signal_key, float(sigma_px), stage_key(("psf",)))
        state = ChainState(g)
        if self._light_cache is not None and self._light_cache[0] == light_key:
            state.light = self._light_cache[1]
        else:
            if self._spectrum_cache is not None and self._spectrum_cache[0] == signal_key:
                spectrum = self._spectrum_cache[1]
            else:
                transmission, t_times_p = self._transmission(float(base["mu_per_mm"]), by_stage.get("path", []))
                state = ChainState(g, transmission=transmission, scatter_source=t_times_p,
                                   fluence=np.ones(g.shape))
                for term, params in by_stage.get("fluence", []):
                    term.apply(state, params)
                state.signal = state.fluence * transmission
                for term, params in by_stage.get("primary", []):
                    term.apply(state, params)
                spectrum = _padded_spectrum(state.signal, g)
                self._spectrum_cache = (signal_key, spectrum)
            # one transfer function per blur width: the Jacobian columns of the other PSF terms
            # (registration shift, glare, ...) share it (terms replace it, never modify it)
            if self._transfer_cache is None or self._transfer_cache[0] != sigma_px:
                self._transfer_cache = (sigma_px, _gauss_transfer(g, sigma_px))
            state.transfer = self._transfer_cache[1]
            for term, params in by_stage.get("psf", []):
                term.apply(state, params)
            state.light = _inverse_spectrum(spectrum * state.transfer, g)
            self._light_cache = (light_key, state.light, {})
        light, memo = self._light_cache[1], self._light_cache[2]

        def gradient():
            if "gradient" not in memo:
                memo["gradient"] = image_gradient(light)
            return memo["gradient"]

        # terms replace the light, never modify it: the cached light itself starts the optics
        # (read-only, so a term that wrote into it would fail instead of corrupting the cache)
        light.flags.writeable = False
        state.light = light
        state.cached_light_gradient = (state.light, gradient)
        for stage in ("optics", "camera"):
            for term, params in by_stage.get(stage, []):
                term.apply(state, params)
        return base["offset_dn"] + base["gain_dn"] * state.light


def simulate_recording(scene: Scene, *, effects: dict[str, dict[str, float]] | None = None,
                       seed: int = 0) -> tuple[np.ndarray, dict]:
    """Simulate a noisy recording (float32 DN) of ``scene``.

    Parameters
    ----------
    scene : Scene
    effects : dict, optional
        ``{term name: params}`` overriding/adding to ``scene.effects`` (params are completed with
        null values and validated).
    seed : int
        Seed of the noise and pulse generator (same seed → same bytes).

    Returns
    -------
    recording : ndarray, float32, (H, W)
    truth : dict
        ``expected`` (noise-free DN, float64), ``pulse_mask`` (bool), ``effects`` used.
    """
    from scipy import ndimage

    all_effects = dict(scene.effects)
    for name, params in (effects or {}).items():
        all_effects[name] = validate_params(get_term(name), params)
    terms = [(get_term(n), p) for n, p in all_effects.items()]
    grid = scene.grid()
    # A supersampled object is blurred before pixel integration (most of the blur on the fine
    # grid); blurring only after block-averaging would alias its sharp edges.
    sigma_px = np.hypot(scene.focal_spot_sigma_mm * grid.magnification_minus_one, scene.detector_sigma_mm) / grid.pitch_mm
    model = ChainModel(scene.thickness_mm, grid, 0.6 * sigma_px if scene.supersample > 1 else 0.0)
    expected = model.expected(scene.base_params(), terms)
    if scene.cfa:
        # RGGB plane gains of a green-emitting screen seen through a Bayer filter
        # (docs/algorithms/simulation.md, section 'Bayer colour filter').
        gains = np.ones(expected.shape)
        gains[0::2, 0::2], gains[1::2, 1::2] = 0.15, 0.10
        expected = scene.offset_dn + (expected - scene.offset_dn) * gains
    rng = np.random.default_rng(seed)
    k = scene.poisson_gain_dn
    signal = np.clip(expected - scene.offset_dn, 0.0, None)
    if k > 0:
        noisy = k * rng.poisson(signal / k).astype(np.float64)
    else:
        noisy = signal.copy()
    noisy += scene.offset_dn + rng.normal(0.0, scene.read_noise_dn, size=signal.shape)
    pulse_mask = np.zeros(signal.shape, dtype=bool)
    n_pulses = rng.poisson(scene.pulse_rate_per_px * signal.size) if scene.pulse_rate_per_px > 0 else 0
    if n_pulses:
        # Direct hits on the sensor: sparse clusters (sigma 0.7 px) with exponential amplitudes.
        impulses = np.zeros(signal.shape)
        rows = rng.integers(0, signal.shape[0], n_pulses)
        cols = rng.integers(0, signal.shape[1], n_pulses)
        np.add.at(impulses, (rows, cols), rng.exponential(scene.pulse_amplitude_dn, n_pulses))
        sigma_c = 0.7
        pulses = ndimage.gaussian_filter(impulses, sigma_c) * (2 * np.pi * sigma_c**2)
        noisy += pulses
        pulse_mask = pulses > 0.5 * scene.read_noise_dn + 1e-9
    return noisy.astype(np.float32), {"expected": expected, "pulse_mask": pulse_mask,
                                      "effects": all_effects}


def phantom_thickness_mm(shape: tuple[int, int], *, max_thickness_mm: float = 8.0) -> np.ndarray:
    """Analytic test phantom (float32, mm of the scene material).

    A ten-step wedge (``max/10 … max``), a disc, a bar tilted by 10° (sub-pixel edges at every
    position) and a near-opaque block (``3 × max``, pins the camera offset) on open field: edges
    in several orientations and many thickness levels make every library term testable. The top
    band and the right strip stay open.
    """
    h, w = shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    rows_n, cols_n = rows / h, cols / w
    t = np.zeros(shape)
    wedge = (rows_n > 0.55) & (rows_n < 0.9) & (cols_n > 0.06) & (cols_n < 0.66)
    t[wedge] = max_thickness_mm * np.floor((cols_n[wedge] - 0.06) / 0.6 * 10 + 1) / 10
    disc = (rows_n - 0.32) ** 2 + (cols_n - 0.3) ** 2 < 0.14**2
    t[disc] = 0.35 * max_thickness_mm
    u = (cols_n - 0.65) * np.cos(0.17) + (rows_n - 0.3) * np.sin(0.17)
    v = -(cols_n - 0.65) * np.sin(0.17) + (rows_n - 0.3) * np.cos(0.17)
    t[(np.abs(u) < 0.08) & (np.abs(v) < 0.2)] += 0.2 * max_thickness_mm
    block = (rows_n > 0.6) & (rows_n < 0.85) & (cols_n > 0.72) & (cols_n < 0.86)
    t[block] = 3.0 * max_thickness_mm
    return t.astype(np.float32)
