"""Chunked exact builds: ``VolumeEVM.from_volume`` on a lazy (Dask) volume equals
``VolumeEVM.from_array`` on the same data in memory — vertices, every axis's table (values and
dtype), grid, geometry, units and interval — for any chunk shape; lazy ``.npy`` files and
OME-Zarr stores build the same way; memory is checked before the first chunk and as the result
grows.
"""

import tracemalloc

import dask
import dask.array as da
import numpy as np
import pytest

from volumeevm_addon import Volume, VolumeEVM, VolumeEVMError, otsu_threshold, read_volume
from volumeevm_addon.model import chunked_build_memory
from zarr_files import pyramid, write_store

VOLUMES = ("ct_head_invesalius", "ct_skull_cgal", "seg_liver_cgal", "mr_t1_itk_kmeans",
           "mr_brainsmall_volpack", "micro_nuclei3d_stardist")


def assert_identical(got, expected):
    """Every field of two VolumeEVMs equal (tables by value and dtype)."""
    assert np.array_equal(got.evm.vertices, expected.evm.vertices)
    assert got.evm.vertices.dtype == expected.evm.vertices.dtype
    for axis in range(3):
        assert got.table(axis).dtype == expected.table(axis).dtype
        assert np.array_equal(got.table(axis), expected.table(axis))
    for name in ("shape", "spacing", "origin", "units", "threshold", "upper", "voxel_count"):
        assert getattr(got, name) == getattr(expected, name), name
    assert np.array_equal(got.orientation, expected.orientation)


def lazy(array, chunks, **geometry):
    return Volume(da.from_array(array, chunks=chunks), **geometry)


