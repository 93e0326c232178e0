"""``dslrxr view``: files checked first, then opened with the plugin's reader, widgets docked."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from napari_dslrxr._cli import view as view_module
from napari_dslrxr._cli.view import plugin_widget_names
from napari_dslrxr.cli import main
from napari_dslrxr.core.io import write_tiff


def test_missing_file_is_a_one_line_error_before_any_window(tmp_path, capsys, monkeypatch):
    import napari

    monkeypatch.setattr(napari, "Viewer", lambda *a, **k: pytest.fail("no window for a bad file"))
    assert main(["view", str(tmp_path / "missing.tif")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("dslrxr: error:") and "missing.tif: no such file" in err
    assert "\n" not in err


def test_widget_names_come_from_the_manifest():
    names = plugin_widget_names()
    assert "Impulse removal" in names and len(names) == len(set(names))


@pytest.mark.gui
def test_view_opens_files_and_docks_every_widget(make_napari_viewer, tmp_path, monkeypatch, rng):
    import napari

    image = rng.integers(0, 4000, (48, 64)).astype(np.uint16)
    path = write_tiff(tmp_path / "chest.tif", image)
    viewers = []

    def fake_viewer(**kwargs):
        viewers.append(make_napari_viewer(**kwargs))
        return viewers[-1]

    monkeypatch.setattr(napari, "Viewer", fake_viewer)
    monkeypatch.setattr(napari, "run", lambda *a, **k: None)
    frozen_with = []  # the real freeze would keep this test process's viewers alive
    monkeypatch.setattr(view_module, "freeze_startup_objects",
                        lambda: frozen_with.append([layer.name for layer in viewers[-1].layers]))
    assert main(["view", str(path)]) == 0
    assert frozen_with == [["chest"]]  # frozen once, after the files were opened
    (viewer,) = viewers
    assert [layer.name for layer in viewer.layers] == ["chest"]
    np.testing.assert_array_equal(viewer.layers["chest"].data, image)
    docked = set(viewer.window.dock_widgets)
    for name in plugin_widget_names():
        assert any(name in key for key in docked), (name, docked)


def test_startup_objects_are_left_out_of_later_collections():
    """After the viewer opens, a full collection walks only what was made since (napari runs
    one on the GUI thread whenever a layer is removed). In a child process: freezing is for
    the life of the process."""
    code = (
        "import gc, time\n"
        "from napari_dslrxr._cli.view import freeze_startup_objects\n"
        "alive = [[i] for i in range(300_000)]\n"
        "freeze_startup_objects()\n"
        "assert gc.get_freeze_count() >= 300_000, gc.get_freeze_count()\n"
        "print('frozen', gc.get_freeze_count())\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "frozen" in done.stdout
