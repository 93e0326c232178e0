"""File in, outputs and sidecar out: the one place.

Every command that reads a file and writes results goes through here, so every output gets the
same atomic write and the same JSON sidecar (parameters, version, input checksums, timings):

* :func:`write_output` - one output file (an image array, written as TIFF, or any file through
  a writer) and its sidecar: what ``dslrxr denoise``, ``deconvolve``, ``psf fit``, ``psf
  kernel`` and ``simulate`` write;
* :func:`run_file` - ``dslrxr run`` for one input: read it, decide its kind, prepare (or reuse)
  the flat reference and the PSF kernel, run :func:`~.pipeline.process_frame` (or the display
  path), and write the TIFF, PNG preview and optional DICOM DX with :func:`write_outputs`.

The frame itself (the stages and their order) is :mod:`.pipeline`'s; this module only adds the
files around it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from .errors import InputError, OutputError, ParameterError
from .params import PipelineParams, params_to_dict, params_to_toml, validate_params
from .pipeline import PipelineResult, impulse_record, process_display_radiograph, process_frame
from .stages.flatfield import FlatReference, prepare_flat_reference


def write_output(path: str | os.PathLike, content: np.ndarray | Callable[[Path], object], *, stage: str,
                 parameters, inputs: Sequence[str | os.PathLike] = (), timings_s: dict | None = None,
                 results: dict | None = None, description: str | None = None,
                 resolution_px_per_mm: float | None = None) -> Path:
    """Write one output and its JSON sidecar (``<path>.json``); return ``path``.

    Parameters
    ----------
    path : path-like
        The output file; its folder must exist. Never one of ``inputs``.
    content : ndarray or callable
        An image array, written as TIFF (:func:`~.io.writers.write_tiff`, with ``description``
        and ``resolution_px_per_mm``); or a function that writes ``path`` itself (atomically,
        refusing to overwrite an input), e.g. a PSF model's or a PNG writer.
    stage, parameters, inputs, timings_s, results
        The sidecar's record (:func:`~.io.provenance.write_sidecar`); ``inputs`` are checksummed.
    """
    from .io import write_tiff
    from .io.provenance import write_sidecar

    path = Path(path)
    if callable(content):
        content(path)
    else:
        write_tiff(path, content, description=description, inputs=inputs,
                   resolution_px_per_mm=resolution_px_per_mm)
    write_sidecar(path, stage=stage, parameters=parameters, inputs=inputs, timings_s=timings_s, results=results)
    return path


def output_paths(input_path: str | os.PathLike, out_dir: str | os.PathLike,
                 params: PipelineParams) -> dict[str, Path]:
    """The files :func:`run_file` writes for one input (``<stem>_dslrxr.tif`` etc.)."""
    stem = Path(input_path).stem + "_dslrxr"
    out_dir = Path(out_dir)
    paths = {}
    if params.output.tiff:
        paths["tiff"] = out_dir / f"{stem}.tif"
    if params.output.png_preview:
        paths["png"] = out_dir / f"{stem}.png"
    if params.output.dicom:
        paths["dicom"] = out_dir / f"{stem}.dcm"
    return paths


def run_identity(input_files: Sequence[str | os.PathLike], params: PipelineParams, extra: str = "") -> str:
    """A hex digest of the input files' contents and every parameter (seeds DICOM UIDs)."""
    from .io import file_sha256

    digest = hashlib.sha256()
    for path in input_files:
        digest.update(file_sha256(path).encode())
    # how the batch was spread (the [batch] section) never changes an output; nor does the
    # [exposure] section of an uncalibrated detector (the files of earlier versions keep their UIDs)
    omit = () if params.exposure.calibrated else ("exposure",)
    digest.update(params_to_toml(params, comments=False, run_sections=False, omit=omit).encode())
    digest.update(extra.encode())
    return digest.hexdigest()


def preview_uint8(display: np.ndarray, max_side_px: int = 2048) -> np.ndarray:
    """8-bit preview of a [0, 1] image, area-downsampled so its longest side <= ``max_side_px``."""
    img = np.clip(display, 0, 1)
    h, w = img.shape[:2]
    if max_side_px and max(h, w) > max_side_px:
        f = max_side_px / max(h, w)
        img = cv2.resize(img, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_AREA)
    return np.round(img * 255).astype(np.uint8)


