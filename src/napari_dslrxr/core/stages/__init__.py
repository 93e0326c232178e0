"""The pipeline stages, in the order a frame goes through them.

* :mod:`.impulse` - impulse-noise (zinger) removal in HSV counts or on the CFA planes;
* :mod:`.flatfield` - dark subtraction and gain (flat-field) correction from open-beam frames;
* :mod:`.region` - the region's parameters and type, its rectification and the VOI window;
  :mod:`.screen` - the screen in the photograph, found on evidence; :mod:`.collimation` - the
  collimated field;
* :mod:`.deconvolution` - deblurring with a known kernel (adaptive, Wiener, regularised least squares);
  :mod:`.deblur_params` - its parameters (the one range of ``reg``); :mod:`.deblur_solvers` - the
  solvers and noise estimate; :mod:`.regularisation` - the automatic regularisation;
  :mod:`.fourier` - the padding, kernel OTF and derivative spectra they share;
* :mod:`.dynamic_range` - latitude reduction and the sigmoid display curve;
* :mod:`.contrast` - multiscale (Laplacian-pyramid) contrast enhancement.

Each stage is a plain function over numpy arrays with a parameter dataclass; the pipeline
(:mod:`napari_dslrxr.core.pipeline`) chains them.
"""

from __future__ import annotations

from .._lazy import lazy_exports

#: Public names, by the module that defines them (imported on first use).
_PUBLIC: dict[str, tuple[str, ...]] = {
    "impulse": ("MEDIAN_RESIDUAL_VARIANCE_FACTOR", "ImpulseParams", "ImpulseResult", "rgb_to_hsv_counts",
        "hsv_counts_to_rgb", "dominant_hue", "remove_impulses", "remove_impulses_cfa",
        "cfa_mask_to_mosaic", "demosaic_cleaned_raw", "clean_raw_frame"),
    "flatfield": ("FlatFieldParams", "FlatReference", "remove_bright_pulses", "combine_frames",
        "prepare_flat_reference", "apply_flat_field"),
    "region": ("RegionParams", "Region", "order_corners", "polygon_mask", "shrink_polygon",
        "direct_exposure_level", "voi_window", "rectify"),
    "screen": ("screen_evidence", "detect_screen"),
    "collimation": ("detect_collimation",),
    "deblur_params": ("METHODS", "DeconvolutionParams", "check_method", "check_reg"),
    "deblur_solvers": ("validate_kernel", "robust_range", "estimate_noise_sigma"),
    "fourier": ("gradient_spectrum", "fo_derivative_spectrum", "kernel_otf", "pad_and_taper"),
    "deconvolution": ("deconvolve_steps", "deconvolve"),
    "regularisation": ("AUTO_MAX_NOISE_GAIN", "RegularisationChoice", "estimate_regularisation",
        "model_regularisation", "choose_regularisation", "flat_noise_gain"),
    "dynamic_range": ("DynamicRangeParams", "masked_lowpass", "edge_aware_lowpass", "reduce_dynamic_range",
        "sigmoid_lut", "lut_input_range", "fit_to_display"),
    "contrast": ("ContrastParams", "auto_levels", "laplacian_pyramid", "reconstruct_pyramid",
        "robust_sigma", "map_coefficients", "enhance_contrast"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
