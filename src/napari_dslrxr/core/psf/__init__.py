"""Blur estimation: the source + detector PSF model and its fit to edge radiographs.

* :mod:`.model` - the PSF model (focal spot and detector blur, scaled by magnification), its
  kernels and its JSON file;
* :mod:`.edge_fit` - fitting the model to slanted-edge radiographs at several object distances,
  the edge configuration file and a synthetic edge generator.
"""

from __future__ import annotations

from .._lazy import lazy_exports

#: Public names, by the module that defines them (imported on first use).
_PUBLIC: dict[str, tuple[str, ...]] = {
    "model": ("DEFAULT_MAX_RADIUS_PX", "SUPPORT_FWHM_MULTIPLE", "DELTA_FWHM_PX", "PSF_FORMAT",
        "PSF_FORMAT_VERSION", "PARAMETER_NAMES", "fwhm_to_scale", "scale_to_fwhm", "magnification_factor",
        "sample_exponential_power", "PSFModel", "save_psf", "load_psf"),
    "edge_fit": ("DEFAULT_ESF_STEP_PX", "EdgeImage", "normalise_edge_image", "fit_edges", "EdgeConfig",
        "load_edge_config", "synthesize_edge_image"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
