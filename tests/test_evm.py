"""EVM: exact voxel equality for extraction, Booleans, measures, splits and sweeps."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import ndimage

from volumeevm_addon import EVM, VolumeEVMError, set_kernel_threads
from volumeevm_addon.model import _evm

VOLUMES = ["ct_head_invesalius", "ct_skull_cgal", "seg_liver_cgal", "mr_t1_itk_kmeans",
           "mr_brainsmall_volpack", "micro_nuclei3d_stardist"]
OPERATIONS = {
    "union": (EVM.__or__, np.logical_or),
    "intersection": (EVM.__and__, np.logical_and),
    "difference": (EVM.__sub__, lambda a, b: a & ~b),
    "xor": (EVM.__xor__, np.logical_xor),
}


def load(data_dir, name):
    return np.load(data_dir / f"{name}.npy")


def thresholds(array):
    """Three thresholds across the data: low (most voxels), middle, high (few voxels)."""
    return [float(q) for q in np.percentile(array[array > array.min()], [5, 50, 95])]


def unit_faces(mask):
    padded = np.pad(mask, 1).astype(np.int8)
    return sum(int(np.count_nonzero(np.diff(padded, axis=axis))) for axis in range(3))


def brute_vertices(mask):
    """Extreme vertices straight from the definition: odd number of the 8 incident voxels."""
    padded = np.pad(mask, 1).astype(np.uint8)
    count = sum(padded[dx:dx + mask.shape[0] + 1, dy:dy + mask.shape[1] + 1,
                       dz:dz + mask.shape[2] + 1]
                for dx in (0, 1) for dy in (0, 1) for dz in (0, 1))
    return np.argwhere(count % 2 == 1)


masks = st.tuples(st.integers(1, 6), st.integers(1, 6), st.integers(1, 6)).flatmap(
    lambda shape: st.tuples(arrays(bool, shape), arrays(bool, shape)))


@pytest.mark.parametrize("name", VOLUMES)
def test_reconstruction_of_every_real_volume_at_three_thresholds(data_dir, name):
    array = load(data_dir, name)
    for threshold in thresholds(array):
        mask = array >= threshold
        evm = EVM.from_mask(mask)
        assert np.array_equal(evm.to_mask(mask.shape), mask)
        assert evm.volume() == np.count_nonzero(mask)


def test_vertices_follow_the_parity_rule_and_are_sorted(data_dir):
    mask = load(data_dir, "mr_brainsmall_volpack") >= 60
    evm = EVM.from_mask(mask)
    assert np.array_equal(evm.vertices, brute_vertices(mask))
    keys = evm.vertices.astype(np.int64) @ np.array([1 << 40, 1 << 20, 1])
    assert (np.diff(keys) > 0).all()


@settings(max_examples=100, deadline=None)
@given(masks, st.integers(1, 60), st.sampled_from([1, 2]))
def test_extraction_is_the_parity_rule_in_any_blocks_on_any_threads(pair, block_voxels, threads):
    """The compiled extraction (blocks of x-slices on a pool of threads) against the definition,
    for masks of any memory layout and dtype; the keys in every other axis order are sorted."""
    mask, other = pair
    previous = set_kernel_threads(threads)
    try:
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(_evm, "_BLOCK_VOXELS", block_voxels)
            variants = (mask, np.asfortranarray(mask), mask[::-1, :, ::-1],
                        mask.astype(np.int16) * other)
            for variant in variants:
                evm = EVM.from_mask(variant)
                assert np.array_equal(evm.vertices, brute_vertices(variant != 0))
                for order in _evm.ORDERS:
                    assert np.array_equal(evm.keys(order), np.sort(evm.keys(order)))
    finally:
        set_kernel_threads(previous)


def test_reference_numbers_of_brainsmall(data_dir):
    """The EV counts measured independently in the design notes (evm_algorithms.md §5.2)."""
    array = load(data_dir, "mr_brainsmall_volpack")
    for threshold, voxels, vertices, faces in [(1, 1193707, 28532, 154556),
                                               (60, 116878, 69528, 135844),
                                               (150, 140, 394, 570)]:
        evm = EVM.from_mask(array >= threshold)
        assert (evm.volume(), len(evm), evm.area()) == (voxels, vertices, faces)


def test_invariants_even_vertices_on_every_axis_line(data_dir):
    evm = EVM.from_mask(load(data_dir, "ct_skull_cgal") >= 2.9)
    v = evm.vertices.astype(np.int64)
    for axis in range(3):
        others = np.delete(v, axis, axis=1)
        _, counts = np.unique(others, axis=0, return_counts=True)
        assert (counts % 2 == 0).all()


def test_a_box_has_eight_vertices_and_coordinates_are_compact():
    mask = np.zeros((300, 5, 5), bool)
    mask[10:290, 1:4, 2:3] = True
    evm = EVM.from_mask(mask)
    assert len(evm) == 8
    assert evm.vertices.dtype == np.int16
    assert EVM.from_mask(mask[:100]).vertices.dtype == np.int8
    assert (evm.volume(), evm.area()) == (280 * 3, 2 * (280 * 3 + 280 + 3))


@settings(max_examples=150, deadline=None)
@given(masks)
def test_booleans_equal_voxel_booleans(pair):
    a, b = pair
    ea, eb = EVM.from_mask(a), EVM.from_mask(b)
    for name, (evm_op, voxel_op) in OPERATIONS.items():
        expected = voxel_op(a, b)
        result = evm_op(ea, eb)
        assert np.array_equal(result.to_mask(a.shape), expected), name
        assert result == EVM.from_mask(expected), name


@settings(max_examples=100, deadline=None)
@given(masks, st.tuples(st.integers(-3, 3), st.integers(-3, 3), st.integers(-3, 3)))
def test_booleans_with_offset_operands(pair, offset):
    """Operands that stick out of each other's boxes exercise the bounding-box fast paths."""
    a, b = pair
    ea, eb = EVM.from_mask(a), EVM.from_mask(b).translate(np.array(offset))
    grid = tuple(s + 6 for s in a.shape)
    big_a = np.zeros(grid, bool)
    big_b = np.zeros(grid, bool)
    big_a[3:3 + a.shape[0], 3:3 + a.shape[1], 3:3 + a.shape[2]] = a
    o = np.array(offset) + 3
    big_b[o[0]:o[0] + b.shape[0], o[1]:o[1] + b.shape[1], o[2]:o[2] + b.shape[2]] = b
    for name, (evm_op, voxel_op) in OPERATIONS.items():
        result = evm_op(ea, eb).to_mask(grid, offset=(-3, -3, -3))
        assert np.array_equal(result, voxel_op(big_a, big_b)), name


