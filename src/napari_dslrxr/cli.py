"""The ``dslrxr`` command: the headless core from a shell, for batch work and CI.

Each group of sub-commands lives in its own module under ``_cli/`` and registers itself on
the one Typer app here. :func:`main` turns user mistakes (:class:`DslrxrError`, usage errors)
into a one-line message on stderr and a non-zero exit code, never a traceback.

Exit codes: 0 success; 1 a batch finished but some files failed; 2 bad input, parameters,
usage or a refused write; 3 an internal error (a bug: one line, the traceback with
DSLRXR_DEBUG=1); 130 interrupted.
"""

from __future__ import annotations

import os
import sys
import warnings

import typer

try:  # recent typer vendors click; older versions use the click package
    from typer._click.exceptions import ClickException
except ImportError:  # pragma: no cover
    from click.exceptions import ClickException

from .core.errors import DslrxrError

EXIT_OK = 0
EXIT_SOME_FAILED = 1
EXIT_USAGE = 2
EXIT_INTERNAL = 3
EXIT_INTERRUPTED = 130

app = typer.Typer(
    name="dslrxr",
    help="Digital radiography from a DSLR photographing an X-ray scintillator.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root() -> None:
    """Digital radiography from a DSLR photographing an X-ray scintillator."""


def _register_commands() -> None:
    from ._cli import blur, deconvolve, denoise, pipeline, simulate, view

    for module in (denoise, pipeline, blur, deconvolve, simulate, view):
        module.register(app)


_register_commands()


def error_line(message: str) -> None:
    """Print a one-line error to stderr in the project's format."""
    print(f"dslrxr: error: {' '.join(str(message).split())}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit code (the console script exits with it)."""
    with warnings.catch_warnings():
        # Library warnings (numpy, tifffile, pydicom) would add lines to the one-line error
        # contract; DSLRXR_DEBUG=1 shows them.
        if not os.environ.get("DSLRXR_DEBUG"):
            warnings.simplefilter("ignore")
        return _run(argv)


def _run(argv: list[str] | None) -> int:
    command = typer.main.get_command(app)
    try:
        result = command.main(args=argv, prog_name="dslrxr", standalone_mode=False)
    except typer.Exit as exc:
        return exc.exit_code
    except typer.Abort:
        error_line("aborted")
        return EXIT_INTERRUPTED
    except ClickException as exc:
        if type(exc).__name__ == "NoArgsIsHelpError":
            exc.show()  # prints the help text
            return EXIT_USAGE
        error_line(f"{exc.format_message()} (see 'dslrxr --help')")
        return exc.exit_code if exc.exit_code else EXIT_USAGE
    except DslrxrError as exc:
        error_line(str(exc))
        return EXIT_USAGE
    except KeyboardInterrupt:
        error_line("interrupted")
        return EXIT_INTERRUPTED
    except MemoryError:
        error_line("out of memory; try a smaller image or raise the machine's memory")
        return EXIT_USAGE
    except OSError as exc:  # the file system refused: disk full, permission denied, closed pipe
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        error_line(f"{where}{exc.strerror or exc}")
        return EXIT_USAGE
    except Exception as exc:  # a bug: still one line, the traceback only on request
        if os.environ.get("DSLRXR_DEBUG"):
            raise
        error_line(f"internal error ({type(exc).__name__}: {exc}); please report it "
                   "(set DSLRXR_DEBUG=1 to see the traceback)")
        return EXIT_INTERNAL
    return result if isinstance(result, int) else EXIT_OK


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
