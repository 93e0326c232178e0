"""``napari_dslrxr.cli.main``: every bad input is one line on stderr and a non-zero exit, never a traceback.

The probe commands registered here for the duration of a test read an image with the core
reader and write a TIFF with its sidecar, like every real command; they let these tests
drive main's error handling whichever stage commands exist. Where ``dslrxr denoise`` exists,
the same bad inputs are also run through it.
"""

from __future__ import annotations

import errno
from pathlib import Path

import numpy as np
import pytest
import tifffile
import typer
from robustness.synthetic_files import write_dng

from napari_dslrxr import cli
from napari_dslrxr.core import io
from napari_dslrxr.core.io import provenance


@pytest.fixture
def probe_commands():
    """Register ``_probe-copy``, ``_probe-bug`` and ``_probe-oserror`` on the real app."""

    def copy(input_path: Path = typer.Argument(...), output: Path = typer.Option(..., "-o")) -> None:
        image = io.read_image(input_path)
        out = io.write_tiff(output, image.data, inputs=[input_path])
        provenance.write_sidecar(out, stage="probe-copy", parameters={}, inputs=[input_path])

    def bug() -> None:
        raise ZeroDivisionError("division by zero in a stage")

    def oserror() -> None:
        raise OSError(errno.ENOSPC, "No space left on device", "/media/card/out.tif")

    def interrupted() -> None:
        raise KeyboardInterrupt

    before = list(cli.app.registered_commands)
    for name, func in [("_probe-copy", copy), ("_probe-bug", bug), ("_probe-oserror", oserror),
                       ("_probe-interrupt", interrupted)]:
        cli.app.command(name)(func)
    yield
    cli.app.registered_commands[:] = before


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(err: str, *needles: str) -> None:
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("dslrxr: error: ") and "Traceback" not in err, err
    for needle in needles:
        assert needle in lines[0], (needle, err)


