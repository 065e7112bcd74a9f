"""VolumeEVM: densities tables, the relation v, dense round trip, files, bad input."""

import zipfile

import numpy as np
import pytest
from scipy import ndimage

from volumeevm_addon import EVM, VolumeEVM, VolumeEVMError
from volumeevm_addon.model._densities import TABLE_ORDERS, run_count


@pytest.fixture(scope="module")
def head(data_dir):
    return np.load(data_dir / "ct_head_invesalius.npy")


@pytest.fixture(scope="module")
def bone(head):
    return VolumeEVM.from_array(head, 300, spacing=(0.9570312, 0.9570312, 1.5),
                                origin=(-120, -130, 10), units="HU")


def test_region_and_table_match_the_dense_volume(head, bone):
    mask = head >= 300
    assert bone.evm == EVM.from_mask(mask)
    assert bone.voxel_count == np.count_nonzero(mask)
    assert np.array_equal(bone.table(0), head[mask])
    assert bone.table(0).dtype == head.dtype


def test_from_array_equals_the_dense_selection_for_any_memory_layout(head):
    """The build works slice by slice from the densities: strided, reversed and Fortran-ordered
    arrays, integer and float, give the region and table of the dense selection exactly."""
    arrays = (np.asfortranarray(head[:100, :90, :50]), head[::2, 1::3, ::-1],
              head[40:104, 60:124, :40].astype(np.float32) * 0.5 + 0.25)
    for array in arrays:
        for threshold, upper in ((300, None), (-500, 100), (np.float32(20.5), np.float64(1e6))):
            vevm = VolumeEVM.from_array(array, threshold, upper)
            mask = (array >= threshold) & (array <= (np.inf if upper is None else upper))
            assert vevm.evm == EVM.from_mask(mask)
            assert np.array_equal(vevm.table(0), array[mask])
            assert vevm.table(0).dtype == array.dtype


def test_band_threshold(head):
    band = VolumeEVM.from_array(head, 0, upper=80)
    mask = (head >= 0) & (head <= 80)
    assert np.array_equal(band.to_dense(background=-1000), np.where(mask, head, -1000))


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_tables_for_each_principal_axis(head, bone, axis):
    axes = ["xyz".index(a) for a in TABLE_ORDERS[axis]]
    moved_mask = np.transpose(head >= 300, axes)
    assert np.array_equal(bone.table(axis), np.transpose(head, axes)[moved_mask])


def test_other_orders_equal_the_transposed_grid_on_random_regions():
    """The tables of the other orders, read scanline by scanline from the stored one, list the
    region's densities exactly as the transposed grid does, in the data's dtype; thin grids,
    single voxels and many slabs of slices included. The runs counted from the boxes are the
    scanlines' runs of the mask."""
    rng = np.random.default_rng(18)
    for trial in range(60):
        shape = tuple(int(n) for n in rng.integers(1, 40 if trial % 3 else 6, 3))
        dtype = (np.int16, np.float32, np.uint8)[trial % 3]
        array = (rng.random(shape) * 100).astype(dtype)
        vevm = VolumeEVM.from_array(array, array.max() * rng.random())
        mask = vevm.evm.to_mask(vevm.shape)
        for order in TABLE_ORDERS:  # the memory estimates' count of the scanlines' runs
            axes = ["xyz".index(a) for a in order]
            lines = np.transpose(mask, axes).reshape(-1, mask.shape[axes[2]]).astype(np.int8)
            starts = np.diff(lines, axis=1, prepend=0) == 1
            assert run_count(vevm.evm, order) == int(starts.sum())
        for axis in (1, 2):
            axes = ["xyz".index(a) for a in TABLE_ORDERS[axis]]
            table = vevm.table(axis)
            assert table.dtype == array.dtype
            assert np.array_equal(table, np.transpose(array, axes)[np.transpose(mask, axes)])


def test_other_orders_need_the_region_not_the_grid(monkeypatch):
    """A small region in a large grid: the other orders' tables fit a memory limit far below the
    grid (256³ bytes) and equal the transposed grid's."""
    array = np.zeros((256, 256, 256), np.uint8)
    array[100:110, 30:50, 7:9] = np.arange(400, dtype=np.uint8).reshape(10, 20, 2)
    array[3, 200:202, 250] = 9
    vevm = VolumeEVM.from_array(array, 1)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "2M")
    for axis in (1, 2):
        axes = ["xyz".index(a) for a in TABLE_ORDERS[axis]]
        expected = np.transpose(array, axes)[np.transpose(array >= 1, axes)]
        assert np.array_equal(vevm.table(axis), expected)