def test_booleans_on_real_pairs(data_dir):
    head = load(data_dir, "ct_head_invesalius")
    skin, bone = head >= -500, head >= 300
    t1 = load(data_dir, "mr_t1_itk_kmeans")
    brain = load(data_dir, "mr_brainsmall_volpack")
    common = tuple(min(s, t) for s, t in zip(t1.shape, brain.shape))
    crop = tuple(slice(0, s) for s in common)
    pairs = [(skin, bone), (bone, skin), (t1[crop] >= 80, brain[crop] >= 40)]
    for a, b in pairs:
        ea, eb = EVM.from_mask(a), EVM.from_mask(b)
        for name, (evm_op, voxel_op) in OPERATIONS.items():
            assert np.array_equal(evm_op(ea, eb).to_mask(a.shape), voxel_op(a, b)), name


def test_cut_by_box_and_sphere_on_ct_head(data_dir):
    bone = load(data_dir, "ct_head_invesalius") >= 300
    x, y, z = np.ogrid[:256, :256, :108]
    sphere = (x - 128) ** 2 + (y - 100) ** 2 + ((z - 54) * 1.5) ** 2 < 60 ** 2
    box = np.zeros_like(bone)
    box[100:180, 80:200, 30:90] = True
    evm = EVM.from_mask(bone)
    for tool in (box, sphere):
        assert np.array_equal((evm - EVM.from_mask(tool)).to_mask(bone.shape), bone & ~tool)


