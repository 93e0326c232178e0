"""All pipeline parameters in one dataclass, saved and loaded as commented TOML.

:class:`PipelineParams` holds one dataclass per stage; the TOML file has one table per stage
(``[input]``, ``[impulse]``, ``[flatfield]``, ``[region]``, ``[deblur]``, ``[dynamic_range]``,
``[contrast]``, ``[output]``). The command line (``dslrxr run -c params.toml``) and the napari
widgets read and write the same file. Missing keys take their defaults; unknown keys, wrong
types and out-of-range values raise :class:`~.errors.ParameterError` with a one-line message
naming the key (and, for a misspelt key, the closest valid name).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path

import tomli_w

from .stages.contrast import ContrastParams
from .stages.dynamic_range import DynamicRangeParams
from .errors import InputError, ParameterError
from .io.input_kind import InputParams
from .stages.flatfield import FlatFieldParams
from .stages.region import RegionParams


def _impulse_class():
    from .stages.impulse import ImpulseParams

    return ImpulseParams


def _default_impulse():
    return _impulse_class()()


@dataclass
class DeblurParams:
    """Parameters of the optional deblurring stage (TOML section ``[deblur]``).

    Deblurring runs only when a PSF model is given (``dslrxr run --psf psf.json``).

    Attributes
    ----------
    method : str
        ``"adaptive"`` (sparse adaptive prior), ``"wiener"`` or ``"rls"``.
    reg : float or str
        Regularisation weight, or ``"auto"`` to estimate it from the image.
    """

    method: str = field(default="adaptive", metadata={
        "help": "deconvolution method (runs only when a PSF model is given)", "choices": ("adaptive", "wiener", "rls")})
    reg: float | str = field(default="auto", metadata={
        "help": "regularisation weight (> 0), or \"auto\" to estimate it from the image", "min": 0.0, "max": 1e6})


@dataclass
class OutputParams:
    """What the run writes (TOML section ``[output]``).

    Attributes
    ----------
    tiff : bool
        16-bit TIFF of the display-ready radiograph.
    png_preview : bool
        8-bit PNG preview.
    preview_max_side_px : int
        Longest side of the PNG preview (px); 0 = full size.
    dicom : bool
        DICOM Digital X-Ray image (For Presentation).
    polarity : str
        ``"bone_white"`` (radiograph convention: more attenuation = brighter) or
        ``"as_captured"`` (more light = brighter).
    outside_region : str
        ``"black"`` or ``"white"``: display value outside the screen region.
    pixel_spacing_mm : float
        Detector pixel pitch at the screen (mm); 0 = unknown (not written to DICOM).
    """

    tiff: bool = field(default=True, metadata={"help": "write the 16-bit TIFF of the display-ready radiograph"})
    png_preview: bool = field(default=True, metadata={"help": "write an 8-bit PNG preview"})
    preview_max_side_px: int = field(default=2048, metadata={
        "help": "longest side of the PNG preview; 0 = full size", "unit": "px", "min": 0, "max": 100000})
    dicom: bool = field(default=False, metadata={"help": "write a DICOM Digital X-Ray image (For Presentation)"})
    polarity: str = field(default="bone_white", metadata={
        "help": "bone_white: more attenuation = brighter (radiograph convention); as_captured: more light = brighter",
        "choices": ("bone_white", "as_captured")})
    outside_region: str = field(default="black", metadata={
        "help": "display value outside the screen region", "choices": ("black", "white")})
    pixel_spacing_mm: float = field(default=0.0, metadata={
        "help": "pixel pitch at the screen; 0 = unknown (then not written to DICOM)", "unit": "mm", "min": 0.0, "max": 100.0})


#: ``[batch] scheduler``: a dask.distributed scheduler address (``tcp://host:8786``, also
#: ``tls://``, ``inproc://``..., or a bare ``host:port``).
_SCHEDULER_ADDRESS = re.compile(r"^([a-z][a-z0-9+]*://\S+|[\w.\-]+:\d+)$")


@dataclass
class BatchParams:
    """How ``dslrxr run`` spreads a batch over processes or machines (TOML section ``[batch]``).

    It changes where files are processed, never the outputs' bytes: it is left out of the
    run identity (DICOM UIDs) and of the check that decides whether a file is already done.

    Attributes
    ----------
    scheduler : str
        ``""``: a process pool on this machine (``jobs`` processes); ``"local"``: a dask
        LocalCluster of ``jobs`` worker processes (one thread each), closed at the end; an
        address such as ``"tcp://host:8786"``: an existing dask.distributed scheduler.
    jobs : int
        Files processed in parallel on this machine (process pool or LocalCluster workers).
    """

    scheduler: str = field(default="", metadata={
        "help": "\"\" = process pool on this machine; \"local\" = dask LocalCluster of `jobs` workers; "
                "or a dask scheduler address such as \"tcp://host:8786\""})
    jobs: int = field(default=1, metadata={
        "help": "files processed in parallel on this machine (processes or LocalCluster workers)",
        "min": 1, "max": 64})

    def __post_init__(self):
        if self.scheduler not in ("", "local") and not _SCHEDULER_ADDRESS.match(self.scheduler):
            raise ParameterError(f"batch.scheduler: expected \"\", \"local\" or an address such as "
                                 f"\"tcp://host:8786\", got {self.scheduler!r}")


@dataclass
class PipelineParams:
    """Every parameter of the six-stage pipeline, one dataclass per stage."""

    input: InputParams = field(default_factory=InputParams)
    impulse: typing.Any = field(default_factory=_default_impulse)
    flatfield: FlatFieldParams = field(default_factory=FlatFieldParams)
    region: RegionParams = field(default_factory=RegionParams)
    deblur: DeblurParams = field(default_factory=DeblurParams)
    dynamic_range: DynamicRangeParams = field(default_factory=DynamicRangeParams)
    contrast: ContrastParams = field(default_factory=ContrastParams)
    output: OutputParams = field(default_factory=OutputParams)
    batch: BatchParams = field(default_factory=BatchParams)


#: Sections that choose how a batch runs, not what it computes (outputs do not depend on them).
RUN_ONLY_SECTIONS = ("batch",)

SECTION_HELP = {
    "input": "what the input is: a camera frame (linear counts) or a display radiograph (bone bright)",
    "impulse": "(i) impulse (pulse) removal on the colour image: switching median driven by a Poisson + pulse mixture",
    "flatfield": "(ii) flat field per colour channel: (R - D) / (F - D) x mean(F - D)",
    "region": "(iii) exposed screen region and value-of-interest scaling",
    "deblur": "(iv) optional deconvolution, only when a PSF model is given (--psf)",
    "dynamic_range": "(v) dynamic-range / latitude reduction in the log domain and the display curve",
    "contrast": "(vi) multiscale contrast enhancement (MUSICA-style Laplacian pyramid)",
    "output": "files written by the run",
    "batch": "how dslrxr run spreads a batch: process pool or dask.distributed cluster (never changes outputs)",
}

# Help, unit and range of ImpulseParams' fields (its dataclass carries docstrings, not field
# metadata); merged under any metadata the fields do carry by :func:`field_info`.
_IMPULSE_META = {
    "passes_h": {"help": "detect-and-replace passes on hue; 0 skips the channel", "unit": "passes", "min": 0, "max": 10},
    "passes_s": {"help": "detect-and-replace passes on saturation", "unit": "passes", "min": 0, "max": 10},
    "passes_v": {"help": "detect-and-replace passes on value V = max(R, G, B)", "unit": "passes", "min": 0, "max": 10},
    "passes_grey": {"help": "detect-and-replace passes on a grey image and on each raw CFA plane",
                    "unit": "passes", "min": 0, "max": 10},
    "window_px": {"help": "median window of the first detection: 3 = the 8 neighbours, 5 = the 8 pixels two "
                          "steps away (finds patches up to 3x3 px)", "unit": "px", "choices": (3, 5)},
    "max_patch_px": {"help": "largest pulse patch side grown into", "unit": "px", "min": 1, "max": 8},
    "spots": {"help": "polarity of the pulses on grey, V and CFA channels: bright (direct X-ray hits), dark or both"},
    "posterior_threshold": {"help": "a pixel is a pulse when its posterior pulse probability exceeds this",
                            "unit": "probability", "min": 0.0, "max": 1.0},
    "min_saturation": {"help": "pixels with saturation below this are left out of hue filtering",
                       "unit": "fraction", "min": 0.0, "max": 1.0},
    "min_value_fraction": {"help": "pixels with V below this fraction of the 99th percentile are left out of "
                                   "hue filtering", "unit": "fraction", "min": 0.0, "max": 1.0},
    "em_samples": {"help": "pixels subsampled for the EM fit", "unit": "px", "min": 1000, "max": 100_000_000},
    "em_iterations": {"help": "maximum EM iterations", "unit": "iterations", "min": 1, "max": 500},
}


def field_info(cls: type, name: str) -> dict:
    """Help, unit, range, choices and default of field ``name`` of parameter dataclass ``cls``.

    The one place the TOML comments, the command-line help and the widgets' tooltips and
    ranges read a parameter's documentation from. Keys: ``help`` (always), ``default``
    (always), and ``unit``, ``min``, ``max``, ``choices`` when the field declares them.
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}
    if name not in fields:
        raise KeyError(f"{cls.__name__} has no field {name!r}")
    f = fields[name]
    info = dict(_IMPULSE_META.get(name, {})) if cls.__name__ == "ImpulseParams" else {}
    info.update(f.metadata or {})
    info.setdefault("help", name.replace("_", " "))
    if f.default is not dataclasses.MISSING:
        info["default"] = f.default
    elif f.default_factory is not dataclasses.MISSING:
        info["default"] = f.default_factory()
    return info


