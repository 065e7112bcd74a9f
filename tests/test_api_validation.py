"""Entry-point validation: every bad argument of a build, a level or a voxelization is a
VolumeEVMError naming the parameter, and memory is checked before a build spends it."""

import tracemalloc

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from volumeevm_addon import EVM, Volume, VolumeEVM, VolumeEVMError, voxelize_mesh
from volumeevm_addon.model import _volumeevm, voxelize_mesh_evm

ONES = np.ones((3, 3, 3), np.int16)
ROTATION = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
TETRA = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float),
         np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))


@pytest.fixture(scope="module")
def head(data_dir):
    return np.load(data_dir / "ct_head_invesalius.npy")


# ---------------------------------------------------------------------- geometry
@pytest.mark.parametrize("spacing", [(0, 1, 1), (1, -2, 1), (1, 1, np.nan), (1, np.inf, 1), (1, 1),
                                     (1, 1, 1, 1), "111", (1j, 1, 1), (True, True, True), None])
def test_spacing_must_be_three_finite_positive_numbers(spacing):
    with pytest.raises(VolumeEVMError,
                       match=r"^scan: spacing must be three finite positive numbers"):
        VolumeEVM.from_array(ONES, 1, spacing=spacing, source="scan")


@pytest.mark.parametrize("origin", [(np.nan, 0, 0), (0, -np.inf, 0), (0, 0), "abc", (0, 0, 1j)])
def test_origin_must_be_three_finite_numbers(origin):
    with pytest.raises(VolumeEVMError, match=r"^scan: origin must be three finite numbers"):
        VolumeEVM.from_array(ONES, 1, origin=origin, source="scan")


@pytest.mark.parametrize("orientation", [2 * np.eye(3), [[1, 0.1, 0], [0, 1, 0], [0, 0, 1]],
                                         np.zeros((3, 3)), np.full((3, 3), np.nan),
                                         np.eye(3) + 1e-4, np.eye(2), np.eye(4)])
def test_orientation_must_be_orthonormal(orientation):
    with pytest.raises(VolumeEVMError, match=r"^scan: orientation must be"):
        VolumeEVM.from_array(ONES, 1, orientation=orientation, source="scan")


@pytest.mark.parametrize("orientation", [ROTATION, np.diag([1.0, -1.0, 1.0]), np.eye(3)[[2, 0, 1]],
                                         np.eye(3) + 1e-7])
def test_rotations_reflections_and_rounding_are_accepted(orientation):
    vevm = VolumeEVM.from_array(ONES, 1, orientation=orientation)
    assert np.array_equal(vevm.orientation, np.asarray(orientation, float))
    assert vevm.voxel_count == ONES.size


