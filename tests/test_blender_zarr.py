"""OME-Zarr stores in Blender (real bpy): import reads metadata and the coarsest level only,
the object keeps the store, level, channel and time across save and reload, and Build reads the
picked level chunk by chunk, exactly as ``from_array`` on the dense data.

The stores are written by ``zarr_files.write_store`` from a crop of the real CT head
(128 x 128 x 50 voxels) as a 3-level pyramid in 16 x 32 x 32 chunks.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13).
"""

import json

import bpy
import numpy as np
import pytest
from blender_helpers import CT_BONE_HU, CT_CROP, api, core, ext, fresh  # noqa: F401 (fixtures)
from zarr_files import chunk_files, pyramid, write_store

LEVELS = 3
CHUNKS_ZYX = (16, 32, 32)


@pytest.fixture(scope="module")
def crop(data_dir):
    return np.ascontiguousarray(np.load(data_dir / "ct_head_invesalius.npy")[CT_CROP])


@pytest.fixture
def store(tmp_path, crop):
    """The CT crop as an NGFF 0.4 store."""
    return write_store(tmp_path / "head.ome.zarr", pyramid(crop, LEVELS), chunks=CHUNKS_ZYX)


def _corrupt(store, level):
    """Truncate a chunk file of ``level``; returns its file."""
    victim = chunk_files(store, level)[3]
    victim.write_bytes(victim.read_bytes()[:-5])
    return victim


# ---------------------------------------------------------------------------- import
@pytest.mark.parametrize("version", [2, 3])
def test_import_reads_metadata_and_the_coarsest_level_only(tmp_path, crop, api, core, version):
    store = write_store(tmp_path / "head.ome.zarr", pyramid(crop, LEVELS), chunks=CHUNKS_ZYX,
                        version=version)
    _corrupt(store, 0)  # the full level is never read by import ...
    _corrupt(store, 1)
    obj = api.import_volume(store)
    s = obj.volumeevm
    assert obj.name == "head.ome" and s.role == "VOLUME"
    assert s.source_path == str(store) and s.level == 0
    levels = json.loads(s.zarr_levels)
    assert [tuple(lv["shape"]) for lv in levels] == [
        crop[::2 ** k, ::2 ** k, ::2 ** k].shape for k in range(LEVELS)]
    assert [lv["bytes"] for lv in levels] == [crop[::2 ** k, ::2 ** k, ::2 ** k].nbytes
                                              for k in range(LEVELS)]
    assert tuple(s.shape) == crop.shape
    assert tuple(s.spacing) == pytest.approx((0.957, 0.957, 1.5))
    coarse = crop[::4, ::4, ::4]
    counts, lo, hi = core.density_histogram(coarse, bins=len(s.histogram))
    np.testing.assert_array_equal(np.asarray(s.histogram), counts)
    assert (s.value_min, s.value_max) == (lo, hi)
    assert s.threshold == pytest.approx(core.otsu_threshold(coarse))
    assert s.dtype == str(crop.dtype)


def test_import_picks_level_channel_and_time_and_a_file_inside_names_the_store(store, api):
    obj = api.import_volume(store, level=1, name="half")
    s = obj.volumeevm
    assert s.level == 1 and tuple(s.shape) == (64, 64, 25)
    assert tuple(s.spacing) == pytest.approx((1.914, 1.914, 3.0))
    assert json.loads(s.reader_options) == {}
    # The file browser may hand over a file in the store, or a folder of one level.
    for picked in (store / ".zattrs", store / "0"):
        assert bpy.ops.volumeevm.import_volume(filepath=str(picked)) == {"FINISHED"}
        assert bpy.context.active_object.volumeevm.source_path == str(store)


def test_bad_level_refused_scene_unchanged(store, api, core):
    with pytest.raises(core.VolumeEVMError, match=r"head\.ome\.zarr: level=3 is not one of"):
        api.import_volume(store, level=3)
    assert len(bpy.data.objects) == 0


def test_store_level_channel_and_time_survive_save_and_reload(tmp_path, api):
    arrays = [np.stack([np.stack([a, a + 1])] * 2) for a in
              pyramid(np.arange(32 * 32 * 16, dtype=np.uint16).reshape(32, 32, 16), 2)]
    store = write_store(tmp_path / "cells.zarr", arrays, axes="tczyx", chunks=(8, 16, 16))
    obj = api.import_volume(store, channel=1, time=1)
    obj.volumeevm.level = 1
    assert tuple(obj.volumeevm.shape) == (16, 16, 8)
    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    s = bpy.data.objects["cells"].volumeevm
    assert (s.source_path, s.level) == (str(store), 1)
    assert json.loads(s.reader_options) == {"channel": 1, "time": 1}
    assert json.loads(s.zarr_levels)[1]["shape"] == [16, 16, 8]
