"""Import -> build -> mesh in the real bpy, against the core; sidecars across save and reopen;
bad input; background progress lines.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13).
"""

import json
import os
import warnings
from pathlib import Path

import bpy
import numpy as np
import pytest

from blender_helpers import CT_BONE_HU, CT_CROP, REPO, assert_surface_is

SKULL_THRESHOLD = 2.9  # CGAL meshes this skull at 2.9


@pytest.fixture
def ct_crop_nrrd(tmp_path, data_dir):
    """The same crop as NRRD with a patient origin (LPS), so placement is not trivial."""
    import nrrd

    meta = json.loads((data_dir / "ct_head_invesalius.json").read_text())
    array = np.load(data_dir / "ct_head_invesalius.npy")[CT_CROP]
    path = tmp_path / "ct_crop.nrrd"
    header = {
        "space": "left-posterior-superior",
        "space directions": np.diag(meta["spacing_mm"]),
        "space origin": np.array([-61.25, -40.5, 102.0]),
    }
    with warnings.catch_warnings():  # pynrrd's own datetime.utcnow deprecation (Python 3.12+)
        warnings.filterwarnings("ignore", "datetime.datetime.utcnow", DeprecationWarning)
        nrrd.write(str(path), np.ascontiguousarray(array), header)
    return path


def _only(objects, role):
    found = [o for o in objects if o.volumeevm.role == role]
    assert len(found) == 1, [o.name for o in objects]
    return found[0]


def _assert_mesh_equals_core(surface, vevm):
    polys = assert_surface_is(surface, vevm)
    assert len(surface.data.polygons) == len(polys)
    smooth = np.ones(len(polys), bool)
    surface.data.polygons.foreach_get("use_smooth", smooth)
    assert not smooth.any()  # a voxel boundary is flat-shaded


# ---------------------------------------------------------------------------- registration
def test_register_unregister_twice(ext):
    for _ in range(2):
        ext.unregister()
        assert not hasattr(bpy.types.Scene, "volumeevm")
        assert not hasattr(bpy.types.Object, "volumeevm")
        assert not hasattr(bpy.types, "VOLUMEEVM_OT_build_vevm")
        assert ext.blender.sidecar.on_load_post not in bpy.app.handlers.load_post
        ext.register()
        assert hasattr(bpy.types.Scene, "volumeevm")
        assert hasattr(bpy.types, "VOLUMEEVM_OT_import_volume")
        assert hasattr(bpy.types, "VOLUMEEVM_PT_main")
        assert ext.blender.sidecar.on_load_post in bpy.app.handlers.load_post


def test_poll_messages_say_why(ext):
    with pytest.raises(RuntimeError, match="Select a volume object"):
        bpy.ops.volumeevm.build_vevm()
    with pytest.raises(RuntimeError, match="Select a volume object"):
        bpy.ops.volumeevm.make_mesh()


