"""Declarative library of physics terms the simple lens-coupled model leaves out.

Each :class:`PhysicsTerm` names one effect of the X-ray → screen → mirror → lens → camera chain
(docs/algorithms/simulation.md, section 'Physics terms'), says at which stage of the chain it
acts, lists its parameters with
their null values (effect switched off), prior ranges, probe values for the score test and a
grid for nonlinear shape parameters, and carries an ``apply(state, params)`` that modifies the
:class:`ChainState` in place. The same functions drive the simulator and the diagnosis, so a
term fitted by the diagnosis is exactly the term the simulator injects.

Stages, in chain order (see :data:`STAGES`):

``path``     line integral ``p = mu * t`` (fine grid)            beam hardening
``fluence``  relative incident fluence (multiplicative field)   heel effect, inverse square
``primary``  signal reaching the screen, before the screen PSF  object scatter
``psf``      transfer function of the screen/optics (Fourier)   focal-spot shape, veiling glare,
                                                                  mirror ghost
``optics``   light image after the PSF                          lens distortion, vignetting
``camera``   normalised light → response before gain/offset     detector gamma

Coordinates: ``x``, ``y`` are in units of ``R`` = half the longer image side (pixels), origin at
the image centre; radial terms use ``rho**2 = (dx**2 + dy**2) / 2`` so the corners of a square
field are at ``rho = 1``. Physical lengths (glare range, scatter width, ghost shift, focal-spot
lobes) are in millimetres on the detector and converted with the (binned) pixel pitch.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

STAGES = ("path", "fluence", "primary", "psf", "optics", "camera")


@dataclass(frozen=True)
class ParamSpec:
    """One parameter of a physics term.

    Parameters
    ----------
    name : str
        Name including its unit suffix where it has one (``width_mm``, ``angle_deg``).
    null : float
        Value at which the term has no effect (or, for shape parameters, a neutral value).
    prior : (float, float)
        Physically plausible range; fits are bounded to it.
    probe : float
        Value used for the score-test columns (amplitudes set to ``probe`` so that the
        derivatives of local parameters such as centres are defined).
    step : float
        Finite-difference step for Jacobian columns, in the parameter's unit.
    grid : tuple of float
        Non-empty for nonlinear shape parameters: the score test maximises over this grid
        (and the BIC counts the parameter), the refit then refines it continuously.
    """

    name: str
    null: float
    prior: tuple[float, float]
    probe: float
    step: float
    grid: tuple[float, ...] = ()
    unit: str = ""
    period: float = 0.0

    def wrap(self, value: float) -> float:
        """Map a periodic parameter (an axis angle) into ``(-period/2, period/2]``."""
        if self.period <= 0:
            return float(value)
        half = self.period / 2.0
        return float(-((-value + half) % self.period - half))

    @property
    def is_grid(self) -> bool:
        return len(self.grid) > 0


@dataclass
class ChainGrid:
    """Geometry of the image grids the chain is evaluated on (cached per image shape).

    Parameters
    ----------
    shape : (int, int)
        Output (coarse) image shape in pixels.
    fine_factor : int
        The thickness map is ``fine_factor`` times larger per axis (supersampled object or the
        full-resolution object of a binned recording); transmission is averaged over blocks.
    pitch_mm : float
        Coarse pixel pitch on the detector in mm.
    magnification_minus_one : float
        ``M - 1 = (SDD - SOD) / SOD``: focal-spot blur scale at the detector.
    source_to_detector_mm : float
        Source-to-detector distance (inverse-square prior).
    """

    shape: tuple[int, int]
    fine_factor: int
    pitch_mm: float
    magnification_minus_one: float
    source_to_detector_mm: float
    pad: tuple[int, int] = field(init=False)
    padded_shape: tuple[int, int] = field(init=False)
    fx: np.ndarray = field(init=False, repr=False)
    fy: np.ndarray = field(init=False, repr=False)
    x: np.ndarray = field(init=False, repr=False)
    y: np.ndarray = field(init=False, repr=False)
    half_size_px: float = field(init=False)
    _f2: np.ndarray = field(init=False, repr=False)
    _cache: dict = field(init=False, repr=False)

    def __post_init__(self) -> None:
        from scipy import fft as sfft

        h, w = self.shape
        # Fixed padding so the model is a smooth function of every kernel width (a padding
        # that grew with the width would make the fit objective jump).
        ph, pw = max(8, h // 4), max(8, w // 4)
        nh, nw = sfft.next_fast_len(h + 2 * ph, real=True), sfft.next_fast_len(w + 2 * pw, real=True)
        self.pad = (ph, pw)
        self.padded_shape = (nh, nw)
        self.fy = np.fft.fftfreq(nh)[:, None]
        self.fx = np.fft.rfftfreq(nw)[None, :]
        self.half_size_px = max(h, w) / 2.0
        self.y = ((np.arange(h) - (h - 1) / 2.0) / self.half_size_px)[:, None]
        self.x = ((np.arange(w) - (w - 1) / 2.0) / self.half_size_px)[None, :]

        self._f2 = self.fx**2 + self.fy**2
        self._cache: dict = {}

    @property
    def f2(self) -> np.ndarray:
        """Squared spatial frequency (cycles/px)² on the padded rfft grid."""
        return self._f2

    def cached(self, key, make):
        """Small per-grid cache of transfer functions (kernel FFTs reused across Jacobian columns)."""
        if key not in self._cache:
            if len(self._cache) > 64:
                self._cache.clear()
            self._cache[key] = make()
        return self._cache[key]


@dataclass
class ChainState:
    """Arrays flowing through the chain; terms modify them in place at their stage.

    ``path`` is the fine-grid line integral ``mu * t`` (dimensionless); ``fluence`` the relative
    incident fluence (1 = open field at the centre); ``signal`` the screen input (relative to the
    open field); ``scatter_source`` ``block_mean(T * p)`` for the scatter kernel (or a function
    returning it: read it with :meth:`scatter_source_image`); ``transfer`` the
    rfft2 transfer function on the padded grid; ``light`` the optical image after the PSF
    (relative units). All coarse arrays are float64.
    """

    grid: ChainGrid
    path: np.ndarray | None = None
    transmission: np.ndarray | None = None
    scatter_source: np.ndarray | Callable[[], np.ndarray] | None = None
    fluence: np.ndarray | None = None
    signal: np.ndarray | None = None
    transfer: np.ndarray | None = None
    light: np.ndarray | None = None
    def scatter_source_image(self) -> np.ndarray:
        """``scatter_source``, evaluated if it was given as a function (computed on demand)."""
        if callable(self.scatter_source):
            self.scatter_source = self.scatter_source()
        return self.scatter_source

    #: ``(light, gradient)`` from the model's light cache: ``gradient()`` is ``np.gradient`` of
    #: that light, computed once per cached light (Jacobian columns of the optics and camera
    #: stages share it)
    cached_light_gradient: tuple | None = None

    def light_gradient(self) -> tuple[np.ndarray, np.ndarray]:
        """``np.gradient(light)`` (rows, columns), from the cache while ``light`` is unchanged."""
        if self.cached_light_gradient is not None and self.cached_light_gradient[0] is self.light:
            return self.cached_light_gradient[1]()
        return image_gradient(self.light)


def image_gradient(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.gradient(image)`` of a 2-D float array (rows, columns), the same numbers to the bit
    (central differences halved inside, one-sided at the borders), written into the outputs
    without ``np.gradient``'s temporaries (it runs at every Jacobian column of a fit)."""
    out = []
    for axis in (0, 1):
        f = np.moveaxis(image, axis, 0)
        grad = np.empty_like(image)
        g = np.moveaxis(grad, axis, 0)
        np.subtract(f[2:], f[:-2], out=g[1:-1])
        np.divide(g[1:-1], 2.0, out=g[1:-1])
        np.subtract(f[1], f[0], out=g[0])
        np.subtract(f[-1], f[-2], out=g[-1])
        out.append(grad)
    return out[0], out[1]