def test_from_volume_names_the_volume_file():
    bad = Volume(ONES, spacing=(1.0, 0.0, 1.0), source="head.nii.gz")
    with pytest.raises(VolumeEVMError, match=r"^head.nii.gz: spacing must be"):
        VolumeEVM.from_volume(bad, 1)
    sheared = Volume(ONES, orientation=np.array([[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]),
                     source="ct.nrrd")
    with pytest.raises(VolumeEVMError, match=r"^ct.nrrd: orientation must be orthonormal"):
        VolumeEVM.from_volume(sheared, 1)
    with pytest.raises(VolumeEVMError, match="volume must be a Volume"):
        VolumeEVM.from_volume(ONES, 1)


# ---------------------------------------------------------------------- densities and interval
@pytest.mark.parametrize("threshold", [np.nan, np.inf, -np.inf, True, np.bool_(False), 1 + 2j,
                                       "300", None, 10**400, np.array([1.0])])
def test_threshold_must_be_a_finite_real_number(threshold):
    with pytest.raises(VolumeEVMError, match=r"^scan: threshold must be a finite number"):
        VolumeEVM.from_array(ONES, threshold, source="scan")


def test_upper_must_be_finite_and_not_below_the_threshold():
    with pytest.raises(VolumeEVMError, match=r"^scan: upper must be a finite number"):
        VolumeEVM.from_array(ONES, 0, upper=np.nan, source="scan")
    with pytest.raises(VolumeEVMError, match=r"^scan: upper \(2\) must be >= threshold \(5\)"):
        VolumeEVM.from_array(ONES, 5, upper=2, source="scan")
    assert VolumeEVM.from_array(ONES, 1, upper=1).voxel_count == ONES.size


def test_integer_thresholds_compare_exactly_with_large_integers():
    """A threshold is compared as given: 2**60 + 1 as a float would round to 2**60."""
    array = np.full((2, 2, 2), 2**60, np.int64)
    array[0, 0, 0] += 1
    assert VolumeEVM.from_array(array, 2**60 + 1).voxel_count == 1
    assert VolumeEVM.from_array(array, np.int64(2**60 + 1)).voxel_count == 1


@pytest.mark.parametrize("array,problem", [
    (np.ones((4, 4)), "expected a 3-D array"),
    (np.ones((2, 2, 2, 2)), "expected a 3-D array"),
    (np.ones((0, 4, 4)), r"the volume is empty \(shape \(0, 4, 4\)\)"),
    (np.ones((2, 2, 2), bool), "got dtype bool; for a mask use EVM.from_mask"),
    (np.ones((2, 2, 2), complex), "got dtype complex128"),
    (np.array([[["a"]]]), "got dtype <U1"),
    (np.ma.masked_array(np.ones((2, 2, 2)), mask=False),
     r"masked array .* \(array.filled\(value\)\)"),
    ([[[1, 2], [3]]], "not an array of densities"),
])
def test_array_must_be_a_3d_nonempty_real_numeric_grid(array, problem):
    with pytest.raises(VolumeEVMError, match=rf"^scan: .*{problem}"):
        VolumeEVM.from_array(array, 0.5, source="scan")


def test_nan_densities_are_located():
    array = np.zeros((3, 4, 5), np.float32)
    array[2, 1, 3] = np.inf
    array[2, 3, 0] = np.nan
    with pytest.raises(VolumeEVMError, match=r"^scan: 2 densities are NaN or infinite "
                                             r"\(first at voxel \(2, 1, 3\)"):
        VolumeEVM.from_array(array, 0, source="scan")


def test_array_likes_and_filled_masked_arrays_build():
    vevm = VolumeEVM.from_array([[[1, 2], [3, 4]]], 2)
    assert vevm.voxel_count == 3 and vevm.shape == (1, 2, 2)
    masked = np.ma.masked_array(np.arange(8.0).reshape(2, 2, 2),
                                mask=np.arange(8).reshape(2, 2, 2) < 3)
    assert VolumeEVM.from_array(masked.filled(-1.0), 0).voxel_count == 5


def test_units_must_be_text():
    with pytest.raises(VolumeEVMError, match=r"^scan: units must be a string"):
        VolumeEVM.from_array(ONES, 1, units=1, source="scan")


def test_a_grid_beyond_the_evm_range_is_refused_before_building():
    too_long = np.ones((2**20, 1, 1), np.int8)
    with pytest.raises(VolumeEVMError, match=r"^scan: grid of shape \(1048576, 1, 1\)"
                                             r".*at most 1048575 voxels"):
        VolumeEVM.from_array(too_long, 1, source="scan")


def test_constructor_checks_its_parts():
    evm = EVM.from_mask(np.ones((2, 2, 2), bool))
    with pytest.raises(VolumeEVMError, match="evm must be an EVM"):
        VolumeEVM(np.ones((2, 2, 2), bool), np.zeros(8), shape=(2, 2, 2))
    with pytest.raises(VolumeEVMError, match="table must be a 1-D array"):
        VolumeEVM(evm, np.zeros((2, 4)), shape=(2, 2, 2))
    with pytest.raises(VolumeEVMError, match="table: 1 densities are NaN"):
        VolumeEVM(evm, np.r_[np.zeros(7), np.nan], shape=(2, 2, 2))
    with pytest.raises(VolumeEVMError, match="shape must be 3 positive integers"):
        VolumeEVM(evm, np.zeros(8), shape=(2, 0, 2))
    with pytest.raises(VolumeEVMError, match="shape must be 3 integers"):
        VolumeEVM(evm, np.zeros(8), shape=(2.0, 2, 2))
    with pytest.raises(VolumeEVMError, match=r"evm: the region spans lattice corners \(0, 0, 0\) "
                                             r"to \(2, 2, 2\), outside the grid of shape "
                                             r"\(2, 1, 2\)"):
        VolumeEVM(evm, np.zeros(8), shape=(2, 1, 2))
    with pytest.raises(VolumeEVMError, match="orientation must be orthonormal"):
        VolumeEVM(evm, np.zeros(8), shape=(2, 2, 2), orientation=np.ones((3, 3)))
    with pytest.raises(VolumeEVMError, match="threshold must be a finite number"):
        VolumeEVM(evm, np.zeros(8), shape=(2, 2, 2), threshold=np.nan)


# ---------------------------------------------------------------------- levels and voxelization
@pytest.mark.parametrize("factor,problem", [
    (10**6, r"1000000 is larger than the grid's largest side \(5 voxels\)"),
    (6, "6 is larger than the grid"), (0, "must be an integer >= 2"),
    (1, "must be an integer >= 2"), (2.0, "must be an integer >= 2"),
    (True, "must be an integer >= 2"), ("2", "must be an integer >= 2"),
    ([2], "must be an integer >= 2")])
def test_level_factor_is_an_integer_from_two_to_the_grid_side(factor, problem):
    vevm = VolumeEVM.from_array(np.arange(60).reshape(3, 4, 5), 10)
    with pytest.raises(VolumeEVMError, match=rf"^level factor {problem}"):
        vevm.level(factor)
    coarse = vevm.level(5)
    assert coarse.shape == (1, 1, 1) and coarse.voxel_count == 1


def test_level_memory_is_checked(monkeypatch, head):
    vevm = VolumeEVM.from_array(head, 300)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "4M")
    with pytest.raises(VolumeEVMError, match=r"^level factor: making level 2 needs about .* MiB "
                                             r"of memory but only 4.0 MiB is available; use a "
                                             r"smaller factor"):
        vevm.level(2)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "16G")
    assert vevm.level(2).shape == (128, 128, 54)


