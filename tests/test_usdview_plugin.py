"""The usdview plugin module against the documented plugin API (pxr.Usdviewq.plugin), with
fakes standing in for usdview's registry, UI builder and UsdviewApi (usd-core has no
usdview): registration, the LSD3D menu, each command end to end, plugInfo.json."""
import json
import subprocess
import sys

import pytest
from pxr import Usd, UsdGeom

from lsd3d_usd.usdview import plugin
from test_usdview_actions import RUNS, scene  # noqa: F401  (fixture)


class FakeCommandPlugin:
    """As usdview's CommandPlugin: name, displayName, description; run() calls back with api."""

    def __init__(self, name, displayName, callback, description, api):
        self.name, self.displayName, self.description = name, displayName, description
        self._callback, self._api = callback, api

    def run(self):
        return self._callback(self._api)


class FakePlugRegistry:
    """registerCommandPlugin(name, displayName, callback, description="") as documented;
    a duplicate name raises, as usdview's DuplicateCommandPlugin does."""

    def __init__(self, api):
        self.api, self.commands = api, {}

    def registerCommandPlugin(self, name, displayName, callback, description=""):
        if name in self.commands:
            raise ValueError(f"duplicate command plugin {name}")
        self.commands[name] = FakeCommandPlugin(name, displayName, callback, description, self.api)
        return self.commands[name]

    def getCommandPlugin(self, name):
        return self.commands.get(name)


class FakeMenu:
    def __init__(self):
        self.items = []

    def addItem(self, commandPlugin, shortcut=None):
        self.items.append(commandPlugin)

    def addSeparator(self):
        self.items.append("---")

    def findOrCreateSubmenu(self, name):
        raise AssertionError("not used")


class FakeUIBuilder:
    def __init__(self):
        self.menus = {}

    def findOrCreateMenu(self, menuName):
        return self.menus.setdefault(menuName, FakeMenu())


class FakeUsdviewApi:
    """The UsdviewApi attributes the plugin reads."""

    def __init__(self, stage, config_dir, camera_prim=None, gf_camera=None, selected=()):
        self.stage = stage
        self.frame = Usd.TimeCode.Default()
        self.cameraPrim = camera_prim
        self.currentGfCamera = gf_camera
        self.viewportSize = (128, 96)
        self.selectedPrims = list(selected)
        self.configDir = str(config_dir)
        self.qMainWindow = None
        self.status = []

    def PrintStatus(self, msg):
        self.status.append(msg)


def loaded(api):
    reg, ui = FakePlugRegistry(api), FakeUIBuilder()
    container = plugin.Lsd3dPluginContainer()
    container.registerPlugins(reg, api)
    container.configureView(reg, ui)
    return reg, ui


def test_imports_without_usdview_and_registers_the_menu(tmp_path):
    assert not plugin.HAVE_USDVIEW              # usd-core: the stand-in base is in use
    with pytest.raises(NotImplementedError):
        plugin.PluginContainer().registerPlugins(None, None)
    api = FakeUsdviewApi(Usd.Stage.CreateInMemory(), tmp_path)
    reg, ui = loaded(api)
    assert list(ui.menus) == ["LSD3D"]
    items = ui.menus["LSD3D"].items
    names = [i if i == "---" else i.displayName for i in items]
    assert names == ["Render Surfels from Current Camera", "---", "Compare GGDS Runs: Solo Next",
                     "GGDS Runs...", "Unmute All GGDS Runs", "---", "Surfel Statistics of Selection"]
    assert all(c.name.startswith("Lsd3dPluginContainer.") and c.description
               for c in reg.commands.values())
    with pytest.raises(ValueError, match="duplicate"):      # names are unique per registry
        plugin.Lsd3dPluginContainer().registerPlugins(reg, api)