def random_chunks(rng, shape, parts=5):
    """Random chunking: per axis, either a regular size or irregular cuts (at most ``parts``
    pieces, so the test stays quick)."""
    chunks = []
    for n in shape:
        if rng.random() < 0.5:
            chunks.append(int(rng.integers(-(-n // parts), n + 1)))
        else:
            cuts = np.sort(rng.choice(np.arange(1, n), size=min(n - 1, int(rng.integers(0, parts))),
                                      replace=False)) if n > 1 else []
            chunks.append(tuple(int(c) for c in np.diff(np.r_[0, cuts, n])))
    return tuple(chunks)


@pytest.mark.parametrize("name", VOLUMES)
def test_chunked_equals_in_memory_on_real_volumes(data_dir, name):
    volume = read_volume(data_dir / f"{name}.npy")
    array = volume.array
    rng = np.random.default_rng(sum(map(ord, name)))
    otsu = otsu_threshold(array)
    low, high = np.percentile(array, [40, 90])
    if array.dtype.kind in "iu":
        otsu, low, high = int(otsu), int(low), int(high)
    for threshold, upper in ((otsu, None), (low, high)):
        expected = VolumeEVM.from_volume(volume, threshold, upper)
        for _ in range(3):
            chunks = random_chunks(rng, array.shape)
            got = VolumeEVM.from_volume(
                Volume(da.from_array(array, chunks=chunks), spacing=volume.spacing,
                       origin=volume.origin, orientation=volume.orientation,
                       units=volume.units, source=volume.source), threshold, upper)
            assert_identical(got, expected)


@pytest.mark.parametrize("case", ["noise", "checkerboard", "full", "corners", "float_band"])
def test_chunked_equals_in_memory_on_synthetic_volumes(case):
    rng = np.random.default_rng(7)
    shape = (23, 17, 29)
    if case == "noise":
        array = rng.integers(0, 100, shape).astype(np.uint8)
    elif case == "checkerboard":
        array = (np.indices(shape).sum(axis=0) % 2).astype(np.int32)
    elif case == "full":
        array = np.ones(shape, np.int16)
    elif case == "corners":
        array = np.zeros(shape, np.uint16)
        array[[0, 7, 8, 22], [0, 5, 6, 16], [0, 9, 10, 28]] = 1000
    else:
        array = rng.normal(size=shape)
    threshold, upper = (0.0, 1.0) if case == "float_band" else (50 if case == "noise" else 1, None)
    expected = VolumeEVM.from_array(array, threshold, upper, spacing=(0.5, 1.0, 2.0))
    for chunks in [(3, 4, 5), (8, 6, 10), (23, 17, 1), (1, 17, 29), random_chunks(rng, shape)]:
        got = VolumeEVM.from_volume(lazy(array, chunks, spacing=(0.5, 1.0, 2.0)), threshold, upper)
        assert_identical(got, expected)


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.uint32, np.int64])
def test_integer_densities_with_any_bounds_equal_in_memory(dtype):
    """Float, integer and out-of-range bounds on integer densities (compared in the densities'
    own type chunk by chunk) select what ``from_array`` selects."""
    info = np.iinfo(dtype)
    middle = int(info.min) // 2 + int(info.max) // 2
    array = (middle + np.random.default_rng(3).integers(-50, 50, (14, 11, 9))).astype(dtype)
    array[0, 0, :2] = (info.min, info.max)
    intervals = [(middle + 0.5, None), (middle - 10.0, middle + 20.25), (middle, None),
                 (info.min - 0.5, None), (info.min - 10**20, -1.5 + middle),
                 (float(info.max), None), (info.max - 0.5, info.max + 0.5), (-(10**20), 10**20)]
    for threshold, upper in intervals:
        expected = VolumeEVM.from_array(array, threshold, upper)
        got = VolumeEVM.from_volume(lazy(array, (5, 4, 9)), threshold, upper)
        assert_identical(got, expected)


def test_thread_count_does_not_change_the_result(data_dir):
    array = np.load(data_dir / "mr_t1_itk_kmeans.npy")
    results = []
    for workers in (1, 2):
        with dask.config.set(scheduler="threads", num_workers=workers):
            results.append(VolumeEVM.from_volume(lazy(array, (32, 40, 16)), 80))
    assert_identical(results[0], results[1])
    assert_identical(results[0], VolumeEVM.from_array(array, 80))


def test_chunks_stored_z_fastest_give_the_same_result(data_dir):
    """Chunks whose x varies fastest in memory (as an OME-Zarr store's, transposed) are swept
    in that order: same result, and a NaN is named by the first voxel in (x, y, z) order."""
    array = np.load(data_dir / "mr_t1_itk_kmeans.npy")
    built = VolumeEVM.from_volume(lazy(np.asfortranarray(array), (32, 40, 16)), 80)
    assert_identical(built, VolumeEVM.from_array(array, 80))
    nan = np.asfortranarray(np.zeros((10, 10, 10), np.float32))
    nan[7, 3, 2] = nan[8, 1, 0] = np.nan
    with pytest.raises(VolumeEVMError, match=r"^f\.npy: densities are NaN or infinite in the "
                                             r"chunk at voxel \(5, 0, 0\) \(first at voxel "
                                             r"\(7, 3, 2\)\)"):
        VolumeEVM.from_volume(lazy(nan, 5, source="f.npy"), 0.5)


def test_bad_lazy_input_refused():
    array = np.zeros((10, 10, 10), np.float32)
    array[7, 3, 2] = np.nan
    with pytest.raises(VolumeEVMError, match=r"^nan\.npy: densities are NaN or infinite in the "
                                             r"chunk at voxel \(5, 0, 0\) \(first at voxel "
                                             r"\(7, 3, 2\)\)"):
        VolumeEVM.from_volume(lazy(array, 5, source="nan.npy"), 0.5)
    with pytest.raises(VolumeEVMError, match=r"^zeros: the region is empty: no density is >= 1 "
                                             r"\(data range 0.0 \.\. 0.0\)"):
        VolumeEVM.from_volume(lazy(np.zeros((4, 4, 4)), 2, source="zeros"), 1)
    with pytest.raises(VolumeEVMError, match=r"^b: expected a non-empty 3-D array"):
        VolumeEVM.from_volume(lazy(np.zeros((4, 4), bool), 2, source="b"), 1)
    with pytest.raises(VolumeEVMError, match=r"^v: upper \(1\) must be >= threshold \(2\)"):
        VolumeEVM.from_volume(lazy(np.zeros((4, 4, 4)), 2, source="v"), 2, 1)


def test_lazy_npy_builds_identically(tmp_path, data_dir):
    path = data_dir / "ct_head_invesalius.npy"
    volume = read_volume(path, lazy=True)
    assert type(volume.array).__module__.startswith("dask")
    eager = read_volume(path)
    assert (volume.spacing, volume.origin, volume.units) == (eager.spacing, eager.origin,
                                                            eager.units)
    assert_identical(VolumeEVM.from_volume(volume, 300), VolumeEVM.from_volume(eager, 300))
    # Fortran order and big-endian data read lazily as the eager reader reads them
    array = np.load(path)[:60, :50, :40]
    for name, stored in (("f.npy", np.asfortranarray(array)), ("b.npy", array.astype(">i2"))):
        np.save(tmp_path / name, stored)
        lazily = read_volume(tmp_path / name, lazy=True)
        assert lazily.array.dtype == np.dtype("=i2")
        assert np.array_equal(lazily.array.compute(), array)
        assert_identical(VolumeEVM.from_volume(lazily, 300),
                         VolumeEVM.from_volume(read_volume(tmp_path / name), 300))
    (tmp_path / "short.npy").write_bytes((tmp_path / "b.npy").read_bytes()[:-2])
    with pytest.raises(VolumeEVMError, match="short.npy: not a readable .npy array"):
        read_volume(tmp_path / "short.npy", lazy=True)


def test_lazy_raw_builds_identically(tmp_path, data_dir):
    array = np.load(data_dir / "ct_head_invesalius.npy")
    path = tmp_path / "head.raw"
    path.write_bytes(b"H" * 100 + array.astype(">i2").tobytes(order="F"))
    layout = {"shape": array.shape, "dtype": "int16", "byte_order": "big", "header_bytes": 100,
              "spacing": (0.957, 0.957, 1.5)}
    volume = read_volume(path, lazy=True, **layout)
    assert volume.array.chunks[:2] == ((256,), (256,))  # whole z planes: contiguous reads
    assert np.array_equal(volume.array.compute(), array)
    assert_identical(VolumeEVM.from_volume(volume, 300),
                     VolumeEVM.from_volume(read_volume(path, **layout), 300))
    with pytest.raises(VolumeEVMError, match="head.raw: file has .* needs exactly"):
        read_volume(path, lazy=True, **{**layout, "header_bytes": 98})


@pytest.mark.parametrize("version", [2, 3])
def test_ome_zarr_levels_build_identically(tmp_path, data_dir, version):
    ct = np.load(data_dir / "ct_head_invesalius.npy")
    store = write_store(tmp_path / "head.ome.zarr", pyramid(ct, 3), version=version,
                        translation_zyx=(-80.0, 10.0, 20.0))
    for level in range(3):
        volume = read_volume(store, level=level)
        step = 2 ** level
        expected = VolumeEVM.from_array(ct[::step, ::step, ::step], 300, spacing=volume.spacing,
                                        origin=(20.0, 10.0, -80.0), source=str(store))
        assert_identical(VolumeEVM.from_volume(volume, 300), expected)


def test_memory_checked_before_and_during_the_build(data_dir, monkeypatch):
    array = np.load(data_dir / "ct_head_invesalius.npy")
    volume = lazy(array, (16, 256, 108), source="head")
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "1M")
    with pytest.raises(VolumeEVMError, match=r"^head: building the VolumeEVM with \d+ chunks in "
                                             r"flight needs about .* only 1.0 MiB is available; "
                                             r"raise the threshold"):
        VolumeEVM.from_volume(volume, 300)
    # The chunks in flight fit, the region at a low threshold (most of the grid) does not.
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "16M")
    with dask.config.set(num_workers=1):
        with pytest.raises(VolumeEVMError, match=r"^head: building the VolumeEVM chunk by chunk "
                                                 r"needs about"):
            VolumeEVM.from_volume(volume, -2000)
        monkeypatch.delenv("VOLUMEEVM_MEMORY_LIMIT")
        monkeypatch.setattr("volumeevm_addon.readers._checks.LAZY_CHUNK_BYTES", 16 * 256 * 108 * 2)
        mapped = read_volume(data_dir / "ct_head_invesalius.npy", lazy=True)
        assert mapped.array.chunks[0] == (16,) * 16
        VolumeEVM.from_volume(mapped, 2000)  # Dask's and the kernels' one-time allocations
        tracemalloc.start()
        try:
            region = VolumeEVM.from_volume(mapped, 1500)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
    result = region.size_report()["total_bytes"]
    print(f"peak {peak / 2**20:.1f} MiB for a {array.nbytes / 2**20:.1f} MiB grid, "
          f"result {result / 2**20:.2f} MiB, chunk {16 * 256 * 108 * 2 / 2**20:.2f} MiB")
    # One chunk in flight and the result, a few times over: far below the grid.
    assert peak < 4 * 16 * 256 * 108 * 2 + 4 * result < array.nbytes / 2