def test_other_tables_are_made_only_when_asked(head):
    region = VolumeEVM.from_array(head[:64, :64, :40], 0)
    before = region.size_report()["tables_bytes"]
    region.table(2)
    assert region.size_report()["tables_bytes"] == 2 * before


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_relation_v_agrees_with_a_dense_lookup(head, bone, axis):
    rng = np.random.default_rng(axis)
    voxels = np.c_[rng.integers(-2, 258, 20000), rng.integers(-2, 258, 20000),
                   rng.integers(-2, 110, 20000)]
    inside = np.all((voxels >= 0) & (voxels < head.shape), axis=1)
    index = bone.index(voxels, axis=axis)
    expected_in = np.zeros(len(voxels), bool)
    expected_in[inside] = head[tuple(voxels[inside].T)] >= 300
    assert np.array_equal(index >= 0, expected_in)
    found = voxels[index >= 0]
    assert np.array_equal(bone.table(axis)[index[index >= 0]], head[tuple(found.T)])


def test_to_dense_round_trip(head, bone):
    assert np.array_equal(bone.to_dense(background=-2000), np.where(head >= 300, head, -2000))


def test_mesh_is_in_physical_millimetres(bone):
    vertices, polygons = bone.mesh()
    lattice, _ = bone.evm.mesh()
    expected = (lattice - 0.5) * np.array(bone.spacing) + np.array(bone.origin)
    np.testing.assert_allclose(vertices, expected)


def test_size_report_against_dense(bone, head):
    report = bone.size_report()
    assert report["dense_bytes"] == head.nbytes
    assert report["total_bytes"] == report["vertices_bytes"] + report["tables_bytes"]
    assert report["ratio"] < 0.35


def test_save_load_round_trip(tmp_path, bone):
    path = tmp_path / "bone.vevm"
    bone.save(path)
    again = VolumeEVM.load(path)
    assert again.evm == bone.evm
    assert (np.array_equal(again.table(0), bone.table(0))
            and again.table(0).dtype == bone.table(0).dtype)
    assert (again.shape, again.spacing, again.origin, again.units, again.threshold) == (
        bone.shape, bone.spacing, bone.origin, bone.units, bone.threshold)
    np.testing.assert_array_equal(again.orientation, bone.orientation)
    assert list(tmp_path.iterdir()) == [path], "no temporary file left behind"


def test_save_never_overwrites_unasked(tmp_path, bone):
    path = tmp_path / "user.vevm"
    path.write_bytes(b"the user's own file")
    with pytest.raises(VolumeEVMError, match="user.vevm: exists"):
        bone.save(path)
    assert path.read_bytes() == b"the user's own file"
    bone.save(path, overwrite=True)
    assert VolumeEVM.load(path).evm == bone.evm


def test_corrupt_and_foreign_files(tmp_path, bone):
    good = tmp_path / "good.vevm"
    bone.save(good)
    truncated = tmp_path / "truncated.vevm"
    truncated.write_bytes(good.read_bytes()[:5000])
    with pytest.raises(VolumeEVMError, match="truncated.vevm: not a readable VolumeEVM file"):
        VolumeEVM.load(truncated)
    foreign = tmp_path / "foreign.vevm"
    with foreign.open("wb") as file:
        np.savez(file, data=np.arange(3))
    with pytest.raises(VolumeEVMError, match="foreign.vevm: not a VolumeEVM file"):
        VolumeEVM.load(foreign)
    pickled = tmp_path / "pickled.vevm"
    with pickled.open("wb") as file:
        np.savez(file, format=np.array("volumeevm"), version=np.array(1),
                 meta=np.array([{"evil": 1}], dtype=object), vertices=np.zeros((0, 3)),
                 table=np.zeros(0))
    with pytest.raises(VolumeEVMError, match="pickled.vevm: not a readable"):
        VolumeEVM.load(pickled)
    # Flip one density inside the archive: the checksum catches it.
    tampered = tmp_path / "tampered.vevm"
    with np.load(good) as archive:
        parts = {k: archive[k] for k in archive.files}
    parts["table"] = parts["table"].copy()
    parts["table"][0] += 1
    with tampered.open("wb") as file:
        np.savez(file, **parts)
    with pytest.raises(VolumeEVMError, match="checksum mismatch"):
        VolumeEVM.load(tampered)
    with pytest.raises(VolumeEVMError, match="missing.vevm: file not found"):
        VolumeEVM.load(tmp_path / "missing.vevm")
    assert zipfile.is_zipfile(good)


