"""All pipeline parameters in one dataclass, saved and loaded as commented TOML.

:class:`PipelineParams` holds one dataclass per stage; the TOML file has one table per stage
(``[input]``, ``[impulse]``, ``[flatfield]``, ``[region]``, ``[deblur]``, ``[dynamic_range]``,
``[contrast]``, ``[output]``, ``[exposure]``). The command line (``dslrxr run -c params.toml``) and the napari
widgets read and write the same file. Missing keys take their defaults; unknown keys, wrong
types and out-of-range values raise :class:`~.errors.ParameterError` with a one-line message
naming the key (and, for a misspelt key, the closest valid name).
"""

from __future__ import annotations

import dataclasses
import difflib
import os
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path

import tomli_w

from .errors import InputError, ParameterError
from .io.input_kind import InputParams
from .param_fields import describe_range, field_info, validate_fields
from .stages.contrast import ContrastParams
from .stages.deblur_params import DeconvolutionParams
from .stages.dynamic_range import DynamicRangeParams
from .stages.exposure_index import ExposureParams
from .stages.flatfield import FlatFieldParams
from .stages.region import RegionParams

__all__ = ["BatchParams", "DeblurParams", "OutputParams", "PipelineParams", "RUN_ONLY_SECTIONS", "SECTION_HELP",
           "default_params_toml", "load_params", "load_section", "section_class", "params_from_dict", "params_to_dict",
           "params_to_toml", "save_params", "validate_params"]


def _impulse_class():
    from .stages.impulse import ImpulseParams

    return ImpulseParams


def _default_impulse():
    return _impulse_class()()


#: The ``[deblur]`` section is the deconvolution stage's own parameter class (one class, one range).
DeblurParams = DeconvolutionParams


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

    def __post_init__(self) -> None:
        validate_fields(self, "output")


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
        validate_fields(self, "batch")
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
    exposure: ExposureParams = field(default_factory=ExposureParams)
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
    "exposure": "exposure index EI and deviation index DI (IEC 62494-1) of camera frames, once calibrated",
    "batch": "how dslrxr run spreads a batch: process pool or dask.distributed cluster (never changes outputs)",
    "psf_fit": "dslrxr psf fit: the joint edge fit (the edges themselves are listed in the edge configuration)",
    "diagnose": "dslrxr diagnose: which physics terms the diagnosis may add to the base model",
    "qc": "dslrxr qc: detector MTF, NNPS and DQE per IEC 62220-1-1 (slanted edge, flats, darks)",
}


def _command_sections() -> dict[str, type]:
    """Sections read by single commands, not by the pipeline run.

    They stay out of :class:`PipelineParams`: its text seeds the run's DICOM UIDs, which must
    not change when a setting of another command does.
    """
    from .diagnosis.params import DiagnoseParams
    from .psf.fit_params import PsfFitParams
    from .qc.params import QcParams

    return {"psf_fit": PsfFitParams, "diagnose": DiagnoseParams, "qc": QcParams}


def _build_section(section: str, cls, values: dict):
    known = {f.name: f for f in dataclasses.fields(cls)}
    for key in values:
        if key not in known:
            hint = difflib.get_close_matches(key, list(known), n=1)
            extra = f"; did you mean '{hint[0]}'?" if hint else f" (valid: {', '.join(known)})"
            raise ParameterError(f"unknown key '{key}' in [{section}]{extra}")
    try:  # each class checks and converts its values on construction (field metadata)
        return cls(**values)
    except ParameterError as exc:
        msg = str(exc)
        raise ParameterError(msg if msg.startswith(section) else f"{section}.{msg}") from None
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"[{section}]: {exc}") from None


def _section_classes() -> dict[str, type]:
    return {f.name: (_impulse_class() if f.name == "impulse" else f.default_factory)
            for f in dataclasses.fields(PipelineParams)}


def section_class(section: str) -> type:
    """The parameter dataclass of TOML section ``section`` (pipeline or command section)."""
    classes = {**_section_classes(), **_command_sections()}
    if section not in classes:
        raise KeyError(f"no parameter section [{section}]")
    return classes[section]


def params_from_dict(data: dict) -> PipelineParams:
    """Build and validate :class:`PipelineParams` from a nested mapping (a parsed TOML file).

    Raises
    ------
    ParameterError
        Unknown section or key (with a suggestion), wrong type or out-of-range value.
    """
    return _sections_from_dict(data)[0]


