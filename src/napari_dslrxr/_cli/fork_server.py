"""Imported last by the fork server of ``dslrxr run --scheduler local`` (see
:func:`~.cluster._worker_start_method`): the server ends without tearing down its interpreter.

The server only forks workers; it has nothing to write or close when the command stops it at the
end of a batch, but the teardown of the modules it imported for its workers (numpy, OpenCV,
dask, the pipeline) took about 1 s on a loaded 2-core machine, while the command waited for it.
Its workers are forked with this exit hook too; it does nothing in them (another process id).
"""

from __future__ import annotations

import atexit
import os
import sys


def _exit_now(server_pid: int) -> None:
    if os.getpid() == server_pid:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (AttributeError, OSError, ValueError):  # closed or absent (the server closes stdin only)
                pass
        os._exit(0)


# the last exit hook registered runs first: the interpreter's teardown is skipped
atexit.register(_exit_now, os.getpid())