def test_bad_input_names_the_source_and_problem():
    array = np.zeros((4, 4, 4), np.float32)
    with pytest.raises(VolumeEVMError, match=r"scan: the region is empty: no density is >= 5 "
                                             r"\(data range 0.0 .. 0.0\)"):
        VolumeEVM.from_array(array, 5, source="scan")
    array[1, 1, 1] = np.nan
    with pytest.raises(VolumeEVMError, match="scan: 1 densities are NaN or infinite"):
        VolumeEVM.from_array(array, 0, source="scan")
    with pytest.raises(VolumeEVMError, match="expected a 3-D array"):
        VolumeEVM.from_array(np.zeros((4, 4)), 0)
    with pytest.raises(VolumeEVMError, match="threshold must be a finite number"):
        VolumeEVM.from_array(np.zeros((2, 2, 2)), float("nan"))
    with pytest.raises(ValueError, match="the region has 8 voxels but the table 3"):
        VolumeEVM(EVM.from_mask(np.ones((2, 2, 2), bool)), np.zeros(3), shape=(2, 2, 2))


# ---------------------------------------------------------------------- editing with densities
@pytest.fixture(scope="module")
def tools(head):
    x, y, z = np.ogrid[: head.shape[0], : head.shape[1], : head.shape[2]]
    sphere = (x - 128) ** 2 + (y - 100) ** 2 + ((z - 54) * 1.5) ** 2 < 60 ** 2
    slab = np.zeros(head.shape, bool)
    slab[:, 120:136, :] = True
    small = np.zeros(head.shape, bool)
    small[60:70, 60:75, 40:44] = True
    return {"sphere": sphere, "slab": slab, "small": small}


@pytest.mark.parametrize("name", ["sphere", "slab", "small"])
def test_cut_keep_add_equal_voxel_by_voxel(head, bone, tools, name):
    tool = tools[name]
    mask = head >= 300
    background = -4000
    cut = bone.cut(EVM.from_mask(tool))
    assert np.array_equal(cut.to_dense(background), np.where(mask & ~tool, head, background))
    kept = bone.keep(EVM.from_mask(tool))
    assert np.array_equal(kept.to_dense(background), np.where(mask & tool, head, background))
    added = bone.add(EVM.from_mask(tool), density=2500)
    expected = np.where(tool, 2500, np.where(mask, head, background))
    assert np.array_equal(added.to_dense(background), expected)
    assert added.evm == EVM.from_mask(mask | tool)
    # The original is unchanged.
    assert np.array_equal(bone.to_dense(background), np.where(mask, head, background))


def test_add_defaults_to_the_largest_density(head, bone, tools):
    added = bone.add(EVM.from_mask(tools["small"]))
    assert (added.to_dense()[tools["small"]] == head[head >= 300].max()).all()


def test_largest_component_and_clip(head, bone):
    mask = head >= 300
    labels, _ = ndimage.label(mask)
    biggest = labels == np.argmax(np.bincount(labels.ravel())[1:]) + 1
    assert np.array_equal(bone.largest_component().to_dense(-1), np.where(biggest, head, -1))
    clipped = bone.clip((50, 40, 10), (200, 180, 90))
    box = np.zeros_like(mask)
    box[50:200, 40:180, 10:90] = True
    assert np.array_equal(clipped.to_dense(-1), np.where(mask & box, head, -1))


def test_editing_on_mri_with_a_tool_sticking_out_of_the_grid(data_dir):
    mri = np.load(data_dir / "mr_t1_itk_kmeans.npy")
    region = VolumeEVM.from_array(mri, 60)
    tool_mask = np.zeros((140, 140, 70), bool)
    tool_mask[100:140, 20:90, 30:70] = True
    tool = EVM.from_mask(tool_mask, offset=(0, 0, 0))
    inside = tool_mask[: mri.shape[0], : mri.shape[1], : mri.shape[2]]
    added = region.add(tool, density=255)
    assert np.array_equal(added.to_dense(-1), np.where(inside, 255, np.where(mri >= 60, mri, -1)))
    assert np.array_equal(region.cut(tool).to_dense(-1), np.where((mri >= 60) & ~inside, mri, -1))


def test_editing_errors(bone, tools):
    with pytest.raises(VolumeEVMError, match="keep inside: the result would be empty"):
        bone.keep(EVM.from_mask(np.zeros((3, 3, 3), bool)))
    with pytest.raises(TypeError, match="tool must be an EVM"):
        bone.cut(tools["small"])
    with pytest.raises(VolumeEVMError, match="does not fit the data type int16"):
        bone.add(EVM.from_mask(tools["small"]), density=40000)
    outside = EVM.from_mask(np.ones((2, 2, 2), bool)).translate(np.array([400, 0, 0]))
    with pytest.raises(VolumeEVMError, match="no voxel inside the volume's grid"):
        bone.add(outside)