# ---------------------------------------------------------------------------- main path
@pytest.mark.parametrize("source, threshold", [
    ("ct_crop_npy", CT_BONE_HU),
    ("ct_crop_nrrd", CT_BONE_HU),
    ("skull", SKULL_THRESHOLD),
])
def test_operators_import_build_mesh_equal_core(request, data_dir, core, source, threshold):
    path = data_dir / "ct_skull_cgal.npy" if source == "skull" else request.getfixturevalue(source)
    assert bpy.ops.volumeevm.import_volume(filepath=str(path)) == {"FINISHED"}
    vol_obj = bpy.context.active_object
    s = vol_obj.volumeevm
    expected = core.read_volume(path)

    # The volume object: name, role, grid facts shown in the sidebar, a box at physical size.
    assert vol_obj.name == path.stem and s.role == "VOLUME"
    assert tuple(s.shape) == expected.shape
    np.testing.assert_allclose(tuple(s.spacing), expected.spacing, rtol=1e-6)
    np.testing.assert_allclose(tuple(s.origin), expected.origin, rtol=1e-6)
    assert s.value_min == pytest.approx(float(expected.array.min()))
    assert s.value_max == pytest.approx(float(expected.array.max()))
    assert sum(s.histogram) == expected.array.size
    assert s.units == expected.units and s.source_path == str(path)
    box = np.empty(24, np.float32)
    vol_obj.data.vertices.foreach_get("co", box)
    matrix = expected.index_to_physical()
    lo = (matrix[:3, :3] @ np.full(3, -0.5) + matrix[:3, 3]) * 0.001
    np.testing.assert_allclose(box.reshape(8, 3).min(axis=0), lo, rtol=1e-6, atol=1e-7)
    assert np.allclose(np.array(vol_obj.matrix_world), np.eye(4))

    assert bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=threshold) == {"FINISHED"}
    vevm = core.VolumeEVM.from_volume(expected, threshold)
    report = vevm.size_report()
    assert s.voxel_count == vevm.voxel_count
    assert s.ev_count == len(vevm.evm)
    assert s.vevm_bytes == report["total_bytes"] and s.dense_bytes == report["dense_bytes"]
    assert s.threshold == pytest.approx(threshold) and s.built_threshold == pytest.approx(threshold)
    built = core.VolumeEVM.load(bpy.path.abspath(s.vevm_path))
    np.testing.assert_array_equal(built.evm.vertices, vevm.evm.vertices)
    np.testing.assert_array_equal(built.table(), vevm.table())

    assert bpy.ops.volumeevm.make_mesh() == {"FINISHED"}
    surface = bpy.context.active_object
    assert surface.name == f"{path.stem}_surface"
    assert surface.volumeevm.role == "SURFACE" and surface.volumeevm.volume == vol_obj
    assert s.surface == surface and surface.parent == vol_obj
    assert np.allclose(np.array(surface.matrix_world), np.eye(4))
    _assert_mesh_equals_core(surface, vevm)


def test_api_gives_the_operators_result(data_dir, api, core):
    path = data_dir / "ct_skull_cgal.npy"
    obj = api.import_volume(path)
    vevm = api.build(obj, SKULL_THRESHOLD, 4.5)
    surface = api.make_mesh(obj)
    assert obj.volumeevm.use_upper and obj.volumeevm.upper == pytest.approx(4.5)
    expected = core.VolumeEVM.from_volume(core.read_volume(path), SKULL_THRESHOLD, 4.5)
    np.testing.assert_array_equal(vevm.evm.vertices, expected.evm.vertices)
    _assert_mesh_equals_core(surface, expected)

    # Rebuilding with another threshold refreshes the same surface object.
    api.build(obj, 3.5)
    again = api.make_mesh(obj)
    assert again == surface and len(bpy.data.objects) == 2
    _assert_mesh_equals_core(again, core.VolumeEVM.from_volume(core.read_volume(path), 3.5))

    # A duplicated volume object gets its own surface, the original's stays as it is.
    twin = obj.copy()
    bpy.context.scene.collection.objects.link(twin)
    api.build(twin, 4.0)
    twin_surface = api.make_mesh(twin)
    assert twin_surface != surface and twin_surface.parent == twin
    _assert_mesh_equals_core(surface, core.VolumeEVM.from_volume(core.read_volume(path), 3.5))
    _assert_mesh_equals_core(twin_surface, core.VolumeEVM.from_volume(core.read_volume(path), 4.0))


def test_cancelled_job_changes_nothing(ext, data_dir, api):
    obj = api.import_volume(data_dir / "ct_skull_cgal.npy")
    api.build(obj, SKULL_THRESHOLD)
    before = (obj.volumeevm.vevm_path, obj.volumeevm.voxel_count, obj.volumeevm.threshold)
    job = ext.blender.volumes.build_job(obj, 1.0)
    assert next(job.steps)[1] == "building EVM"
    job.steps.close()  # what Esc does: the generator stops, commit never runs
    assert (obj.volumeevm.vevm_path, obj.volumeevm.voxel_count, obj.volumeevm.threshold) == before
    surface_job = ext.blender.volumes.mesh_job(bpy.context, obj)
    next(surface_job.steps)
    surface_job.steps.close()
    assert obj.volumeevm.surface is None and len(bpy.data.objects) == 1