def bad_inputs(tmp_path: Path, shared_dir: Path | None) -> dict[str, tuple[Path, str]]:
    """The bad inputs issue 2 names, each with a phrase its error must contain."""
    tifffile.imwrite(tmp_path / "good.tif", np.arange(64 * 80, dtype=np.uint16).reshape(64, 80))
    data = (tmp_path / "good.tif").read_bytes()
    (tmp_path / "truncated.tif").write_bytes(data[: len(data) // 2])
    (tmp_path / "empty.tif").write_bytes(b"")
    (tmp_path / "text.tif").write_text("not an image\n")
    tifffile.imwrite(tmp_path / "nan.tif", np.full((16, 16), np.nan, np.float32))
    tifffile.imwrite(tmp_path / "one.tif", np.zeros((1, 1), np.uint16))
    cases = {
        "truncated": (tmp_path / "truncated.tif", "corrupt or truncated TIFF"),
        "empty": (tmp_path / "empty.tif", "empty file"),
        "text": (tmp_path / "text.tif", "not a TIFF file"),
        "nan": (tmp_path / "nan.tif", "NaN"),
        "one_by_one": (tmp_path / "one.tif", "1x1"),
        "missing": (tmp_path / "absent.tif", "no such file"),
    }
    if shared_dir is not None:
        cases["stripped_cr2"] = (shared_dir / "raw_files" / "CanonRaw_stripped.cr2", "unreadable camera raw")
    return cases


def test_bad_inputs_give_one_line_and_exit_2_without_output(tmp_path, capsys, probe_commands, shared_data):
    for name, (path, phrase) in bad_inputs(tmp_path, shared_data).items():
        out = tmp_path / f"out_{name}.tif"
        code, stdout, err = run(["_probe-copy", path, "-o", out], capsys)
        assert code == cli.EXIT_USAGE, (name, err)
        assert_one_line_error(err, str(path), phrase)
        assert not out.exists() and not Path(str(out) + ".json").exists()
    leftovers = [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert leftovers == []


def test_good_input_succeeds_and_output_equals_input(tmp_path, capsys, probe_commands, rng):
    image = rng.integers(0, 65535, (16, 24)).astype(np.uint16)
    tifffile.imwrite(tmp_path / "in.tif", image)
    code, _, err = run(["_probe-copy", tmp_path / "in.tif", "-o", tmp_path / "out.tif"], capsys)
    assert code == 0 and err == ""
    np.testing.assert_array_equal(io.read_image(tmp_path / "out.tif").data, image)
    assert (tmp_path / "out.tif.json").exists()


def test_overwriting_the_input_is_refused(tmp_path, capsys, probe_commands, monkeypatch):
    tifffile.imwrite(tmp_path / "in.tif", np.full((16, 16), 9, np.uint16))
    before = io.file_sha256(tmp_path / "in.tif")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "alias.tif").symlink_to(tmp_path / "in.tif")
    for target in ("in.tif", "./in.tif", tmp_path / "alias.tif"):
        code, _, err = run(["_probe-copy", "in.tif", "-o", target], capsys)
        assert code == cli.EXIT_USAGE
        assert_one_line_error(err, "refusing to overwrite the input")
    assert io.file_sha256(tmp_path / "in.tif") == before


def test_size_limit_via_environment_is_a_one_line_error(tmp_path, capsys, probe_commands, monkeypatch, rng):
    write_dng(tmp_path / "f.dng", rng.integers(0, 4000, (32, 48)).astype(np.uint16))
    monkeypatch.setenv("DSLRXR_MAX_PIXELS", "1000")
    code, _, err = run(["_probe-copy", tmp_path / "f.dng", "-o", tmp_path / "o.tif"], capsys)
    assert code == cli.EXIT_USAGE
    assert_one_line_error(err, "exceeds the limit of 1000 pixels")


def test_usage_errors_exit_2_with_one_line(capsys, probe_commands):
    for argv in (["no-such-command"], ["_probe-copy"], ["_probe-copy", "x.tif", "--bogus"]):
        code, _, err = run(argv, capsys)
        assert code == cli.EXIT_USAGE, argv
        assert_one_line_error(err)


def test_a_bug_is_one_line_exit_3_and_traceback_only_on_request(capsys, probe_commands, monkeypatch):
    code, _, err = run(["_probe-bug"], capsys)
    assert code == cli.EXIT_INTERNAL
    assert_one_line_error(err, "internal error", "ZeroDivisionError", "DSLRXR_DEBUG")
    monkeypatch.setenv("DSLRXR_DEBUG", "1")
    with pytest.raises(ZeroDivisionError):
        cli.main(["_probe-bug"])


def test_file_system_errors_and_interrupts(capsys, probe_commands):
    code, _, err = run(["_probe-oserror"], capsys)
    assert code == cli.EXIT_USAGE
    assert_one_line_error(err, "/media/card/out.tif", "No space left on device")
    code, _, err = run(["_probe-interrupt"], capsys)
    assert code == cli.EXIT_INTERRUPTED
    assert_one_line_error(err, "interrupted")


def test_library_warnings_do_not_reach_stderr(tmp_path, capsys, probe_commands):
    """A stage's numpy RuntimeWarning must not add lines to the command's output."""

    def noisy() -> None:
        np.log(np.zeros(3))  # RuntimeWarning: divide by zero

    cli.app.command("_probe-noisy")(noisy)
    code, out, err = run(["_probe-noisy"], capsys)
    assert code == 0 and err == ""


def test_denoise_bad_inputs_leave_no_partial_output(tmp_path, capsys, shared_data):
    for name, (path, phrase) in bad_inputs(tmp_path, shared_data).items():
        out = tmp_path / f"den_{name}.tif"
        mask = tmp_path / f"mask_{name}.tif"
        code, _, err = run(["denoise", path, "-o", out, "--mask-out", mask], capsys)
        assert code == cli.EXIT_USAGE, (name, err)
        assert_one_line_error(err, str(path), phrase)
        assert not out.exists() and not mask.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
