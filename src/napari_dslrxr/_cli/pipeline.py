"""``dslrxr run`` (the whole pipeline over a batch of files) and ``dslrxr params``."""

from __future__ import annotations

import signal
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import typer

from ..core.errors import ParameterError
from .file_job import freed_memory_kept, keep_freed_memory, process_one, remove_unfinished_outputs
from .shared_reference import shared_reference, sigterm_as_interrupt, worker_reference


#: Flat references this worker process (``--jobs > 1``) mapped or prepared, and PSF kernels, for
#: its later files. Set by the pool initializer, never in the parent.
_worker_references: dict | None = None


def _init_worker() -> None:
    global _worker_references
    _worker_references = {}
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # forked from the command, which turns it into Ctrl-C
    keep_freed_memory()


def _stop_pool(pool: ProcessPoolExecutor, unreported: list[dict]) -> None:
    """Cancel the files not started and stop the workers' running ones; clean up after the jobs
    not reported finished (:func:`~.file_job.remove_unfinished_outputs`)."""
    import multiprocessing

    pool.shutdown(wait=False, cancel_futures=True)
    workers = multiprocessing.active_children()  # this command's children are the pool's workers
    for worker in workers:
        worker.terminate()
    for worker in workers:
        worker.join()
    remove_unfinished_outputs(unreported)


def _process_one_in_worker(job: dict) -> tuple[str, bool, str, float, list[str]]:
    return process_one(job, _worker_references, worker_reference(job.get("shared_reference")))


def _expand_inputs(inputs: list[Path]) -> list[Path]:
    from ..core.io import DICOM_EXTENSIONS, PNG_EXTENSIONS, RAW_EXTENSIONS, TIFF_EXTENSIONS

    known = RAW_EXTENSIONS | TIFF_EXTENSIONS | PNG_EXTENSIONS | DICOM_EXTENSIONS
    files: list[Path] = []
    for item in inputs:
        if item.is_dir():
            files.extend(sorted(p for p in item.iterdir() if p.is_file() and p.suffix.lower() in known))
        else:
            files.append(item)
    return files


def _run_params(config: Path | None, *, dicom: bool | None, scheduler: str | None, jobs: int | None):
    """The parameter file (defaults without one) with the command line's options on top, checked
    as the file's values are."""
    from ..core.params import PipelineParams, load_params, validate_params

    params = load_params(config) if config is not None else PipelineParams()
    if dicom is not None:
        params.output.dicom = dicom
    if scheduler is not None:
        params.batch.scheduler = scheduler
    if jobs is not None:
        params.batch.jobs = jobs
    return validate_params(params)  # an option's value gets the parameter file's checks


def _plan_jobs(files: list[Path], out: Path, params, request: dict, *, overwrite: bool) -> list[dict]:
    """One job per input whose finished outputs do not match a rerun (all of them with
    ``overwrite``); says on stderr which files are skipped and why others are redone."""
    from ..core.params import params_to_dict
    from ..core.rerun import check_finished

    todo, skipped, redo = [], 0, {}
    checksums: dict = {}  # reference files are hashed once for the whole batch
    params_dict = params_to_dict(params)  # the same for every job
    for f in files:
        if not overwrite:
            check = check_finished(f, out, params, checksums=checksums, **request)
            if check.done:
                skipped += 1
                continue
            if not check.new:
                redo.setdefault(check.reason, []).append(f.name)
        todo.append({"input": str(f), "out_dir": str(out), "params": params_dict,
                     "flats": [str(p) for p in request["flat_paths"]], "darks": [str(p) for p in request["dark_paths"]],
                     "psf": str(request["psf_path"]) if request["psf_path"] else None,
                     "sod": request["source_to_object_mm"], "sdd": request["source_to_detector_mm"],
                     "patient": request["patient"]})
    if skipped:
        print(f"dslrxr: skipped {skipped} file(s): their finished outputs match the inputs, parameters "
              "and version (use --overwrite to redo)", file=sys.stderr)
    for reason, names in redo.items():
        shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
        print(f"dslrxr: redoing {shown}: {reason}", file=sys.stderr)
    return todo


def _run_jobs(todo: list[dict], params) -> int:
    """Run the jobs (one after the other, in a process pool, or on dask.distributed) and report
    each on stderr as it finishes; return how many failed."""
    failed = 0
    total = len(todo)

    def report(i: int, outcome: tuple[str, bool, str, float, list[str]]) -> None:
        nonlocal failed
        name, ok, message, seconds, warnings = outcome
        for warning in warnings:  # a stage skipped or guessed: one line each
            print(f"dslrxr: warning: {name}: {warning}", file=sys.stderr)
        if ok:
            print(f"[{i}/{total}] {name}: {message} ({seconds:.1f} s)", file=sys.stderr)
        else:
            failed += 1
            text = " ".join(message.split())
            text = text if text.startswith(name) else f"{name}: {text}"
            print(f"[{i}/{total}] dslrxr: error: {text}", file=sys.stderr)

    scheduler, jobs = params.batch.scheduler, params.batch.jobs
    if scheduler and total:
        from .cluster import run_on_cluster

        run_on_cluster(todo, scheduler=scheduler, n_workers=jobs, report=report)
    elif jobs > 1 and total > 1:
        with shared_reference(todo) as shared:
            pool = ProcessPoolExecutor(max_workers=min(jobs, total), initializer=_init_worker)
            reported = 0  # the pool's outcomes come in the order of todo
            try:
                # the workers start (fork) with the first job, before the thread preparing the reference
                outcomes = pool.map(_process_one_in_worker,
                                    [{**job, "shared_reference": shared.folder} for job in todo])
                shared.start()
                for reported, outcome in enumerate(outcomes, start=1):
                    report(reported, outcome)
            except BaseException:  # Ctrl-C, SIGTERM: stop now, not after the queued files
                _stop_pool(pool, todo[reported:])
                raise
            pool.shutdown()
    else:
        cache: dict = {}  # flats and darks are read and prepared once for the batch
        i = 0
        with freed_memory_kept(), sigterm_as_interrupt():
            try:
                for i, job in enumerate(todo, start=1):
                    report(i, process_one(job, cache))
            except BaseException:  # Ctrl-C, SIGTERM
                remove_unfinished_outputs(todo[i - 1:i])
                raise
    return failed