def test_render_command_from_camera_prim_and_free_camera(scene, tmp_path):  # noqa: F811
    stage = scene.open_stage()
    prim = stage.GetPrimAtPath("/World/Cameras/Front")
    api = FakeUsdviewApi(stage, tmp_path, camera_prim=prim)
    reg, _ = loaded(api)
    path = reg.getCommandPlugin("Lsd3dPluginContainer.renderSurfels").run()
    assert path == tmp_path / "lsd3d" / "render.png" and path.is_file()
    assert "rendered 1,600 surfels at 128x96" in api.status[-1]
    assert "no Qt: image not shown" in api.status[-1]
    first = path.read_bytes()
    # usdview's free camera (no camera prim): a Gf.Camera, same view -> same image.
    gf = UsdGeom.Camera(prim).GetCamera(Usd.TimeCode.Default())
    api2 = FakeUsdviewApi(stage, tmp_path, gf_camera=gf)
    reg2, _ = loaded(api2)
    assert reg2.getCommandPlugin("Lsd3dPluginContainer.renderSurfels").run() == path
    import numpy as np

    from lsd3d_usd.views.images import read_image
    assert np.abs(read_image(str(path)).astype(float) - read_image_bytes(first, tmp_path)).max() <= 1


def read_image_bytes(data, tmp_path):
    from lsd3d_usd.views.images import read_image
    p = tmp_path / "first.png"
    p.write_bytes(data)
    return read_image(str(p)).astype(float)


def test_errors_go_to_the_status_bar(tmp_path):
    api = FakeUsdviewApi(Usd.Stage.CreateInMemory(), tmp_path)
    reg, _ = loaded(api)
    assert reg.getCommandPlugin("Lsd3dPluginContainer.renderSurfels").run() is None
    assert api.status[-1].startswith("error: usdview: no camera")
    assert reg.getCommandPlugin("Lsd3dPluginContainer.surfelStatistics").run() is None
    assert api.status[-1].startswith("error: no surfel (ParticleField) prim in the stage")


def test_ggds_commands_and_statistics(scene, tmp_path, capsys):  # noqa: F811
    stage = scene.open_stage()
    api = FakeUsdviewApi(stage, tmp_path, selected=[stage.GetPrimAtPath("/World")])
    reg, _ = loaded(api)
    run = lambda n: reg.getCommandPlugin(f"Lsd3dPluginContainer.{n}").run()  # noqa: E731
    assert run("cycleGgdsRuns") == f"only {RUNS[2]}"
    assert api.status[-1] == f"only {RUNS[2]}"
    assert run("unmuteGgdsRuns") == 2
    assert stage.GetMutedLayers() == []
    runs = run("chooseGgdsRuns")                    # no Qt: printed, one line per run
    assert len(runs) == 3
    out = capsys.readouterr().out
    assert f"{RUNS[0]} [active, 7 steps]" in out
    text = run("surfelStatistics")
    assert "/World/Surfels (Lsd3dSurfelField): 1,600 surfels" in text
    assert text in capsys.readouterr().out
    assert api.status[-1] == "statistics of 1 surfel prim(s)"


def test_pluginfo_declares_the_container_and_includes_the_schema(tmp_path):
    with open(plugin.plugin_dir() + "/plugInfo.json") as fh:
        info = json.load(fh)
    (entry,) = info["Plugins"]
    assert entry["Type"] == "python" and entry["Name"] == "lsd3d_usd.usdview.plugin"
    # Registration as usdview would do it (PXR_PLUGINPATH_NAME), in a fresh process: the
    # container type is declared with usdview's base, loading imports our module, and the
    # surfel schema comes along through "Includes" (so it is registered before any stage).
    code = f"""
from pxr import Plug, Tf, Usd
import sys
Plug.Registry().RegisterPlugins({plugin.plugin_dir()!r})
t = Tf.Type.FindByName("lsd3d_usd.usdview.plugin.Lsd3dPluginContainer")
assert not t.isUnknown, "type not declared"
assert [b.typeName for b in t.baseTypes] == ["pxr.Usdviewq.plugin.PluginContainer"]
assert Usd.SchemaRegistry().FindConcretePrimDefinition("Lsd3dSurfelField") is not None
p = Plug.Registry().GetPluginForType(t)
p.Load()
assert "lsd3d_usd.usdview.plugin" in sys.modules
print("ok")
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr
