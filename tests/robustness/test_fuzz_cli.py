"""The command line under hostile arguments: random commands, files and option values.

In-process: every sub-command that reads files (``run``, ``params``, ``deconvolve``,
``simulate``, ``diagnose``) gets positional files and option values drawn from pools of good,
damaged and absurd ones (truncated images, text renamed .tif, NaN images, a folder, a missing
path, the input itself as output, "nan", "1e999", "-1"...). The exit code must be 0, 1 (some
files of a batch failed), 2 (one-line error) or 130, never 3 (an internal error: a bug), and
stderr never holds a traceback. A few cases run the real ``dslrxr`` process, where the C
libraries' own stderr would show too.
"""

from __future__ import annotations

import contextlib

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile
import tomli_w
import typer.main
from hypothesis import given
from hypothesis import strategies as st
from robustness.fuzzing import FUZZ_LOG, check_outcome, fuzz_settings
from robustness.synthetic_files import write_dng

from napari_dslrxr import cli

#: Commands that would open a window or only group others are left out.
_SKIPPED_COMMANDS = {"view", "psf"}
_COMMANDS = {name: cmd for name, cmd in typer.main.get_command(cli.app).commands.items()
             if name not in _SKIPPED_COMMANDS and hasattr(cmd, "params") and not hasattr(cmd, "commands")}

_VALUES = ["", "-1", "0", "1", "3", "nan", "inf", "-inf", "1e999", "abc", "3,1,1", "0.5", "auto", "wiener",
           "x" * 500, "ümlaut é", "--", "-o", "1,2,3,4", "veiling_glare:eta=0.02", "veiling_glare:eta=nan"]


