"""Fixtures of the Blender tests: the extension loaded from the source tree and registered once
per test module, an empty scene around every test, and the objects most tests start from."""

import importlib

import pytest

from blender_helpers import addon, reset_blender, write_ct_crop


@pytest.fixture(scope="module")
def ext():
    """The extension from the source tree, registered for each test module,
    with its script API (``blender.api``) imported as a script imports it."""
    module = addon()
    importlib.import_module(f"{module.__name__}.blender.api")
    module.register()
    yield module
    module.unregister()


@pytest.fixture(autouse=True)
def fresh(ext):
    """Every test starts and ends with an empty scene."""
    reset_blender()
    yield
    reset_blender()


@pytest.fixture
def ct_crop_npy(tmp_path, data_dir):
    """A crop of the real CT head as .npy with its JSON sidecar (spacing, HU)."""
    path = tmp_path / "ct_crop.npy"
    write_ct_crop(path, data_dir)
    return path


@pytest.fixture
def core(ext):
    """The core as the extension imports it (same classes as the operators use)."""
    return ext.volumeevm_addon


@pytest.fixture
def api(ext):
    """The extension's script API."""
    return ext.blender.api