def write_outputs(result: PipelineResult, paths: dict[str, Path], *, inputs: Sequence[str | os.PathLike],
                  params: PipelineParams, pixel_spacing_mm: float | None = None,
                  patient: dict | None = None, uid_seed: str | None = None,
                  run_options: dict | None = None) -> list[Path]:
    """Write the TIFF / PNG / DICOM outputs of a run, each with a JSON sidecar.

    ``run_options`` (for example the deblurring geometry in mm) are recorded in each sidecar
    beside the parameters, so an output can be reproduced from its sidecar alone.

    Returns
    -------
    list of Path
        The image files written (sidecars are ``<file>.json``).
    """
    from .. import __version__
    from .io import write_png

    written = []
    sidecar_results = {**result.results, "voi_window": list(result.voi_window)}
    if run_options:
        sidecar_results["run_options"] = dict(run_options)
    if params.batch.scheduler:  # where it ran; the [batch] section never changes the bytes
        sidecar_results["batch"] = {"scheduler": params.batch.scheduler}
    description = json.dumps({"software": "napari-dslrxr", "version": __version__, "stage": "run",
                              "polarity": params.output.polarity}, sort_keys=True)
    spacing = pixel_spacing_mm or (params.output.pixel_spacing_mm or None)
    parameters = params_to_dict(params, run_sections=False)  # the same in every sidecar
    # the TIFF and the DICOM hold the same 16-bit image: converted once when both are written
    shared_uint16 = result.display_uint16() if {"tiff", "dicom"} <= paths.keys() else None
    for kind, path in paths.items():
        if kind == "tiff":
            content = shared_uint16 if shared_uint16 is not None else result.display_uint16()
        elif kind == "png":
            content = partial(write_png, data=preview_uint8(result.display, params.output.preview_max_side_px),
                              inputs=inputs)
        elif kind == "dicom":
            image = shared_uint16 if shared_uint16 is not None else result.display_uint16()
            content = partial(_write_dicom, image=image, result=result, params=params, spacing=spacing,
                              uid_seed=uid_seed, patient=patient, inputs=inputs)
        else:  # pragma: no cover
            raise OutputError(f"{path}: unknown output kind {kind!r}")
        write_output(path, content, stage="run", parameters=parameters,
                     inputs=inputs, timings_s=result.timings_s, results=sidecar_results, description=description,
                     resolution_px_per_mm=(1.0 / spacing) if spacing else None)
        written.append(path)
    return written


def _write_dicom(path: Path, image: np.ndarray, result: PipelineResult, params: PipelineParams, *,
                 spacing: float | None, uid_seed: str | None, patient: dict | None,
                 inputs: Sequence[str | os.PathLike]) -> None:
    """The DICOM DX output of a run (``image``: its uint16 display image); its UIDs derive from
    ``uid_seed`` (default: the inputs and parameters)."""
    from .io.dicom import write_dicom_dx
    from .stages.exposure_index import dicom_exposure_tags

    write_dicom_dx(path, image, pixel_spacing_mm=spacing,
                   uid_seed=uid_seed or run_identity(inputs, params), patient=patient,
                   series_description="napari-dslrxr processed radiograph", inputs=inputs,
                   attributes=dicom_exposure_tags(result.results.get("exposure_index")))


def load_frames(paths: Sequence[str | os.PathLike]) -> list[np.ndarray]:
    """Read reference frames (flats, darks) as arrays in counts."""
    from .io import read_image

    return [read_image(p).data for p in paths]


def input_black_level(input_path: str | os.PathLike, params: PipelineParams):
    """The dark offset :func:`run_file` uses without dark frames (0 for camera raw, whose
    decoded RGB has the black level subtracted already; else the parameter)."""
    from .io import RAW_EXTENSIONS

    return 0.0 if Path(input_path).suffix.lower() in RAW_EXTENSIONS else params.flatfield.black_level_counts


def _file_versions(paths: Sequence[str | os.PathLike]) -> tuple:
    """Each path with its size and modification time (ns): a cache keyed by it never serves what
    was prepared from an earlier version of the file (a dask worker outlives a run, and the user
    may replace the flat between runs)."""
    versions = []
    for path in paths:
        try:
            info = os.stat(path)
            versions.append((str(path), info.st_size, info.st_mtime_ns))
        except OSError:  # reading it will say what is wrong
            versions.append((str(path), None, None))
    return tuple(versions)