@settings(max_examples=100, deadline=None)
@given(masks)
def test_volume_and_area_equal_voxel_counts(pair):
    a, _ = pair
    evm = EVM.from_mask(a)
    assert evm.volume() == np.count_nonzero(a)
    assert evm.area() == unit_faces(a)


def test_area_on_real_volume(data_dir):
    mask = load(data_dir, "ct_head_invesalius") >= 300
    assert EVM.from_mask(mask).area() == unit_faces(mask)


@settings(max_examples=100, deadline=None)
@given(masks, st.integers(0, 2), st.integers(-1, 7))
def test_split_by_an_axis_plane(pair, axis, c):
    a, _ = pair
    below, above = EVM.from_mask(a).split(axis, c)
    coordinate = np.indices(a.shape)[axis]
    assert np.array_equal(below.to_mask(a.shape), a & (coordinate < c))
    assert np.array_equal(above.to_mask(a.shape), a & (coordinate >= c))


def test_clip_by_a_box_and_translate(data_dir):
    mask = load(data_dir, "ct_skull_cgal") >= 2.9
    evm = EVM.from_mask(mask)
    lo, hi = (10, 5, 20), (50, 40, 33)
    expected = np.zeros_like(mask)
    expected[10:50, 5:40, 20:33] = mask[10:50, 5:40, 20:33]
    assert np.array_equal(evm.clip(lo, hi).to_mask(mask.shape), expected)
    moved = evm.translate(np.array([3, -2, 1]))
    assert np.array_equal(moved.to_mask(mask.shape, offset=(3, -2, 1)), mask)
    with pytest.raises(ValueError, match="offset must be 3 integers"):
        evm.translate(np.array([0.5, 0, 0]))


def test_sorting_orders_planes_and_sections_forwards_and_backwards(data_dir):
    mask = load(data_dir, "micro_nuclei3d_stardist") >= 200
    evm = EVM.from_mask(mask)
    for order in ("xyz", "xzy", "yxz", "yzx", "zxy", "zyx"):
        axes = ["xyz".index(a) for a in order]
        v = evm.sorted(order).astype(np.int64)
        assert np.array_equal(np.lexsort(v[:, axes[::-1]].T), np.arange(len(v)))
        assert sum(len(p) for _, p in evm.planes(order)) == len(evm)
        forward = list(evm.sections(order))
        backward = list(evm.sections(order, reverse=True))
        assert [(s.lo, s.hi) for s in forward] == [(s.lo, s.hi) for s in backward[::-1]]
        moved = np.transpose(mask, axes)
        for slab_f, slab_b in zip(forward, backward[::-1]):
            assert np.array_equal(slab_f.section, slab_b.section)
            # Every voxel layer of the slab has the section's cross-section.
            cross = _section_mask(slab_f.section, moved.shape[1:])
            for a in range(slab_f.lo, slab_f.hi):
                assert np.array_equal(moved[a], cross)


def _section_mask(points, shape):
    """Voxels of a 2-D EVM (prefix XOR in 2-D)."""
    grid = np.zeros((shape[0] + 1, shape[1] + 1), np.uint8)
    if len(points):
        np.bitwise_xor.at(grid, tuple(np.asarray(points, np.int64).T), 1)
    grid = np.bitwise_xor.accumulate(np.bitwise_xor.accumulate(grid, 0), 1)
    return grid[: shape[0], : shape[1]].astype(bool)


@pytest.mark.parametrize("name,threshold", [("micro_nuclei3d_stardist", 250),
                                            ("ct_head_invesalius", 300), ("seg_liver_cgal", 100)])
def test_face_connected_components_equal_flood_fill(data_dir, name, threshold):
    mask = load(data_dir, name) >= threshold
    labels, count = ndimage.label(mask)
    components = EVM.from_mask(mask).components()
    assert len(components) == count
    sizes = np.bincount(labels.ravel())[1:]
    assert [c.volume() for c in components] == sorted(sizes.tolist(), reverse=True)
    largest = components[0].to_mask(mask.shape)
    assert np.array_equal(largest, labels == np.argmax(sizes) + 1)


