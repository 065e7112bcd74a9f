"""What an ordinary volume object gives, an OME-Zarr store's object gives too (real bpy): the
native Blender Volume of its region, label meshes and label colours of a label store, and Render
VolumeEVM, each exactly as for the same voxels imported from a ``.npy`` file.

The stores are written by ``zarr_files.write_store`` from crops of the real CT head and of the
real liver label map, as 2-level pyramids in 16 x 32 x 32 chunks.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13).
"""

import dataclasses
import json

import bpy
import numpy as np
import pytest
from test_blender_native_volume import assert_grid_is_region, read_grid
from test_blender_render import add_camera

from blender_helpers import CT_BONE_HU, CT_CROP, assert_mesh_is, write_ct_crop
from zarr_files import pyramid, write_store

CHUNKS_ZYX = (16, 32, 32)
LIVER_CROP = (slice(150, 278), slice(100, 196), slice(60, 108))  # 128 x 96 x 48 voxels


@pytest.fixture(scope="module")
def crop(data_dir):
    return np.ascontiguousarray(np.load(data_dir / "ct_head_invesalius.npy")[CT_CROP])


def _spacing_zyx(data_dir, name):
    """The real volume's spacing (its JSON), in the store's z, y, x order."""
    meta = json.loads((data_dir / f"{name}.json").read_text())
    return tuple(reversed(meta["spacing_mm"]))


@pytest.fixture
def store(tmp_path, crop, data_dir):
    """The CT crop as an NGFF 0.4 store, with the spacing its ``.npy`` sidecar says."""
    return write_store(tmp_path / "head.ome.zarr", pyramid(crop, 2), chunks=CHUNKS_ZYX,
                       spacing_zyx=_spacing_zyx(data_dir, "ct_head_invesalius"))


@pytest.fixture
def liver(tmp_path, data_dir):
    """The liver label map's crop (labels 0, 84, 85, 127, 255 in it) as a store, and the crop."""
    array = np.ascontiguousarray(np.load(data_dir / "seg_liver_cgal.npy")[LIVER_CROP])
    path = write_store(tmp_path / "liver.ome.zarr", pyramid(array, 2), chunks=CHUNKS_ZYX,
                       spacing_zyx=_spacing_zyx(data_dir, "seg_liver_cgal"))
    return path, array


def _dense(core, path, **options):
    """The store's level read whole into memory (the in-memory path to compare with)."""
    vol = core.read_volume(path, **options)
    return dataclasses.replace(vol, array=np.asarray(vol.array))


def test_make_volume_object_of_a_store_is_exactly_its_region(ext, api, core, store):
    nv = ext.blender.native_volume
    obj = api.import_volume(store)
    vevm = api.build(obj, CT_BONE_HU)
    native = api.make_volume_object(obj)
    assert native.parent == obj and native.volumeevm.role == "NATIVE"
    assert_grid_is_region(nv, read_grid(nv, native), vevm)
    dense = core.VolumeEVM.from_volume(_dense(core, store), CT_BONE_HU)
    assert vevm.voxel_count == dense.voxel_count
    assert_grid_is_region(nv, read_grid(nv, native), dense)


def test_label_store_gives_the_label_meshes_of_from_labels_in_memory(api, core, liver):
    path, array = liver
    obj = api.import_volume(path, labels=True)
    s = obj.volumeevm
    present = sorted(set(np.unique(array).tolist()) - {0})  # the level built, read whole
    assert s.label_count == len(present) and present
    made = api.make_label_meshes(obj)
    regions = core.VolumeEVM.from_labels(_dense(core, path, labels=True))
    assert [o["volumeevm_label"] for o in made] == list(regions)
    assert list(regions) == present
    meshes = regions.meshes()
    for made_obj, label in zip(made, regions):
        assert_mesh_is(made_obj, *meshes[label])
        assert regions[label].voxel_count == np.count_nonzero(array == label)


def test_a_label_image_imports_as_a_label_map_in_its_colours(api, tmp_path, data_dir):
    """A store whose group says NGFF ``image-label`` needs no ``labels=``: the object's label
    table holds its labels with the store's colours and names."""
    array = np.ascontiguousarray(np.load(data_dir / "seg_liver_cgal.npy")[LIVER_CROP])
    present = sorted(set(np.unique(array).tolist()) - {0})
    colors = [{"label-value": label, "rgba": [0, 255, 5 * k, 255]}
              for k, label in enumerate(present)]
    path = write_store(tmp_path / "seg.ome.zarr", [array], chunks=CHUNKS_ZYX,
                       attributes={"image-label": {"colors": colors, "properties": [
                           {"label-value": present[-1], "name": "body"}]}})
    obj = api.import_volume(path)
    rows = {row.label: row for row in obj.volumeevm.labels}
    assert sorted(rows) == present and obj.volumeevm.label_count == len(present)
    for k, label in enumerate(present):
        assert tuple(rows[label].color) == pytest.approx((0.0, 1.0, 5 * k / 255), abs=1e-6)
    assert rows[present[-1]].name == "body" and rows[present[0]].name == f"label {present[0]}"