# ---------------------------------------------------------------------------- sidecars
def test_sidecar_beside_blend_found_after_reopen(tmp_path, data_dir, api, core, ext):
    obj = api.import_volume(data_dir / "ct_skull_cgal.npy")
    vevm = api.build(obj, SKULL_THRESHOLD)
    api.make_mesh(obj)
    temporary = Path(obj.volumeevm.vevm_path)
    assert temporary.is_file() and not obj.volumeevm.vevm_path.startswith("//")
    assert REPO not in temporary.parents  # never inside the add-on's folder

    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    assert obj.volumeevm.vevm_path == "//scene_volumeevm/ct_skull_cgal.vevm"
    sidecar_file = tmp_path / "scene_volumeevm" / "ct_skull_cgal.vevm"
    assert sidecar_file.is_file()

    bpy.ops.wm.open_mainfile(filepath=str(blend))
    obj = bpy.data.objects["ct_skull_cgal"]
    assert ext.blender.runtime.status(obj.volumeevm.uid) == ""
    assert ext.blender.sidecar.resolve(obj) == sidecar_file
    found = api.get_vevm(obj)
    np.testing.assert_array_equal(found.evm.vertices, vevm.evm.vertices)
    np.testing.assert_array_equal(found.table(), vevm.table())
    surface = bpy.data.objects["ct_skull_cgal_surface"]
    _assert_mesh_equals_core(surface, vevm)

    # The dense volume is gone after reopening: Build re-reads the source file.
    assert ext.blender.runtime.volume(obj.volumeevm.uid) is None
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=3.5) == {"FINISHED"}
    assert obj.volumeevm.voxel_count == core.VolumeEVM.from_volume(
        core.read_volume(data_dir / "ct_skull_cgal.npy"), 3.5).voxel_count
    # Until the next save the sidecar beside the .blend still matches the saved .blend.
    np.testing.assert_array_equal(core.VolumeEVM.load(sidecar_file).evm.vertices,
                                  vevm.evm.vertices)


def test_save_as_elsewhere_and_save_copy(tmp_path, data_dir, api, core):
    obj = api.import_volume(data_dir / "ct_skull_cgal.npy")
    vevm = api.build(obj, SKULL_THRESHOLD)
    first = tmp_path / "a" / "first.blend"
    first.parent.mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(first))
    original = (tmp_path / "a" / "first_volumeevm" / "ct_skull_cgal.vevm")
    stamp = original.stat().st_mtime_ns

    copy = tmp_path / "c" / "copy.blend"
    copy.parent.mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(copy), copy=True)
    assert (tmp_path / "c" / "copy_volumeevm" / "ct_skull_cgal.vevm").is_file()
    assert obj.volumeevm.vevm_path == "//first_volumeevm/ct_skull_cgal.vevm"  # put back

    second = tmp_path / "b" / "second.blend"
    second.parent.mkdir()
    bpy.ops.wm.save_as_mainfile(filepath=str(second))
    assert obj.volumeevm.vevm_path == "//second_volumeevm/ct_skull_cgal.vevm"
    moved = tmp_path / "b" / "second_volumeevm" / "ct_skull_cgal.vevm"
    np.testing.assert_array_equal(core.VolumeEVM.load(moved).evm.vertices, vevm.evm.vertices)
    assert original.stat().st_mtime_ns == stamp  # the first .blend's sidecar is untouched

    for blend in (copy, second):
        bpy.ops.wm.open_mainfile(filepath=str(blend))
        found = api.get_vevm(bpy.data.objects["ct_skull_cgal"])
        np.testing.assert_array_equal(found.evm.vertices, vevm.evm.vertices)


def test_foreign_file_in_sidecar_folder_is_not_overwritten(tmp_path, data_dir, api):
    folder = tmp_path / "scene_volumeevm"
    folder.mkdir()
    foreign = folder / "ct_skull_cgal.vevm"
    foreign.write_bytes(b"the user's own file")
    obj = api.import_volume(data_dir / "ct_skull_cgal.npy")
    api.build(obj, SKULL_THRESHOLD)
    bpy.ops.wm.save_as_mainfile(filepath=str(tmp_path / "scene.blend"))
    assert foreign.read_bytes() == b"the user's own file"
    assert obj.volumeevm.vevm_path.startswith("//scene_volumeevm/ct_skull_cgal-")
    assert Path(bpy.path.abspath(obj.volumeevm.vevm_path)).is_file()


