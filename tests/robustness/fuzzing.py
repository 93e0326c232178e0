"""Fuzzing budget and bookkeeping for the robustness tests (shared by their modules).

Two hypothesis profiles, used as decorators through :func:`fuzz_settings` (never loaded
globally, so other areas' hypothesis tests keep their own settings):

* ``dslrxr-ci`` (default): a modest, derandomised number of cases per reader, so CI is
  reproducible and bounded.
* ``dslrxr-fuzz``: thousands of random cases per reader; run it locally with
  ``DSLRXR_FUZZ=fuzz .venv/bin/python -m pytest tests/robustness -p no:xvfb -q -s``
  (``DSLRXR_FUZZ_EXAMPLES`` sets the number of cases).

Every fuzz test records each case (reader, outcome kind) in :data:`FUZZ_LOG`; the terminal
summary prints the counts per reader and, with ``DSLRXR_FUZZ_REPORT=file.json``, writes them.
"""

from __future__ import annotations

import collections
import faulthandler
import os
import re
import resource
import sys
import traceback
from pathlib import Path

from hypothesis import HealthCheck, settings

from napari_dslrxr.core.errors import DslrxrError

_CI_EXAMPLES = 40
_SUPPRESS = [HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much,
             HealthCheck.function_scoped_fixture]

settings.register_profile("dslrxr-ci", max_examples=_CI_EXAMPLES, derandomize=True, deadline=None,
                          suppress_health_check=_SUPPRESS, database=None, print_blob=True)
settings.register_profile("dslrxr-fuzz", max_examples=int(os.environ.get("DSLRXR_FUZZ_EXAMPLES", "2000")),
                          derandomize=False, deadline=None, suppress_health_check=_SUPPRESS,
                          print_blob=True)

#: (reader, outcome kind) -> number of cases, over the whole session.
FUZZ_LOG: collections.Counter = collections.Counter()


def fuzz_settings(scale: float = 1.0) -> settings:
    """The active profile's settings, with ``max_examples`` scaled for expensive readers."""
    name = "dslrxr-fuzz" if os.environ.get("DSLRXR_FUZZ") == "fuzz" else "dslrxr-ci"
    base = settings.get_profile(name)
    return settings(base, max_examples=max(5, int(base.max_examples * scale)))


#: Distinct unexpected failures (reader, exception type, where) collected in the big local run,
#: which keeps going after a failure to find every kind; CI fails on the first one.
FAILURES: dict[tuple[str, str, str], str] = {}

#: A case that takes longer than this is a hang: the watchdog ends the process with a traceback.
HANG_S = 60
#: Extra address space a case may use; beyond it an allocation fails (a "memory blow-up").
MEMORY_HEADROOM_BYTES = 3 << 30
#: A case whose peak resident memory grows by more than this (512 MB) is a blow-up too.
MEMORY_GROWTH_KIB = 512 << 10


def big_run() -> bool:
    return os.environ.get("DSLRXR_FUZZ") == "fuzz"


def _address_space_bytes() -> int:
    try:
        return int(Path("/proc/self/statm").read_text().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return 0


def check_outcome(reader: str, call, source=None, *, success_kind: str | None = "read"):
    """Run ``call()`` and accept only a result or the project's one-line error.

    Returns the result, or None when the project's :class:`DslrxrError` was raised (its
    message must be one line, name ``source`` when given, and not be the readers'
    out-of-memory refusal, which would mean the size limit did not act before allocating).
    Any other exception, a case that grows the peak memory by more than
    :data:`MEMORY_GROWTH_KIB` or one that hangs for :data:`HANG_S` is a failure: raised at
    once in CI, recorded by kind in the big run.
    """
    peak_before_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    used = _address_space_bytes()
    old_limit = resource.getrlimit(resource.RLIMIT_AS)
    if used:
        cap = used + MEMORY_HEADROOM_BYTES
        if old_limit[1] != resource.RLIM_INFINITY:
            cap = min(cap, old_limit[1])
        resource.setrlimit(resource.RLIMIT_AS, (cap, old_limit[1]))
    faulthandler.dump_traceback_later(HANG_S, exit=True, file=sys.__stderr__)
    result, kind = None, success_kind
    try:
        result = call()
    except DslrxrError as exc:
        message, kind = str(exc), "refused"
        problems = []
        if "\n" in message:
            problems.append("message has several lines")
        if source is not None and str(source) not in message:
            problems.append("message does not name the file")
        if "too large to decode in memory" in message:  # the readers' MemoryError path
            problems.append("ran out of memory instead of refusing the declared size")
        if problems:
            _fail(reader, AssertionError("; ".join(problems) + f": {message!r}"))
    except Exception as exc:  # anything else is a bug
        _fail(reader, exc)
        return None
    finally:
        faulthandler.cancel_dump_traceback_later()
        resource.setrlimit(resource.RLIMIT_AS, old_limit)
    grown_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak_before_kib
    if grown_kib > MEMORY_GROWTH_KIB:
        _fail(reader, AssertionError(f"peak memory grew by {grown_kib // 1024} MB in one case"))
    if kind:
        FUZZ_LOG[(reader, kind)] += 1
    return result


def _fail(reader: str, exc: BaseException) -> None:
    FUZZ_LOG[(reader, "FAILED")] += 1
    if not big_run():
        raise exc
    frames = traceback.extract_tb(exc.__traceback__)
    where = f"{Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else "?"
    if isinstance(exc, AssertionError):  # an oracle's verdict: the kind is in its message
        where = re.sub(r"/\S+", "<path>", str(exc).split(" [from ")[0])[:120]
    FAILURES.setdefault((reader, type(exc).__name__, where), f"{type(exc).__name__}: {exc}"[:300])
