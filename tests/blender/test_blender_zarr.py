"""OME-Zarr stores in Blender (real bpy): import reads metadata and the coarsest level only,
the object keeps the store, level, channel and time across save and reload, and Build reads the
picked level chunk by chunk, exactly as ``from_array`` on the dense data.

The stores are written by ``zarr_files.write_store`` from a crop of the real CT head
(128 x 128 x 50 voxels) as a 3-level pyramid in 16 x 32 x 32 chunks.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13).
"""

import dataclasses
import json
import re
import threading
import time

import bpy
import numpy as np
import pytest

from blender_helpers import CT_BONE_HU, CT_CROP, assert_identical, assert_surface_is
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
    for picked in (dict(filepath=str(store / ".zattrs")), dict(filepath=str(store / "0")),
                   dict(directory=f"{store}/")):  # inside the store, nothing selected
        assert bpy.ops.volumeevm.import_volume(**picked) == {"FINISHED"}
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


# ---------------------------------------------------------------------------- levels panel
def test_volume_panel_lists_the_levels_and_the_picked_one_is_built(store, crop, api, core, ext):
    from test_blender_ui import draw_all, texts

    obj = api.import_volume(store)
    bpy.context.view_layer.objects.active = obj
    calls = draw_all(ext, bpy.context)
    shown = texts(calls)
    assert "0: 128 × 128 × 50, 0.957 × 0.957 × 1.5 mm" in shown
    assert "1: 64 × 64 × 25, 1.91 × 1.91 × 3 mm" in shown
    assert "2: 32 × 32 × 13, 3.83 × 3.83 × 6 mm" in shown
    disk = sum(f.stat().st_size for f in [*chunk_files(store, 0), store / "0" / ".zarray"])
    levels = ext.blender.volumes.zarr_levels(obj)
    assert levels[0]["disk_bytes"] == disk
    assert [lv["bytes"] for lv in levels] == [crop[::2 ** k, ::2 ** k, ::2 ** k].nbytes
                                              for k in range(LEVELS)]
    for level in levels:
        assert any(t.startswith(f"Disk {ext.ui.panels.human_bytes(level['disk_bytes'])}, "
                                f"memory {ext.ui.panels.human_bytes(level['bytes'])}, build ~")
                   for t in shown)
    icons = [kw["icon"] for name, _, kw in calls if name == "label" and
             kw.get("icon", "").startswith("RADIOBUT")]
    assert icons == ["RADIOBUT_ON", "RADIOBUT_OFF", "RADIOBUT_OFF"]
    assert ("prop", (obj.volumeevm, "level"), {}) in calls
    # What building needs follows the threshold: the chunks in flight alone when nothing is in
    # the region, plus twice the table when all is; the coarse histogram's estimate of the
    # region is close to the full level's.
    s = obj.volumeevm
    s.threshold = s.value_max + 1
    empty = [lv["build_bytes"] for lv in ext.blender.volumes.zarr_levels(obj)]
    s.threshold = s.value_min
    full = [lv["build_bytes"] for lv in ext.blender.volumes.zarr_levels(obj)]
    for level, none, everything in zip(levels, empty, full):
        assert none == core.model.chunked_build_memory(level["chunks"], level["dtype"], 0)
        assert everything - none == 2 * level["bytes"]
    s.threshold = CT_BONE_HU
    assert ext.blender.volumes.region_fraction(s) == pytest.approx(
        np.mean(crop >= CT_BONE_HU), abs=0.02)
    # Picking a level: the object's size and spacing are that level's, Build reads it.
    s.level = 1
    shown = texts(draw_all(ext, bpy.context))
    assert "Size: 64 × 64 × 25 voxels" in shown and "Spacing: 1.914 × 1.914 × 3 mm" in shown
    assert ext.blender.volumes.source_of(obj) == (str(store), {"level": 1})
    lazy = api.get_volume(obj)
    assert lazy.shape == (64, 64, 25) and not isinstance(lazy.array, np.ndarray)
    s.level = 7  # beyond the pyramid: the coarsest
    assert s.level == 2 and tuple(s.shape) == (32, 32, 13)


# ---------------------------------------------------------------------------- build
def _dense_build(core, store, level, threshold):
    """``from_array`` on the level's data in memory (the core's in-memory path)."""
    vol = core.read_volume(store, level=level)
    return core.VolumeEVM.from_volume(dataclasses.replace(vol, array=np.asarray(vol.array)),
                                      threshold)


@pytest.mark.parametrize("version", [2, 3])
def test_build_at_each_level_equals_from_array_on_the_dense_data(tmp_path, crop, api, core,
                                                                 version):
    store = write_store(tmp_path / "head.ome.zarr", pyramid(crop, LEVELS), chunks=CHUNKS_ZYX,
                        version=version)
    obj = api.import_volume(store)
    for level in (0, 1):
        obj.volumeevm.level = level
        vevm = api.build(obj, CT_BONE_HU)
        assert_identical(vevm, _dense_build(core, store, level, CT_BONE_HU))
        assert_identical(api.get_vevm(obj), vevm)
        s = obj.volumeevm
        assert (s.built_level, s.voxel_count) == (level, vevm.voxel_count)
        assert s.voxel_count == np.count_nonzero(crop[::2 ** level, ::2 ** level, ::2 ** level]
                                                 >= CT_BONE_HU)
    surface = api.make_mesh(obj)
    assert_surface_is(surface, vevm)


def test_corrupt_chunk_reported_by_name_object_unchanged(store, api, core, ext):
    from test_blender_jobs import scene_state

    victim = _corrupt(store, 0)
    obj = api.import_volume(store)  # the full level is never read by import
    bpy.context.view_layer.objects.active = obj
    obj.volumeevm.level = 1
    api.build(obj, CT_BONE_HU)  # a sound level builds
    obj.volumeevm.level = 0
    before = scene_state(api)
    key = victim.name
    named = rf"{re.escape(str(store))}: level 0 \(0\), chunk \(\d+, \d+, \d+\): .*{key}"
    with pytest.raises(RuntimeError, match=named):
        bpy.ops.volumeevm.build_vevm()
    assert scene_state(api) == before
    with pytest.raises(core.VolumeEVMError, match=named):
        api.build(obj)
    assert scene_state(api) == before
    assert obj.volumeevm.built_level == 1


def test_background_progress_line_per_chunk(store, crop, api, capfd):
    obj = api.import_volume(store)
    bpy.context.view_layer.objects.active = obj
    capfd.readouterr()
    assert bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=CT_BONE_HU) == {"FINISHED"}
    lines = [line for line in capfd.readouterr().out.splitlines()
             if line.startswith("[volumeevm]")]
    total = 4 * 4 * 4  # 50 x 128 x 128 (z, y, x) in 16 x 32 x 32 chunks
    chunks = [line for line in lines if "building EVM: chunk" in line]
    assert [line.split("chunk ")[1] for line in chunks] == [f"{n} of {total}"
                                                            for n in range(1, total + 1)]
    assert chunks[-1] == f"[volumeevm]  90% building EVM: chunk {total} of {total}"
    assert lines.index("[volumeevm]  30% building EVM") < lines.index(chunks[0])
    assert lines[-1] == "[volumeevm] 100% done"


def test_escape_stops_the_build_at_the_next_chunk_nothing_changed(store, api, ext,
                                                                  monkeypatch):
    from test_blender_jobs import scene_state
    from test_blender_ui import _Context, _driver, _Event

    zarr = ext.volumeevm_addon.readers._zarr
    read_chunk, reads = zarr.read_chunk, []

    def slow_read(level, chunk):
        reads.append(chunk)
        time.sleep(0.05)
        return read_chunk(level, chunk)

    monkeypatch.setattr(zarr, "read_chunk", slow_read)
    obj = api.import_volume(store)
    bpy.context.view_layer.objects.active = obj
    before, jobs = scene_state(api), ext.blender.jobs
    op = _driver(ext, lambda: ext.blender.volumes.build_job(obj, CT_BONE_HU))
    context = _Context()
    assert op.start(context) == {"RUNNING_MODAL"}
    assert jobs.CURRENT.label == "Build VolumeEVM of head.ome (level 0)"
    for _ in range(500):
        assert op.modal(context, _Event("TIMER")) == {"RUNNING_MODAL"}
        if jobs.CURRENT.text.startswith("building EVM: chunk"):
            break
        time.sleep(0.01)
    assert jobs.CURRENT.text.startswith("building EVM: chunk")
    assert op.modal(context, _Event("ESC")) == {"CANCELLED"}
    op._executor.shutdown(wait=True)  # the steps closed: the build stopped and was waited for
    assert not any(t.name == "volumeevm-build" for t in threading.enumerate())
    assert len(reads) < 64  # stopped early, not built to the end
    assert scene_state(api) == before
    assert ({"WARNING"}, "Build VolumeEVM of head.ome (level 0): cancelled, nothing changed") \
        in op.reports


