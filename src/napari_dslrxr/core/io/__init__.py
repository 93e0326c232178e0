"""Files in and out: image readers and writers, DICOM DX export and provenance sidecars.

* :mod:`.images` - the image records, format tables, size limits and checks every reader shares
  (:func:`validate_image`);
* :mod:`.readers` - checked readers for TIFF, PNG and DICOM, and structured (TOML/JSON) files;
* :mod:`.raw` - camera raw: the linear RGB and the CFA planes;
* :mod:`.writers` - atomic TIFF/PNG writers and input checksums;
* :mod:`.dicom` - the DICOM DX writer with deterministic UIDs;
* :mod:`.report_files` - figures as PNG bytes and text reports, written atomically;
* :mod:`.provenance` - the JSON sidecar written beside every output (parameters, version, input
  checksums, timings);
* :mod:`.input_kind` - whether an input is a camera frame (linear light) or a display radiograph
  (bone bright): the one rule ``dslrxr run``, the reader and the contrast widget use.

Depends only on :mod:`napari_dslrxr.core.errors`; every other area builds on it.
"""

from __future__ import annotations

from .._lazy import lazy_exports

#: Public names, by the module that defines them (imported on first use).
_PUBLIC: dict[str, tuple[str, ...]] = {
    "images": ("RAW_EXTENSIONS", "TIFF_EXTENSIONS", "PNG_EXTENSIONS", "DICOM_EXTENSIONS",
        "MIN_SIDE_PX", "DEFAULT_MAX_PIXELS", "max_pixels_limit", "RawFrame", "LoadedImage", "validate_image"),
    "readers": ("read_image", "read_structured_file"),
    "raw": ("read_raw", "postprocess_linear"),
    "writers": ("file_sha256", "known_sha256", "remember_sha256", "check_not_an_input", "atomic_write", "write_tiff", "write_png"),
    "dicom": ("DX_FOR_PRESENTATION", "ALLOWED_PATIENT_FIELDS", "deterministic_uid", "write_dicom_dx"),
    "report_files": ("figure_png", "write_text", "report_folder"),
    "provenance": ("sidecar_path", "to_jsonable", "describe_inputs", "library_versions", "write_sidecar"),
    "input_kind": ("CAMERA", "DISPLAY", "INPUT_KINDS", "InputKind", "InputParams", "decide_input_kind",
        "input_kind_of"),
}

__all__, __getattr__, __dir__ = lazy_exports(__name__, _PUBLIC)