def test_edit_memory_is_checked_and_follows_the_region(monkeypatch, head):
    """An edit selects the densities its result keeps with a byte per region voxel, checked
    first (refused naming the edit); measured by tracemalloc, the whole cut of the head
    (-500 HU) stays under 8 bytes per region voxel (the counts it replaced took 19)."""
    vevm = VolumeEVM.from_array(head, -500)
    tool = EVM.from_mask(np.ones((100, 100, 50), bool), offset=(80, 60, 30))
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "256K")
    with pytest.raises(VolumeEVMError, match=r"^cut: selecting the densities the result keeps "
                                             r"needs about .* but only 256.0 KiB is available"):
        vevm.cut(tool)
    with pytest.raises(VolumeEVMError, match=r"^add: selecting the densities"):
        vevm.add(tool)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "1G")
    expected = np.where((head >= -500) & ~tool.to_mask(head.shape), head, -4000)
    assert np.array_equal(vevm.cut(tool).to_dense(-4000), expected)  # kernels compiled
    tracemalloc.start()
    try:
        vevm.cut(tool)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 * vevm.voxel_count, peak / vevm.voxel_count


def test_voxelizing_into_a_huge_grid_is_refused_before_allocating():
    vertices, faces = TETRA
    to_grid = np.diag([4.0, 4.0, 4.0, 1.0])
    with pytest.raises(VolumeEVMError, match=r"^tool mesh: voxelizing into a grid of shape "
                                             r"\(1000000, 1000000, 1000000\) needs about .* GiB"):
        voxelize_mesh(vertices, faces, (10**6, 10**6, 10**6), to_grid)
    with pytest.raises(VolumeEVMError, match=r"^shape \(2000000, 8, 8\): .*at most 1048575 voxels"):
        voxelize_mesh_evm(vertices, faces, (2 * 10**6, 8, 8), to_grid)
    # A small tool in a huge grid is voxelized on its own bounding box only.
    evm = voxelize_mesh_evm(vertices, faces, (10**6, 10**6, 10**6), to_grid)
    assert evm.volume() == 20


def test_voxelize_memory_is_checked(monkeypatch):
    vertices, faces = TETRA
    to_grid = np.diag([60.0, 60.0, 60.0, 1.0])
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "256K")
    with pytest.raises(VolumeEVMError, match=r"^tool mesh: voxelizing into a grid of shape "
                                             r"\(64, 64, 64\) needs about .* MiB of memory but "
                                             r"only 256.0 KiB is available"):
        voxelize_mesh(vertices, faces, (64, 64, 64), to_grid)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "1G")
    mask = voxelize_mesh(vertices, faces, (64, 64, 64), to_grid)
    i, j, k = np.indices(mask.shape)
    assert np.array_equal(mask, i + j + k < 60)