def _check_value(section: str, f: dataclasses.Field, value, default):
    """Type and range check of one value; returns the (possibly converted) value."""
    name = f"{section}.{f.name}"
    meta = f.metadata or {}
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ParameterError(f"{name}: expected true or false, got {value!r}")
        return value
    if f.name == "reg" and section == "deblur":
        if isinstance(value, str):
            if value != "auto":
                raise ParameterError(f"{name}: expected a number > 0 or \"auto\", got {value!r}")
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= meta.get("max", 1e6):
            raise ParameterError(f"{name}: expected a number in (0, {meta.get('max', 1e6):g}] or \"auto\", got {value!r}")
        return float(value)
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            else:
                raise ParameterError(f"{name}: expected an integer, got {value!r}")
    elif isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParameterError(f"{name}: expected a number, got {value!r}")
        value = float(value)
        if value != value:
            raise ParameterError(f"{name}: expected a number, got NaN")
    elif isinstance(default, str):
        if not isinstance(value, str):
            raise ParameterError(f"{name}: expected a string, got {value!r}")
        choices = meta.get("choices")
        if choices and value not in choices:
            hint = difflib.get_close_matches(value, choices, n=1)
            extra = f"; did you mean '{hint[0]}'?" if hint else ""
            raise ParameterError(f"{name}: must be one of {', '.join(choices)}, got {value!r}{extra}")
        return value
    elif isinstance(default, list):
        if not isinstance(value, list):
            raise ParameterError(f"{name}: expected a list, got {value!r}")
        if f.name == "polygon_xy" and value:
            ok = len(value) == 4 and all(isinstance(p, list) and len(p) == 2 and
                                         all(isinstance(c, (int, float)) and not isinstance(c, bool)
                                             and math.isfinite(c) for c in p)
                                         for p in value)
            if not ok:
                raise ParameterError(f"{name}: expected [] or 4 [x, y] points in pixels, got {value!r}")
            value = [[float(c) for c in p] for p in value]
        return value
    lo, hi = meta.get("min"), meta.get("max")
    if lo is not None and value < lo or hi is not None and value > hi:
        raise ParameterError(f"{name}: {value} is out of range [{lo}, {hi}]")
    return value


