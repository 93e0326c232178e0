"""Golden outputs: the exact bytes the ``dslrxr`` process writes for fixed, generated inputs.

These tests pin behaviour while code is moved or restructured: any change to a number in the
pipeline (impulse removal, flat field, region, deblurring, dynamic range, contrast), the PSF fit,
the simulator or the diagnosis changes a hash here.

Inputs are made by the project's own seeded generators (the demo's DSLR-like frame with flat,
dark and edge radiographs; the simulator's phantom scene), small so the whole module runs in a
few seconds. Every command runs in its own ``dslrxr`` process, as a user would run it.

What is hashed (sha256):

* ``dslrxr run`` outputs: the 16-bit TIFF, the PNG preview and the DICOM DX file, as bytes;
* ``dslrxr simulate`` recording (float32 TIFF), as bytes;
* ``psf.json`` from ``dslrxr psf fit`` and ``diagnosis.json`` from ``dslrxr diagnose``: parsed,
  the fields in :data:`VOLATILE_JSON_KEYS` dropped at any depth, then dumped with sorted keys.

Sidecars (``<file>.json``) are not hashed: they hold input paths (a temporary folder here),
timings and library versions by design.

The expected hashes live in ``tests/golden_hashes.json``. After an intended change of results,
regenerate them with ``DSLRXR_REGEN_GOLDEN=1 python -m pytest tests/test_golden.py`` and say in
the commit why the outputs changed.

Each set of hashes in the file records the environment it was made in (:func:`environment`: the
numerical libraries' versions and the CPU's SIMD features numpy dispatches to). Floating-point
results may differ in the last bit with either (a new OpenBLAS kernel, an AVX-512 sort), so the
file keeps one set per environment the project runs in (this workplace's machine kinds: AVX2 and
AVX-512 CPUs) and the test compares with the set of the environment it runs in. Where it has none,
a changed hash cannot tell a code change from a library change: the test is then skipped with the
differences from the nearest set named, instead of failing on code that did not change.
``DSLRXR_REGEN_GOLDEN=1`` replaces this environment's set; when its hashes changed (the results
did) or it had none, the other environments' sets are dropped, since they may no longer describe
the code: regenerate on those machines too. ``DSLRXR_REGEN_GOLDEN=add`` adds a set for an
environment that has none and keeps the others, for code whose outputs are unchanged where a set
exists (where this environment has a set, it acts as ``1``). The test environment is pinned
(``requirements/test-constraints.txt``).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from scenes import PHANTOM_SCENE_TOML

GOLDEN_FILE = Path(__file__).with_name("golden_hashes.json")
#: "1": regenerate this environment's set (after an intended change of results); "add": add a
#: set for a new environment beside the others (the same code, checked on a machine that has a set).
REGENERATE = os.environ.get("DSLRXR_REGEN_GOLDEN", "")

#: JSON keys dropped before hashing, and why: run times differ from run to run ("timings_s",
#: "elapsed_s", "seconds"; "fit_time_s" of older psf.json files); the package and library versions
#: and the creation date change without any change of results ("version", "versions",
#: "library_versions", "created"); input and output paths name the temporary folder of the test ("path", "inputs", "output",
#: "outputs").
VOLATILE_JSON_KEYS = frozenset({"timings_s", "elapsed_s", "seconds", "fit_time_s", "version", "versions",
                                "library_versions", "created", "path", "inputs", "output", "outputs"})

FRAME_SHAPE = (192, 288)
SOURCE_TO_OBJECT_MM = 1150.0
SOURCE_TO_DETECTOR_MM = 1200.0

SCENE = PHANTOM_SCENE_TOML


#: Libraries whose releases can move a floating-point result of the pipeline.
NUMERICAL_LIBRARIES = ("numpy", "scipy", "scikit-image", "opencv-contrib-python-headless", "tifffile",
                       "pydicom", "matplotlib", "rawpy")


def environment() -> dict:
    """The numerical libraries' versions and the CPU features numpy dispatches to."""
    from importlib.metadata import PackageNotFoundError, version

    libraries = {}
    for name in NUMERICAL_LIBRARIES:
        try:
            libraries[name] = version(name)
        except PackageNotFoundError:
            libraries[name] = None
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as features
    except ImportError:  # numpy < 2
        from numpy.core._multiarray_umath import __cpu_features__ as features
    return {"libraries": libraries, "cpu_features": sorted(k for k, on in features.items() if on)}


