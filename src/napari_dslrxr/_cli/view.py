"""``dslrxr view [FILES]``: open napari with the files loaded and the plugin's widgets docked.

napari is imported only when the command runs, so the rest of the command line works without
it. Files are checked before any window opens: a missing file is a one-line error, exit 2.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

from ..core.errors import DslrxrError, InputError

if TYPE_CHECKING:
    import napari

PLUGIN_NAME = "napari-dslrxr"
READER_RGB = "napari-dslrxr.get_reader"
#: Width of the right dock: the widgets' labels and sliders fit without truncation.
DOCK_WIDTH_PX = 470


def _manifest():
    """The plugin's npe2 manifest (napari.yaml) as the plugin manager knows it."""
    from npe2 import PluginManager

    manager = PluginManager.instance()
    manager.discover()
    return manager.get_manifest(PLUGIN_NAME)


def plugin_widget_names() -> list[str]:
    """Display names of the widgets the manifest declares, in manifest order."""
    return [w.display_name for w in (_manifest().contributions.widgets or [])]


def check_files(files: list[Path]) -> list[Path]:
    """Raise :class:`InputError` for a path that does not exist or is a folder."""
    for path in files:
        if not path.exists():
            raise InputError(path, "no such file")
        if path.is_dir():
            raise InputError(path, "is a folder, not an image file")
    return files


def populate_viewer(viewer: napari.Viewer, files: list[Path], *, cfa_planes: bool = False,
                    widgets: list[str] | None = None) -> list:
    """Open ``files`` with the plugin's reader and dock ``widgets`` (default: all of them).

    Returns the docked widgets (magicgui containers) in order. The widgets are tabbed in the
    right dock area so the canvas keeps its room, with the first one (impulse removal) in front.
    """
    for path in files:
        if cfa_planes:
            from .._cfa_planes import add_cfa_planes

            add_cfa_planes(viewer, [str(path)])
        else:
            viewer.open(str(path), plugin=READER_RGB)
    docked, docks = [], []
    names = plugin_widget_names() if widgets is None else widgets
    for i, name in enumerate(names):
        dock, widget = viewer.window.add_plugin_dock_widget(PLUGIN_NAME, name, tabify=i > 0)
        dock.setWindowTitle(name)  # the tab shows "Flat field", not "Flat field (napari-dslrxr)"
        docked.append(widget)
        docks.append(dock)
    if docks:
        from qtpy.QtCore import QTimer

        # Deferred: Qt lays the tabs out after this returns.
        QTimer.singleShot(0, lambda: arrange_docks(viewer, docks))
    return docked


def reader_patterns() -> list[str]:
    """The file name patterns of the plugin's reader, as the manifest declares them."""
    return [pattern for reader in (_manifest().contributions.readers or []) for pattern in reader.filename_patterns]


def prefer_plugin_reader() -> dict[str, str]:
    """Make napari open the plugin's file types with its reader, without asking.

    napari's built-in reader claims every image extension too, so opening a file that two
    plugins claim shows a "choose a reader" dialog. For each reader pattern the user has no
    preference for (lower and upper case), this session prefers this plugin (as ticking
    "remember" in that dialog would); patterns the user chose a reader for are left alone.

    Returns
    -------
    dict
        The preferences added; give them to :func:`restore_reader_preferences` when the viewer
        closes, so the user's settings are as they were.
    """
    from napari.settings import get_settings

    plugins = get_settings().plugins
    before = dict(plugins.extension2reader)
    # napari matches preferences case-sensitively; cameras often write upper-case names (IMG_1.CR2)
    patterns = [p for pattern in reader_patterns() for p in (pattern.lower(), pattern.upper())]
    added = {pattern: PLUGIN_NAME for pattern in patterns if pattern not in before}
    if added:
        plugins.extension2reader = {**before, **added}
    return added


def restore_reader_preferences(added: dict[str, str]) -> None:
    """Remove the preferences :func:`prefer_plugin_reader` added (choices made since are kept)."""
    from napari.settings import get_settings

    plugins = get_settings().plugins
    current = dict(plugins.extension2reader)
    kept = {k: v for k, v in current.items() if not (k in added and v == added[k])}
    if kept != current:
        plugins.extension2reader = kept


def arrange_docks(viewer: napari.Viewer, docks: list) -> None:
    """Widen the dock area, show whole tab titles (scroll arrows rather than "F..."), and put
    the first stage's tab in front."""
    from qtpy.QtCore import Qt
    from qtpy.QtWidgets import QTabBar

    window = viewer.window._qt_window
    try:
        window.resizeDocks(docks, [DOCK_WIDTH_PX] * len(docks), Qt.Orientation.Horizontal)
        for bar in window.findChildren(QTabBar):
            if bar.parent() is window:  # the tab bars of tabified docks
                bar.setElideMode(Qt.TextElideMode.ElideNone)
                bar.setUsesScrollButtons(True)
        docks[0].raise_()
    except RuntimeError:  # the window closed before the deferred call
        pass


def freeze_startup_objects() -> None:
    """Leave the objects of the opened viewer out of every later garbage collection.

    napari collects in full on the GUI thread whenever a layer is removed, and Python does
    now and then; each such collection walks every tracked object, about 400 000 once the
    viewer, the widgets and the samples are open (0.1-0.4 s with the GUI frozen). Those
    objects live as long as the viewer, so they are collected once now and frozen
    (:func:`gc.freeze`): later collections walk only the objects made since. Only for the
    viewer this command owns; the plugin inside someone else's napari leaves their
    collector alone.
    """
    import gc

    gc.collect()
    gc.freeze()


def register(app: typer.Typer) -> None:
    """Add ``dslrxr view`` to ``app``."""

    @app.command("view")
    def view(
        files: list[Path] = typer.Argument(None, help="Radiographs or camera raw files to open."),
        cfa_planes: bool = typer.Option(False, "--cfa-planes",
                                        help="Open camera raw files as the four CFA planes (R, G1, G2, B)."),
        no_widgets: bool = typer.Option(False, "--no-widgets", help="Do not dock the plugin's widgets."),
    ) -> None:
        """Open napari with FILES loaded and the DSLR-radiography widgets docked."""
        files = check_files(list(files or []))
        try:
            import napari
        except ImportError:
            raise DslrxrError("'dslrxr view' needs napari: pip install 'napari-dslrxr[napari]' "
                              "plus a Qt binding (e.g. PyQt6)") from None
        added = prefer_plugin_reader()  # dropped .tif/.dcm/raw files open without a reader dialog
        try:
            viewer = napari.Viewer(title="dslrxr")
            populate_viewer(viewer, files, cfa_planes=cfa_planes, widgets=[] if no_widgets else None)
            freeze_startup_objects()
            napari.run()
        finally:
            restore_reader_preferences(added)