@dataclass(frozen=True)
class PhysicsTerm:
    """One candidate physics term (declarative).

    Attributes
    ----------
    name, stage : str
        Library name and chain stage (one of :data:`STAGES`).
    params : tuple of ParamSpec
    main : str
        The main amplitude parameter (what a single value for the term sets, e.g. ``dslrxr simulate --effect NAME=VALUE``).
    apply : callable
        ``apply(state, params_dict)`` modifies the :class:`ChainState` in place.
    physics : str
        One-paragraph physical explanation (goes into the report).
    covariate : str
        Organising covariate of its residual signature (profile to look at).
    separating : str
        Acquisition that separates it from its confusable partners (docs/algorithms/diagnosis.md,
        section 'Identifiability').
    even_in_main : bool
        The effect is even in its main amplitude (two lobes at ±a): no gradient at the null, so
        the score test's linearisation at the probe point cannot choose its shape-grid point,
        and the diagnosis's refit tries each.
    linear_params : tuple of str
        Parameters in which the term's output is affine, jointly (an amplitude multiplying a
        fixed pattern): its derivative in them is the same at every value.
    linear_in_light : bool
        An optics or camera term whose map from the light it receives to the light it passes on
        is affine (a field, a warp, a copy; not a non-linear response). A PSF term always is (it
        multiplies the transfer function).
    """

    name: str
    stage: str
    params: tuple[ParamSpec, ...]
    main: str
    apply: Callable[[ChainState, dict], None] = field(repr=False)
    physics: str = ""
    covariate: str = ""
    separating: str = ""
    even_in_main: bool = False
    linear_params: tuple[str, ...] = ()
    linear_in_light: bool = False

    def passes_light_linearly(self) -> bool:
        """Whether the term's map of the light it receives is affine (see ``linear_in_light``)."""
        return self.stage == "psf" or self.linear_in_light

    def spec(self, name: str) -> ParamSpec:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(name)

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    def null_params(self) -> dict[str, float]:
        """Parameters at which the term has no effect."""
        return {p.name: p.null for p in self.params}

    def probe_params(self) -> dict[str, float]:
        """Amplitudes at their probe values, shape parameters neutral."""
        return {p.name: p.probe for p in self.params}

    def grid_points(self) -> list[dict[str, float]]:
        """Every combination of the shape-grid values (one empty dict when there is no grid)."""
        grid_specs = [p for p in self.params if p.is_grid]
        if not grid_specs:
            return [{}]
        return [dict(zip([p.name for p in grid_specs], combo))
                for combo in itertools.product(*[p.grid for p in grid_specs])]


