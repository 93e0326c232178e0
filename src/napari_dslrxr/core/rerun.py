"""Is an input already done? A rerun redoes every file whose finished outputs do not match.

A file counts as done only when, for every output the parameters ask for, the output and its
sidecar exist, and the sidecar records this package version, the same parameters (every
section but ``[batch]``, which never changes an output), the same input checksums role by
role (the frame, its flats, darks and PSF model) and the same deblurring geometry; the
output's bytes must still have the checksum its sidecar records (so an output replaced by an
interrupted later run is never taken for the old one), and a DICOM output must name the
patient asked for. Anything else is a reason to process the file again, and the reason is
given in words.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from .params import RUN_ONLY_SECTIONS, PipelineParams, params_to_dict


@dataclass
class RerunCheck:
    """Whether an input's outputs are finished for this request.

    Attributes
    ----------
    done : bool
        True: every output matches; the file can be skipped.
    reason : str
        Why it is done, or why it must be (re)processed.
    new : bool
        True when none of its outputs exists yet (a first run, not a redo).
    """

    done: bool
    reason: str
    new: bool = False


def _sha(path: str | os.PathLike, checksums: dict | None) -> str:
    from .io import file_sha256

    key = os.fspath(path)
    if checksums is not None and key in checksums:
        return checksums[key]
    value = file_sha256(path)
    if checksums is not None:
        checksums[key] = value
    return value


def _flat_items(data, prefix: str = "") -> dict:
    if isinstance(data, dict):
        out = {}
        for key, value in data.items():
            out.update(_flat_items(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: data}


def _parameter_change(recorded: dict, wanted: dict) -> str | None:
    """``None`` when equal, else a short list of what changed (``contrast.bone_contrast 1.0 -> 1.5``)."""
    old, new = _flat_items(recorded), _flat_items(wanted)
    changed = sorted(k for k in old.keys() | new.keys() if old.get(k, "(absent)") != new.get(k, "(absent)"))
    if not changed:
        return None
    shown = [f"{k} {json.dumps(old.get(k, '(absent)'))} -> {json.dumps(new.get(k, '(absent)'))}" for k in changed[:3]]
    more = f" and {len(changed) - 3} more" if len(changed) > 3 else ""
    return "parameters changed: " + ", ".join(shown) + more


def _dicom_patient_change(path: Path, patient: dict | None) -> str | None:
    import pydicom

    from .io.dicom import ALLOWED_PATIENT_FIELDS

    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True, specific_tags=list(ALLOWED_PATIENT_FIELDS))
    except Exception:  # an unreadable DICOM output is simply redone
        return f"{path.name} cannot be read"
    for key in ALLOWED_PATIENT_FIELDS:
        if str(ds.get(key, "") or "") != str((patient or {}).get(key, "") or ""):
            return "patient fields changed"
    return None


def check_finished(input_path: str | os.PathLike, out_dir: str | os.PathLike, params: PipelineParams, *,
                   flat_paths: Sequence[str | os.PathLike] = (), dark_paths: Sequence[str | os.PathLike] = (),
                   psf_path: str | os.PathLike | None = None, source_to_object_mm: float | None = None,
                   source_to_detector_mm: float | None = None, patient: dict | None = None,
                   checksums: dict | None = None) -> RerunCheck:
    """Decide whether :func:`~napari_dslrxr.core.files.run_file` would write what is already there.

    Parameters
    ----------
    input_path, out_dir, params, flat_paths, dark_paths, psf_path, source_to_object_mm, source_to_detector_mm, patient
        The request, as given to :func:`~napari_dslrxr.core.files.run_file`.
    checksums : dict, optional
        SHA-256 by path, filled as files are hashed (a batch hashes its references once).

    Returns
    -------
    RerunCheck
    """
    from .. import __version__
    from .files import output_paths
    from .io.provenance import sidecar_path, to_jsonable

    expected = output_paths(input_path, out_dir, params)
    if not expected:
        return RerunCheck(False, "no outputs asked for", new=True)
    present = {kind: p for kind, p in expected.items() if p.exists()}
    if not present:
        return RerunCheck(False, "no outputs yet", new=True)
    for path in expected.values():
        if path not in present.values():
            return RerunCheck(False, f"{path.name} missing")
        if not sidecar_path(path).exists():
            return RerunCheck(False, f"{path.name} has no sidecar (an interrupted run?)")
    wanted_params = json.loads(json.dumps(to_jsonable(params_to_dict(params, run_sections=False))))
    roles = [("input frame", Path(input_path))] + [("flat frame", Path(p)) for p in flat_paths] + \
            [("dark frame", Path(p)) for p in dark_paths] + ([("PSF model", Path(psf_path))] if psf_path else [])
    for kind, path in expected.items():
        try:
            side = json.loads(sidecar_path(path).read_text(encoding="utf-8"))
            recorded_params = {k: v for k, v in side["parameters"].items() if k not in RUN_ONLY_SECTIONS}
            recorded_inputs = side["inputs"]
            results = side.get("results", {})
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            return RerunCheck(False, f"{path.name}.json cannot be read")
        if side.get("version") != __version__:
            return RerunCheck(False, f"made by version {side.get('version')} (this is {__version__})")
        change = _parameter_change(recorded_params, wanted_params)
        if change:
            return RerunCheck(False, change)
        frames = results.get("reference_frames")
        if not isinstance(frames, dict) or not all(isinstance(frames.get(k), int) for k in ("flat", "dark")):
            return RerunCheck(False, f"{path.name}.json does not say which inputs were flats and darks")
        recorded_roles = ["input frame"] + ["flat frame"] * frames["flat"] + ["dark frame"] * frames["dark"]
        recorded_roles += ["PSF model"] * (len(recorded_inputs) - len(recorded_roles))
        if recorded_roles != [role for role, _ in roles]:
            return RerunCheck(False, "not the same number of flat, dark or PSF files as the last run")
        if psf_path is not None:
            geometry = {"source_to_object_mm": float(source_to_object_mm), "source_to_detector_mm": float(source_to_detector_mm)}
            if results.get("run_options") != geometry:
                return RerunCheck(False, "deblurring geometry changed")
        try:
            for (role, wanted), recorded in zip(roles, recorded_inputs, strict=True):
                if not wanted.is_file():
                    return RerunCheck(False, f"{role} {wanted} not found")  # run_file reports it
                if recorded.get("bytes") != wanted.stat().st_size or recorded.get("sha256") != _sha(wanted, checksums):
                    return RerunCheck(False, f"{role} {wanted.name} changed (checksum)")
            if _sha(path, None) != (side.get("output") or {}).get("sha256"):
                return RerunCheck(False, f"{path.name} differs from the file its sidecar describes")
        except OSError as exc:  # unreadable: processing it again reports the problem for this file
            return RerunCheck(False, f"cannot checksum {exc.filename or path} ({exc.strerror or exc})")
        if kind == "dicom":
            change = _dicom_patient_change(path, patient)
            if change:
                return RerunCheck(False, change)
    return RerunCheck(True, "finished outputs match the inputs, parameters and version")
