"""Mismatch diagnosis: what the base model of a scene leaves out of a recording, and its report.

* :mod:`.mismatch` - residual maps and profiles, and the search that locates the mismatch,
  compares candidate physics terms by their refits and names the one that explains it;
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
    "mismatch": ("BASE_FREE", "DiagnosisOptions", "AddedTerm", "DiagnosisResult", "auto_binning",
        "parse_binning", "residual_profiles", "multiscale_maps", "diagnose", "diagnose_scene", "clean_repeats",
        "noise_model_from_repeats", "edge_object_from_image", "diagnose_edge_repeats"),
    "noise": ("NoiseModel", "estimate_from_residual", "estimate_from_noise_sample", "variogram"),
    "terms": ("REGISTRATION", "GENERIC_COMPETITORS", "physical_bounds", "inverse_square_strength"),
    "structure": ("structure_tests", "flagged_regions"),
    "report": ("PROFILE_LABELS", "residual_maps_figure", "profiles_figure", "write_png_bytes",
        "render_html", "write_report"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