# --------------------------------------------------------------------------- helpers


def _radial_sq(grid: ChainGrid, cx: float, cy: float) -> np.ndarray:
    """``rho**2`` about centre ``(cx, cy)`` (units of the half side); corners of a square at 1."""
    return ((grid.x - cx) ** 2 + (grid.y - cy) ** 2) / 2.0


def _px(grid: ChainGrid, length_mm: float) -> float:
    return float(length_mm) / grid.pitch_mm


# --------------------------------------------------------------------------- apply functions


def _apply_beam_hardening(state: ChainState, p: dict) -> None:
    # Mono attenuation over-predicts thick parts: p_meas = p / (1 + beta p) = p - beta p^2 + ...
    # (docs/algorithms/simulation.md, 'Beam hardening': equal to first order; this form stays
    # monotone for opaque objects).
    state.path = state.path / (1.0 + p["beta"] * state.path)


def _apply_heel(state: ChainState, p: dict) -> None:
    g = state.grid
    a = np.deg2rad(p["angle_deg"])
    u = g.x * np.cos(a) + g.y * np.sin(a)  # coordinate along the anode-cathode axis
    state.fluence = state.fluence * np.exp(p["h1"] * u + p["h2"] * u**2)


def _apply_inverse_square(state: ChainState, p: dict) -> None:
    g = state.grid
    rho2 = _radial_sq(g, p["foot_x"], p["foot_y"])
    # cos^3 gamma with cos gamma = 1/sqrt(1 + s rho^2), s = (R_diag / SDD_eff)^2
    # (docs/algorithms/simulation.md, section 'Inverse square').
    state.fluence = state.fluence * _inverse_three_halves(1.0 + p["strength"] * rho2)


def _gauss_transfer(grid: ChainGrid, sigma_px: float) -> np.ndarray:
    c = -2.0 * np.pi**2 * sigma_px**2
    # separable: exp(c fy^2) exp(c fx^2) as an outer product (cheaper than exp on the grid)
    return np.exp(c * grid.fy**2) * np.exp(c * grid.fx**2)


def _padded_spectrum(image: np.ndarray, grid: ChainGrid) -> np.ndarray:
    """rfft2 of ``image`` reflect-padded to ``grid.padded_shape``."""
    from scipy import fft as sfft

    ph, pw = grid.pad
    nh, nw = grid.padded_shape
    h, w = image.shape
    return sfft.rfft2(np.pad(image, ((ph, nh - h - ph), (pw, nw - w - pw)), mode="reflect"))