def test_progress_after_each_chunk_and_an_exception_in_it_stops_the_build(data_dir):
    array = np.load(data_dir / "ct_head_invesalius.npy")
    volume = lazy(array, (64, 100, 50))  # 4 x 3 x 3 chunks
    calls = []
    built = VolumeEVM.from_volume(volume, 300, progress=lambda *args: calls.append(args))
    assert calls == [(n, 36) for n in range(1, 37)]
    assert_identical(built, VolumeEVM.from_array(array, 300))

    class Stop(Exception):
        pass

    def stop_at_five(done, _total):
        calls.append(done)
        if done == 5:
            raise Stop

    calls.clear()
    with pytest.raises(Stop):
        VolumeEVM.from_volume(volume, 300, progress=stop_at_five)
    assert calls == [1, 2, 3, 4, 5]
    calls.clear()
    VolumeEVM.from_volume(Volume(array), 300, progress=lambda *args: calls.append(args))
    assert calls == [(1, 1)]


def test_memory_estimate_is_what_the_build_checks(data_dir, monkeypatch):
    array = np.load(data_dir / "ct_head_invesalius.npy")
    checked = []
    monkeypatch.setattr("volumeevm_addon.model._chunked.check_memory",
                        lambda needed, *a, **k: checked.append(needed))
    with dask.config.set(num_workers=3):
        region = VolumeEVM.from_volume(lazy(array, (64, 100, 50)), 300)
    held = chunked_build_memory((64, 100, 50), array.dtype, 0, workers=3)
    assert checked[0] == held == 3 * (3 * 64 * 100 * 50 * 2 + 10 * 64 * 100 * 50)
    # After the last batch: the whole table held twice (keys add a little), chunks in flight.
    assert checked[-1] >= chunked_build_memory((64, 100, 50), array.dtype, region.voxel_count,
                                               workers=3)


