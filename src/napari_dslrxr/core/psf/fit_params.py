"""Parameters of ``dslrxr psf fit`` (TOML section ``[psf_fit]`` of the parameter file).

The edge images and their geometry come from the edge configuration file (:mod:`.edge_fit`);
this section holds the fit's tunables, so a fit tuned once reproduces from the parameter file.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..param_fields import validate_fields


@dataclass
class PsfFitParams:
    """Tunables of the joint edge fit (TOML section ``[psf_fit]``), checked on construction.

    Attributes
    ----------
    outlier_sigma : float
        Residuals beyond this many robust standard deviations are masked and the model refitted
        (dust, scratches on the edge); 0 disables the rejection.
    """

    outlier_sigma: float = field(default=5.0, metadata={
        "help": "mask residuals beyond this many robust sigmas and refit; 0 disables",
        "unit": "sigma", "min": 0.0, "max": 100.0})

    def __post_init__(self) -> None:
        validate_fields(self, "psf_fit")