def _inverse_spectrum(spectrum: np.ndarray, grid: ChainGrid) -> np.ndarray:
    """Inverse of :func:`_padded_spectrum` (cropped to ``grid.shape``)."""
    from scipy import fft as sfft

    ph, pw = grid.pad
    h, w = grid.shape
    # The inverse along the rows first, then only the rows kept go through the real inverse
    # along the columns: the same transform (to rounding), in less than half the time of
    # irfft2 on the whole padded grid.
    rows = sfft.ifft(spectrum, axis=0)[ph:ph + h]
    return sfft.irfft(rows, n=grid.padded_shape[1], axis=1)[:, pw:pw + w]


def _fft_filter(image: np.ndarray, transfer: np.ndarray, grid: ChainGrid) -> np.ndarray:
    """Filter ``image`` with an rfft2 transfer function on the reflect-padded grid."""
    return _inverse_spectrum(_padded_spectrum(image, grid) * transfer, grid)


def _apply_scatter(state: ChainState, p: dict) -> None:
    g = state.grid
    # Object scatter ∝ primary · (-ln T) spread by a wide kernel, a scatter-kernel superposition
    # (docs/algorithms/simulation.md, section 'Object scatter').
    source = state.fluence * state.scatter_source_image()
    state.signal = state.signal + p["amplitude"] * _fft_filter(
        source, _gauss_transfer(g, _px(g, p["sigma_mm"])), g)


def _apply_focal_spot_shape(state: ChainState, p: dict) -> None:
    g = state.grid
    a = np.deg2rad(p["axis_deg"])
    half_sep_px = _px(g, p["half_separation_mm"]) * g.magnification_minus_one
    f_axis = g.fx * np.cos(a) + g.fy * np.sin(a)
    # Two-lobed focal spot 1/2[δ(v - a) + δ(v + a)] (⊛ the Gaussian already in the transfer).
    state.transfer = state.transfer * np.cos(2.0 * np.pi * half_sep_px * f_axis)


def _inverse_three_halves(t: np.ndarray) -> np.ndarray:
    """``t ** -1.5`` for positive ``t`` (to rounding), in place in ``t``: a square root and a
    product instead of ``pow`` (a third of the time on a padded 512² grid)."""
    root = np.sqrt(t)
    np.multiply(t, root, out=t)
    return np.divide(1.0, t, out=t)


def _apply_veiling_glare(state: ChainState, p: dict) -> None:
    g = state.grid
    w_px = _px(g, p["range_mm"])
    # PSF = (1 - eta) δ + eta K_w, K_w = exp(-r/w)/(2 pi w^2): MTF (1 + (2 pi w f)^2)^(-3/2).
    mtf_tail = g.cached(("glare", w_px), lambda: _inverse_three_halves(1.0 + (2.0 * np.pi * w_px) ** 2 * g.f2))
    state.transfer = state.transfer * ((1.0 - p["eta"]) + p["eta"] * mtf_tail)


def _apply_mirror_ghost(state: ChainState, p: dict) -> None:
    g = state.grid
    a = np.deg2rad(p["axis_deg"])
    d_px = _px(g, p["shift_mm"])
    # O = L(q) + eps L(q + d): front-face reflection of a back-silvered mirror
    # (docs/algorithms/simulation.md, section 'Mirror ghost').
    # The shift's phase factor is separable in fy and fx.
    shift = g.cached(("shift", d_px, p["axis_deg"]), lambda: (
        np.exp(2j * np.pi * d_px * np.sin(a) * g.fy) * np.exp(2j * np.pi * d_px * np.cos(a) * g.fx)))
    state.transfer = state.transfer * (1.0 + p["epsilon"] * shift)


def _apply_lens_distortion(state: ChainState, p: dict) -> None:
    from scipy import ndimage

    if p["k1"] == 0.0:
        return
    g = state.grid
    h, w = state.light.shape
    rho2 = _radial_sq(g, 0.0, 0.0)
    factor = 1.0 + p["k1"] * rho2
    rows = (h - 1) / 2.0 + g.y * g.half_size_px * factor
    cols = (w - 1) / 2.0 + g.x * g.half_size_px * factor
    rows, cols = np.broadcast_arrays(rows, cols)
    # Brown radial model q_d = q (1 + k1 rho^2): the sensor sees the screen image at q_d.
    state.light = ndimage.map_coordinates(state.light, [rows, cols], order=3, mode="reflect")


