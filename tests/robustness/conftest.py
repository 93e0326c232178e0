"""Robustness tests: print (and optionally save) how many fuzz cases ran per reader."""

from __future__ import annotations

import collections
import json
import os

import pytest
from robustness.fuzzing import FAILURES, FUZZ_LOG


@pytest.fixture(autouse=True)
def _no_failures_collected():
    """In the big local run failures are collected rather than raised; fail the test at its end."""
    before = set(FAILURES)
    yield
    new = {k: v for k, v in FAILURES.items() if k not in before}
    assert not new, "distinct failure kinds: " + "; ".join(f"{k}: {v}" for k, v in new.items())


def pytest_terminal_summary(terminalreporter):
    if FAILURES:
        terminalreporter.section("dslrxr fuzz: distinct failure kinds")
        for key, text in FAILURES.items():
            terminalreporter.write_line(f"{key}: {text}")
    if not FUZZ_LOG:
        return
    per_reader: dict[str, dict[str, int]] = collections.defaultdict(dict)
    for (reader, kind), n in sorted(FUZZ_LOG.items()):
        per_reader[reader][kind] = n
    terminalreporter.section("dslrxr fuzz cases per reader")
    for reader, kinds in per_reader.items():
        total = sum(kinds.values())
        detail = ", ".join(f"{k} {n}" for k, n in kinds.items())
        terminalreporter.write_line(f"{reader:>14}: {total:6d} cases ({detail})")
    report = os.environ.get("DSLRXR_FUZZ_REPORT")
    if report:
        with open(report, "w", encoding="utf-8") as fh:
            json.dump(per_reader, fh, indent=2, sort_keys=True)
