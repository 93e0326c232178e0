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

# Before numpy is imported (it reads this once): no transparent huge pages for its arrays.
# With the kernel's "defrag = madvise" a huge-page fault may stall for compaction; together
# with keep_freed_arrays_mapped it halved the system time of a 24 Mpx denoise (docs/impulse.md,
# 'Speed'). The user's own setting wins.
os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")

import typer  # noqa: E402

try:  # recent typer vendors click; older versions use the click package
    from typer._click.exceptions import ClickException
except ImportError:  # pragma: no cover
    from click.exceptions import ClickException

from ._cli.common import HELP_MARKUP_MODE
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
    rich_markup_mode=HELP_MARKUP_MODE,
)


def _print_version(value: bool) -> None:
    if value:
        from . import __version__

        typer.echo(f"dslrxr (napari-dslrxr) {__version__}")
        raise typer.Exit(EXIT_OK)


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", is_eager=True, callback=_print_version,
                                 help="Print the package version and exit."),
) -> None:
    """Digital radiography from a DSLR photographing an X-ray scintillator."""


def _register_commands() -> None:
    from ._cli import blur, deconvolve, denoise, pipeline, qc, simulate, view

    for module in (denoise, pipeline, blur, deconvolve, simulate, qc, view):
        module.register(app)


_register_commands()


def error_line(message: str) -> None:
    """Print a one-line error to stderr in the project's format."""
    print(f"dslrxr: error: {' '.join(str(message).split())}", file=sys.stderr)


#: glibc mallopt parameters (malloc.h): M_TRIM_THRESHOLD, M_MMAP_THRESHOLD.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_HEAP_KEPT_BYTES = 1 << 30


def keep_freed_arrays_mapped() -> bool:
    """Let glibc serve and keep large arrays in the heap instead of mapping each anew.

    By default glibc maps every allocation over 32 MB (a 24 Mpx float32 plane is 96 MB) on
    its own and unmaps it when freed, so the next plane's pages are faulted in and zeroed
    again: with huge pages off, 1.4-2.7 s of system time of a 24 Mpx ``dslrxr denoise``
    fell to 0.6-1.4 s (docs/impulse.md, 'Speed'). A batch command is short-lived and its arrays come and go
    in the same sizes, so freed memory is kept for reuse. Not for ``dslrxr view`` (a
    long-lived process). Returns whether the allocator took the setting (False off glibc).
    """
    try:  # glibc only (musl and macOS have no such setting; confstr raises there)
        if not (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc"):
            return False
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(_M_MMAP_THRESHOLD, _HEAP_KEPT_BYTES)
                    and libc.mallopt(_M_TRIM_THRESHOLD, _HEAP_KEPT_BYTES))
    except (OSError, ValueError, AttributeError):
        return False


def main(argv: list[str] | None = None) -> int:
    """Run the command line; return the exit code (the console script exits with it)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args[:1] != ["view"]:
        keep_freed_arrays_mapped()
    with warnings.catch_warnings():
        # Library warnings (numpy, tifffile, pydicom) would add lines to the one-line error
        # contract; DSLRXR_DEBUG=1 shows them.
        if not os.environ.get("DSLRXR_DEBUG"):
            warnings.simplefilter("ignore")
        return _run(args)


#: Words a user may write after an on/off flag ("--dicom true"); click would take them as the
#: next positional argument (an input file named "true").
_BOOLEAN_WORDS = frozenset({"true", "false", "yes", "no", "on", "off", "1", "0", "y", "n", "t", "f"})


def check_flag_values(command, argv: list[str]) -> None:
    """Refuse a boolean word right after an on/off flag, unless a file of that name exists.

    ``--dicom true`` is a flag followed by a positional argument to click; the user meant a
    value. Raises :class:`ParameterError` naming the flag and its two spellings.
    """
    from pathlib import Path

    from .core.errors import ParameterError

    current = command
    for i, token in enumerate(argv):
        if token == "--":
            return
        subcommands = getattr(current, "commands", None)
        if subcommands and token in subcommands:
            current = subcommands[token]
            continue
        for param in getattr(current, "params", []):
            if not getattr(param, "is_flag", False) or getattr(param, "count", False):
                continue
            if token not in (*param.opts, *param.secondary_opts) or i + 1 >= len(argv):
                continue
            value = argv[i + 1]
            if value.lower() in _BOOLEAN_WORDS and not Path(value).exists():
                spellings = " or ".join((*param.opts, *param.secondary_opts)[:2])
                raise ParameterError(f"{token} is an on/off flag and takes no value (got {value!r}); "
                                     f"write {spellings}")


def _run(args: list[str]) -> int:
    command = typer.main.get_command(app)
    try:
        check_flag_values(command, args)
        result = command.main(args=args, prog_name="dslrxr", standalone_mode=False)
        if result == EXIT_INTERRUPTED:  # typer turns Ctrl-C into this exit code, silently
            error_line("interrupted")
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