def environment_differences(recorded: dict | None, current: dict) -> list[str]:
    """What differs between the environment the hashes were made in and this one."""
    if not recorded:
        return ["the hashes do not record their environment"]
    out = [f"{name} {recorded['libraries'].get(name)} -> {current['libraries'].get(name)}"
           for name in sorted(set(recorded["libraries"]) | set(current["libraries"]))
           if recorded["libraries"].get(name) != current["libraries"].get(name)]
    gone = sorted(set(recorded["cpu_features"]) - set(current["cpu_features"]))
    new = sorted(set(current["cpu_features"]) - set(recorded["cpu_features"]))
    if gone or new:
        out.append(" ".join(["CPU features", *(["-" + ",".join(gone)] if gone else []),
                             *(["+" + ",".join(new)] if new else [])]))
    return out


def _dslrxr(*args: str | Path) -> None:
    """Run one ``dslrxr`` command in its own process; fail the test with its stderr if it fails."""
    proc = subprocess.run([sys.executable, "-m", "napari_dslrxr.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"dslrxr {' '.join(map(str, args))} exited {proc.returncode}: {proc.stderr}"


def _strip_volatile(value):
    if isinstance(value, dict):
        return {k: _strip_volatile(v) for k, v in value.items() if k not in VOLATILE_JSON_KEYS}
    if isinstance(value, list):
        return [_strip_volatile(v) for v in value]
    return value


def _file_hash(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _json_hash(path: Path) -> str:
    stable = _strip_volatile(json.loads(path.read_text(encoding="utf-8")))
    return hashlib.sha256(json.dumps(stable, sort_keys=True).encode()).hexdigest()


def produce_outputs(folder: Path) -> dict[str, str]:
    """Generate the inputs in ``folder``, run the commands, return {output name: sha256}."""
    from napari_dslrxr.core.io import write_tiff
    from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph
    from napari_dslrxr.core.simulation.simulator import phantom_thickness_mm
    from napari_dslrxr.demo import write_edge_radiographs

    inputs = folder / "input"
    inputs.mkdir(parents=True)
    frames = make_dslr_radiograph(FRAME_SHAPE, seed=0)
    for name, arr in (("radiograph", frames.raw_rgb), ("flat", frames.flat), ("dark", frames.dark)):
        write_tiff(inputs / f"{name}.tif", arr)
    edges = write_edge_radiographs(inputs, frames.truth.blur_sigma_px, seed=0)
    write_tiff(inputs / "thickness.tif", phantom_thickness_mm((96, 96)))
    scene = inputs / "scene.toml"
    scene.write_text(SCENE, encoding="utf-8")

    out = folder / "out"
    out.mkdir()
    _dslrxr("psf", "fit", edges, "-o", out / "psf.json")
    # psf.json holds no time stamp, so the run reads it as written (its checksum seeds the DICOM UIDs).
    _dslrxr("run", inputs / "radiograph.tif", "--flat", inputs / "flat.tif", "--dark", inputs / "dark.tif",
            "--psf", out / "psf.json", "--source-to-object-mm", SOURCE_TO_OBJECT_MM,
            "--source-to-detector-mm", SOURCE_TO_DETECTOR_MM, "--dicom", "-o", out)
    _dslrxr("simulate", scene, "-o", out / "recording.tif",
            "--effect", "mirror_ghost=epsilon:0.03,shift_mm:0.4", "--seed", "4")
    _dslrxr("diagnose", scene, out / "recording.tif", "-o", out / "diagnosis")

    hashes = {name: _file_hash(out / name) for name in
              ("radiograph_dslrxr.tif", "radiograph_dslrxr.png", "radiograph_dslrxr.dcm", "recording.tif")}
    hashes["psf.json"] = _json_hash(out / "psf.json")
    hashes["diagnosis.json"] = _json_hash(out / "diagnosis" / "diagnosis.json")
    return hashes


@pytest.fixture(scope="module")
def produced(tmp_path_factory) -> dict[str, str]:
    return produce_outputs(tmp_path_factory.mktemp("golden"))


def read_golden_sets(path: Path = GOLDEN_FILE) -> list[dict]:
    """The file's hash sets, each ``{"environment": ..., "hashes": ...}``; none without a file."""
    if not path.exists():
        return []
    return json.loads(path.read_text(encoding="utf-8"))["sets"]


def made_in(candidate: dict, here: dict) -> bool:
    """Whether a hash set was made in environment ``here`` (same libraries and CPU features)."""
    return not environment_differences(candidate.get("environment"), here)


def with_regenerated_set(sets: list[dict], here: dict, produced: dict[str, str], *, add: bool = False) -> list[dict]:
    """The sets after regenerating in environment ``here``: its own set replaced or added; the
    other environments' sets kept only when this environment's hashes did not change (the same
    results, so theirs still hold) or, with ``add``, when it had no set (a new environment for
    unchanged code), sorted so the file's bytes do not depend on the order."""
    own = [s for s in sets if made_in(s, here)]
    keep_others = own[0]["hashes"] == produced if own else add
    others = [s for s in sets if not made_in(s, here)] if keep_others else []
    new = [*others, {"environment": here, "hashes": produced}]
    return sorted(new, key=lambda s: json.dumps(s["environment"], sort_keys=True))


def set_for(sets: list[dict], here: dict) -> tuple[dict | None, list[str]]:
    """The set made in environment ``here``, or None and what differs from the nearest set."""
    for candidate in sets:
        if made_in(candidate, here):
            return candidate, []
    nearest = min((environment_differences(s.get("environment"), here) for s in sets), key=len,
                  default=["the file holds no hashes"])
    return None, nearest


@pytest.mark.slow
def test_outputs_match_the_golden_hashes(produced):
    here = environment()
    sets = read_golden_sets()
    if REGENERATE in ("1", "add"):
        record = {"sets": with_regenerated_set(sets, here, produced, add=REGENERATE == "add")}
        GOLDEN_FILE.write_text(json.dumps(record, indent=2, sort_keys=True) + "\n", encoding="utf-8")
        pytest.skip(f"regenerated {GOLDEN_FILE.name} ({len(record['sets'])} environment(s))")
    golden, differences = set_for(sets, here)
    if golden is None:
        pytest.skip(f"no golden hashes for this environment ({'; '.join(differences)}): regenerate here "
                    "with DSLRXR_REGEN_GOLDEN=add, on code whose outputs match a set elsewhere")
    expected = golden["hashes"]
    assert set(produced) == set(expected)
    changed = sorted(name for name in expected if produced[name] != expected[name])
    assert not changed, f"outputs changed: {changed} (regenerate with DSLRXR_REGEN_GOLDEN=1 if intended)"


def test_regenerating_keeps_other_environments_only_for_the_same_results():
    here = environment()
    other = {"libraries": here["libraries"], "cpu_features": [*here["cpu_features"], "AVX512X"]}
    old = {"a.tif": "1", "b.json": "2"}
    sets = [{"environment": other, "hashes": {"a.tif": "9", "b.json": "8"}}, {"environment": here, "hashes": old}]
    # same results here: the other machine's set still describes the code
    kept = with_regenerated_set(sets, here, dict(old))
    assert len(kept) == 2 and set_for(kept, other)[0]["hashes"] == {"a.tif": "9", "b.json": "8"}
    # changed results: the other set is stale and goes; that environment then skips, naming why
    changed = with_regenerated_set(sets, here, {"a.tif": "1", "b.json": "3"})
    assert changed == [{"environment": here, "hashes": {"a.tif": "1", "b.json": "3"}}]
    missing, why = set_for(changed, other)
    assert missing is None and why == ["CPU features +AVX512X"]
    # a first set in a new environment: beside the others when asked to add, alone otherwise
    elsewhere = [s for s in sets if s["environment"] == other]
    assert with_regenerated_set(elsewhere, here, old, add=True) == kept
    assert with_regenerated_set(elsewhere, here, old) == [{"environment": here, "hashes": old}]
    # "add" where this environment has a set with other results: the other sets are stale too
    assert with_regenerated_set(sets, here, {"a.tif": "1", "b.json": "3"}, add=True) == changed
    # the file's order does not depend on the order of regeneration
    assert with_regenerated_set(sets[::-1], here, dict(old)) == kept


def test_the_golden_file_holds_sets_with_environments():
    sets = read_golden_sets()
    assert sets, "tests/golden_hashes.json holds no hash set"
    for candidate in sets:
        assert set(candidate) == {"environment", "hashes"}
        assert {"libraries", "cpu_features"} <= set(candidate["environment"])
    environments = [json.dumps(s["environment"], sort_keys=True) for s in sets]
    assert len(set(environments)) == len(environments), "two sets for one environment"


def test_environment_differences_name_what_changed():
    here = environment()
    assert environment_differences(here, here) == []
    older = {"libraries": {**here["libraries"], "numpy": "1.0.0"}, "cpu_features": here["cpu_features"] + ["AVX512X"]}
    differences = environment_differences(older, here)
    assert differences[0] == f"numpy 1.0.0 -> {here['libraries']['numpy']}"
    assert differences[1] == "CPU features -AVX512X"
    assert environment_differences(None, here) == ["the hashes do not record their environment"]


def test_volatile_fields_are_the_only_ones_dropped(tmp_path):
    """The JSON hash ignores timings and paths but not a result: a changed number changes it."""
    doc = {"model": {"fwhm_mm": 0.25}, "timings_s": {"fit": 1.0}, "inputs": [{"path": "/a"}]}
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps(doc))
    b.write_text(json.dumps({**doc, "timings_s": {"fit": 9.0}, "inputs": [{"path": "/b"}]}))
    assert _json_hash(a) == _json_hash(b)
    b.write_text(json.dumps({**doc, "model": {"fwhm_mm": float(np.nextafter(0.25, 1.0))}}))
    assert _json_hash(a) != _json_hash(b)
