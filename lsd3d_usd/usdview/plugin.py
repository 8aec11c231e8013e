"""The usdview plugin: an "LSD3D" menu over lsd3d_usd.usdview.actions.

usdview finds it through ``plugInfo.json`` beside this file (put this folder on
PXR_PLUGINPATH_NAME; docs/usdview.md). Plug imports this module and usdview instantiates
``Lsd3dPluginContainer``, calls ``registerPlugins(plugRegistry, usdviewApi)`` and then
``configureView(plugRegistry, plugUIBuilder)``.

The module must import without usdview (usd-core from PyPI ships none): when
``pxr.Usdviewq`` is missing, a minimal stand-in ``PluginContainer`` base is used. It exists
only so this module imports and its container can be exercised with fakes in tests; it is
never registered with Plug and usdview never sees it.
"""
from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

try:  # the real base class, inside usdview
    from pxr.Usdviewq.plugin import PluginContainer
    HAVE_USDVIEW = True
except ImportError:  # stand-in for import and tests only (see module doc)
    HAVE_USDVIEW = False

    class PluginContainer:  # noqa: D401
        """Stand-in for pxr.Usdviewq.plugin.PluginContainer (usdview not installed)."""

        def registerPlugins(self, plugRegistry, usdviewApi):
            raise NotImplementedError  # abstract: usdview's base class, stood in for

        def configureView(self, plugRegistry, plugUIBuilder):
            raise NotImplementedError  # abstract: usdview's base class, stood in for

MENU = "LSD3D"
PREFIX = "Lsd3dPluginContainer."


# ------------------------------------------------------------------------------- Qt
def qt():
    """(QtWidgets, QtGui, QtCore) as usdview uses them, or None without Qt."""
    try:
        # local import: usdview loads the plugin at start: kept lazy
        from pxr.Usdviewq.qt import QtCore, QtGui, QtWidgets
        return QtWidgets, QtGui, QtCore
    except ImportError:
        pass
    for mod in ("PySide6", "PySide2"):
        try:
            m = __import__(mod, fromlist=["QtWidgets", "QtGui", "QtCore"])
            return m.QtWidgets, m.QtGui, m.QtCore
        except ImportError:
            continue
    return None


def _status(api, msg: str) -> None:
    if hasattr(api, "PrintStatus"):
        api.PrintStatus(msg)
    print(f"LSD3D: {msg}", file=sys.stderr)


def _output_dir(api) -> Path:
    base = getattr(api, "configDir", None) or tempfile.gettempdir()
    d = Path(base) / "lsd3d"
    d.mkdir(parents=True, exist_ok=True)
    return d


def _guard(fn):
    """Menu callbacks report errors in the status bar instead of raising into Qt's loop."""
    def wrapped(api, **kw):
        # local import: usdview loads the plugin at start: kept lazy
        from lsd3d_usd.errors import Lsd3dError
        try:
            return fn(api, **kw)
        except Lsd3dError as e:
            _status(api, f"error: {e}")
            return None
    wrapped.__name__ = fn.__name__
    wrapped.__doc__ = fn.__doc__
    return wrapped


def _show_image(api, image, title: str) -> bool:
    q = qt()
    if q is None:
        return False
    QtWidgets, QtGui, _ = q
    h, w = image.shape[:2]
    qimg = QtGui.QImage(image.tobytes(), w, h, 3 * w, QtGui.QImage.Format_RGB888).copy()
    dlg = QtWidgets.QDialog(getattr(api, "qMainWindow", None))
    dlg.setWindowTitle(title)
    label = QtWidgets.QLabel(dlg)
    label.setPixmap(QtGui.QPixmap.fromImage(qimg))
    lay = QtWidgets.QVBoxLayout(dlg)
    lay.addWidget(label)
    dlg.show()
    return True


def _show_text(api, title: str, text: str) -> bool:
    q = qt()
    if q is None:
        print(text)
        return False
    QtWidgets, QtGui, _ = q
    box = QtWidgets.QMessageBox(getattr(api, "qMainWindow", None))
    box.setWindowTitle(title)
    box.setText(text)
    box.setFont(QtGui.QFontDatabase.systemFont(QtGui.QFontDatabase.FixedFont))
    box.show()
    return True


# -------------------------------------------------------------------------- commands
def _camera(api):
    # local import: usdview loads the plugin at start: kept lazy
    from . import actions
    return actions.view_camera(getattr(api, "cameraPrim", None),
                               getattr(api, "currentGfCamera", None),
                               getattr(api, "frame", None),
                               getattr(api, "viewportSize", None))