# ---------------------------------------------------------------------------- preview
def test_the_viewport_preview_is_the_coarsest_level_while_a_finer_one_builds(store, api, core,
                                                                              ext):
    from test_blender_ui import _Context, _driver, _Event, _ticks

    jobs, preview = ext.blender.jobs, ext.blender.preview
    obj = api.import_volume(store)
    coarse = _dense_build(core, store, LEVELS - 1, CT_BONE_HU)
    vertices, polygons = coarse.mesh()
    seen = []
    for level in (0, LEVELS - 1):
        obj.volumeevm.level = level
        op = _driver(ext, lambda: ext.blender.volumes.build_job(obj, CT_BONE_HU))
        context = _Context()
        assert op.start(context) == {"RUNNING_MODAL"}
        for _ in range(1000):
            result = op.modal(context, _Event("TIMER"))
            if result != {"RUNNING_MODAL"}:
                break
            if jobs.CURRENT.text.startswith("building EVM"):
                seen.append(preview.current())
            time.sleep(0.01)
        if result == {"RUNNING_MODAL"}:
            result = _ticks(op, context)
        assert result == {"FINISHED"} and preview.current() is None  # gone with the job
        assert obj.volumeevm.built_level == level
    shown = [p for p in seen if p is not None]
    assert shown and len(shown) == len(seen[:len(shown)])  # only while level 0 built
    first = shown[0]
    assert (first.name, first.level) == (obj.name, LEVELS - 1)
    np.testing.assert_array_equal(first.co, (vertices * 0.001).astype(np.float32))
    np.testing.assert_array_equal(first.edges, polygons.unique_edges()[0])
    assert all(p is first for p in shown)


DRAW_SCRIPT = """
import sys
sys.path[:0] = [{repo!r}, {tests!r}]
import bpy, gpu
import numpy as np
from mathutils import Matrix
from blender_helpers import addon

import importlib
ext = addon()
try:
    ext.blender.gpu_context.ensure_context()
except ext.blender.gpu_context.GPUUnavailable as error:
    print("no GPU context:", error)
    sys.exit(0)
api = importlib.import_module(ext.__name__ + ".blender.api")
ext.register()
jobs, preview = ext.blender.jobs, ext.blender.preview
obj = api.import_volume({store!r})
co = np.array([[0.01, 0.01, 0.01], [0.12, 0.12, 0.05]], np.float32)
counts = []
for job in (jobs.Progress("build", preview=preview.Preview(obj.name, 2, co,
                                                           np.array([[0, 1]], np.int32))),
            None):
    jobs.CURRENT = job
    off = gpu.types.GPUOffScreen(64, 64, format="RGBA32F")
    with off.bind():
        fb = gpu.state.active_framebuffer_get()
        fb.clear(color=(0.0, 0.0, 0.0, 0.0), depth=1.0)
        with gpu.matrix.push_pop(), gpu.matrix.push_pop_projection():
            gpu.matrix.load_identity()
            gpu.matrix.load_projection_matrix(Matrix.Translation((-1.0, -1.0, 0.0))
                                              @ Matrix.Diagonal((2 / 0.13, 2 / 0.13, 4.0, 1.0)))
            preview.draw()
        rgba = np.array(fb.read_color(0, 0, 64, 64, 4, 0, "FLOAT").to_list())
    off.free()
    lit = np.all(np.abs(rgba - preview.COLOR) < 0.01, axis=-1)
    counts.append(int(lit.sum()))
    if job is not None:
        diagonal = [bool(lit[i, i]) for i in range(10, 55)]
        print("diagonal", all(diagonal))
jobs.CURRENT = None
print("lit", counts)
ext.unregister()
"""


def test_preview_draws_its_edges_in_the_viewport_and_nothing_once_the_job_ends(store):
    """The draw handler's drawing over an offscreen (a process of its own, as the GPU tests)."""
    import subprocess
    import sys

    from blender_helpers import REPO

    script = DRAW_SCRIPT.format(repo=str(REPO), tests=str(REPO / "tests"), store=str(store))
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    if "no GPU context" in done.stdout:  # no viewport without one either
        pytest.skip(done.stdout.strip())
    assert "diagonal True" in done.stdout
    lit = json.loads(done.stdout.split("lit ")[1].splitlines()[0])
    assert lit[0] >= 45 and lit[1] == 0