def _apply_vignetting(state: ChainState, p: dict) -> None:
    rho2 = _radial_sq(state.grid, p["centre_x"], p["centre_y"])
    state.light = state.light * (1.0 + p["k1"] * rho2 + p["k2"] * rho2**2)


def _apply_detector_gamma(state: ChainState, p: dict) -> None:
    # Soft non-linearity of the camera response DN = b + K e (1 - kappa e)
    # (docs/algorithms/simulation.md, section 'Detector gamma').
    state.light = state.light * (1.0 - p["kappa"] * state.light)


# --------------------------------------------------------------------------- the library

P = ParamSpec

LIBRARY: tuple[PhysicsTerm, ...] = (
    PhysicsTerm(
        "beam_hardening", "path",
        (P("beta", 0.0, (0.0, 0.5), 0.01, 1e-3),),
        "beta", _apply_beam_hardening,
        physics="Polychromatic beam: the mono model over-predicts attenuation of thick parts; "
                "measured line integral p / (1 + beta p) ≈ p - beta p^2 "
                "(docs: simulation.md, 'Beam hardening').",
        covariate="line integral p", separating="two-material wedge; kV series"),
    PhysicsTerm(
        "heel_effect", "fluence",
        (P("h1", 0.0, (-0.6, 0.6), 0.02, 2e-3), P("h2", 0.0, (-0.4, 0.4), 0.02, 2e-3),
         P("angle_deg", 0.0, (-360.0, 360.0), 0.0, 1.0, grid=(0.0, 90.0), unit="deg", period=360.0)),
        "h1", _apply_heel,
        physics="Anode heel: fluence falls toward the anode along the anode-cathode axis, "
                "exp(h1 u + h2 u^2), u in half-sides (docs: simulation.md, 'Heel effect').",
        covariate="position along the anode-cathode axis", separating="rotate the tube 180°"),
    PhysicsTerm(
        "inverse_square", "fluence",
        (P("strength", 0.0, (0.0, 0.5), 0.02, 2e-3), P("foot_x", 0.0, (-0.8, 0.8), 0.0, 0.02),
         P("foot_y", 0.0, (-0.8, 0.8), 0.0, 0.02)),
        "strength", _apply_inverse_square,
        physics="Inverse square and obliquity: cos^3 of the angle from the X-ray foot point, "
                "(1 + s rho^2)^(-3/2), s = (half diagonal / SDD)^2 (docs: simulation.md, 'Inverse square').",
        covariate="radius about the X-ray foot point", separating="SDD series (f-number does not change it)"),
    PhysicsTerm(
        "scatter", "primary",
        (P("amplitude", 0.0, (0.0, 2.0), 0.05, 5e-3),
         P("sigma_mm", 2.0, (0.3, 30.0), 2.0, 0.1, grid=(1.0, 2.0, 4.0, 8.0), unit="mm")),
        "amplitude", _apply_scatter,
        physics="Object scatter: a low-frequency haze A [(I T (-ln T)) ⊛ G_sigma] under and beside "
                "thick parts (docs: simulation.md, 'Object scatter').",
        covariate="blurred thickness (neighbourhood p)", separating="air-gap or field-size series; beam-stop discs",
        linear_params=("amplitude",)),
    PhysicsTerm(
        "focal_spot_shape", "psf",
        (P("half_separation_mm", 0.0, (0.0, 3.0), 0.4, 0.02, unit="mm"),
         P("axis_deg", 0.0, (-360.0, 360.0), 0.0, 1.0, grid=(0.0, 90.0), unit="deg", period=180.0)),
        "half_separation_mm", _apply_focal_spot_shape,
        physics="Two-lobed focal spot (line focus): 1/2[N(-a) + N(+a)] along one axis, scaled by "
                "M - 1 at the detector; anisotropic 'W'-shaped edge residual "
                "(docs: simulation.md, 'Focal-spot shape').",
        covariate="edge orientation", separating="two object heights × two edge orientations; pinhole",
        even_in_main=True),
    PhysicsTerm(
        "veiling_glare", "psf",
        (P("eta", 0.0, (0.0, 0.5), 0.02, 2e-3),
         P("range_mm", 1.0, (0.05, 20.0), 1.0, 0.05, grid=(0.2, 0.5, 1.0, 2.0, 4.0, 8.0), unit="mm")),
        "eta", _apply_veiling_glare,
        physics="Screen veiling glare: long exponential PSF tail (1 - eta) G + eta exp(-r/w)/(2 pi w^2) "
                "from grain scatter, backing reflection and light piping "
                "(docs: simulation.md, 'Veiling glare').",
        covariate="signed distance to edges", separating="thin high-Z edge without scatterer",
        linear_params=("eta",)),
    PhysicsTerm(
        "mirror_ghost", "psf",
        (P("epsilon", 0.0, (0.0, 0.3), 0.02, 2e-3),
         P("shift_mm", 0.5, (-5.0, 5.0), 0.5, 0.01,
           grid=(-1.6, -1.2, -0.8, -0.6, -0.4, -0.2, 0.2, 0.4, 0.6, 0.8, 1.2, 1.6), unit="mm"),
         P("axis_deg", 0.0, (-360.0, 360.0), 0.0, 1.0, grid=(0.0, 90.0), unit="deg", period=360.0)),
        "epsilon", _apply_mirror_ghost,
        physics="Mirror ghost: the front face of a back-silvered mirror adds a faint shifted copy "
                "eps L(q + d), eps ≈ 6.6 %, d 1.5-3 mm (docs: simulation.md, 'Mirror ghost').",
        covariate="residual autocorrelation at lag d", separating="front-surface mirror",
        linear_params=("epsilon",)),
    PhysicsTerm(
        "lens_distortion", "optics",
        (P("k1", 0.0, (-0.1, 0.1), 0.005, 5e-4),),
        "k1", _apply_lens_distortion,
        physics="Radial lens distortion q_d = q (1 + k1 rho^2) about the image centre; edge "
                "dipoles growing with radius (docs: simulation.md, 'Lens distortion').",
        covariate="radius × edge direction", separating="grid phantom",
        linear_in_light=True),
    PhysicsTerm(
        "vignetting", "optics",
        (P("k1", 0.0, (-0.8, 0.3), -0.02, 2e-3), P("k2", 0.0, (-0.8, 0.3), -0.02, 2e-3),
         P("centre_x", 0.0, (-0.8, 0.8), 0.0, 0.02), P("centre_y", 0.0, (-0.8, 0.8), 0.0, 0.02)),
        "k1", _apply_vignetting,
        physics="Lens vignetting 1 + k1 rho^2 + k2 rho^4 about the optical centre "
                "(docs: simulation.md, 'Vignetting').",
        covariate="radius about the optical centre", separating="flats at two f-numbers",
        linear_params=("k1", "k2"), linear_in_light=True),
    PhysicsTerm(
        "detector_gamma", "camera",
        (P("kappa", 0.0, (-0.3, 0.3), 0.01, 1e-3),),
        "kappa", _apply_detector_gamma,
        physics="Non-linear camera response DN = b + K e (1 - kappa e), e relative to the open "
                "field (docs: simulation.md, 'Detector gamma').",
        covariate="expected intensity", separating="exposure series / photon transfer",
        linear_params=("kappa",)),
)