@pytest.fixture(scope="module")
def file_pool(tmp_path_factory) -> dict[str, Path]:
    """Good, damaged and absurd files for the command line to chew on."""
    d = tmp_path_factory.mktemp("pool")
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:64, 0:80]
    image = (20000 + 5000 * np.sin(x / 9.0) + rng.normal(0, 200, (64, 80))).astype(np.uint16)
    tifffile.imwrite(d / "good.tif", image)
    data = (d / "good.tif").read_bytes()
    (d / "truncated.tif").write_bytes(data[: len(data) // 2])
    (d / "text.tif").write_text("not an image\n")
    (d / "empty.tif").write_bytes(b"")
    tifffile.imwrite(d / "nan.tif", np.full((16, 16), np.nan, np.float32))
    tifffile.imwrite(d / "one.tif", np.zeros((1, 1), np.uint16))
    tifffile.imwrite(d / "thickness.tif", np.full((32, 32), 2.0, np.float32))
    write_dng(d / "good.dng", np.clip(image[:, :] // 8 + 64, 0, 4095).astype(np.uint16))
    dng = (d / "good.dng").read_bytes()
    (d / "cut.dng").write_bytes(dng[: len(dng) // 2])
    (d / "folder").mkdir()
    params = pytest.importorskip("napari_dslrxr.core.params")
    (d / "good.toml").write_text(params.default_params_toml())
    (d / "bad.toml").write_text("[impulse]\npases_h = 3\n")
    (d / "scene.toml").write_text(tomli_w.dumps({
        "geometry": {"source_to_detector_mm": 1200.0, "source_to_object_mm": 1150.0, "pixel_pitch_mm": 0.1},
        "object": {"thickness_mm": "thickness.tif", "material": "aluminium"}, "source": {"kvp": 60}}))
    (d / "bad.json").write_text('{"format": "dslrxr-psf", "format_version": 1, "pixel_pitch_mm": NaN}')
    (d / "garbage.json").write_bytes(b"\xff\xfe{{{")
    pool = {p.name: p for p in d.iterdir()}
    pool["missing.tif"] = d / "missing.tif"
    return pool


@st.composite
def command_line(draw, files: dict[str, Path], out_dir: Path) -> list[str]:
    name = draw(st.sampled_from(sorted(_COMMANDS)))
    argv = [name]
    file_names = sorted(files)
    for param in _COMMANDS[name].params:
        if getattr(param, "param_type_name", "") == "argument":
            for _ in range(draw(st.integers(1 if param.required else 0, 2))):
                argv.append(str(files[draw(st.sampled_from(file_names))]))
            continue
        if not param.required and not draw(st.integers(0, 3)) == 0:
            continue  # most options absent
        flag = param.opts[0]
        if getattr(param, "is_flag", False):
            argv.append(flag)
        elif flag in ("-o", "--out", "--output"):
            target = draw(st.sampled_from(["out", "same-as-input", "missing-folder", "folder"]))
            argv += [flag, {"out": str(out_dir / "result.tif"), "same-as-input": str(files["good.tif"]),
                            "missing-folder": str(out_dir / "no" / "such" / "x.tif"),
                            "folder": str(files["folder"])}[target]]
        else:
            value = draw(st.one_of(st.sampled_from(_VALUES), st.sampled_from([str(files[n]) for n in file_names])))
            argv += [flag, value]
    return argv


def _run_in_process(argv: list[str], capsys) -> tuple[int, str]:
    code = cli.main(argv)
    _, err = capsys.readouterr()
    if code == cli.EXIT_INTERNAL or "Traceback" in err:
        last = err.strip().splitlines()[-1] if err.strip() else ""
        raise AssertionError(f"exit {code}: {last[:300]} [from dslrxr {' '.join(argv)[:300]}]")
    assert code in (cli.EXIT_OK, cli.EXIT_SOME_FAILED, cli.EXIT_USAGE, cli.EXIT_INTERRUPTED), code
    if code == cli.EXIT_USAGE:
        assert err.strip().splitlines()[-1].startswith("dslrxr: error: "), err
    return code, err


@fuzz_settings()
@given(data=st.data())
def test_fuzz_command_line(file_pool, tmp_path, capsys, data):
    out_dir = tmp_path / "out"
    out_dir.mkdir(exist_ok=True)
    before = {n: p.read_bytes() for n, p in file_pool.items() if p.is_file()}
    argv = data.draw(command_line(file_pool, out_dir))
    outputs = {argv[i + 1] for i, a in enumerate(argv[:-1]) if a in ("-o", "--out", "--output")}
    inputs = {n for n, p in file_pool.items() if str(p) in argv and str(p) not in outputs}
    try:
        # Run inside the output folder: a drawn value such as "-1" taken as a relative output
        # path must not land in the working tree.
        with contextlib.chdir(out_dir):
            result = check_outcome("command-line", lambda: _run_in_process(argv, capsys), success_kind=None)
        if result is not None:
            FUZZ_LOG[("command-line", f"exit {result[0]}")] += 1
        changed = {n for n, p in file_pool.items() if p.is_file() and n in before and p.read_bytes() != before[n]}
        assert not changed & inputs, f"input file(s) {sorted(changed & inputs)} modified by {argv}"
    finally:  # an existing file named as the output may rightly be replaced: restore the pool
        for n, content in before.items():
            if not file_pool[n].is_file() or file_pool[n].read_bytes() != content:
                file_pool[n].write_bytes(content)


@pytest.mark.parametrize("name", ["truncated.tif", "text.tif", "cut.dng",
                                  pytest.param("stripped", marks=pytest.mark.realdata)])
def test_real_process_prints_one_line_and_no_traceback(file_pool, tmp_path, name, request):
    """The installed entry point, in its own process: C-level stderr (LibRaw) would show here."""
    if name == "stripped":
        path = request.getfixturevalue("shared_data") / "raw_files" / "CanonRaw_stripped.cr2"
    else:
        path = file_pool[name]
    proc = subprocess.run([sys.executable, "-m", "napari_dslrxr.cli", "run", str(path), "-o", str(tmp_path / "o")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == cli.EXIT_SOME_FAILED, proc.stderr  # a batch whose only file failed
    assert "Traceback" not in proc.stderr and proc.stdout == ""
    errors = [line for line in proc.stderr.splitlines() if "error" in line]
    assert errors and all(str(path) in line or "failed" in line for line in errors), proc.stderr
    assert not [line for line in proc.stderr.splitlines() if "Unexpected end" in line and "error" not in line]
    assert not any(p.suffix in (".tif", ".png") for p in (tmp_path / "o").glob("*")), "partial output"


def test_negative_seed_is_a_one_line_error(file_pool, tmp_path, capsys):
    """Found by fuzzing the command line: ``--seed -1`` ended in an internal error (exit 3)."""
    code = cli.main(["simulate", str(file_pool["scene.toml"]), "-o", str(tmp_path / "sim.tif"), "--seed", "-1"])
    err = capsys.readouterr().err
    assert code == cli.EXIT_USAGE and err.startswith("dslrxr: error: ") and "seed" in err
