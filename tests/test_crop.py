"""Building a region of interest: ``VolumeEVM.from_volume(..., crop=box)`` equals the whole
volume's VolumeEVM clipped to the box and moved to the box's first voxel — vertices and every
axis's table exactly, each voxel at the same physical place — in memory and chunk by chunk (only
the chunks meeting the box are read), with oblique orientations, boxes on the grid's edges and
boxes across chunks; ``Volume.index_box`` turns physical bounds into such a box; bad boxes are
refused by name and memory is checked for the box, not the grid.
"""

import dask
import dask.array as da
import numpy as np
import pytest

from volumeevm_addon import Volume, VolumeEVM, VolumeEVMError, otsu_threshold, read_volume

VOLUMES = ("ct_head_invesalius", "ct_skull_cgal", "seg_liver_cgal", "mr_t1_itk_kmeans",
           "mr_brainsmall_volpack", "micro_nuclei3d_stardist")


def rotation(rng):
    """A random orthonormal matrix (a rotation or a reflection): an oblique grid."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.diag(r))


def boxes(rng, shape, count):
    """Boxes of voxel indices: the whole grid, one voxel in a corner, slabs on the far edges,
    and random boxes (start and stop anywhere, not on chunk planes)."""
    found = [tuple((0, n) for n in shape), ((0, 1), (0, 1), (0, 1)),
             tuple((n - 1, n) for n in shape), ((0, shape[0]), (shape[1] // 3, shape[1]), (0, 1)),
             tuple((n // 4, n) for n in shape)]
    for _ in range(count):
        box = []
        for n in shape:
            a, b = sorted(rng.choice(n + 1, size=2, replace=False))
            box.append((int(a), int(b)))
        found.append(tuple(box))
    return found


def assert_crop_of(part, full, box):
    """``part`` is ``full`` clipped to ``box`` and moved by ``-box`` starts, exactly, and each of
    its voxels sits where the same voxel of ``full`` sits."""
    lo, hi = [a for a, _ in box], [b for _, b in box]
    assert part.shape == tuple(b - a for a, b in box)
    assert part.spacing == full.spacing and part.units == full.units
    assert np.array_equal(part.orientation, full.orientation)
    assert (part.threshold, part.upper) == (full.threshold, full.upper)
    clipped = full.clip(lo, hi)
    moved = clipped.evm.translate([-a for a in lo])
    assert np.array_equal(part.evm.vertices, moved.vertices)
    for axis in range(3):
        assert part.table(axis).dtype == clipped.table(axis).dtype
        assert np.array_equal(part.table(axis), clipped.table(axis))
    # The same voxels at the same physical places: lattice corners, and voxel centres.
    corners = part.evm.vertices.astype(np.float64)
    scale = max(1.0, np.abs(full.origin).max() + np.max(full.shape) * max(full.spacing))
    assert np.allclose(part.corner_positions(corners), full.corner_positions(corners + lo),
                       rtol=0, atol=1e-12 * scale)
    centres = np.c_[part.evm.voxels()[:50], np.ones(min(50, part.voxel_count))]
    shifted = centres + np.r_[lo, 0]
    assert np.allclose(centres @ part.index_to_physical().T, shifted @ full.index_to_physical().T,
                       rtol=0, atol=1e-12 * scale)
    assert np.array_equal(part.table()[part.index(centres[:, :3].astype(np.int64))],
                          full.table()[full.index(shifted[:, :3].astype(np.int64))])


def check_boxes(volume, threshold, upper, found, chunks=None):
    """Every box of ``found``: the cropped build (in memory, and lazy with ``chunks``) is the
    whole build clipped; a box the region misses is refused as an empty region."""
    full = VolumeEVM.from_volume(volume, threshold, upper)
    lazy = None if chunks is None else Volume(
        da.from_array(volume.array, chunks=chunks), spacing=volume.spacing, origin=volume.origin,
        orientation=volume.orientation, units=volume.units, source=volume.source)
    for box in found:
        lo, hi = [a for a, _ in box], [b for _, b in box]
        if full.evm.clip(lo, hi).is_empty():
            with pytest.raises(VolumeEVMError, match="the region is empty"):
                VolumeEVM.from_volume(volume, threshold, upper, crop=box)
            continue
        assert_crop_of(VolumeEVM.from_volume(volume, threshold, upper, crop=box), full, box)
        if lazy is not None:
            assert_crop_of(VolumeEVM.from_volume(lazy, threshold, upper, crop=box), full, box)


@pytest.mark.parametrize("name", VOLUMES)
def test_crop_equals_the_whole_build_clipped_on_real_volumes(data_dir, name):
    volume = read_volume(data_dir / f"{name}.npy")
    rng = np.random.default_rng(sum(map(ord, name)))
    otsu = otsu_threshold(volume.array)
    low, high = np.percentile(volume.array, [40, 90])
    if volume.array.dtype.kind in "iu":
        otsu, low, high = int(otsu), int(low), int(high)
    found = boxes(rng, volume.shape, 2)
    check_boxes(volume, otsu, None, found, chunks=(37, 50, 23))
    check_boxes(volume, low, high, found[:5])


def test_crop_on_an_oblique_grid(data_dir):
    """A real CT placed obliquely (rotated and reflected, moved): each kept voxel stays put."""
    rng = np.random.default_rng(5)
    array = np.load(data_dir / "ct_head_invesalius.npy")
    volume = Volume(array, spacing=(0.957, 0.957, 1.5), origin=(-120.5, 33.25, 1000.0),
                    orientation=rotation(rng), units="HU", source="head")
    check_boxes(volume, 300, None, boxes(rng, array.shape, 3), chunks=(64, 100, 50))


class GuardedArray:
    """A NumPy array read only through ``[...]``, recording each read; a read that misses
    ``box`` raises (a chunk the crop must never compute)."""

    def __init__(self, array, box):
        self.array, self.box, self.reads = array, box, []
        self.shape, self.dtype, self.ndim = array.shape, array.dtype, array.ndim

    def __getitem__(self, key):
        block = self.array[key]
        if block.size == 0:  # Dask's probe of the type, not a read
            return block
        spans = [range(*k.indices(n)) for k, n in zip(key, self.shape)]
        if any(s.start >= b or s.stop <= a for s, (a, b) in zip(spans, self.box)):
            raise AssertionError(f"read {key} outside the crop {self.box}")
        self.reads.append(key)
        return block


@pytest.mark.parametrize("box", [((10, 100), (57, 190), (3, 60)),       # across chunk planes
                                 ((0, 64), (0, 100), (0, 50)),          # one chunk exactly
                                 ((200, 256), (240, 256), (100, 108))])  # the far corner
def test_lazy_crop_reads_only_the_chunks_meeting_the_box(data_dir, box):
    array = np.load(data_dir / "ct_head_invesalius.npy")
    chunks = (64, 100, 50)
    guarded = GuardedArray(array, box)
    lazy = Volume(da.from_array(guarded, chunks=chunks, asarray=True), spacing=(0.9, 0.9, 1.5))
    calls = []
    with dask.config.set(scheduler="threads", num_workers=2):
        part = VolumeEVM.from_volume(lazy, -1000, crop=box,
                                     progress=lambda *a: calls.append(a))
    meeting = [len(range(a // c, -(-b // c))) for (a, b), c in zip(box, chunks)]
    assert len(guarded.reads) == np.prod(meeting) == calls[-1][1] == len(calls)
    full = VolumeEVM.from_volume(Volume(array, spacing=(0.9, 0.9, 1.5)), -1000)
    assert_crop_of(part, full, box)


@pytest.mark.parametrize("crop, message", [
    (((0, 0), (0, 4), (0, 4)), "empty"),
    (((3, 1), (0, 4), (0, 4)), "reversed"),
    (((0, 5), (0, 4), (0, 4)), "outside"),
    (((-1, 2), (0, 4), (0, 4)), "outside"),
    (((0, 2), (0, 4)), "3 \\(start, stop\\) pairs"),
    (((0, 2), (0, 4), (0, 4), (0, 1)), "3 \\(start, stop\\) pairs"),
    (((0, 2, 3), (0, 4), (0, 4)), "3 \\(start, stop\\) pairs"),
    (((0, 2.0), (0, 4), (0, 4)), "not integers"),
    (((0, True), (0, 4), (0, 4)), "not integers"),
    ((("0", 2), (0, 4), (0, 4)), "not integers"),
    (7, "3 \\(start, stop\\) pairs"),
])
def test_bad_crops_refused_by_name(crop, message):
    volume = Volume(np.ones((4, 4, 4), np.uint8))
    for vol in (volume, Volume(da.from_array(volume.array, chunks=2))):
        with pytest.raises(VolumeEVMError, match=f"^crop must be .*{message}"):
            VolumeEVM.from_volume(vol, 1, crop=crop)


def test_memory_is_checked_for_the_box_not_the_grid(data_dir, monkeypatch):
    volume = read_volume(data_dir / "ct_head_invesalius.npy")
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "4M")
    with pytest.raises(VolumeEVMError, match="building the VolumeEVM needs about"):
        VolumeEVM.from_volume(volume, -2000)  # every voxel: a 14 MB table
    box = ((100, 164), (100, 164), (20, 60))
    part = VolumeEVM.from_volume(volume, -2000, crop=box)
    assert part.voxel_count == 64 * 64 * 40
    assert np.array_equal(part.table(), volume.array[100:164, 100:164, 20:60].ravel())


def test_index_box_covers_the_physical_box():
    rng = np.random.default_rng(11)
    for oblique in (False, True):
        volume = Volume(np.zeros((30, 20, 10)), spacing=(0.5, 1.25, 3.0),
                        origin=tuple(rng.uniform(-50, 50, 3)),
                        orientation=rotation(rng) if oblique else np.eye(3))
        matrix = volume.index_to_physical()
        index = np.indices(volume.shape).reshape(3, -1).T.astype(np.float64)
        centres = index @ matrix[:3, :3].T + matrix[:3, 3]
        for _ in range(20):
            centre = centres[rng.integers(len(centres))]  # a box holding a voxel's centre
            lo, hi = centre - rng.uniform(0, 10, 3), centre + rng.uniform(0, 10, 3)
            box = volume.index_box(lo, hi)
            inside = np.zeros(volume.shape, bool)
            inside[tuple(slice(a, b) for a, b in box)] = True
            # Every voxel whose centre lies in the physical box is in the crop ...
            held = ((centres >= lo) & (centres <= hi)).all(axis=1).reshape(volume.shape)
            assert not (held & ~inside).any()
            if not oblique:  # ... and, on an upright grid, every voxel of it meets the box.
                cell_lo = centres - 0.5 * np.asarray(volume.spacing)
                cell_hi = centres + 0.5 * np.asarray(volume.spacing)
                meets = ((cell_hi > lo) & (cell_lo < hi)).all(axis=1).reshape(volume.shape)
                assert np.array_equal(meets, inside)


def test_index_box_of_the_grid_and_on_cell_faces():
    volume = Volume(np.zeros((10, 8, 6)), spacing=(2.0, 1.0, 0.5), origin=(1.0, 0.5, 0.25))
    # The grid's own bounds (cell faces): the whole grid, no neighbour taken by rounding.
    assert volume.index_box((0.0, 0.0, 0.0), (20.0, 8.0, 3.0)) == ((0, 10), (0, 8), (0, 6))
    assert volume.index_box((-5.0, -5.0, -5.0), (99.0, 99.0, 99.0)) == ((0, 10), (0, 8), (0, 6))
    assert volume.index_box((4.0, 2.0, 1.0), (6.0, 3.0, 1.5)) == ((2, 3), (2, 3), (2, 3))
    assert volume.index_box((4.1, 2.0, 1.0), (6.1, 3.0, 1.5)) == ((2, 4), (2, 3), (2, 3))


@pytest.mark.parametrize("lo, hi, message", [
    ((30.0, 0.0, 0.0), (40.0, 1.0, 1.0), "misses the volume's grid"),
    ((5.0, 0.0, 0.0), (4.0, 1.0, 1.0), "lo_mm <= hi_mm"),
    ((0.0, np.nan, 0.0), (4.0, 1.0, 1.0), "must be finite"),
    ((0.0, 0.0), (4.0, 1.0, 1.0), "lo_mm must be 3 finite numbers"),
    ((0.0, 0.0, 0.0), "far", "hi_mm must be 3 finite numbers"),
])
def test_bad_index_boxes_refused_by_name(lo, hi, message):
    volume = Volume(np.zeros((10, 8, 6)), spacing=(2.0, 1.0, 0.5))
    with pytest.raises(VolumeEVMError, match=f"^crop: .*{message}"):
        volume.index_box(lo, hi)


def test_crop_to_a_tool_mesh_bounds(data_dir):
    """A CAD tool's bounds (a real mesh placed in the head) crop the build to the tool's box:
    the crop holds every voxel of the region the tool keeps."""
    volume = read_volume(data_dir / "ct_head_invesalius.npy")
    mesh = np.load(data_dir / "mesh_tool_rotor.npz")
    vertices = mesh["vertices"] - mesh["vertices"].mean(axis=0)
    vertices = vertices * (60.0 / np.ptp(vertices, axis=0).max()) + (120.0, 130.0, 80.0)
    box = volume.index_box(vertices.min(axis=0), vertices.max(axis=0))
    part = VolumeEVM.from_volume(volume, 300, crop=box)
    full = VolumeEVM.from_volume(volume, 300)
    assert_crop_of(part, full, box)
    assert 0 < part.voxel_count < full.voxel_count