def flat_reference_key(flat_paths: Sequence[str | os.PathLike], dark_paths: Sequence[str | os.PathLike],
                       shape: tuple[int, ...], offset, params: PipelineParams) -> tuple:
    """Key of a prepared :class:`FlatReference` in a ``reference_cache`` (see :func:`run_file`):
    the frames' paths and versions, the shape, the dark offset and the flat-field parameters."""
    return (_file_versions(flat_paths), _file_versions(dark_paths), tuple(shape), repr(offset),
            repr(params.flatfield))


def save_flat_reference(reference: FlatReference, folder: str | os.PathLike, key: tuple = ()) -> Path:
    """Write a prepared reference to the new folder ``folder`` (one ``.npy`` per array, its
    counts and its ``key``, :func:`flat_reference_key`), so other processes can map it with
    :func:`load_flat_reference` instead of preparing it again. The folder appears complete or
    not at all (written beside it, then renamed)."""
    import shutil

    folder = Path(folder)
    partial_folder = folder.with_name(folder.name + ".partial")
    partial_folder.mkdir()
    try:
        for name in _REFERENCE_ARRAYS:
            array = getattr(reference, name)
            if array is not None:
                np.save(partial_folder / f"{name}.npy", np.ascontiguousarray(array), allow_pickle=False)
        counts = {field.name: getattr(reference, field.name) for field in dataclasses.fields(reference)
                  if field.name not in _REFERENCE_ARRAYS}  # every other field: none can be dropped
        (partial_folder / "counts.json").write_text(json.dumps({**counts, "key": repr(key)}), encoding="utf-8")
        os.replace(partial_folder, folder)
    except BaseException:
        shutil.rmtree(partial_folder, ignore_errors=True)
        raise
    return folder


def load_flat_reference(folder: str | os.PathLike, key: tuple = ()) -> FlatReference:
    """A reference written by :func:`save_flat_reference` with ``key``, its arrays
    memory-mapped read-only (processes on one machine share the pages; nothing is copied).

    Raises
    ------
    OSError, ValueError
        The folder is missing (not visible from this machine), not a reference, or one
        prepared for another key.
    """
    folder = Path(folder)
    counts = json.loads((folder / "counts.json").read_text(encoding="utf-8"))
    if counts.get("key") != repr(key):
        raise ValueError(f"{folder}: a flat reference prepared for other frames or parameters")
    del counts["key"]
    arrays = {name: np.load(folder / f"{name}.npy", mmap_mode="r", allow_pickle=False)
              if (folder / f"{name}.npy").exists() else None for name in _REFERENCE_ARRAYS}
    return FlatReference(**arrays, **counts)


#: The :class:`FlatReference` fields a shared reference keeps as memory-mapped ``.npy`` files.
_REFERENCE_ARRAYS = ("offset", "denominator", "scale")


def psf_kernel_key(psf_path: str | os.PathLike, source_to_object_mm: float, source_to_detector_mm: float) -> tuple:
    """Key of a PSF kernel in a ``reference_cache`` (see :func:`run_file`): the model file's
    path and version and the geometry."""
    return ("psf", *_file_versions([psf_path]), float(source_to_object_mm), float(source_to_detector_mm))


def _psf_kernel(psf_path: str | os.PathLike, source_to_object_mm: float | None,
                source_to_detector_mm: float | None, cache: dict | None) -> np.ndarray:
    """The PSF kernel at this geometry: from ``cache`` (keyed by :func:`psf_kernel_key`), or
    read from the model file and stored there."""
    if source_to_object_mm is None or source_to_detector_mm is None:
        raise ParameterError("a PSF model needs the object's geometry: both source_to_object_mm and source_to_detector_mm")
    key = psf_kernel_key(psf_path, source_to_object_mm, source_to_detector_mm)
    kernel = cache.get(key) if cache is not None else None
    if kernel is None:
        from .psf import load_psf

        kernel = load_psf(psf_path).kernel(source_to_object_mm, source_to_detector_mm)
        if cache is not None:
            cache[key] = kernel
    return kernel


def flat_reference_from_files(flat_paths: Sequence[str | os.PathLike], dark_paths: Sequence[str | os.PathLike],
                              offset, params: PipelineParams, *, shape: tuple[int, ...] | None = None,
                              shape_of: str = "the first reference frame") -> tuple[tuple, FlatReference]:
    """Read the flats and darks and prepare their flat reference (dark offset ``offset`` when
    there is no dark): the one preparation of :func:`run_file` and of a batch that prepares it
    once for its workers. The frames must all have ``shape`` (default: the first frame's);
    ``shape_of`` says whose, for the message. Returns the reference's key
    (:func:`flat_reference_key`) and the reference."""
    flats, darks = load_frames(flat_paths), load_frames(dark_paths)
    if shape is None:
        shape = (*flats, *darks)[0].shape
    for name, frame_paths, frames in (("flat", flat_paths, flats), ("dark", dark_paths, darks)):
        for p, f in zip(frame_paths, frames, strict=True):
            if f.shape != shape:
                raise InputError(p, f"{name} frame shape {f.shape} differs from {shape_of}")
    return (flat_reference_key(flat_paths, dark_paths, shape, offset, params),
            prepare_flat_reference(shape, flats=flats, darks=darks, black_level=offset, params=params.flatfield))


