"""The ``[deblur]`` parameters: the method and the one range of the knob ``reg``.

:class:`DeconvolutionParams` is the one source of the section's defaults, ranges and help; the
parameter file, ``dslrxr deconvolve --method/--reg``, the deconvolution widget's slider and the
solvers (:func:`check_method`, :func:`check_reg`) all check against its field metadata, so a value
is accepted or refused identically everywhere. See :mod:`.deconvolution` for what ``reg`` means.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..param_fields import check_value, validate_fields

METHODS = ("adaptive", "wiener", "rls")

#: Bounds for reg (beyond them the solution is either the inverse filter or a flat image).
REG_MIN, REG_MAX = 1e-3, 1e9


@dataclass
class DeconvolutionParams:
    """Parameters of the deconvolution stage (TOML section ``[deblur]``), checked on construction.

    The one class of the section: ``dslrxr run`` (where deblurring runs only when a PSF model is
    given), ``dslrxr deconvolve`` and the deconvolution widget all use it.

    Attributes
    ----------
    method : str
        ``"adaptive"`` (sparse adaptive prior, default), ``"wiener"`` or ``"rls"``.
    reg : float or str
        The regularisation knob (dimensionless prior precision of the image gradient, relative
        to the noise; see the module docstring) or ``"auto"`` to estimate it from the image.
    """

    method: str = field(default="adaptive", metadata={
        "help": "deconvolution method (in a pipeline run only when a PSF model is given)", "choices": METHODS})
    reg: float | str = field(default="auto", metadata={
        "help": "regularisation knob, larger = smoother (prior precision of the image gradient relative "
                "to the noise), or \"auto\" to estimate it from the image",
        "min": REG_MIN, "max": REG_MAX, "auto": True})

    def __post_init__(self) -> None:
        validate_fields(self, "deblur")

    def validate(self) -> DeconvolutionParams:
        """The values are checked on construction; kept for callers that re-check after edits."""
        validate_fields(self, "deblur")
        return self


def check_method(method: str) -> str:
    """Return ``method`` if it is one of :data:`METHODS`, else raise :class:`ParameterError`."""
    return check_value(DeconvolutionParams, "deblur", "method", method)


def check_reg(reg: float | str) -> float | str:
    """Return ``reg`` as ``"auto"`` or a float in [REG_MIN, REG_MAX]; else raise ParameterError.

    Text (a command-line value) that reads as a number is taken as that number.
    """
    if isinstance(reg, str) and reg.strip().lower() != "auto":
        try:
            reg = float(reg)
        except ValueError:
            pass  # refused below with the parameter file's message
    return check_value(DeconvolutionParams, "deblur", "reg", reg)
