"""Errors meant for the user: one line, naming the file and the problem.

Every failure caused by bad input (a corrupt file, a wrong shape, NaN pixels, a missing
parameter) raises :class:`DslrxrError` or a subclass. The command line prints its message on
one line and exits non-zero; the napari widgets turn it into a notification. Anything else
that escapes is a bug in this package.
"""

from __future__ import annotations

from os import PathLike


class DslrxrError(Exception):
    """A user-facing error with a one-line message."""

    def __init__(self, message: str):
        # Keep the message on one line whatever the caller passed in.
        super().__init__(" ".join(str(message).split()))


class InputError(DslrxrError):
    """A bad input file or array.

    Parameters
    ----------
    source : str or path-like or None
        The file (or a short description such as ``"flat frame"``) the problem is in.
    problem : str
        What is wrong with it, e.g. ``"truncated TIFF (strip 3 of 7 missing)"``.
    """

    def __init__(self, source: str | PathLike | None, problem: str):
        self.source = None if source is None else str(source)
        self.problem = problem
        super().__init__(problem if source is None else f"{source}: {problem}")

    def __reduce__(self):
        # Rebuild from (source, problem), so the error survives pickling, e.g. on its way back
        # from a worker process of a parallel batch.
        return (type(self), (self.source, self.problem))


class ParameterError(DslrxrError):
    """A parameter out of range, of the wrong type, unknown or missing."""


class OutputError(DslrxrError):
    """An output that cannot or must not be written (for example, it would overwrite an input)."""


class WorkCancelled(DslrxrError):
    """The user cancelled a long stage.

    Long core stages take a ``progress`` callable and call it between their steps (chunks,
    passes, channels); a caller that wants them to stop raises this from that callable, and
    the stage lets it propagate: nothing half-made is returned. The core itself never raises
    it.
    """
