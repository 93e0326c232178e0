"""The npe2 manifest: valid with every python_name importable, and shipped inside the wheel."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import yaml

REPO_ROOT = Path(__file__).resolve().parents[1]
MANIFEST = REPO_ROOT / "napari.yaml"
PACKAGE_MANIFEST = REPO_ROOT / "src" / "napari_dslrxr" / "napari.yaml"


def _npe2() -> list[str]:
    exe = Path(sys.executable).with_name("npe2")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "npe2"]


def test_npe2_validate_with_imports():
    result = subprocess.run([*_npe2(), "validate", "--imports", str(MANIFEST)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "valid" in result.stdout


def test_npe2_validate_catches_a_wrong_python_name(tmp_path):
    """The check above can fail: a manifest pointing at a missing function is rejected."""
    broken = MANIFEST.read_text().replace("_reader:get_reader", "_reader:no_such_function", 1)
    assert broken != MANIFEST.read_text()
    path = tmp_path / "napari.yaml"
    path.write_text(broken)
    result = subprocess.run([*_npe2(), "validate", "--imports", str(path)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode != 0


def test_package_manifest_is_the_top_level_one():
    assert PACKAGE_MANIFEST.is_symlink()
    assert PACKAGE_MANIFEST.resolve() == MANIFEST.resolve()


def test_every_contribution_points_at_a_declared_command():
    manifest = yaml.safe_load(MANIFEST.read_text())
    contributions = manifest["contributions"]
    command_ids = {c["id"] for c in contributions["commands"]}
    used = [r["command"] for r in contributions.get("readers", [])]
    used += [w["command"] for w in contributions.get("widgets", [])]
    used += [s["command"] for s in contributions.get("sample_data", [])]
    used += [w["command"] for w in contributions.get("writers", [])]
    assert set(used) <= command_ids
    assert all(cid.startswith("napari-dslrxr.") for cid in command_ids)
    for menu_items in contributions.get("menus", {}).values():
        assert {item["command"] for item in menu_items if "command" in item} <= command_ids


@pytest.mark.slow
def test_wheel_contains_the_manifest(tmp_path):
    """Build the wheel from a copy of the sources (no network, no build isolation)."""
    pytest.importorskip("setuptools")
    src = tmp_path / "src_copy"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "napari.yaml", "LICENSE"):
        if (REPO_ROOT / name).exists():
            shutil.copy2(REPO_ROOT / name, src / name)
    shutil.copytree(REPO_ROOT / "src", src / "src", symlinks=True,
                    ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    out = tmp_path / "wheel"
    result = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out), str(src)],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    (wheel,) = out.glob("napari_dslrxr-*.whl")
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        assert "napari_dslrxr/napari.yaml" in names
        assert zf.read("napari_dslrxr/napari.yaml") == MANIFEST.read_bytes()
        entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
        assert "napari_dslrxr:napari.yaml" in zf.read(entry_points).decode()