def _build_section(section: str, cls, values: dict):
    known = {f.name: f for f in dataclasses.fields(cls)}
    for key in values:
        if key not in known:
            hint = difflib.get_close_matches(key, list(known), n=1)
            extra = f"; did you mean '{hint[0]}'?" if hint else f" (valid: {', '.join(known)})"
            raise ParameterError(f"unknown key '{key}' in [{section}]{extra}")
    defaults = cls()
    kwargs = {}
    for key, value in values.items():
        kwargs[key] = _check_value(section, known[key], value, getattr(defaults, key))
    try:
        return cls(**kwargs)
    except ParameterError as exc:
        msg = str(exc)
        raise ParameterError(msg if msg.startswith(section) else f"{section}.{msg}") from None
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"[{section}]: {exc}") from None


def _section_classes() -> dict[str, type]:
    return {f.name: (_impulse_class() if f.name == "impulse" else f.default_factory)
            for f in dataclasses.fields(PipelineParams)}


def params_from_dict(data: dict) -> PipelineParams:
    """Build and validate :class:`PipelineParams` from a nested mapping (a parsed TOML file).

    Raises
    ------
    ParameterError
        Unknown section or key (with a suggestion), wrong type or out-of-range value.
    """
    classes = _section_classes()
    kwargs = {}
    for section, values in data.items():
        if section not in classes:
            hint = difflib.get_close_matches(section, list(classes), n=1)
            extra = f"; did you mean '[{hint[0]}]'?" if hint else f" (valid: {', '.join(classes)})"
            raise ParameterError(f"unknown section [{section}]{extra}")
        if not isinstance(values, dict):
            raise ParameterError(f"[{section}] must be a table of key = value pairs, got {values!r}")
        kwargs[section] = _build_section(section, classes[section], values)
    return PipelineParams(**kwargs)