def run_file(input_path: str | os.PathLike, out_dir: str | os.PathLike, *,
             params: PipelineParams | None = None, flat_paths: Sequence[str | os.PathLike] = (),
             dark_paths: Sequence[str | os.PathLike] = (), psf_path: str | os.PathLike | None = None,
             source_to_object_mm: float | None = None, source_to_detector_mm: float | None = None,
             reference: Callable[[tuple], FlatReference | None] | None = None, patient: dict | None = None,
             progress: Callable[[int, int], object] | None = None,
             reference_cache: dict | None = None,
             warn: Callable[[str], object] | None = None) -> list[Path]:
    """Read one frame, run the pipeline and write its outputs (with sidecars).

    The input's kind (:func:`~napari_dslrxr.core.io.input_kind.decide_input_kind` under
    ``params.input.input_kind``) picks the path: a camera frame goes through the whole chain,
    a display radiograph (a CR/DX DICOM...) through :func:`run_display_pipeline` only. The
    decision is recorded in the sidecar (``results.input_kind``).

    Parameters
    ----------
    input_path : path-like
        Camera raw, TIFF, PNG or DICOM.
    out_dir : path-like
        Existing output folder.
    params : PipelineParams, optional
    flat_paths, dark_paths : sequence of path-like
        Reference frames.
    psf_path : path-like, optional
        PSF model JSON (:func:`napari_dslrxr.core.psf.load_psf`); with the two distances it
        turns on deblurring.
    source_to_object_mm, source_to_detector_mm : float, optional
    reference : callable, optional
        A batch's prepared flat reference: called with the reference's key
        (:func:`flat_reference_key`) when the flat-field stage starts (impulse removal runs
        first, so a worker need not wait for a reference prepared elsewhere meanwhile); returns
        it, or None when it has none for that key (prepared here then).
    patient : dict, optional
        DICOM patient fields supplied by the user (``PatientName``, ``PatientID``...).
    reference_cache : dict, optional
        References prepared by earlier calls: flat
        references keyed by :func:`flat_reference_key`, PSF kernels by
        :func:`psf_kernel_key`; a batch passes one dict so its flats, darks and PSF model are
        read and prepared once, not once per file.
    warn : callable, optional
        Receives one line (without the file name) when the input kind was guessed or a given
        reference frame or PSF does not apply to the input's kind.

    Returns
    -------
    list of Path
        Files written.
    """
    from .io.input_kind import DISPLAY, input_kind_of
    from .io import read_image

    params = validate_params(params or PipelineParams())
    loaded = read_image(input_path)
    kind = input_kind_of(loaded, params.input.input_kind)
    if warn is not None and kind.message():
        warn(kind.message())
    if kind.kind == DISPLAY:
        return _run_display_file(loaded, out_dir, kind, params=params, flat_paths=flat_paths,
                                 dark_paths=dark_paths, psf_path=psf_path, patient=patient,
                                 progress=progress, warn=warn, source_to_object_mm=source_to_object_mm,
                                 source_to_detector_mm=source_to_detector_mm)
    black = None
    image = loaded.data
    impulses_removed = None
    t_cfa = time.perf_counter()
    if loaded.format == "raw":
        black = 0.0  # rawpy's linear RGB has the black level subtracted already
        if loaded.raw is not None and params.impulse.passes_grey > 0 and params.impulse.space in ("auto", "cfa"):
            # stage (i) on the Bayer planes, before demosaicing spreads each zinger
            from .stages.impulse import clean_raw_frame

            image, cfa = clean_raw_frame(loaded, params.impulse)
            impulses_removed = impulse_record(cfa, space="cfa")
    t_cfa = time.perf_counter() - t_cfa
    kernel = None
    if psf_path is not None:
        kernel = _psf_kernel(psf_path, source_to_object_mm, source_to_detector_mm, reference_cache)
    offset = black if black is not None else params.flatfield.black_level_counts

    def flat_reference() -> FlatReference:  # when the flat-field stage starts
        key = flat_reference_key(flat_paths, dark_paths, image.shape, offset, params)
        prepared = reference_cache.get(key) if reference_cache is not None else None
        if prepared is None and reference is not None:
            prepared = reference(key)
        if prepared is None:
            _, prepared = flat_reference_from_files(flat_paths, dark_paths, offset, params, shape=image.shape,
                                                 shape_of=f"{input_path}'s {image.shape}")
        if reference_cache is not None:
            reference_cache[key] = prepared
        return prepared

    result = process_frame(image, params=params, reference=flat_reference, psf_kernel=kernel, progress=progress,
                           impulses_removed=impulses_removed)
    result.results["input_kind"] = kind.as_record()
    if impulses_removed is not None:
        result.timings_s["impulse"] = t_cfa
    extra = f"{source_to_object_mm}|{source_to_detector_mm}|{json.dumps(patient or {}, sort_keys=True)}"
    return _write_file_outputs(result, loaded, out_dir, extra, params=params, flat_paths=flat_paths,
                               dark_paths=dark_paths, psf_path=psf_path, patient=patient,
                               source_to_object_mm=source_to_object_mm,
                               source_to_detector_mm=source_to_detector_mm)


