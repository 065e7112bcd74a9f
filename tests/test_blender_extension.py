"""The extension as users get it: the Linux x64 zip (this machine's and CI's platform), built with
``--split-platforms`` as ``make extension`` builds each platform's, by the tool inside the bpy wheel
(``bl_pkg/cli/blender_ext.py``, the code of ``blender --command extension build/validate``),
validated, installed into a fresh bpy and enabled; then, in Blender started again, enabled (neither
imports Numba), its operators and script API run, disabled; in a third session, importing the
installed API enables the extension (README's second-session lines). Building and meshing a
VolumeEVM runs the EVM and mesh kernels: they compile with the bundled Numba and llvmlite (not the
venv's), cached in the extension's user folder, and the job prints that it compiles them.

The fresh bpy is a child process of the running venv's Python (the same bpy version) with
``BLENDER_USER_RESOURCES`` in ``tmp_path``, so nothing is written to the user's Blender folders
and the kernels compile from cold. The wheels come from PyPI once, into ``wheels/``
(git-ignored), as ``make extension`` fetches them (``requirements/fetch_wheels.py``).
"""

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest

from blender_helpers import REPO

MANIFEST = tomllib.loads((REPO / "blender_manifest.toml").read_text())
PLATFORM = "linux-x64"
ZIP_NAME = f"{MANIFEST['id']}-{MANIFEST['version']}-{PLATFORM.replace('-', '_')}.zip"
FIRST_USE = "compiling VolumeEVM's Numba kernels (first use only)"

_spec = importlib.util.spec_from_file_location("fetch_wheels",
                                               REPO / "requirements" / "fetch_wheels.py")
fetch_wheels = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fetch_wheels)

INSTALL = r'''
import glob, json, os, sys
import bpy

zip_path, repo_dir = sys.argv[1], sys.argv[2]
bpy.context.preferences.extensions.repos.new(
    name="vevm_test", module="vevm_test", custom_directory=repo_dir, source="USER")
result = {"install": sorted(bpy.ops.extensions.package_install_files(
    filepath=zip_path, repo="vevm_test", enable_on_install=True))}
result["registered"] = hasattr(bpy.types, "VOLUMEEVM_OT_import_volume")
result["numba_imported_by_enabling"] = "numba" in sys.modules
site = glob.glob(os.path.join(bpy.utils.user_resource("EXTENSIONS"), ".local", "lib", "python*",
                              "site-packages"))
result["site_packages"] = sorted(os.listdir(site[0])) if site else []
print("RESULT " + json.dumps(result), flush=True)
'''

# Blender started again after the install (the extension's wheels now come first on sys.path,
# before the venv's own Numba): enable the extension, run its operators and script API.
RUN = r'''
import glob, json, os, sys, time
import bpy, addon_utils

repo_dir, volume, threshold = sys.argv[1], sys.argv[2], float(sys.argv[3])
package = "bl_ext.vevm_test.volumeevm"
bpy.context.preferences.extensions.repos.new(
    name="vevm_test", module="vevm_test", custom_directory=repo_dir, source="USER")
result = {}

def fail(error):
    raise error

start = time.perf_counter()
addon_utils.enable(package, default_set=True, handle_error=fail)
result["enable_seconds"] = time.perf_counter() - start
result["numba_imported_by_enabling"] = "numba" in sys.modules
result["dask_imported_by_enabling"] = [m for m in ("dask", "numcodecs") if m in sys.modules]
result["module"] = package in sys.modules
result["registered"] = hasattr(bpy.types, "VOLUMEEVM_OT_import_volume")
extension = sys.modules[package]
extension.unregister()
start = time.perf_counter()
extension.register()
result["register_seconds"] = time.perf_counter() - start
start = time.perf_counter()
result["import"] = sorted(bpy.ops.volumeevm.import_volume(filepath=volume))
result["build"] = sorted(bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=threshold))
result["mesh"] = sorted(bpy.ops.volumeevm.make_mesh())
result["first_use_seconds"] = time.perf_counter() - start
import numba, llvmlite
site = os.path.realpath(os.path.join(bpy.utils.user_resource("EXTENSIONS"), ".local"))
result["numba"] = [numba.__version__, llvmlite.__version__,
                   all(os.path.realpath(m.__file__).startswith(site) for m in (numba, llvmlite))]
cache = bpy.utils.extension_path_user(package, path="numba")
result["cached_kernels"] = len(glob.glob(os.path.join(cache, "**", "*.nbi"), recursive=True))
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
addon_utils.disable(package, default_set=True)
result["unregistered"] = not hasattr(bpy.types, "VOLUMEEVM_OT_import_volume")
# Disabling gave the kernel cache folder back (the core's default): set_kernel_cache_dir
# returns the folder it replaces.
core = sys.modules[package + ".volumeevm_addon"]
result["cache_dir_after_disable"] = core.system.set_kernel_cache_dir(None)
print("RESULT " + json.dumps(result), flush=True)
'''