def test_corrupt_sidecar_reported_after_reopen(tmp_path, data_dir, api, ext):
    obj = api.import_volume(data_dir / "ct_skull_cgal.npy")
    api.build(obj, SKULL_THRESHOLD)
    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    sidecar_file = tmp_path / "scene_volumeevm" / "ct_skull_cgal.vevm"
    sidecar_file.write_bytes(sidecar_file.read_bytes()[:500])
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    obj = bpy.data.objects["ct_skull_cgal"]
    assert "not a readable VolumeEVM file" in ext.blender.runtime.status(obj.volumeevm.uid)
    bpy.context.view_layer.objects.active = obj
    with pytest.raises(RuntimeError, match="not a readable VolumeEVM file"):
        bpy.ops.volumeevm.make_mesh()
    assert obj.volumeevm.surface is None
    # Building again repairs it (a new file; the broken one is left as it is).
    assert bpy.ops.volumeevm.build_vevm() == {"FINISHED"}
    assert bpy.ops.volumeevm.make_mesh() == {"FINISHED"}
    assert len(sidecar_file.read_bytes()) == 500


# ---------------------------------------------------------------------------- bad input
def test_corrupt_file_reported_nothing_lost(tmp_path):
    bad = tmp_path / "broken.npy"
    content = b"\x93NUMPY\x01\x00garbage that is not a header"
    bad.write_bytes(content)
    with pytest.raises(RuntimeError, match="broken.npy: not a readable .npy"):
        bpy.ops.volumeevm.import_volume(filepath=str(bad))
    assert len(bpy.data.objects) == 0 and len(bpy.data.meshes) == 0
    assert bad.read_bytes() == content
    with pytest.raises(RuntimeError, match="no such file"):
        bpy.ops.volumeevm.import_volume(filepath=str(tmp_path / "missing.nrrd"))


def test_empty_region_reported_previous_build_kept(data_dir, api):
    bpy.ops.volumeevm.import_volume(filepath=str(data_dir / "ct_skull_cgal.npy"))
    obj = bpy.context.active_object
    bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=SKULL_THRESHOLD)
    before = (obj.volumeevm.vevm_path, obj.volumeevm.voxel_count, obj.volumeevm.threshold)
    with pytest.raises(RuntimeError, match="the region is empty"):
        bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=100.0)
    with pytest.raises(RuntimeError, match="upper bound 1.0 is below the threshold"):
        bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=2.0, use_upper=True,
                                     upper=1.0)
    assert (obj.volumeevm.vevm_path, obj.volumeevm.voxel_count, obj.volumeevm.threshold) == before
    assert Path(obj.volumeevm.vevm_path).is_file()


def test_missing_source_after_reopen_is_reported(tmp_path, data_dir, api):
    source = tmp_path / "skull.npy"
    source.write_bytes((data_dir / "ct_skull_cgal.npy").read_bytes())
    api.import_volume(source)
    blend = tmp_path / "scene.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    os.remove(source)
    bpy.ops.wm.open_mainfile(filepath=str(blend))
    bpy.context.view_layer.objects.active = bpy.data.objects["skull"]
    with pytest.raises(RuntimeError, match="skull.npy: no such file"):
        bpy.ops.volumeevm.build_vevm()
    assert not bpy.data.objects["skull"].volumeevm.vevm_path


# ---------------------------------------------------------------------------- progress
def test_background_progress_lines(capfd, data_dir):
    assert bpy.app.background
    bpy.ops.volumeevm.import_volume(filepath=str(data_dir / "ct_skull_cgal.npy"))
    bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=SKULL_THRESHOLD)
    bpy.ops.volumeevm.make_mesh()
    lines = [line for line in capfd.readouterr().out.splitlines()
             if line.startswith("[volumeevm]")]
    for expected in ("[volumeevm]   0% reading ct_skull_cgal", "[volumeevm]  30% building EVM",
                     "[volumeevm]  20% meshing", "[volumeevm] 100% done"):
        assert expected in lines
    assert lines.index("[volumeevm]  30% building EVM") < lines.index("[volumeevm]  20% meshing")


def test_nothing_written_into_the_addon_folder():
    shipped = [REPO / "blender", REPO / "operators", REPO / "ui", REPO / "volumeevm_addon"]
    assert [p for folder in shipped for p in folder.rglob("*.vevm")] == []
    assert list(REPO.glob("*.vevm")) == []
