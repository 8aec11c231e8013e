"""The surfel schema: generated files current, registration (also from a built wheel)."""
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from pxr import Usd, UsdVol

import lsd3d_usd
from conftest import ROOT


def test_generated_schema_files_are_current():
    # Runs in a fresh process: usdGenSchema must configure USD before pxr loads.
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "regenerate_schema.py"), "--check"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_stale_generated_file_is_detected(tmp_path, monkeypatch):
    # Point the checker at a copy whose schema.usda differs from the generated files.
    import shutil
    copy = tmp_path / "repo"
    shutil.copytree(ROOT / "lsd3d_usd" / "schemas", copy / "lsd3d_usd" / "schemas")
    (copy / "tools").mkdir()
    shutil.copy(ROOT / "tools" / "regenerate_schema.py", copy / "tools")
    schema = copy / "lsd3d_usd" / "schemas" / "schema.usda"
    schema.write_text(schema.read_text().replace(
        'uniform int lsd3d:scene:seed = 0', 'uniform int lsd3d:scene:seed = 7'))
    r = subprocess.run([sys.executable, str(copy / "tools" / "regenerate_schema.py"), "--check"],
                       capture_output=True, text=True)
    assert r.returncode == 1
    assert "generatedSchema.usda" in r.stdout


def test_surfel_type_inherits_particle_field_with_official_apis():
    assert lsd3d_usd.SCHEMA_REGISTERED
    stage = Usd.Stage.CreateInMemory()
    prim = stage.DefinePrim("/S", lsd3d_usd.SURFEL_TYPE)
    assert prim.IsA(UsdVol.ParticleField)
    applied = set(prim.GetAppliedSchemas())
    for api in ("ParticleFieldPositionAttributeAPI", "ParticleFieldOrientationAttributeAPI",
                "ParticleFieldScaleAttributeAPI", "ParticleFieldOpacityAttributeAPI",
                "ParticleFieldKernelGaussianSurfletAPI", "ParticleFieldSphericalHarmonicsAttributeAPI"):
        assert api in applied
    names = set(prim.GetPropertyNames())
    assert {"positions", "orientations", "scales", "opacities",
            "radiance:sphericalHarmonicsCoefficients", "lsd3d:semanticIds"} <= names
    scene_api = Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(lsd3d_usd.SCENE_API)
    assert "lsd3d:scene:seed" in scene_api.GetPropertyNames()