# ---------------------------------------------------------------------- label maps
def assert_same_label_sets(got, expected):
    """Two LabelSets with the same labels, names and colours, each label's region identical."""
    assert list(got) == list(expected)
    assert got.infos == expected.infos
    for label in expected:
        assert_identical(got[label], expected[label])


def test_lazy_liver_labels_equal_in_memory_for_any_chunks(data_dir):
    path = data_dir / "seg_liver_cgal.npy"
    volume = read_volume(path, lazy=True)
    assert type(volume.array).__module__.startswith("dask")
    expected = VolumeEVM.from_labels(read_volume(path))
    assert list(expected) == [84, 85, 127, 255]
    assert_same_label_sets(VolumeEVM.from_labels(volume), expected)
    array = np.load(path)
    rng = np.random.default_rng(22)
    for chunks in [(64, 64, 64), (100, 71, 33), (438, 353, 7), (1, 353, 165),
                   random_chunks(rng, array.shape), random_chunks(rng, array.shape)]:
        lazily = Volume(da.from_array(array, chunks=chunks), spacing=volume.spacing,
                        origin=volume.origin, orientation=volume.orientation, units=volume.units,
                        source=volume.source, labels=volume.labels)
        assert_same_label_sets(VolumeEVM.from_labels(lazily), expected)
    picked = VolumeEVM.from_labels(Volume(da.from_array(array, chunks=(50, 60, 70))),
                                   labels=[127, 84])
    assert_same_label_sets(picked, VolumeEVM.from_labels(array, labels=[127, 84]))


