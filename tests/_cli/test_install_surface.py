"""What a new user meets first, run as the ``dslrxr`` process: the version, on/off flags, and
help text readable at 80 columns for every command and sub-command."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest
import typer

from napari_dslrxr import __version__, cli
from napari_dslrxr.core.io import write_tiff
from napari_dslrxr.core.simulation.phantom import make_dslr_radiograph


def dslrxr(*args: str, columns: int = 80, cwd: Path | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "COLUMNS": str(columns)}
    env.pop("TERMINAL_WIDTH", None)
    return subprocess.run([sys.executable, "-m", "napari_dslrxr.cli", *args], capture_output=True,
                          text=True, env=env, cwd=cwd, timeout=300)


def command_paths() -> list[tuple[list[str], object]]:
    """Every command and group of the real app, with its click object, root first."""
    found = []

    def walk(path, command):
        found.append((path, command))
        for name, sub in sorted(getattr(command, "commands", {}).items()):
            walk([*path, name], sub)

    walk([], typer.main.get_command(cli.app))
    return found


def test_version_prints_the_package_version():
    proc = dslrxr("--version")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == f"dslrxr (napari-dslrxr) {__version__}"
    assert __version__ == version("napari-dslrxr")  # the code and the installed metadata agree


def test_the_app_has_every_documented_command():
    paths = {" ".join(p) for p, _ in command_paths()}
    assert {"run", "params", "denoise", "deconvolve", "simulate", "diagnose", "view", "psf", "psf fit",
            "psf kernel", "metrics", "metrics pe", "metrics gcf"} <= paths


@pytest.mark.parametrize("path", [p for p, _ in command_paths()], ids=lambda p: " ".join(p) or "dslrxr")
def test_help_at_80_columns_shows_every_option_name_whole(path):
    command = dict((tuple(p), c) for p, c in command_paths())[tuple(path)]
    proc = dslrxr(*path, "--help")
    assert proc.returncode == 0, proc.stderr
    text = proc.stdout
    assert "…" not in text and "Traceback" not in text
    assert "<bool>" not in text  # on/off options are shown as flags, never as taking a value
    assert max(len(line) for line in text.splitlines()) <= 80, text
    names = [o for param in command.params if param.param_type_name == "option"
             for o in (*param.opts, *param.secondary_opts)]
    names.append("--help")
    for name in names:
        assert re.search(rf"(?<![\w-]){re.escape(name)}(?![\w-])", text), (name, text)
    for name in getattr(command, "commands", {}):
        assert re.search(rf"^  {re.escape(name)}\s", text, re.M), (name, text)


def test_flags_are_shown_as_flags_not_as_values():
    text = dslrxr("run", "--help").stdout
    assert "--dicom / --no-dicom" in text
    assert "<bool>" not in text


@pytest.fixture(scope="module")
def small_frame(tmp_path_factory):
    folder = tmp_path_factory.mktemp("frame")
    frames = make_dslr_radiograph((96, 128), seed=3)
    return {"shot": write_tiff(folder / "shot.tif", frames.raw_rgb),
            "flat": write_tiff(folder / "flat.tif", frames.flat)}


def test_dicom_flag_value_word_is_refused_not_read_as_an_input(tmp_path, small_frame):
    out = tmp_path / "out"
    proc = dslrxr("run", str(small_frame["shot"]), "--dicom", "true", "-o", str(out))
    assert proc.returncode == 2
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("dslrxr: error: --dicom"), proc.stderr
    assert "--no-dicom" in lines[0] and "true" in lines[0]
    assert not out.exists()  # nothing was run


def test_dicom_flags_parse_and_override_the_parameter_file(tmp_path, small_frame):
    config = tmp_path / "params.toml"
    config.write_text("[output]\ndicom = true\npng_preview = false\n")
    on, off = tmp_path / "on", tmp_path / "off"
    proc = dslrxr("run", str(small_frame["shot"]), "--flat", str(small_frame["flat"]), "--dicom", "-o", str(on))
    assert proc.returncode == 0, proc.stderr
    proc = dslrxr("run", str(small_frame["shot"]), "--flat", str(small_frame["flat"]), "-c", str(config),
                  "--no-dicom", "-o", str(off))
    assert proc.returncode == 0, proc.stderr
    assert (on / "shot_dslrxr.dcm").is_file() and (on / "shot_dslrxr.tif").is_file()
    assert (off / "shot_dslrxr.tif").is_file() and not (off / "shot_dslrxr.dcm").exists()
    assert not (off / "shot_dslrxr.png").exists()  # the rest of the file still applies


def test_a_file_really_named_true_is_still_an_input(tmp_path, small_frame):
    (tmp_path / "true").write_bytes(Path(small_frame["shot"]).read_bytes())
    proc = dslrxr("run", str(small_frame["shot"]), "--dicom", "true", "-o", "out", cwd=tmp_path)
    # "true" exists, so it is read as the second input: a TIFF without a .tif suffix, processed
    assert proc.returncode == 0, proc.stderr
    assert "[2/2]" in proc.stderr
