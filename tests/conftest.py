"""Shared fixtures: the real data folder (skipped with a reason when absent) and seeded RNGs.

Every test that uses the ``shared_data`` fixture, directly or through another fixture, gets the
``realdata`` marker at collection, so ``-m "not realdata"`` leaves out the tests that read the
real data; a test that asks for the folder only at run time (``request.getfixturevalue``) carries
the marker itself.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path:
    """The real data folder: $DSLRXR_DATA, default ../shared/data beside the checkout."""
    env = os.environ.get("DSLRXR_DATA")
    return Path(env) if env else (REPO_ROOT.parent / "shared" / "data")


def pytest_collection_modifyitems(config, items):
    # fixturenames is the whole fixture closure: a fixture built on shared_data counts too
    for item in items:
        if "shared_data" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.realdata)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of the third-party real data set; skips the test when it is not there."""
    folder = shared_data_dir()
    if not folder.is_dir():
        pytest.skip(f"real data folder {folder} is absent (set DSLRXR_DATA to run this test)")
    return folder


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded generator, so synthetic test data are the same on every run."""
    return np.random.default_rng(20261122)


@pytest.fixture(scope="session")
def phantom_scene_text() -> str:
    """A simulator scene over the phantom thickness map ``thickness.tif`` beside it."""
    from scenes import PHANTOM_SCENE_TOML

    return PHANTOM_SCENE_TOML