@_guard
def render_surfels(api, textures=None):
    """Render the scene from usdview's current camera with the CPU rasteriser; show the
    image in a dialog (with Qt), and always write it as a PNG."""
    # local import: usdview loads the plugin at start: kept lazy
    from . import actions
    cam = _camera(api)
    res = actions.render_view(api.stage, cam, getattr(api, "frame", None), textures=textures)
    path = actions.save_png(res, _output_dir(api) / "render.png")
    shown = _show_image(api, res.image, f"LSD3D surfels ({res.surfels:,}, {res.seconds:.1f} s)")
    _status(api, f"rendered {res.surfels:,} surfels at {cam.width}x{cam.height} in "
                 f"{res.seconds:.1f} s -> {path}" + ("" if shown else " (no Qt: image not shown)"))
    return path


@_guard
def cycle_ggds_runs(api):
    """Solo the next GGDS run (all -> newest -> ... -> none -> all) to compare runs."""
    # local import: usdview loads the plugin at start: kept lazy
    from . import actions
    msg = actions.solo_next_run(api.stage)
    _status(api, msg)
    return msg


@_guard
def unmute_all_ggds_runs(api):
    """Unmute every GGDS run muted from this menu."""
    # local import: usdview loads the plugin at start: kept lazy
    from . import actions
    n = actions.unmute_all_runs(api.stage)
    _status(api, f"unmuted {n} GGDS run(s)")
    return n


@_guard
def choose_ggds_runs(api):
    """A dialog with one checkbox per GGDS run (checked = active); without Qt, print them."""
    # local import: usdview loads the plugin at start: kept lazy
    from . import actions
    runs = actions.ggds_runs(api.stage)
    if not runs:
        _status(api, "no GGDS runs in this stage")
        return runs
    q = qt()
    if q is None:
        print("\n".join(r.label() for r in runs))
        return runs
    QtWidgets, _, _ = q
    dlg = QtWidgets.QDialog(getattr(api, "qMainWindow", None))
    dlg.setWindowTitle("LSD3D: GGDS runs")
    lay = QtWidgets.QVBoxLayout(dlg)
    for r in runs:
        box = QtWidgets.QCheckBox(r.label(), dlg)
        box.setChecked(not r.muted)
        box.setEnabled(not r.persistent)

        def toggled(checked, name=r.name, box=box):
            now = actions.set_run_muted(api.stage, name, not checked)
            box.setText(now.label())
        box.toggled.connect(toggled)
        lay.addWidget(box)
    dlg.show()
    return runs


@_guard
def selection_statistics(api):
    """Statistics of the selected surfel prims (or all surfel prims when none is selected)."""
    # local import: usdview loads the plugin at start: kept lazy
    from . import actions
    stats = actions.selection_stats(api.stage, list(getattr(api, "selectedPrims", None) or []))
    text = actions.format_stats(stats)
    _show_text(api, "LSD3D surfel statistics", text)
    _status(api, f"statistics of {len(stats)} surfel prim(s)")
    return text


COMMANDS = (
    ("renderSurfels", "Render Surfels from Current Camera", render_surfels),
    ("cycleGgdsRuns", "Compare GGDS Runs: Solo Next", cycle_ggds_runs),
    ("chooseGgdsRuns", "GGDS Runs...", choose_ggds_runs),
    ("unmuteGgdsRuns", "Unmute All GGDS Runs", unmute_all_ggds_runs),
    ("surfelStatistics", "Surfel Statistics of Selection", selection_statistics),
)


class Lsd3dPluginContainer(PluginContainer):
    """Registers the LSD3D commands and puts them in an "LSD3D" menu."""

    def registerPlugins(self, plugRegistry, usdviewApi):
        import lsd3d_usd  # noqa: F401  the surfel schema (see docs/usdview.md on ordering)
        # local import: usdview loads the plugin at start: kept lazy
        from lsd3d_usd.views.stage_data import TextureCache
        textures = TextureCache()  # env textures decoded once per usdview session
        self._commands = []
        for name, display, fn in COMMANDS:
            call = (lambda api, fn=fn: fn(api, textures=textures)) if fn is render_surfels else fn
            self._commands.append(plugRegistry.registerCommandPlugin(
                PREFIX + name, display, call, (fn.__doc__ or "").split("\n")[0]))

    def configureView(self, plugRegistry, plugUIBuilder):
        menu = plugUIBuilder.findOrCreateMenu(MENU)
        for i, cmd in enumerate(self._commands):
            if i in (1, 4):
                menu.addSeparator()
            menu.addItem(cmd)


if HAVE_USDVIEW:  # usdview loads containers through Plug: the class must be a Tf type
    from pxr import Tf
    Tf.Type.Define(Lsd3dPluginContainer)


def plugin_dir() -> str:
    """The folder to put on PXR_PLUGINPATH_NAME."""
    return os.path.dirname(os.path.abspath(__file__))
