"""The extension as users get it: build the zip with the validator inside the bpy wheel
(``bl_pkg/cli/blender_ext.py``, the code of ``blender --command extension build/validate``),
validate it, install it into a fresh bpy, enable it, run its operators, disable it.

The fresh bpy is a child process of the running venv's Python (the same bpy version) with
``BLENDER_USER_RESOURCES`` in ``tmp_path``, so nothing is written to the user's Blender folders.
"""

import importlib.util
import json
import os
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest
from blender_helpers import REPO

MANIFEST = tomllib.loads((REPO / "blender_manifest.toml").read_text())
ZIP_NAME = f"{MANIFEST['id']}-{MANIFEST['version']}.zip"

INSTALL_AND_RUN = r'''
import glob, json, os, sys
import bpy, addon_utils

zip_path, repo_dir, volume, threshold = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
result = {}
bpy.context.preferences.extensions.repos.new(
    name="vevm_test", module="vevm_test", custom_directory=repo_dir, source="USER")
result["install"] = sorted(bpy.ops.extensions.package_install_files(
    filepath=zip_path, repo="vevm_test", enable_on_install=True))
result["module"] = "bl_ext.vevm_test.volumeevm" in sys.modules
result["registered"] = hasattr(bpy.types, "VOLUMEEVM_OT_import_volume")
site = glob.glob(os.path.join(bpy.utils.user_resource("EXTENSIONS"), ".local", "lib", "python*",
                              "site-packages", "*"))
result["site_packages"] = sorted(os.path.basename(p) for p in site)
result["import"] = sorted(bpy.ops.volumeevm.import_volume(filepath=volume))
result["build"] = sorted(bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=threshold))
result["mesh"] = sorted(bpy.ops.volumeevm.make_mesh())
surface = bpy.context.active_object
settings = surface.volumeevm.volume.volumeevm
result["voxels"] = settings.voxel_count
result["evs"] = settings.ev_count
result["polygons"] = len(surface.data.polygons)
result["vertices"] = len(surface.data.vertices)
# The scripting API of the installed package (as README's headless examples use it).
from bl_ext.vevm_test.volumeevm.blender import api
vol = api.import_volume(volume, name="by_api")
vevm = api.build(vol, threshold)
surface = api.make_mesh(vol)
result["api"] = [vol.name, vevm.voxel_count, len(surface.data.polygons)]
addon_utils.disable("bl_ext.vevm_test.volumeevm", default_set=True)
result["unregistered"] = not hasattr(bpy.types, "VOLUMEEVM_OT_import_volume")
print("RESULT " + json.dumps(result), flush=True)
'''


def _blender_ext():
    """``blender_ext.py`` from the bpy wheel of the running venv."""
    bpy_dir = Path(importlib.util.find_spec("bpy").origin).parent
    found = sorted(bpy_dir.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    assert found, f"blender_ext.py not found in {bpy_dir}"
    return found[0]


def _ensure_wheels():
    """The wheels the manifest lists, downloaded from PyPI once (as ``make extension`` does)."""
    wanted = [REPO / w for w in MANIFEST["wheels"]]
    missing = [w for w in wanted if not w.is_file()]
    if missing:
        pins = ["==".join(w.name.split("-")[:2]) for w in missing]
        done = subprocess.run(
            [sys.executable, "-m", "pip", "download", "--quiet", "--disable-pip-version-check",
             "--no-deps", "--only-binary=:all:", "--dest", str(REPO / "wheels"), *pins],
            capture_output=True, text=True)
        if done.returncode != 0:
            pytest.fail(f"could not download the extension's wheels ({' '.join(pins)}); "
                        f"run `make extension` with network access:\n{done.stderr}")
    return wanted


def test_manifest_wheels_are_pure_python_and_numpy_free():
    for wheel in MANIFEST["wheels"]:
        assert wheel.startswith("./wheels/") and wheel.endswith("-py3-none-any.whl"), wheel
        assert not Path(wheel).name.lower().startswith("numpy")
    assert MANIFEST["blender_version_min"] == "4.5.0"
    assert MANIFEST["license"] == ["SPDX:GPL-3.0-or-later"]


def test_extension_builds_validates_installs_and_runs(tmp_path, data_dir):
    wheels = _ensure_wheels()
    tool = _blender_ext()
    dist = tmp_path / "dist"
    dist.mkdir()
    built = subprocess.run(
        [sys.executable, str(tool), "build", "--source-dir", str(REPO), "--output-dir", str(dist)],
        capture_output=True, text=True)
    assert built.returncode == 0, built.stdout + built.stderr
    archive = dist / ZIP_NAME
    assert archive.is_file()

    with zipfile.ZipFile(archive) as z:
        names = set(z.namelist())
    for needed in ("blender_manifest.toml", "__init__.py", "blender/api.py", "ui/panels.py",
                   "volumeevm_addon/__init__.py", "volumeevm_addon/readers/__init__.py",
                   "volumeevm_addon/model/_evm.py", "volumeevm_addon/rendering/_render.py",
                   "volumeevm_addon/phantoms.py", "volumeevm_addon/metrics.py"):
        assert needed in names
    assert {f"wheels/{w.name}" for w in wheels} <= names
    for left_out in ("tests/", "bench/", "sample_blends/", ".venv/", ".git/", "requirements/",
                     "Makefile", "pytest.ini", "out/", "dist/"):
        assert not any(n == left_out or n.startswith(left_out) for n in names), left_out
    assert not any("__pycache__" in n for n in names)

    valid = subprocess.run([sys.executable, str(tool), "validate", str(archive)],
                           capture_output=True, text=True)
    assert valid.returncode == 0, valid.stdout + valid.stderr

    script = tmp_path / "install_and_run.py"
    script.write_text(INSTALL_AND_RUN)
    repo_dir = tmp_path / "repo"
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "user"))
    volume = data_dir / "ct_skull_cgal.npy"
    run = subprocess.run(
        [sys.executable, str(script), str(archive), str(repo_dir), str(volume), "2.9"],
        capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)
    lines = [line for line in run.stdout.splitlines() if line.startswith("RESULT ")]
    assert run.returncode == 0 and lines, run.stdout[-3000:] + run.stderr[-3000:]
    result = json.loads(lines[-1][len("RESULT "):])

    from volumeevm_addon import VolumeEVM, read_volume

    expected = VolumeEVM.from_volume(read_volume(volume), 2.9)
    verts, polys = expected.mesh()
    assert result["install"] == ["FINISHED"]
    assert result["module"] and result["registered"]
    assert {"pydicom", "nibabel", "nrrd", "tifffile"} <= set(result["site_packages"])
    assert not any(name.lower().startswith("numpy") for name in result["site_packages"])
    assert result["import"] == result["build"] == result["mesh"] == ["FINISHED"]
    assert result["voxels"] == expected.voxel_count and result["evs"] == len(expected.evm)
    assert result["polygons"] == len(polys) and result["vertices"] == len(np.asarray(verts))
    assert result["api"] == ["by_api", expected.voxel_count, len(polys)]
    assert result["unregistered"]
    # The installed add-on's folder got nothing written into it.
    installed = repo_dir / MANIFEST["id"]
    assert (installed / "blender_manifest.toml").is_file()
    assert list(installed.rglob("*.vevm")) == []
    assert "[volumeevm]  30% building EVM" in run.stdout
