"""Headless core of napari-dslrxr: plain functions and small dataclasses over numpy arrays.

Nothing in this package imports Qt or napari; every stage is usable from scripts and CI.

Where things are (data flows down this list; nothing imports a module above it):

* :mod:`.rerun` - whether a file's finished outputs match a rerun (``dslrxr run`` skips or redoes it);
* :mod:`.files` - file in, outputs and sidecar out: the one place (``dslrxr run`` per file, and the
  output + sidecar of every command);
* :mod:`.pipeline` - the whole pipeline over a frame: the stages in order;
* :mod:`.display` - the display end of the chain (VOI scaling, dynamic range, contrast, display
  curve), shared by the pipeline, the display-radiograph path and the contrast widget;
* :mod:`.params` - the pipeline parameters, one dataclass per TOML section, and the TOML file;
* :mod:`.stages` - the pipeline stages: impulse removal, flat field, region (screen, collimation,
  VOI), deconvolution, dynamic range, multiscale contrast;
* :mod:`.psf` - the blur model and its fit to edge radiographs (``dslrxr psf``);
* :mod:`.diagnosis` - mismatch diagnosis of a recording against its scene, and its report
  (``dslrxr diagnose``), built on :mod:`.simulation`;
* :mod:`.simulation` - the imaging-chain simulator, its library of physical effects, and the
  synthetic DSLR frames (``dslrxr simulate``, sample data, demo);
* :mod:`.metrics` - image-quality figures (percentage error, global contrast factor);
* :mod:`.io` - image readers and writers, DICOM DX, provenance sidecars;
* :mod:`.errors` - the exceptions every area raises for bad input, parameters or outputs.

The names below are the public entry points of each area; each subpackage re-exports the rest of
its public names.
"""

from __future__ import annotations

from ._lazy import lazy_exports

#: Public names, by the module that defines them (imported on first use).
_PUBLIC: dict[str, tuple[str, ...]] = {
    "errors": ("DslrxrError", "InputError", "OutputError", "ParameterError"),
    "io": ("LoadedImage", "RawFrame", "atomic_write", "decide_input_kind", "read_image", "read_raw",
        "sidecar_path", "validate_image", "write_dicom_dx", "write_png", "write_sidecar", "write_tiff"),
    "stages": ("ContrastParams", "DeconvolutionParams", "DynamicRangeParams", "FlatFieldParams",
        "FlatReference", "ImpulseParams", "ImpulseResult", "Region", "RegionParams", "apply_flat_field",
        "deconvolve", "detect_collimation", "detect_screen", "enhance_contrast", "prepare_flat_reference",
        "rectify", "reduce_dynamic_range", "remove_impulses", "remove_impulses_cfa", "sigmoid_lut",
        "voi_window"),
    "psf": ("EdgeImage", "PSFModel", "fit_edges", "load_edge_config", "load_psf", "save_psf"),
    "simulation": ("LIBRARY", "PhantomFrames", "PhysicsTerm", "Scene", "get_term", "load_scene",
        "make_dslr_radiograph", "parse_scene", "simulate_recording"),
    "diagnosis": ("DiagnosisOptions", "DiagnosisResult", "diagnose", "diagnose_scene", "write_report"),
    "metrics": ("global_contrast_factor", "percentage_error"),
    "params": ("BatchParams", "DeblurParams", "OutputParams", "PipelineParams", "default_params_toml", "load_params",
        "params_from_dict", "params_to_dict", "params_to_toml", "save_params", "validate_params"),
    "pipeline": ("PIPELINE_STAGES", "PipelineResult", "enhance_radiograph", "process_display_radiograph",
        "process_frame", "run_display_pipeline", "run_pipeline"),
    "display": ("apply_display_stages", "scale_display_radiograph"),
    "files": ("run_file", "write_output"),
    "rerun": ("RerunCheck", "check_finished"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