def test_label_store_builds_and_renders_its_label_colours(api, liver, data_dir, tmp_path):
    path, array = liver
    obj = api.import_volume(path, labels=True)
    vevm = api.build(obj, obj.volumeevm.threshold)
    assert vevm.voxel_count == np.count_nonzero(array)
    npy = tmp_path / "liver.npy"
    np.save(npy, array)
    meta = json.loads((data_dir / "seg_liver_cgal.json").read_text())
    side = {k: meta[k] for k in ("spacing_mm", "spacing_known", "axis_order", "dtype")}
    npy.with_suffix(".json").write_text(json.dumps(dict(side, shape=list(array.shape))))
    ref = api.import_volume(npy, labels=True)
    api.build(ref, ref.volumeevm.threshold)
    scene = bpy.context.scene
    add_camera(scene, (0.3, -0.25, 0.2), target=_centre(obj))
    scene.render.resolution_x, scene.render.resolution_y = 48, 40
    got = api.render_dvr(obj, image_name="store")
    expected = api.render_dvr(ref, image_name="file")
    assert got.visible
    np.testing.assert_array_equal(got.dvr_rgba, expected.dvr_rgba)


def _centre(obj):
    from mathutils import Vector

    corners = [obj.matrix_world @ Vector(c) for c in obj.bound_box]
    return sum(corners, Vector()) / 8


def test_render_of_a_store_equals_the_same_volume_from_npy(api, store, data_dir, tmp_path):
    npy = tmp_path / "ct_crop.npy"
    write_ct_crop(npy, data_dir)
    objs = []
    for source in (store, npy):
        obj = api.import_volume(source)
        api.build(obj, CT_BONE_HU)
        objs.append(obj)
    scene = bpy.context.scene
    api.load_preset(scene.volumeevm_render, "ct_bone", objs[0])
    add_camera(scene, (0.3, -0.3, 0.2), target=_centre(objs[0]))
    scene.render.resolution_x, scene.render.resolution_y = 48, 40
    results = []
    for obj in objs:
        other = objs[1] if obj is objs[0] else objs[0]
        other.hide_viewport = other.hide_render = True
        obj.hide_viewport = False
        results.append(api.render_dvr(obj, image_name=obj.name))
    assert results[0].visible
    np.testing.assert_array_equal(results[0].dvr_rgba, results[1].dvr_rgba)
    assert np.count_nonzero(results[0].dvr_rgba[..., 3]) > 100


def test_label_store_measurements_equal_those_in_memory(api, core, liver):
    path, _ = liver
    rows = api.measure_labels(api.import_volume(path, labels=True))
    regions = core.VolumeEVM.from_labels(_dense(core, path, labels=True))
    assert [label for label, _, _ in rows] == list(regions)
    for label, _, row in rows:
        assert row == regions[label].measure()


def test_the_buttons_and_f12_on_a_store(ext, api, store, tmp_path):
    """Make Volume Object and Render VolumeEVM from their operators, then F12 with the DVR
    composited over the scene: the EXR holds the composite the operator made."""
    from test_blender_render import cycles, f12_exr, image_rgba

    obj = api.import_volume(store)
    bpy.context.view_layer.objects.active = obj
    assert bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=CT_BONE_HU) == {"FINISHED"}
    assert bpy.ops.volumeevm.make_volume_object() == {"FINISHED"}
    native = obj.volumeevm.native
    assert native.volumeevm.role == "NATIVE" and native.data.grids.load()
    assert [g.name for g in native.data.grids] == [ext.blender.native_volume.GRID_NAME]
    native.hide_render = True  # F12 shows the DVR over the scene, not Cycles' own volume
    scene = bpy.context.scene
    add_camera(scene, (0.3, -0.3, 0.2), ortho=True, target=_centre(obj))
    cycles(scene, (48, 40), samples=1)
    scene.render.film_transparent = False
    scene.render.compositor_device = "CPU"
    settings = scene.volumeevm_render
    settings.volume, settings.method = obj, "raycast"
    api.load_preset(settings, "ct_bone", obj)
    assert bpy.ops.volumeevm.render_dvr() == {"FINISHED"}
    dvr = ext.blender.dvr
    assert (image_rgba(f"{dvr.DEFAULT_IMAGE} DVR")[..., 3] > 0.2).any()
    assert bpy.ops.volumeevm.setup_compositor() == {"FINISHED"}
    np.testing.assert_allclose(f12_exr(scene, tmp_path / "f12.exr"),
                               image_rgba(dvr.DEFAULT_IMAGE), atol=2e-3)
