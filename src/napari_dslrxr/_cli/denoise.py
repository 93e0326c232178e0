"""``dslrxr denoise`` (impulse removal) and ``dslrxr metrics pe|gcf``.

``denoise`` writes a TIFF with the input's shape and dtype (for camera raw input, the
linear 16-bit RGB) in which only detected pulses are replaced, optionally a uint8 mask
TIFF (255 where any channel's pixel was replaced), and a provenance sidecar beside each
output holding the estimated gain and pulse rate of every channel. Its parameters are the
``[impulse]`` section of a parameter file (``-c``); options given on the command line
override the file's values.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from .common import HELP_MARKUP_MODE


def parse_passes(text: str | None) -> dict[str, int]:
    """``"H,S,V"`` -> passes on hue, saturation, value; a single ``"N"`` -> grey/CFA passes."""
    from ..core.errors import ParameterError
    from .common import parse_int_list

    if text is None:
        return {}
    if "," not in text:
        try:
            return {"passes_grey": int(text)}
        except ValueError:
            raise ParameterError(f"--passes: expected H,S,V or one integer, got {text!r}") from None
    h, s, v = parse_int_list(text, 3, "--passes")
    return {"passes_h": h, "passes_s": s, "passes_v": v}


def _results(result) -> dict:
    """Gain, pulse rate and replaced-pixel count of each channel, for the sidecar."""
    import numpy as np

    return {
        "gain": {k: float(v) for k, v in result.gain.items()},
        "pulse_rate": {k: float(v) for k, v in result.pulse_rate.items()},
        "replaced_px": {k: int(np.count_nonzero(m)) for k, m in result.masks.items()},
    }


def impulse_params(config: Path | None = None, *, passes: str | None = None, **overrides):
    """The ``[impulse]`` parameters of ``config`` (defaults without one), with the command
    line's options (those not None) on top; every value is checked as the file's are."""
    from ..core.params import load_section

    return load_section(config, "impulse", **parse_passes(passes), **overrides)


def denoise_file(input_path: Path, output: Path, *, passes: str | None = None, space: str | None = None,
                 mask_out: Path | None = None, config: Path | None = None, spots: str | None = None,
                 window_px: int | None = None, posterior_threshold: float | None = None,
                 min_contrast: float | None = None) -> dict:
    """Run impulse removal on one file and write the outputs; return the sidecar results."""
    import dataclasses
    from functools import partial

    import numpy as np

    from ..core.errors import ParameterError
    from ..core.stages.impulse import cfa_mask_to_mosaic, clean_raw_frame, remove_impulses
    from ..core.files import write_output
    from ..core.io import check_not_an_input, read_image, write_tiff
    from .common import ensure_parent

    params = impulse_params(config, passes=passes, space=space, spots=spots, window_px=window_px,
                            posterior_threshold=posterior_threshold, min_contrast=min_contrast)
    space = params.space
    if mask_out is not None and Path(mask_out).resolve() == Path(output).resolve():
        raise ParameterError("--mask-out must differ from the output file")
    check_not_an_input(output, [input_path])
    if mask_out is not None:
        check_not_an_input(mask_out, [input_path])
    t0 = time.perf_counter()
    loaded = read_image(input_path)
    t_read = time.perf_counter() - t0
    is_raw = loaded.format == "raw" and loaded.raw is not None
    used_space = ("cfa" if is_raw else "grey" if loaded.data.ndim == 2 else "hsv") if space == "auto" else space
    t0 = time.perf_counter()
    if used_space == "cfa":
        if not is_raw:
            raise ParameterError(f"--space cfa needs a camera raw input; {input_path} is {loaded.format}")
        image, result = clean_raw_frame(loaded, params)
        mask = cfa_mask_to_mosaic(result.masks, loaded.raw.plane_offsets, image.shape[:2])
    else:
        result = remove_impulses(loaded.data, dataclasses.replace(params, space=used_space))
        image = result.image
        mask = result.any_mask()
    t_denoise = time.perf_counter() - t0
    results = {"space": used_space, **_results(result)}
    parameters = {**dataclasses.asdict(params), "space": used_space, "space_requested": space}
    timings = {"read": t_read, "denoise": t_denoise}
    ensure_parent(output)
    write_output(output, image, stage="denoise", parameters=parameters, inputs=[input_path],
                 timings_s=timings, results=results)
    if mask_out is not None:
        ensure_parent(mask_out)
        # the mask must not overwrite the cleaned output either; its sidecar names the input only
        write_mask = partial(write_tiff, data=np.where(mask, 255, 0).astype(np.uint8), inputs=[input_path, output])
        write_output(mask_out, write_mask, stage="denoise-mask", parameters=parameters, inputs=[input_path],
                     timings_s=timings, results=results)
    return results


def register(app: typer.Typer) -> None:
    """Add ``denoise`` and the ``metrics`` group (``pe``, ``gcf``) to ``app``."""

    @app.command("denoise")
    def denoise_command(
        input_path: Path = typer.Argument(..., metavar="INPUT", help="Linear image: TIFF, PNG, DICOM or camera raw."),
        output: Path = typer.Option(..., "-o", "--output", help="Output TIFF (input's shape and dtype; raw: 16-bit RGB)."),
        config: Optional[Path] = typer.Option(None, "-c", "--config", help="Parameter file: its [impulse] section (dslrxr params --default)."),
        passes: Optional[str] = typer.Option(None, "--passes", help="H,S,V passes (default 3,1,1), or one number for grey/CFA."),
        space: Optional[str] = typer.Option(None, "--space", help="auto | grey | hsv | cfa (auto: cfa for raw, hsv for RGB, grey for grey)."),
        spots: Optional[str] = typer.Option(None, "--spots", help="bright | dark | both: polarity of the pulses (default bright)."),
        window_px: Optional[int] = typer.Option(None, "--window", help="Detection window, 3 or 5 px (default 5)."),
        threshold: Optional[float] = typer.Option(None, "--threshold", help="Posterior pulse probability above which a pixel is a pulse (0 < t < 1; default 0.5)."),
        min_contrast: Optional[float] = typer.Option(None, "--min-contrast", help="Least Weber contrast of a pulse on grey/V/CFA channels (0 to 1; default 0.07)."),
        mask_out: Optional[Path] = typer.Option(None, "--mask-out", help="uint8 TIFF, 255 where a pixel was replaced."),
    ) -> None:
        """Remove impulse noise (zingers) from INPUT: only detected pulses are replaced.

        Parameters come from the [impulse] section of -c FILE (every key: passes, window,
        thresholds, spots, space...); the options above override it."""
        results = denoise_file(input_path, output, passes=passes, space=space, mask_out=mask_out,
                               config=config, spots=spots, window_px=window_px,
                               posterior_threshold=threshold, min_contrast=min_contrast)
        rates = ", ".join(f"{k} {v:.4g}" for k, v in results["pulse_rate"].items())
        gains = ", ".join(f"{k} {v:.4g}" for k, v in results["gain"].items() if v == v)
        typer.echo(f"{output}: space {results['space']}; pulse rate {rates}; gain {gains or 'n/a'}")

    metrics_app = typer.Typer(help="Image-quality metrics: percentage error and global contrast factor.",
                              rich_markup_mode=HELP_MARKUP_MODE,
                              no_args_is_help=True)

    @metrics_app.command("pe")
    def pe_command(
        reference: Path = typer.Argument(..., metavar="A", help="Reference image."),
        estimate: Path = typer.Argument(..., metavar="B", help="Processed image (same shape)."),
        roi: Optional[str] = typer.Option(None, "--roi", help="r0,c0,r1,c1 in pixels, end exclusive."),
    ) -> None:
        """Print the percentage error 100*||A - B||/||A|| (in %) over the ROI."""
        from ..core.io import read_image
        from ..core.metrics import percentage_error
        from .common import parse_roi

        region = parse_roi(roi)
        value = percentage_error(read_image(reference).data, read_image(estimate).data, roi=region)
        typer.echo(f"{value:.6g}")

    @metrics_app.command("gcf")
    def gcf_command(
        image: Path = typer.Argument(..., metavar="IMAGE", help="Display image (uint8, uint16 or float in [0, 1])."),
    ) -> None:
        """Print the global contrast factor (GCF) of IMAGE.

        GCF after Matkovic, Neumann, Neumann, Psik and Purgathofer (2005).
        """
        from ..core.io import read_image
        from ..core.metrics import global_contrast_factor

        typer.echo(f"{global_contrast_factor(read_image(image).data):.6g}")

    app.add_typer(metrics_app, name="metrics")