def validate_params(params: PipelineParams) -> PipelineParams:
    """Re-check every value of a :class:`PipelineParams` (e.g. one edited in a GUI)."""
    return params_from_dict(params_to_dict(params))


def params_to_dict(params: PipelineParams, *, run_sections: bool = True) -> dict:
    """Nested plain dict of every parameter (TOML-ready).

    ``run_sections=False`` leaves out :data:`RUN_ONLY_SECTIONS` (the parameters an output
    depends on).
    """
    out = {}
    for f in dataclasses.fields(params):
        if not run_sections and f.name in RUN_ONLY_SECTIONS:
            continue
        section = getattr(params, f.name)
        out[f.name] = {sf.name: getattr(section, sf.name) for sf in dataclasses.fields(section)}
    return out


def load_params(path: str | os.PathLike) -> PipelineParams:
    """Read a parameter file; missing keys take their defaults.

    Raises
    ------
    ParameterError
        Missing or unreadable file, TOML syntax error, unknown key, wrong type or range.
    """
    from .io import read_structured_file

    path = Path(path)
    try:
        data = read_structured_file(path, what="parameter file")
    except InputError as exc:  # a parameter problem for the caller, whatever the file's fault
        raise ParameterError(str(exc)) from None
    try:
        return params_from_dict(data)
    except ParameterError as exc:
        raise ParameterError(f"{path}: {exc}") from None


def _field_comment(cls: type, f: dataclasses.Field) -> str:
    meta = field_info(cls, f.name)
    bits = []
    if meta.get("unit"):
        bits.append(f"unit: {meta['unit']}")
    if meta.get("min") is not None or meta.get("max") is not None:
        bits.append(f"range {meta.get('min')} to {meta.get('max')}")
    if meta.get("choices"):
        bits.append("one of " + ", ".join(str(c) for c in meta["choices"]))
    return f"# {meta['help']}" + (f" ({'; '.join(bits)})" if bits else "")


def params_to_toml(params: PipelineParams | None = None, *, comments: bool = True,
                   run_sections: bool = True) -> str:
    """The TOML text of ``params`` (default: the defaults), with a comment above every key.

    ``run_sections=False`` leaves out :data:`RUN_ONLY_SECTIONS`.
    """
    params = params or PipelineParams()
    lines = ["# napari-dslrxr pipeline parameters (dslrxr run -c this_file.toml).",
             "# Missing keys take their defaults; unknown keys are an error.", ""]
    for f in dataclasses.fields(params):
        if not run_sections and f.name in RUN_ONLY_SECTIONS:
            continue
        section = getattr(params, f.name)
        if comments:
            lines.append(f"# {SECTION_HELP.get(f.name, f.name)}")
        lines.append(f"[{f.name}]")
        for sf in dataclasses.fields(section):
            if comments:
                lines.append(_field_comment(type(section), sf))
            lines.append(tomli_w.dumps({sf.name: getattr(section, sf.name)}).strip())
        lines.append("")
    return "\n".join(lines)


def default_params_toml() -> str:
    """The full default parameter file, every key with a comment (units, range, meaning)."""
    return params_to_toml(PipelineParams())


def save_params(params: PipelineParams, path: str | os.PathLike) -> Path:
    """Write ``params`` as commented TOML (atomically)."""
    from .io import atomic_write

    text = params_to_toml(validate_params(params))
    return atomic_write(Path(path), lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
