"""Progress of a long core stage: ``progress(done, total)`` called between its steps.

The convention of every long stage (deconvolution, PSF fit, impulse removal, flat field): an
optional callable the stage calls between chunks, passes or channels. A caller that wants to
stop the stage raises :class:`napari_dslrxr.core.errors.WorkCancelled` from it; the stage
lets it propagate and returns nothing half-made. The core never starts threads.
"""

from __future__ import annotations

from collections.abc import Callable

#: ``progress(done, total)``; its return value is ignored.
ProgressCallback = Callable[[int, int], object]


class Steps:
    """Counts a stage's steps and reports each one as ``progress(done, total)``.

    ``progress`` None: counting only (the stage reads the same with or without a caller).
    """

    def __init__(self, progress: ProgressCallback | None, total: int):
        self.progress = progress
        self.total = max(int(total), 1)
        self.done = 0

    def advance(self, n: int = 1) -> None:
        """``n`` more steps are done; report them (the caller may raise here to stop)."""
        self.done = min(self.done + n, self.total)
        self.check()

    def to(self, done: int) -> None:
        """Jump to ``done`` (steps skipped, e.g. passes not needed); report it."""
        self.done = min(max(self.done, int(done)), self.total)
        self.check()

    def check(self) -> None:
        """Report the current count again (between chunks of one long step)."""
        if self.progress is not None:
            self.progress(self.done, self.total)