LIBRARY_BY_NAME: dict[str, PhysicsTerm] = {t.name: t for t in LIBRARY}


def get_term(name: str) -> PhysicsTerm:
    """Look a term up by name; unknown names raise a one-line ParameterError with a suggestion."""
    from difflib import get_close_matches

    from ..errors import ParameterError

    if name in LIBRARY_BY_NAME:
        return LIBRARY_BY_NAME[name]
    close = get_close_matches(name, list(LIBRARY_BY_NAME), n=1) or \
        [known for known in LIBRARY_BY_NAME if name and name.lower() in known][:1]
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    raise ParameterError(f"unknown effect {name!r}{hint}; known: {', '.join(LIBRARY_BY_NAME)}")


def validate_params(term: PhysicsTerm, params: dict[str, float]) -> dict[str, float]:
    """Complete ``params`` with null values and check names and prior ranges (one-line errors)."""
    from ..errors import ParameterError

    full = term.null_params()
    for key, value in params.items():
        if key not in full:
            raise ParameterError(f"effect {term.name}: unknown parameter {key!r}; "
                                 f"known: {', '.join(term.param_names)}")
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise ParameterError(f"effect {term.name}: {key} must be a number, got {value!r}") from None
        lo, hi = term.spec(key).prior
        if not (np.isfinite(value) and lo <= value <= hi):
            raise ParameterError(f"effect {term.name}: {key}={value} outside its range [{lo}, {hi}]")
        full[key] = value
    return full
