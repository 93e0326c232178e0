"""What a diagnosis returns (:class:`DiagnosisResult`, :class:`AddedTerm`) and its settings
(:class:`DiagnosisOptions`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class DiagnosisOptions:
    """Settings of :func:`diagnose`.

    Parameters
    ----------
    accept_delta_bic : float
        Minimum ΔBIC to accept a term (10 = "very strong", Kass & Raftery).
    max_terms : int
        At most this many terms are added.
    tile_px : int
        Tile size (pixels of the fitted grid) for the locate step.
    heldout_block_px : int
        Checkerboard block size for the held-out check (larger than the correlation length).
    max_fit_size_px : int
        With automatic binning, recordings larger than this along an axis are block-averaged,
        as long as the blur stays at least one binned pixel.
    candidates : tuple of str or None
        Library terms to consider (default: all).
    confusable_correlation : float
        Canonical correlation above which two candidates are flagged as confusable.
    compare_top : int
        Candidates (best by score) refitted and compared per round.
    ambiguity_bic : float
        A runner-up whose refitted ΔBIC is within this of the winner's makes the pair ambiguous.
    max_nfev : int
        Function-evaluation limit per least-squares fit.
    binning : int or None
        Force this block-averaging factor (default: automatic, see :func:`auto_binning`).
    pre_blur_fraction : float
        With a supersampled object or a binned fit, this fraction of the starting blur width is
        applied on the fine grid before block-averaging (avoids aliasing of sharp edges); the
        fitted width cannot go below it.
    fixed_offset_dn : float or None
        Hold the camera offset at this value (from a dark frame); default: fitted.
    noise_model_binned : (float, float) or None
        ``(K, c)`` with ``v(mu) = K mu + c`` (absolute DN) for the *binned* recording, e.g. from
        repeated frames (:func:`noise_model_from_repeats`); default: estimated from the residual.
    noise_sample_binned : ndarray or None
        A pure noise field with the binned recording's noise (e.g. the halved even/odd
        difference of repeats, binned): gives the noise power spectrum directly.
    registration : bool
        Fit shift, scale and rotation in the base model.
    """

    accept_delta_bic: float = 10.0
    max_terms: int = field(default=4, metadata={
        "help": "at most this many effects are added to the scene model", "unit": "terms", "min": 1, "max": 10})
    tile_px: int = 32
    heldout_block_px: int = 32
    max_fit_size_px: int = 512
    candidates: tuple[str, ...] | None = None
    confusable_correlation: float = 0.9
    compare_top: int = 3
    ambiguity_bic: float = 6.0
    max_nfev: int = 40
    binning: int | None = None
    noise_model_binned: tuple[float, float] | None = None
    noise_sample_binned: np.ndarray | None = None
    fixed_offset_dn: float | None = None
    pre_blur_fraction: float = 0.6
    registration: bool = True


@dataclass
class AddedTerm:
    """A term the diagnosis accepted."""

    effect: str
    params: dict[str, float]
    uncertainty: dict[str, float]
    delta_bic: float
    chi2_per_dof: float
    score: float
    likelihood_ratio: float
    heldout_gain: float
    confusable_with: list[tuple[str, float]] = field(default_factory=list)
    runner_up: str | None = None
    runner_up_delta_bic: float | None = None
    ambiguous: bool = False
    separating: str = ""
    at_bound: list[str] = field(default_factory=list)


@dataclass
class DiagnosisResult:
    """Everything the diagnosis found; :meth:`to_json` gives the ``diagnosis.json`` content."""

    base_chi2_per_dof: float
    base_bic: float
    regions: list[list[int]]
    added: list[AddedTerm]
    final_chi2_per_dof: float
    unexplained: bool
    unexplained_regions: list[list[int]]
    noise_poisson_gain_dn: float
    noise_read_dn: float
    base_params: dict[str, float]
    final_base_params: dict[str, float]
    z_base: np.ndarray
    z_final: np.ndarray
    mask: np.ndarray
    profiles_base: dict
    profiles_final: dict
    rankings: list[list[dict]]
    binning: int
    n_pixels: int
    smooth_delta_bic: float
    message: str
    registration: dict = field(default_factory=dict)
    noise: dict = field(default_factory=dict)
    structure: dict = field(default_factory=dict)
    signatures: list[str] = field(default_factory=list)
    comparisons: list[list[dict]] = field(default_factory=list)

    def to_json(self) -> dict:
        """The ``diagnosis.json`` content."""
        def term_json(a: AddedTerm) -> dict:
            out = {"effect": a.effect,
                   "params": {k: round(v, 7) for k, v in a.params.items()},
                   "uncertainty": {k: round(v, 7) for k, v in a.uncertainty.items()},
                   "delta_bic": round(a.delta_bic, 2), "chi2_per_dof": round(a.chi2_per_dof, 5),
                   "runner_up": a.runner_up,
                   "runner_up_delta_bic": None if a.runner_up_delta_bic is None else round(a.runner_up_delta_bic, 2),
                   "ambiguous": a.ambiguous}
            if a.ambiguous:
                out["separating_acquisition"] = a.separating
            if a.at_bound:
                out["at_bound"] = {k: "at bound: not an estimate" for k in a.at_bound}
            return out

        return {
            "base": {"chi2_per_dof": round(self.base_chi2_per_dof, 5), "bic": round(self.base_bic, 2)},
            "registration": {k: round(v, 6) for k, v in self.registration.items()},
            "noise": self.noise,
            "mismatch": {"regions": self.regions},
            "added": [term_json(a) for a in self.added],
            "final": {"chi2_per_dof": round(self.final_chi2_per_dof, 5)},
            "unexplained": bool(self.unexplained),
            "unexplained_signatures": self.signatures,
        }

    def details(self) -> dict:
        """Supporting numbers (noise model, rankings, comparisons, structure tests)."""
        return {
            "noise": {"poisson_gain_dn": self.noise_poisson_gain_dn, "read_noise_dn": self.noise_read_dn,
                      **self.noise},
            "base_params": self.base_params, "final_base_params": self.final_base_params,
            "binning": self.binning, "n_pixels": self.n_pixels,
            "added": [{"effect": a.effect, "score": a.score, "likelihood_ratio": a.likelihood_ratio,
                       "heldout_gain": a.heldout_gain,
                       "confusable_with": [[n, round(c, 4)] for n, c in a.confusable_with]}
                      for a in self.added],
            "rankings": self.rankings, "comparisons": self.comparisons,
            "unexplained_regions": self.unexplained_regions,
            "structure_tests": self.structure.get("tests", {}),
            "smooth_term_delta_bic": self.smooth_delta_bic, "message": self.message,
        }