# A second session after the install, as README shows it: a new Python imports the installed
# extension's API, which enables the extension (not enabled: the bpy module saves no preferences).
SECOND_SESSION = r'''
import json, sys
import bpy
import addon_utils

repo_dir, volume = sys.argv[1], sys.argv[2]
bpy.context.preferences.extensions.repos.new(
    name="vevm_test", module="vevm_test", custom_directory=repo_dir, source="USER")
result = {"enabled_before": addon_utils.check("bl_ext.vevm_test.volumeevm")[1]}
from bl_ext.vevm_test.volumeevm.blender import api
result["enabled_after"] = addon_utils.check("bl_ext.vevm_test.volumeevm")[1]
vol = api.import_volume(volume, name="second")
result["volume"] = [vol.name, vol.volumeevm.role, list(vol.volumeevm.shape)]
print("RESULT " + json.dumps(result), flush=True)
'''


def _blender_ext():
    """``blender_ext.py`` from the bpy wheel of the running venv."""
    bpy_dir = Path(importlib.util.find_spec("bpy").origin).parent
    found = sorted(bpy_dir.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    assert found, f"blender_ext.py not found in {bpy_dir}"
    return found[0]


def _bpy_process(tmp_path, script, env, *args):
    """Run ``script`` in a fresh bpy (a child Python) with ``args``; its output and RESULT."""
    path = tmp_path / "script.py"
    path.write_text(script)
    run = subprocess.run([sys.executable, str(path), *map(str, args)], capture_output=True,
                         text=True, env=env, timeout=600, cwd=tmp_path)
    lines = [line for line in run.stdout.splitlines() if line.startswith("RESULT ")]
    assert run.returncode == 0 and lines, run.stdout[-3000:] + run.stderr[-3000:]
    return run, json.loads(lines[-1][len("RESULT "):])


#: The compiled wheels the extension bundles per platform and Python, by lower-case name.
COMPILED = ("numba", "llvmlite", "numcodecs", "pyyaml")


def _pins():
    """``{name: version}`` of the compiled wheels (:data:`COMPILED`), the same in both
    environments' requirements."""
    pattern = rf"^({'|'.join(COMPILED)})==(\S+)$"
    pins = [dict(re.findall(pattern, (REPO / "requirements" / name).read_text(), re.M | re.I))
            for name in ("py311.txt", "py313.txt")]
    pins = [{name.lower(): version for name, version in p.items()} for p in pins]
    assert pins[0] == pins[1] and set(pins[0]) == set(COMPILED)
    return pins[0]


def _platform_source(tmp_path, wheels):
    """A copy of the source tree whose manifest names only :data:`PLATFORM` and ``wheels``
    (``wheels/`` itself linked, not copied): the tool builds that one platform's zip."""
    def skip(folder, names):
        top = {".git", ".venv", "wheels", "dist", "out"} if Path(folder) == REPO else set()
        return [n for n in names if n in top or n == "__pycache__"]

    source = tmp_path / "source"
    shutil.copytree(REPO, source, ignore=skip)
    (source / "wheels").symlink_to(REPO / "wheels", target_is_directory=True)
    names = {w.name for w in wheels}
    lines = []
    for line in (REPO / "blender_manifest.toml").read_text().splitlines(keepends=True):
        if line.startswith("platforms = "):
            line = f'platforms = ["{PLATFORM}"]\n'
        listed = re.fullmatch(r'\s*"\./wheels/(\S+\.whl)",\n', line)
        if not listed or listed.group(1) in names:
            lines.append(line)
    (source / "blender_manifest.toml").write_text("".join(lines))
    manifest = tomllib.loads((source / "blender_manifest.toml").read_text())
    assert manifest["platforms"] == [PLATFORM]
    assert manifest["wheels"] == [f"./wheels/{w.name}" for w in wheels]
    return source


def test_manifest_bundles_compiled_wheels_per_platform_and_no_numpy():
    tags = [fetch_wheels.wheel_tags(w) for w in MANIFEST["wheels"]]
    assert all(w.startswith("./wheels/") for w in MANIFEST["wheels"])
    assert not any(t[0].lower() == "numpy" for t in tags)  # Blender's own, never bundled
    # The platforms with llvmlite wheels on PyPI: no Intel macOS.
    assert MANIFEST["platforms"] == ["windows-x64", "linux-x64", "linux-arm64", "macos-arm64"]
    pins = _pins()
    platform_wheels = sorted((name, version, python, abi, fetch_wheels.blender_platform(platform))
                             for name, version, python, abi, platform in tags if platform != "any")
    assert platform_wheels == sorted(
        (name, pins[name], python, python, platform) for name in COMPILED
        for python in ("cp311", "cp313") for platform in MANIFEST["platforms"])
    assert all(t[2] in ("py3", "py2.py3") and t[3:] == ("none", "any")
               for t in tags if t[4] == "any")
    assert MANIFEST["blender_version_min"] == "4.5.0"
    assert MANIFEST["license"] == ["SPDX:GPL-3.0-or-later"]


def test_extension_builds_validates_installs_and_runs(tmp_path, data_dir):
    try:
        wheels = fetch_wheels.fetch(PLATFORM)
    except RuntimeError as error:
        pytest.fail(f"could not download the extension's wheels for {PLATFORM}; run "
                    f"`make extension` with network access:\n{error}")
    tool = _blender_ext()
    dist = tmp_path / "dist"
    dist.mkdir()
    source = _platform_source(tmp_path, wheels)
    built = subprocess.run(
        [sys.executable, str(tool), "build", "--source-dir", str(source), "--output-dir",
         str(dist), "--split-platforms"],
        capture_output=True, text=True)
    assert built.returncode == 0, built.stdout + built.stderr
    archive = dist / ZIP_NAME
    assert archive.is_file()

    with zipfile.ZipFile(archive) as z:
        names = set(z.namelist())
    for needed in ("blender_manifest.toml", "__init__.py", "blender/api.py", "ui/panels.py",
                   "volumeevm_addon/__init__.py", "volumeevm_addon/readers/__init__.py",
                   "volumeevm_addon/model/_evm.py", "volumeevm_addon/rendering/_render.py",
                   "volumeevm_addon/phantoms.py", "volumeevm_addon/metrics.py",
                   "volumeevm_addon/rendering/shaders/dvr.frag.glsl"):
        assert needed in names
    assert {n for n in names if n.startswith("wheels/")} == {f"wheels/{w.name}" for w in wheels}
    for left_out in ("tests/", "bench/", "sample_blends/", ".venv/", ".git/", "requirements/",
                     "Makefile", "pytest.ini", "pyproject.toml", "docs/",
                     "out/", "dist/"):
        assert not any(n == left_out or n.startswith(left_out) for n in names), left_out
    assert not any("__pycache__" in n for n in names)

    valid = subprocess.run([sys.executable, str(tool), "validate", str(archive)],
                           capture_output=True, text=True)
    assert valid.returncode == 0, valid.stdout + valid.stderr

    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "user"))
    repo_dir = tmp_path / "repo"
    volume = data_dir / "ct_skull_cgal.npy"
    _, installed = _bpy_process(tmp_path, INSTALL, env, archive, repo_dir)
    run, result = _bpy_process(tmp_path, RUN, env, repo_dir, volume, 2.9)
    second_run, second = _bpy_process(tmp_path, SECOND_SESSION, env, repo_dir, volume)

    from volumeevm_addon import VolumeEVM, read_volume

    expected = VolumeEVM.from_volume(read_volume(volume), 2.9)
    verts, polys = expected.mesh()
    print(f"enable {result['enable_seconds']:.2f} s, register() "
          f"{1000 * result['register_seconds']:.1f} ms; import, build and mesh with the kernels' "
          f"first use {result['first_use_seconds']:.1f} s")
    assert installed["install"] == ["FINISHED"] and installed["registered"]
    assert {"pydicom", "nibabel", "nrrd", "tifffile", "numba", "llvmlite", "dask", "numcodecs",
            "yaml", "toolz"} <= set(installed["site_packages"])
    assert not any(name.lower().startswith("numpy") for name in installed["site_packages"])
    assert not installed["numba_imported_by_enabling"] and not result["numba_imported_by_enabling"]
    assert result["dask_imported_by_enabling"] == []
    assert result["module"] and result["registered"]
    assert result["import"] == result["build"] == result["mesh"] == ["FINISHED"]
    pins = _pins()
    assert result["numba"] == [pins["numba"], pins["llvmlite"], True]  # the bundled ones
    assert result["cached_kernels"] > 0
    assert re.search(rf"^\[volumeevm\] +\d+% {re.escape(FIRST_USE)}$", run.stdout, re.M)
    assert result["voxels"] == expected.voxel_count and result["evs"] == len(expected.evm)
    assert result["polygons"] == len(polys) and result["vertices"] == len(np.asarray(verts))
    assert result["api"] == ["by_api", expected.voxel_count, len(polys)]
    assert result["unregistered"]
    assert result["cache_dir_after_disable"] is None
    # The installed add-on's folder got nothing written into it.
    folder = repo_dir / MANIFEST["id"]
    assert (folder / "blender_manifest.toml").is_file()
    assert list(folder.rglob("*.vevm")) == [] and list(folder.rglob("*.nbi")) == []
    assert "[volumeevm]  30% building EVM" in run.stdout
    assert second == {"enabled_before": False, "enabled_after": True,
                      "volume": ["second", "VOLUME", list(np.load(volume).shape)]}
    assert "reloading" not in second_run.stdout, second_run.stdout  # no second import
    assert "Exception" not in second_run.stdout + second_run.stderr  # nor at exit