# ---------------------------------------------------------------------- memory at build
def test_a_small_budget_refuses_the_build_naming_source_and_amounts(monkeypatch, head):
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "1M")
    with pytest.raises(VolumeEVMError, match=r"^ct_head: building the VolumeEVM needs about "
                                             r"[\d.]+ MiB of memory but only 1.0 MiB is "
                                             r"available; crop the volume, raise the threshold"):
        VolumeEVM.from_array(head, 300, source="ct_head")
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "4G")
    vevm = VolumeEVM.from_array(head, 300, source="ct_head")
    assert vevm.voxel_count == np.count_nonzero(head >= 300)


def test_the_refusal_comes_while_the_vertices_are_extracted(monkeypatch):
    """A checkerboard has a box per voxel: the budget is exceeded long before the last slice."""
    checker = (np.indices((64, 64, 64)).sum(axis=0) % 2).astype(np.uint8)
    seen = []
    real_check = _volumeevm.check_memory

    def check(needed, *args, **kwargs):
        seen.append(needed)
        real_check(needed, *args, **kwargs)

    monkeypatch.setattr(_volumeevm, "check_memory", check)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "2M")
    with pytest.raises(VolumeEVMError, match="building the VolumeEVM needs about"):
        VolumeEVM.from_array(checker, 1)
    assert len(seen) == 1 and 2 * 2**20 < seen[0] < 4 * 2**20


def _estimate_and_peak(monkeypatch, array, threshold):
    """The estimate from_array checks, and its measured peak (tracemalloc traces NumPy)."""
    # Loads the compiled kernels: a one-time cost, not the data's.
    VolumeEVM.from_array(array, threshold)
    seen = []
    monkeypatch.setattr(_volumeevm, "check_memory",
                        lambda needed, *args, **kwargs: seen.append(needed))
    tracemalloc.start()
    try:
        vevm = VolumeEVM.from_array(array, threshold)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert vevm.voxel_count == np.count_nonzero(array >= threshold)
    return seen[-1], peak


@pytest.mark.parametrize("threshold", [300, -500])
def test_the_build_estimate_is_a_close_upper_bound_on_the_ct_head(monkeypatch, head, threshold):
    estimate, peak = _estimate_and_peak(monkeypatch, head, threshold)
    assert peak <= estimate <= 1.5 * peak


@settings(max_examples=60, deadline=None)
@given(st.tuples(st.integers(1, 6), st.integers(1, 6), st.integers(1, 6)).flatmap(
    lambda shape: arrays(np.uint8, shape, elements=st.integers(0, 3))))
def test_the_estimate_counts_the_region_vertices_and_boxes_exactly(array):
    """The estimate's counts, made slice by slice before the EVM exists, are the EVM's own."""
    assume((array >= 2).any())
    seen = []
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(_volumeevm, "check_memory",
                      lambda needed, *args, **kwargs: seen.append(needed))
        vevm = VolumeEVM.from_array(array, 2)
    evm = EVM.from_mask(array >= 2)
    assert vevm.evm == evm
    assert seen[-1] == _volumeevm.build_memory(array.shape, array.dtype, evm.volume(), len(evm),
                                               len(evm.boxes()[0]))


def test_voxel_mask_and_dense_grid_check_memory(monkeypatch):
    vevm = VolumeEVM.from_array(np.arange(64**3).reshape(64, 64, 64) % 7, 5)
    expected = (np.arange(64**3).reshape(64, 64, 64) % 7) >= 5
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "256K")
    with pytest.raises(VolumeEVMError, match=r"^EVM grid \(64, 64, 64\): making the voxel mask "
                                             r"needs about [\d.]+ MiB of memory but only 256.0 KiB "
                                             r"is available"):
        vevm.evm.to_mask(vevm.shape)
    with pytest.raises(VolumeEVMError, match=r"^VolumeEVM grid \(64, 64, 64\): making the dense "
                                             r"grid needs about"):
        vevm.to_dense()
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "1G")
    assert np.array_equal(vevm.evm.to_mask(vevm.shape), expected)
    assert np.array_equal(vevm.to_dense(),
                          np.where(expected, np.arange(64**3).reshape(64, 64, 64) % 7, 0))


def test_other_axis_tables_check_memory(monkeypatch):
    array = np.arange(64**3).reshape(64, 64, 64) % 7
    vevm = VolumeEVM.from_array(array, 5)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "256K")
    with pytest.raises(VolumeEVMError, match=r"^VolumeEVM table\(2\): the densities table in zxy "
                                             r"order needs about"):
        vevm.table(2)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "1G")
    expected = np.transpose(array, (2, 0, 1))[np.transpose(array >= 5, (2, 0, 1))]
    assert np.array_equal(vevm.table(2), expected)
