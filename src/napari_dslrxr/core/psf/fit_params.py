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


@dataclass
class EdgeFitSettings:
    """The geometry and model choices an edge fit needs beside the images (GUI and config
    defaults, ranges and help; :func:`~.edge_fit.fit_edges` takes them as arguments)."""

    source_to_object_mm: float = field(default=1000.0, metadata={
        "help": "distance from the focal spot to the edge (object)", "unit": "mm", "min": 1.0, "max": 1e5})
    source_to_detector_mm: float = field(default=1100.0, metadata={
        "help": "distance from the focal spot to the scintillator screen (detector)", "unit": "mm",
        "min": 1.0, "max": 1e5})
    pixel_pitch_mm: float = field(default=0.1, metadata={
        "help": "size of one image pixel at the screen", "unit": "mm", "min": 1e-4, "max": 100.0})
    shape_power: float = field(default=1.0, metadata={
        "help": "profile of the focal spot and of a detector tail: 1 = exponential (SABER), 2 = Gaussian "
                "(the detector core's shape is fitted)",
        "choices": (1.0, 2.0)})
