"""``dslrxr deconvolve``: remove a known blur (see the module docstring of napari_dslrxr._cli).

The kernel comes either from a fitted PSF model at the object's geometry (``--psf`` with the
two distances) or from a kernel TIFF (``--kernel``, e.g. written by ``dslrxr psf kernel``).
The output is a float32 TIFF in the input's linear units (not clipped, so slight undershoot
below zero and overshoot above the input range survive for later stages), with a provenance
sidecar recording the method and the numeric regularisation actually used.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Optional

import typer

from .common import option_help

#: Relative tolerance on the sum of a kernel read from a file (it must be a normalised kernel).
KERNEL_SUM_TOLERANCE = 0.05


def read_kernel_tiff(path: Path):
    """Read a blur kernel TIFF: 2-D, odd sides, finite, non-negative, sum 1 within 5 %.

    Returns the kernel as float32 normalised to unit sum; raises :class:`InputError` with a
    one-line message otherwise.
    """
    import numpy as np
    import tifffile

    from ..core.stages.deconvolution import validate_kernel
    from ..core.errors import InputError

    if not path.is_file():
        raise InputError(path, "kernel file not found")
    try:
        data = tifffile.imread(path)
    except Exception as exc:  # tifffile raises many types for corrupt files
        raise InputError(path, f"cannot read the kernel TIFF ({type(exc).__name__})") from None
    data = np.squeeze(np.asarray(data))
    kernel = validate_kernel(data, str(path))
    total = float(np.asarray(data, dtype=np.float64).sum())
    if abs(total - 1.0) > KERNEL_SUM_TOLERANCE:
        raise InputError(path, f"kernel sums to {total:.4g}, expected 1 (a normalised blur kernel)")
    return kernel


def blur_kernel(psf: Path | None, kernel: Path | None, source_to_object_mm: float | None,
                source_to_detector_mm: float | None, inputs: list, parameters: dict):
    """The kernel ``--psf`` (at the two distances) or ``--kernel`` gives; its file is appended
    to ``inputs`` and its options recorded in ``parameters``."""
    from ..core.errors import ParameterError
    from ..core.psf import load_psf
    from ..core.stages.deconvolution import validate_kernel

    if (psf is None) == (kernel is None):
        raise ParameterError("give either --psf (with both distances) or --kernel, not both or neither")
    if kernel is not None:
        if source_to_object_mm is not None or source_to_detector_mm is not None:
            raise ParameterError("the distances go with --psf, not with --kernel")
        inputs.append(kernel)
        parameters["kernel"] = str(kernel)
        return read_kernel_tiff(kernel)
    if source_to_object_mm is None or source_to_detector_mm is None:
        raise ParameterError("--psf needs --source-to-object-mm and --source-to-detector-mm")
    if not 0 < source_to_object_mm <= source_to_detector_mm:
        raise ParameterError("need 0 < --source-to-object-mm <= --source-to-detector-mm, "
                             f"got {source_to_object_mm:g} and {source_to_detector_mm:g}")
    model = load_psf(psf)
    kern = validate_kernel(model.kernel(source_to_object_mm, source_to_detector_mm), str(psf))
    inputs.append(psf)
    parameters.update(psf=str(psf), source_to_object_mm=source_to_object_mm,
                      source_to_detector_mm=source_to_detector_mm)
    return kern


def register(app: typer.Typer) -> None:
    """Add the ``deconvolve`` command to ``app``."""

    @app.command("deconvolve")
    def deconvolve_command(
        input_path: Path = typer.Argument(..., metavar="INPUT", help="Blurred linear image (TIFF, PNG, DICOM, raw)."),
        output: Path = typer.Option(..., "-o", "--output", help="Output float32 TIFF."),
        psf: Optional[Path] = typer.Option(None, "--psf", help="Fitted PSF model (psf.json from 'dslrxr psf fit')."),
        source_to_object_mm: Optional[float] = typer.Option(None, "--source-to-object-mm", help="With --psf."),
        source_to_detector_mm: Optional[float] = typer.Option(None, "--source-to-detector-mm", help="With --psf."),
        kernel: Optional[Path] = typer.Option(None, "--kernel", help="Kernel TIFF (odd size, sums to 1)."),
        config: Optional[Path] = typer.Option(None, "-c", "--config",
                                              help="Parameter file (its deblur section; options override it)."),
        method: Optional[str] = typer.Option(None, "--method", help=option_help("deblur", "method", "method")),
        reg: Optional[str] = typer.Option(None, "--reg", help=option_help("deblur", "reg", "regularisation knob (larger = smoother) or 'auto'")),
    ) -> None:
        """Deconvolve INPUT with a known blur kernel and write a float32 TIFF."""
        import numpy as np

        from ..core.stages import deconvolution as dc
        from ..core.stages.regularisation import choose_regularisation
        from ..core.files import write_output
        from ..core.io import read_image
        from ..core.params import load_section
        from .common import ensure_parent

        settings = load_section(config, "deblur", method=method,
                                reg=None if reg is None else dc.check_reg(reg))
        method, reg_value = settings.method, settings.reg
        inputs = [input_path] + ([config] if config is not None else [])
        parameters: dict = {"method": method, "reg": reg_value}
        kern = blur_kernel(psf, kernel, source_to_object_mm, source_to_detector_mm, inputs, parameters)

        t0 = time.perf_counter()
        image = read_image(input_path).data
        t_read = time.perf_counter() - t0
        t0 = time.perf_counter()
        auto = choose_regularisation(image, kern, method) if reg_value == "auto" else None
        reg_used = auto.reg if auto is not None else float(reg_value)
        for warning in auto.warnings if auto is not None else ():
            print(f"dslrxr: warning: {input_path}: automatic regularisation unreliable: {warning}", file=sys.stderr)
        t_auto = time.perf_counter() - t0
        t0 = time.perf_counter()
        result = dc.deconvolve(image, kern, method=method, reg=reg_used)
        t_deconv = time.perf_counter() - t0

        ensure_parent(output)
        description = (f"dslrxr deconvolve: method={method} reg={reg_used:.6g}"
                       f"{' (auto)' if reg_value == 'auto' else ''}; float32, linear, input units")
        write_output(output, result.astype(np.float32, copy=False), description=description, stage="deconvolve",
                     parameters=parameters, inputs=inputs,
                     timings_s={"read": t_read, "auto_reg": t_auto, "deconvolve": t_deconv},
                     results={"reg_used": reg_used, "reg_was_auto": reg_value == "auto",
                              **({"auto": auto.as_dict()} if auto is not None else {}),
                              "kernel_shape": list(kern.shape), "output_dtype": "float32"})
        typer.echo(f"{output}: {method} deconvolution, reg {reg_used:.4g}"
                   f"{' (auto)' if reg_value == 'auto' else ''}, kernel {kern.shape[0]}x{kern.shape[1]}")
