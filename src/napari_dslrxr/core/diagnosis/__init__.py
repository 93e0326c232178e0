"""Mismatch diagnosis: what the base model of a scene leaves out of a recording, and its report.

* :mod:`.mismatch` - :func:`diagnose` by phases: prepare, base fit, search, final checks;
* :mod:`.result` - options and results; :mod:`.fitting` - layout, problem, least squares;
* :mod:`.locating` - residual profiles and maps; :mod:`.acceptance` - rank, compare, accept;
* :mod:`.repeats` - repeated frames of a plate edge (:func:`diagnose_edge_repeats`);
* :mod:`.noise` - variance law and noise power spectrum (prewhitening), from repeats or the
  residual;
* :mod:`.terms` - registration, generic smooth competitors and the scene's physical bounds;
* :mod:`.structure` - tests of the final residual ("unexplained" with signature and location);
* :mod:`.report` - ``diagnosis.json``, residual TIFFs and the offline ``report.html``.

Builds on :mod:`napari_dslrxr.core.simulation`.
"""

from __future__ import annotations

from .._lazy import lazy_exports

#: Public names, by the module that defines them (imported on first use).
_PUBLIC: dict[str, tuple[str, ...]] = {
    "result": ("DiagnosisOptions", "AddedTerm", "DiagnosisResult"),
    "mismatch": ("BASE_FREE", "auto_binning", "parse_binning", "diagnose", "diagnose_scene"),
    "locating": ("residual_profiles", "multiscale_maps"),
    "repeats": ("clean_repeats", "noise_model_from_repeats", "edge_object_from_image", "diagnose_edge_repeats"),
    "noise": ("NoiseModel", "estimate_from_residual", "estimate_from_noise_sample", "variogram"),
    "terms": ("REGISTRATION", "GENERIC_COMPETITORS", "physical_bounds", "inverse_square_strength"),
    "structure": ("structure_tests", "flagged_regions"),
    "report": ("PROFILE_LABELS", "residual_maps_figure", "profiles_figure", "write_png_bytes",
        "render_html", "write_report"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