def register(app: typer.Typer) -> None:
    """Add ``run`` and ``params`` to ``app``."""

    @app.command("run")
    def run(
        inputs: list[Path] = typer.Argument(..., help="Camera raw / TIFF / PNG / DICOM files or folders."),
        out: Path = typer.Option(..., "-o", "--out", help="Output folder (created if needed)."),
        config: Path | None = typer.Option(None, "-c", "--config", help="Parameter file (dslrxr params --default)."),
        flat: list[Path] = typer.Option([], "--flat", help="Open-beam (flat) frame; repeat for several."),
        dark: list[Path] = typer.Option([], "--dark", help="Dark frame (X-rays off); repeat for several."),
        psf: Path | None = typer.Option(None, "--psf", help="PSF model JSON; turns on deblurring."),
        source_to_object_mm: float | None = typer.Option(None, "--source-to-object-mm", help="SOD for the PSF, mm."),
        source_to_detector_mm: float | None = typer.Option(None, "--source-to-detector-mm", help="SDD for the PSF, mm."),
        dicom: bool | None = typer.Option(
            None, "--dicom/--no-dicom", show_default=False,
            help="Write a DICOM DX file, or not (default: [output] dicom of the parameter file)."),
        patient_name: str | None = typer.Option(None, "--patient-name", help="DICOM PatientName (only if given)."),
        patient_id: str | None = typer.Option(None, "--patient-id", help="DICOM PatientID (only if given)."),
        jobs: int | None = typer.Option(None, "--jobs", "-j", min=1, max=64,
                                        help="Files processed in parallel on this machine: processes, or the "
                                             "LocalCluster's workers with --scheduler local (default [batch] jobs)."),
        scheduler: str | None = typer.Option(None, "--scheduler", help=(
            "Run the batch on dask.distributed: 'local' (a LocalCluster of --jobs processes) or a scheduler "
            "address such as tcp://host:8786 (default [batch] scheduler; none: process pool).")),
        overwrite: bool = typer.Option(False, "--overwrite", help="Redo files even when their outputs are finished."),
    ) -> int:
        """Run the whole pipeline on each input; write TIFF, PNG (and DICOM) with JSON sidecars.

        A file is skipped only when its finished outputs' sidecars record the same input
        checksums, parameters and version; otherwise it is processed again.
        """
        params = _run_params(config, dicom=dicom, scheduler=scheduler, jobs=jobs)
        if params.batch.scheduler:
            from .cluster import require_distributed

            require_distributed()  # says how to install it before any work is done
        if psf is not None and (source_to_object_mm is None or source_to_detector_mm is None):
            raise ParameterError("--psf needs --source-to-object-mm and --source-to-detector-mm")
        for ref in [*flat, *dark, *([psf] if psf else [])]:
            if not ref.is_file():
                raise ParameterError(f"{ref}: reference file not found")
        files = _expand_inputs(inputs)
        if not files:
            raise ParameterError("no input files found")
        if params.batch.scheduler not in ("", "local"):
            # workers elsewhere do not share this working folder: give them absolute names
            files, flat, dark = [f.absolute() for f in files], [p.absolute() for p in flat], [p.absolute() for p in dark]
            psf, out = (psf.absolute() if psf else None), out.absolute()
        out.mkdir(parents=True, exist_ok=True)
        request = {"flat_paths": flat, "dark_paths": dark, "psf_path": psf, "source_to_object_mm": source_to_object_mm,
                   "source_to_detector_mm": source_to_detector_mm,
                   "patient": {k: v for k, v in (("PatientName", patient_name), ("PatientID", patient_id)) if v}}
        todo = _plan_jobs(files, out, params, request, overwrite=overwrite)
        failed = _run_jobs(todo, params)
        if failed:
            print(f"dslrxr: {failed} of {len(todo)} file(s) failed", file=sys.stderr)
            raise typer.Exit(1)
        return 0

    @app.command("params")
    def params_cmd(
        default: bool = typer.Option(False, "--default", help="Print the full default parameter file."),
        check: Path | None = typer.Option(None, "--check", help="Validate a parameter file."),
    ) -> int:
        """Print the default parameter file (with a comment per key) or check one."""
        from ..core.params import default_params_toml, load_params

        if check is not None:
            load_params(check)
            print(f"{check}: ok")
            return 0
        if not default:
            raise ParameterError("give --default (print the defaults) or --check FILE")
        sys.stdout.write(default_params_toml())
        return 0