def _run_display_file(loaded, out_dir: str | os.PathLike, kind, *, params: PipelineParams,
                      flat_paths: Sequence[str | os.PathLike], dark_paths: Sequence[str | os.PathLike],
                      psf_path: str | os.PathLike | None, patient: dict | None,
                      progress: Callable[[int, int], object] | None,
                      warn: Callable[[str], object] | None, source_to_object_mm: float | None = None,
                      source_to_detector_mm: float | None = None) -> list[Path]:
    """:func:`run_file` for a display radiograph: the display path, then the same outputs.

    References given for the batch are checksummed and recorded (with their roles and the
    deblurring geometry) like a camera frame's, so a rerun compares them the same way."""
    ignored = [what for what, given in (("flat/dark frames", flat_paths or dark_paths), ("the PSF", psf_path))
               if given]
    if ignored and warn is not None:
        warn(f"{' and '.join(ignored)} not applied: a display radiograph is not linear light")
    result = process_display_radiograph(loaded.data, params=params, progress=progress)
    result.results["input_kind"] = kind.as_record()
    result.results.update({"impulse": "skipped (display radiograph)", "flatfield": "skipped (display radiograph)",
                           "deblur": "skipped (display radiograph)"})
    extra = f"display|{json.dumps(patient or {}, sort_keys=True)}"
    return _write_file_outputs(result, loaded, out_dir, extra, params=params, flat_paths=flat_paths,
                               dark_paths=dark_paths, psf_path=psf_path, patient=patient,
                               source_to_object_mm=source_to_object_mm,
                               source_to_detector_mm=source_to_detector_mm)


def _write_file_outputs(result: PipelineResult, loaded, out_dir: str | os.PathLike, extra: str, *,
                        params: PipelineParams, flat_paths: Sequence[str | os.PathLike],
                        dark_paths: Sequence[str | os.PathLike], psf_path: str | os.PathLike | None,
                        patient: dict | None, source_to_object_mm: float | None,
                        source_to_detector_mm: float | None) -> list[Path]:
    """The outputs of :func:`run_file` (either path): the references by role and the
    deblurring geometry go into the sidecars; ``extra`` seeds the DICOM UIDs with the inputs'
    checksums and the parameters."""
    # which of the checksummed inputs are flats and darks (a rerun compares them by role)
    result.results["reference_frames"] = {"flat": len(flat_paths), "dark": len(dark_paths)}
    inputs = [loaded.path, *map(Path, flat_paths), *map(Path, dark_paths), *([Path(psf_path)] if psf_path else [])]
    spacing = loaded.metadata.get("pixel_spacing_mm")
    spacing = float(spacing[0]) if spacing else None
    run_options = None
    if psf_path is not None and source_to_object_mm is not None and source_to_detector_mm is not None:
        run_options = {"source_to_object_mm": float(source_to_object_mm),
                       "source_to_detector_mm": float(source_to_detector_mm)}
    return write_outputs(result, output_paths(loaded.path, out_dir, params), inputs=inputs, params=params,
                         pixel_spacing_mm=spacing, patient=patient, uid_seed=run_identity(inputs, params, extra),
                         run_options=run_options)