@pytest.mark.parametrize("dtype", [np.uint8, np.int32, np.uint16])
def test_lazy_synthetic_label_maps_equal_in_memory(dtype):
    """Many labels (up to 200) touching across chunk planes, at the grid's borders, speckled
    points where three or more meet, and labels found in one chunk only."""
    rng = np.random.default_rng(int(np.dtype(dtype).itemsize))
    shape = (23, 17, 29)
    array = np.zeros(shape, dtype)
    for _ in range(60):
        lo = [int(rng.integers(0, n)) for n in shape]
        hi = [int(rng.integers(low + 1, n + 1)) for low, n in zip(lo, shape)]
        array[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = rng.integers(1, 200)
    speckle = rng.random(shape) < 0.1
    array[speckle] = rng.integers(0, 200, int(speckle.sum()))
    array[22, 16, 28] = 250  # one voxel in the last chunk's corner
    expected = VolumeEVM.from_labels(array, spacing=(0.5, 1.0, 2.0))
    assert len(expected) > 100
    for chunks in [(3, 4, 5), (8, 6, 10), (23, 17, 1), (1, 17, 29), (5, 5, 5),
                   random_chunks(rng, shape)]:
        got = VolumeEVM.from_labels(lazy(array, chunks, spacing=(0.5, 1.0, 2.0)))
        assert_same_label_sets(got, expected)
    with dask.config.set(scheduler="threads", num_workers=1):
        assert_same_label_sets(VolumeEVM.from_labels(lazy(array, (7, 7, 7),
                                                          spacing=(0.5, 1.0, 2.0))), expected)


def test_bad_lazy_label_maps_refused_by_name_and_chunk():
    array = np.ones((10, 10, 10), np.int16)
    array[7, 3, 2] = -4
    with pytest.raises(VolumeEVMError, match=r"^m\.npy: the chunk at voxel \(5, 0, 0\): a label "
                                             r"map holds labels >= 0 .* 1 voxels are negative"):
        VolumeEVM.from_labels(lazy(array, 5, source="m.npy"))
    with pytest.raises(VolumeEVMError, match=r"^f: a label map must hold integers, got dtype "
                                             r"float32"):
        VolumeEVM.from_labels(lazy(np.ones((4, 4, 4), np.float32), 2, source="f"))
    with pytest.warns(UserWarning, match=r"^z: labels \[3\] have no voxels"):
        regions = VolumeEVM.from_labels(lazy(np.ones((4, 4, 4), np.uint8), 2, source="z"),
                                        labels=[1, 3])
    assert list(regions) == [1] and regions[1].voxel_count == 64
    many = np.arange(1, 2 * 3 * 10923 + 1, dtype=np.int32).reshape(2, 3, 10923)  # 65538 labels
    with pytest.raises(VolumeEVMError, match=r"^many: more than the 65536 labels"):
        VolumeEVM.from_labels(lazy(many, (2, 3, 4000), source="many"))


def test_lazy_label_map_memory_checked_before_and_during_the_sweep(data_dir, monkeypatch):
    array = np.load(data_dir / "seg_liver_cgal.npy")
    volume = lazy(array, (16, 353, 165), source="liver")
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "1M")
    with pytest.raises(VolumeEVMError, match=r"^liver: building the label map's VolumeEVMs with "
                                             r"\d+ chunks in flight needs about .* only 1.0 MiB "
                                             r"is available; pick fewer labels"):
        VolumeEVM.from_labels(volume)
    # One chunk in flight fits, the vertices of a speckled map (most of its points) do not.
    speckled = np.random.default_rng(5).integers(0, 3, (64, 64, 64)).astype(np.uint8)
    monkeypatch.setenv("VOLUMEEVM_MEMORY_LIMIT", "4M")
    with dask.config.set(scheduler="threads", num_workers=1):
        with pytest.raises(VolumeEVMError, match=r"^speckle: building the label map's "
                                                 r"VolumeEVMs chunk by chunk needs about"):
            VolumeEVM.from_labels(lazy(speckled, (4, 64, 64), source="speckle"))