def test_components_of_touching_edges_are_separate():
    mask = np.zeros((3, 3, 3), bool)
    mask[0, 0, 0] = mask[1, 1, 0] = mask[2, 2, 2] = True
    assert [c.volume() for c in EVM.from_mask(mask).components()] == [1, 1, 1]


def test_bad_arguments():
    with pytest.raises(ValueError, match="mask must be 3-D"):
        EVM.from_mask(np.zeros((2, 2), bool))
    with pytest.raises(ValueError, match="duplicates"):
        EVM(np.array([[0, 0, 0], [0, 0, 0]]))
    with pytest.raises(TypeError, match="expected an EVM"):
        EVM() | np.zeros((2, 2, 2), bool)
    with pytest.raises(ValueError, match="order must be one of"):
        EVM().sorted("abc")


# ---------------------------------------------------------------------- property tests: patterns
LIMIT = 2**20  # lattice coordinates an EVM holds: [-LIMIT, LIMIT)
shapes = st.tuples(st.integers(1, 6), st.integers(1, 6), st.integers(1, 6))


def _checkerboard(shape, period, phase):
    index = np.indices(shape)
    return (sum(index[a] // period[a] for a in range(3)) + phase) % 2 == 1


def _touching(shape, seeds, steps):
    """Voxels at ``seeds`` and their diagonal neighbours ``seed + step``: pairs that share only
    an edge (two non-zero step components) or a corner (three)."""
    mask = np.zeros(shape, bool)
    for seed, step in zip(seeds, steps):
        for point in (np.array(seed), np.array(seed) + step):
            if (point >= 0).all() and (point < shape).all():
                mask[tuple(point)] = True
    return mask


def _border(shape, keep):
    """Voxels on the faces of the grid (all of them, or a random subset)."""
    mask = np.ones(shape, bool)
    mask[1:-1, 1:-1, 1:-1] = False
    return mask & keep


diagonal_steps = st.tuples(*[st.sampled_from([-1, 0, 1])] * 3).filter(
    lambda s: sum(map(abs, s)) >= 2)
patterns = st.one_of(
    shapes.flatmap(lambda shape: arrays(bool, shape)),
    st.builds(_checkerboard, shapes, st.tuples(*[st.integers(1, 2)] * 3), st.integers(0, 1)),
    shapes.flatmap(lambda shape: st.builds(
        _touching, st.just(shape),
        st.lists(st.tuples(*[st.integers(0, n - 1) for n in shape]), min_size=1, max_size=4),
        st.lists(diagonal_steps, min_size=4, max_size=4))),
    shapes.flatmap(lambda shape: st.builds(_border, st.just(shape), arrays(bool, shape))),
)


def offsets(shape):
    """Placements of a grid of ``shape``: near the origin, or against either end of the range."""
    def axis(n):
        return st.one_of(st.integers(-3, 3), st.integers(-LIMIT, -LIMIT + 3),
                         st.integers(LIMIT - 1 - n - 3, LIMIT - 1 - n))
    return st.tuples(*[axis(n) for n in shape])


placed_pairs = patterns.flatmap(lambda a: st.tuples(
    st.just(a), patterns.map(lambda b: _fit(b, a.shape)), offsets(a.shape)))


def _fit(mask, shape):
    """``mask`` cropped or zero-padded to ``shape``, for Booleans of two patterns."""
    out = np.zeros(shape, bool)
    common = tuple(slice(0, min(s, t)) for s, t in zip(mask.shape, shape))
    out[common] = mask[common]
    return out


@settings(max_examples=120, deadline=None)
@given(placed_pairs)
def test_patterns_round_trip_and_booleans_anywhere_in_the_range(case):
    a, b, offset = case
    ea, eb = EVM.from_mask(a, offset), EVM.from_mask(b, offset)
    assert np.array_equal(ea.to_mask(a.shape, offset), a)
    assert np.array_equal(ea.vertices.astype(np.int64), brute_vertices(a) + offset)
    assert ea.volume() == np.count_nonzero(a) and ea.area() == unit_faces(a)
    for name, (evm_op, voxel_op) in OPERATIONS.items():
        result = evm_op(ea, eb)
        assert np.array_equal(result.to_mask(a.shape, offset), voxel_op(a, b)), name
        assert result == EVM.from_mask(voxel_op(a, b), offset), name


@settings(max_examples=80, deadline=None)
@given(patterns.flatmap(lambda a: st.tuples(st.just(a), offsets(a.shape), offsets(a.shape))))
def test_translate_round_trips_to_any_placement_in_the_range(case):
    mask, start, end = case
    evm = EVM.from_mask(mask, start)
    step = np.subtract(end, start)
    moved = evm.translate(step)
    assert moved == EVM.from_mask(mask, end)
    assert moved.translate(-step) == evm
    assert np.array_equal(moved.to_mask(mask.shape, end), mask)


@settings(max_examples=80, deadline=None)
@given(patterns.flatmap(lambda a: st.tuples(st.just(a), offsets(a.shape), st.integers(0, 2),
                                            st.integers(-2, 8),
                                            st.sampled_from([0, 2**40, -2**40]))))
def test_split_and_clip_at_any_plane_even_beyond_the_range(case):
    """Planes past the range's ends are exact too: everything or nothing lies beyond them."""
    mask, offset, axis, c, far = case
    evm = EVM.from_mask(mask, offset)
    coordinate = np.indices(mask.shape)[axis] + offset[axis]
    plane = offset[axis] + c + far
    below, above = evm.split(axis, plane)
    assert np.array_equal(below.to_mask(mask.shape, offset), mask & (coordinate < plane))
    assert np.array_equal(above.to_mask(mask.shape, offset), mask & (coordinate >= plane))
    lo, hi = [-2**62] * 3, [2**62] * 3
    hi[axis] = plane
    expected = mask & (coordinate < plane)
    assert np.array_equal(evm.clip(lo, hi).to_mask(mask.shape, offset), expected)
    assert evm.clip(lo, hi) == below


def test_coordinates_beyond_the_range_are_refused_naming_the_parameter():
    voxel = np.ones((1, 1, 1), bool)
    edge = EVM.from_mask(voxel, (LIMIT - 2, -LIMIT, 0))  # vertices reach LIMIT - 1 and -LIMIT
    assert np.array_equal(edge.to_mask((1, 1, 1), (LIMIT - 2, -LIMIT, 0)), voxel)
    with pytest.raises(VolumeEVMError,
                       match=r"^mask placed at offset: .*from -1048576 to 1048575 only"):
        EVM.from_mask(voxel, (LIMIT - 1, 0, 0))
    with pytest.raises(VolumeEVMError, match=r"^mask placed at offset: "):
        EVM.from_mask(voxel, (0, -LIMIT - 1, 0))
    with pytest.raises(VolumeEVMError, match=r"^mask placed at offset: "):
        EVM.from_mask(np.zeros((LIMIT, 1, 1), bool))
    with pytest.raises(VolumeEVMError, match=r"^offset: the region would span lattice coordinates "
                                             r"\(1048575, -1048576, 0\) to "
                                             r"\(1048576, -1048575, 1\)"):
        edge.translate(np.array([1, 0, 0]))
    with pytest.raises(VolumeEVMError, match=r"^offset: "):
        edge.translate(np.array([0, 2**62, 0]))  # no wrap-around in int64
    with pytest.raises(VolumeEVMError, match="offset must be 3 integers"):
        EVM.from_mask(voxel, (0.5, 0, 0))
    with pytest.raises(VolumeEVMError, match=r"^vertices: .*from -1048576 to 1048575 only"):
        EVM(np.array([[0, 0, 0], [LIMIT, 0, 0]]))
    with pytest.raises(VolumeEVMError, match="vertices must be integer lattice points"):
        EVM(np.array([[0.5, 0, 0]]))
    with pytest.raises(VolumeEVMError, match="split plane c must be an integer"):
        edge.split(0, 1.5)
    with pytest.raises(VolumeEVMError, match="axis must be 0, 1 or 2"):
        edge.split(3, 0)
    with pytest.raises(VolumeEVMError, match="clip lo must be 3 integers"):
        edge.clip((0.5, 0, 0), (1, 1, 1))