def _sections_from_dict(data: dict) -> tuple[PipelineParams, dict]:
    """The pipeline parameters and the command sections (built, checked) of a parsed file."""
    pipeline_classes = _section_classes()
    command_classes = _command_sections()
    classes = {**pipeline_classes, **command_classes}
    kwargs, commands = {}, {}
    for section, values in data.items():
        if section not in classes:
            hint = difflib.get_close_matches(section, list(classes), n=1)
            extra = f"; did you mean '[{hint[0]}]'?" if hint else f" (valid: {', '.join(classes)})"
            raise ParameterError(f"unknown section [{section}]{extra}")
        if not isinstance(values, dict):
            raise ParameterError(f"[{section}] must be a table of key = value pairs, got {values!r}")
        built = _build_section(section, classes[section], values)
        (kwargs if section in pipeline_classes else commands)[section] = built
    commands = {name: commands.get(name) or cls() for name, cls in command_classes.items()}
    return PipelineParams(**kwargs), commands


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


def _read_file(path: Path) -> dict:
    from .io import read_structured_file

    try:
        return read_structured_file(path, what="parameter file")
    except InputError as exc:  # a parameter problem for the caller, whatever the file's fault
        raise ParameterError(str(exc)) from None


def load_params(path: str | os.PathLike) -> PipelineParams:
    """Read a parameter file; missing keys take their defaults.

    Every section is checked, the command sections (``[psf_fit]``, ``[diagnose]``, ``[qc]``) too.

    Raises
    ------
    ParameterError
        Missing or unreadable file, TOML syntax error, unknown key, wrong type or range.
    """
    return _load_all(Path(path))[0]


def _load_all(path: Path) -> tuple[PipelineParams, dict]:
    data = _read_file(path)
    try:
        return _sections_from_dict(data)
    except ParameterError as exc:
        raise ParameterError(f"{path}: {exc}") from None


def load_section(path: str | os.PathLike | None, section: str, **overrides):
    """The parameters of one TOML section, for a command: from the file ``path`` (defaults when
    None), then ``overrides`` (command-line options; None = not given) on top.

    The whole file is checked, so a file refused by ``dslrxr run`` is refused here too. An
    out-of-range option gets the same message as the same value in the file (without the file
    name).
    """
    if path is None:
        pipeline, commands = PipelineParams(), {n: c() for n, c in _command_sections().items()}
    else:
        pipeline, commands = _load_all(Path(path))
    current = commands[section] if section in commands else getattr(pipeline, section)
    given = {k: v for k, v in overrides.items() if v is not None}
    return dataclasses.replace(current, **given) if given else current


def _field_comment(cls: type, name: str) -> str:
    info = field_info(cls, name)
    bits = [f"unit: {info['unit']}"] if info.get("unit") else []
    limits = describe_range(info)
    if limits:
        bits.append(limits)
    return f"# {info['help']}" + (f" ({'; '.join(bits)})" if bits else "")


def params_to_toml(params: PipelineParams | None = None, *, comments: bool = True,
                   run_sections: bool = True, commands: dict | None = None, omit: tuple[str, ...] = ()) -> str:
    """The TOML text of ``params`` (default: the defaults), with a comment above every key.

    ``run_sections=False`` leaves out :data:`RUN_ONLY_SECTIONS`; ``omit`` leaves out the named
    sections; ``commands`` adds the command sections (``[psf_fit]``, ``[diagnose]``, ``[qc]``)
    after the pipeline's.
    """
    params = params or PipelineParams()
    # The first line is part of the text that seeds the run's DICOM UIDs: keep it as it is.
    lines = ["# napari-dslrxr pipeline parameters (dslrxr run -c this_file.toml).",
             "# Missing keys take their defaults; unknown keys are an error.", ""]
    if commands:
        lines.insert(1, "# The same file sets dslrxr denoise ([impulse]), deconvolve ([deblur]), "
                        "psf fit ([psf_fit]), diagnose ([diagnose]) and qc ([qc]): -c this_file.toml.")
    sections = [(f.name, getattr(params, f.name)) for f in dataclasses.fields(params)
                if (run_sections or f.name not in RUN_ONLY_SECTIONS) and f.name not in omit]
    sections += list((commands or {}).items())
    for name, section in sections:
        if comments:
            lines.append(f"# {SECTION_HELP.get(name, name)}")
        lines.append(f"[{name}]")
        for sf in dataclasses.fields(section):
            if comments:
                lines.append(_field_comment(type(section), sf.name))
            lines.append(tomli_w.dumps({sf.name: getattr(section, sf.name)}).strip())
        lines.append("")
    return "\n".join(lines)


def default_params_toml() -> str:
    """The full default parameter file, every key with a comment (units, range, meaning)."""
    return params_to_toml(PipelineParams(), commands={n: c() for n, c in _command_sections().items()})


def save_params(params: PipelineParams, path: str | os.PathLike) -> Path:
    """Write ``params`` as commented TOML (atomically)."""
    from .io import atomic_write

    text = params_to_toml(validate_params(params))
    return atomic_write(Path(path), lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
