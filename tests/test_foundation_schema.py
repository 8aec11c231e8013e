"""The surfel schema: generated files current, registration (also from a built wheel)."""
import subprocess
import sys
import zipfile

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
        "print('registered', lsd3d_usd.SCHEMA_REGISTERED)")
    r = subprocess.run([sys.executable, "-c", code, str(site)], capture_output=True, text=True,
                       cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "registered True" in r.stdout


def test_late_import_warns(tmp_path):
    # Opening a stage before importing lsd3d_usd leaves the schema unregistered: say so.
    code = ("from pxr import Usd; Usd.Stage.CreateInMemory().DefinePrim('/X', 'Xform');"
            "import warnings; warnings.simplefilter('always');"
            "import lsd3d_usd; print(lsd3d_usd.SCHEMA_REGISTERED)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert r.stdout.strip() == "False"
    assert "PXR_PLUGINPATH_NAME" in r.stderr
