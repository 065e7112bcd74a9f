"""Building a region of interest in the real bpy: ``api.build(obj, crop=...)`` with an object's
bounds or a box of voxel indices, and the build panel's Crop To object, give exactly the core's
``VolumeEVM.from_volume(..., crop=box)`` (the whole build clipped to the box, each voxel where it
sat); an OME-Zarr store's chunks outside the box are never read; bad crops leave the scene as
it was.

Runs under both pinned bpy versions (4.5 on Python 3.11, 5.2 on Python 3.13).
"""

import bpy
import numpy as np
import pytest
from mathutils import Euler, Matrix

from blender_helpers import CT_BONE_HU, CT_CROP, assert_identical, assert_surface_is
from zarr_files import pyramid, write_store

BRAIN_HU = 20  # soft tissue: some boxes below lie in the brain


def box_object(name, lo_bu, hi_bu):
    """A box mesh object from world corner ``lo_bu`` to ``hi_bu`` (Blender units)."""
    lo, hi = np.asarray(lo_bu, float), np.asarray(hi_bu, float)
    corners = [tuple(lo + (hi - lo) * (i, j, k)) for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(corners, [], faces)
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    bpy.context.view_layer.update()
    return obj


def assert_crop_of(core, part, volume, threshold, box):
    """``part`` is the core's cropped build, and the whole build clipped to ``box`` and moved."""
    assert_identical(part, core.VolumeEVM.from_volume(volume, threshold, crop=box))
    lo, hi = [a for a, _ in box], [b for _, b in box]
    clipped = core.VolumeEVM.from_volume(volume, threshold).clip(lo, hi)
    assert part.shape == tuple(b - a for a, b in box)
    assert np.array_equal(part.evm.vertices, clipped.evm.translate([-a for a in lo]).vertices)
    assert np.array_equal(part.table(), clipped.table())


@pytest.fixture
def volume(api, ct_crop_npy):
    """The CT crop imported: (volume object, the core's Volume of the same file)."""
    obj = api.import_volume(ct_crop_npy)
    bpy.context.view_layer.objects.active = obj
    return obj, api.get_volume(obj)


def test_build_cropped_to_an_object_bounds(volume, api, core):
    obj, vol = volume
    lo_bu, hi_bu = (0.02, 0.015, 0.01), (0.07, 0.09, 0.04)  # inside the crop's 122 x 122 x 75 mm
    crop = box_object("ROI", lo_bu, hi_bu)
    part = api.build(obj, CT_BONE_HU, crop=crop)
    box = vol.index_box(np.array(lo_bu) / 0.001, np.array(hi_bu) / 0.001)
    assert_crop_of(core, part, vol, CT_BONE_HU, box)
    # The voxels whose cells meet the box: 0.957 mm cells from -0.478 mm, 1.5 mm from -0.75 mm.
    assert box == ((21, 74), (16, 95), (7, 28))
    assert 0 < part.voxel_count < np.count_nonzero(vol.array >= CT_BONE_HU)
    assert_identical(api.get_vevm(obj), part)  # the sidecar holds the cropped build
    s = obj.volumeevm
    assert (s.voxel_count, s.ev_count) == (part.voxel_count, len(part.evm))
    assert s.dense_bytes == np.prod(part.shape) * 2
    surface = api.make_mesh(obj)
    assert_surface_is(surface, part)  # each voxel where it sits in the whole volume
    co = np.array([v.co for v in surface.data.vertices])
    assert (co.min(axis=0) >= np.array(lo_bu) - 0.0016).all()
    assert (co.max(axis=0) <= np.array(hi_bu) + 0.0016).all()


def test_crop_to_object_on_a_moved_volume_and_a_rotated_box(volume, api, core):
    """The crop is the object's bounding box taken into the volume's frame: a volume object
    moved and turned keeps its voxels, and the box follows it."""
    obj, vol = volume
    obj.matrix_world = (Matrix.Translation((0.5, -0.2, 0.1))
                        @ Euler((0.3, -0.2, 0.7)).to_matrix().to_4x4())
    crop = box_object("ROI", (-0.015, -0.02, -0.01), (0.015, 0.02, 0.01))
    crop.matrix_world = obj.matrix_world @ Matrix.Translation((0.06, 0.06, 0.04)) @ Euler(
        (0.0, 0.0, 0.4)).to_matrix().to_4x4()
    bpy.context.view_layer.update()
    part = api.build(obj, BRAIN_HU, crop=crop)
    # In the volume's frame the box is the ROI turned by 0.4 rad about z, at (60, 60, 40) mm.
    turn = np.array(Euler((0.0, 0.0, 0.4)).to_matrix(), np.float64)
    local = np.array([[x, y, z] for x in (-15, 15) for y in (-20, 20) for z in (-10, 10)], float)
    corners = local @ turn.T + (60.0, 60.0, 40.0)
    box = vol.index_box(corners.min(axis=0), corners.max(axis=0))
    assert_crop_of(core, part, vol, BRAIN_HU, box)


def test_crop_to_setting_and_voxel_boxes(volume, api, core):
    """The panel's Crop To object is what the Build button and ``api.build`` use by default; a
    box of voxel indices crops a script's build; clearing Crop To builds the whole grid."""
    obj, vol = volume
    crop = box_object("ROI", (0.0, 0.0, 0.0), (0.05, 0.05, 0.05))
    obj.volumeevm.crop_object = crop
    assert bpy.ops.volumeevm.build_vevm(use_settings=False, threshold=CT_BONE_HU) == {"FINISHED"}
    box = vol.index_box((0.0, 0.0, 0.0), (50.0, 50.0, 50.0))
    assert box == ((0, 53), (0, 53), (0, 34))
    assert_crop_of(core, api.get_vevm(obj), vol, CT_BONE_HU, box)
    assert_crop_of(core, api.build(obj), vol, CT_BONE_HU, box)
    for box in (((5, 128), (0, 128), (0, 50)), ((100, 128), (127, 128), (49, 50))):
        try:
            part = api.build(obj, 0.0, crop=box)
        except core.VolumeEVMError as error:  # a corner of air: the region is empty
            assert "the region is empty" in str(error)
            assert not (vol.array[tuple(slice(a, b) for a, b in box)] >= 0.0).any()
            continue
        assert_crop_of(core, part, vol, 0.0, box)
    obj.volumeevm.crop_object = None
    whole = api.build(obj, CT_BONE_HU)
    assert_identical(whole, core.VolumeEVM.from_volume(vol, CT_BONE_HU))
    assert whole.shape == tuple(s.stop - s.start for s in CT_CROP)


def test_bad_crops_leave_the_scene_as_it_was(volume, api, core):
    from test_blender_jobs import scene_state

    obj, _ = volume
    api.build(obj, CT_BONE_HU)
    away = box_object("Away", (1.0, 1.0, 1.0), (1.1, 1.1, 1.1))
    before = scene_state(api)
    with pytest.raises(core.VolumeEVMError, match=r"^crop: the box .* misses the volume's grid"):
        api.build(obj, CT_BONE_HU, crop=away)
    assert scene_state(api) == before
    for bad in (((0, 200), (0, 10), (0, 10)), ((4, 4), (0, 10), (0, 10)), ((0, 1.5),) * 3,
                ((0, 10), (0, 10))):
        with pytest.raises(core.VolumeEVMError, match=r"^crop must be 3 \(start, stop\) pairs"):
            api.build(obj, CT_BONE_HU, crop=bad)
        assert scene_state(api) == before
    obj.volumeevm.crop_object = away
    before = scene_state(api)
    with pytest.raises(RuntimeError, match="misses the volume's grid"):
        bpy.ops.volumeevm.build_vevm()
    assert scene_state(api) == before


def test_build_panel_shows_crop_to(volume, ext):
    from test_blender_ui import draw_all

    obj, _ = volume
    calls = draw_all(ext, bpy.context)
    assert any(name == "prop" and args[1] == "crop_object" and kw.get("text") == "Crop To"
               for name, args, kw in calls)
    # Only mesh objects that are not volumes can be picked.
    assert obj.volumeevm.bl_rna.properties["crop_object"].fixed_type.identifier == "Object"
    crop = box_object("ROI", (0.0, 0.0, 0.0), (0.01, 0.01, 0.01))
    props = ext.ui.props
    assert props.is_mesh_object(obj.volumeevm, crop)
    assert not props.is_mesh_object(obj.volumeevm, obj)


def test_store_reads_only_the_chunks_meeting_the_crop(tmp_path, data_dir, api, core, ext,
                                                      monkeypatch):
    crop = np.ascontiguousarray(np.load(data_dir / "ct_head_invesalius.npy")[CT_CROP])
    store = write_store(tmp_path / "head.ome.zarr", pyramid(crop, 2), chunks=(16, 32, 32))
    zarr = ext.volumeevm_addon.readers._zarr
    read_chunk, reads = zarr.read_chunk, []

    def counted(level, chunk):
        reads.append(chunk)
        return read_chunk(level, chunk)

    monkeypatch.setattr(zarr, "read_chunk", counted)
    obj = api.import_volume(store)
    reads.clear()
    box = ((40, 70), (10, 100), (20, 33))  # x, y, z; chunks are 32 x 32 x 16
    part = api.build(obj, BRAIN_HU, crop=box)
    assert len(reads) == 2 * 4 * 2
    assert_crop_of(core, part, api.get_volume(obj), BRAIN_HU, box)