def test_registration_from_built_wheel(tmp_path):
    """Build a wheel, unpack it, and import lsd3d_usd from there in a clean process:
    the schema files must ship inside the package and register on import."""
    pytest.importorskip("setuptools")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                        "-q", "-w", str(tmp_path / "dist"), str(ROOT)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    wheel = next((tmp_path / "dist").glob("lsd3d_usd-*.whl"))
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    code = (
        "import sys; sys.path.insert(0, sys.argv[1]);"
        "import lsd3d_usd; from pxr import Usd;"
        "assert lsd3d_usd.__file__.startswith(sys.argv[1]), lsd3d_usd.__file__;"
        "s = Usd.Stage.CreateInMemory(); p = s.DefinePrim('/S', 'Lsd3dSurfelField');"
        "assert 'ParticleFieldKernelGaussianSurfletAPI' in p.GetAppliedSchemas();"
        "from lsd3d_usd.commands import plugin_path;"
        "print('registered', lsd3d_usd.SCHEMA_REGISTERED); print('plugin', plugin_path())")
    r = subprocess.run([sys.executable, "-c", code, str(site)], capture_output=True, text=True,
                       cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "registered True" in r.stdout
    # `lsd3d-usd plugin-path` of a wheel install: its site-packages folder, with the plugInfo
    plugin = r.stdout.split("plugin ", 1)[1].strip()
    assert plugin.startswith(str(site)) and (Path(plugin) / "plugInfo.json").is_file()


def test_late_import_warns(tmp_path):
    # Opening a stage before importing lsd3d_usd leaves the schema unregistered: say so.
    code = ("from pxr import Usd; Usd.Stage.CreateInMemory().DefinePrim('/X', 'Xform');"
            "import warnings; warnings.simplefilter('always');"
            "import lsd3d_usd; print(lsd3d_usd.SCHEMA_REGISTERED)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert r.stdout.strip() == "False"
    assert "PXR_PLUGINPATH_NAME" in r.stderr


PLAIN_USD = """
import json, os, sys
from pxr import Usd, UsdVol
out = {"registered": Usd.SchemaRegistry().FindConcretePrimDefinition("Lsd3dSurfelField") is not None}
for path, prim_path in json.loads(sys.argv[1]):
    stage = Usd.Stage.Open(path)
    p = stage.GetPrimAtPath(prim_path)
    out[path] = {"authored": p.GetTypeName(), "particle_field": p.IsA(UsdVol.ParticleField),
                 "schema": p.GetPrimTypeInfo().GetSchemaTypeName(),
                 "apis": list(p.GetAppliedSchemas()), "n": len(p.GetAttribute("positions").Get())}
out["lsd3d_usd imported"] = "lsd3d_usd" in sys.modules
print(json.dumps(out))
"""


def test_plain_usd_without_the_plugin_sees_particle_fields(tmp_path, field_factory, run_cli):
    """A scene, a stand-alone surfel file and a per-chunk file opened by plain usd-core (no
    `import lsd3d_usd`, no PXR_PLUGINPATH_NAME): ParticleField prims with the official APIs.
    With `lsd3d-usd plugin-path` on PXR_PLUGINPATH_NAME they are Lsd3dSurfelField."""
    import json
    import os

    from lsd3d_usd import scene
    from lsd3d_usd.splats import chunkio, usdio
    sc = scene.Scene.create(tmp_path / "s")
    st = scene.new_stage()
    usdio.write_surfels(st, scene.SURFELS_PATH, field_factory(50))
    sc.write_layer("surfels", st)
    usdio.write_surfel_file(str(tmp_path / "alone.usdc"), field_factory(40))
    chunkio.write_chunk(tmp_path / "c_chunks", (0, 1), field_factory(30))
    chunkio.write_root(tmp_path / "c.usdc", tmp_path / "c_chunks",
                       {(0, 1): chunkio.chunk_info((0, 1), field_factory(30))})
    files = [(str(sc.root_layer_path), "/World/Surfels"), (str(tmp_path / "alone.usdc"), "/World/Surfels"),
             (str(tmp_path / "c.usdc"), "/World/Surfels/Chunk_0_1")]

    def plain(plugin_path=None):
        env = {k: v for k, v in os.environ.items() if k != "PXR_PLUGINPATH_NAME"}
        if plugin_path:
            env["PXR_PLUGINPATH_NAME"] = plugin_path
        r = subprocess.run([sys.executable, "-c", PLAIN_USD, json.dumps(files)], capture_output=True,
                           text=True, cwd=tmp_path, env=env)
        assert r.returncode == 0, r.stderr
        return json.loads(r.stdout)

    out = plain()
    assert not out["registered"] and not out["lsd3d_usd imported"]
    for (path, _), n in zip(files, (50, 40, 30)):
        got = out[path]
        assert got["authored"] == "Lsd3dSurfelField" and got["particle_field"], (path, got)
        assert got["schema"] == "ParticleField" and got["n"] == n
        assert set(lsd3d_usd.SURFEL_API_SCHEMAS) <= set(got["apis"]), (path, got["apis"])
    r = run_cli("plugin-path")
    assert r.returncode == 0 and r.stdout.strip() == str(lsd3d_usd.SCHEMA_DIR)
    out = plain(r.stdout.strip())
    assert out["registered"] and not out["lsd3d_usd imported"]
    assert all(out[p]["schema"] == "Lsd3dSurfelField" and out[p]["particle_field"] for p, _ in files)
    r = run_cli("plugin-path", "--export", "--usdview")
    assert r.stdout.strip() == (f'export PXR_PLUGINPATH_NAME="{lsd3d_usd.USDVIEW_PLUGIN_DIR}'
                                '${PXR_PLUGINPATH_NAME:+:$PXR_PLUGINPATH_NAME}"')
