"""The densities at a glance: the histogram stored on an imported volume, and Otsu's threshold
that starts the threshold field."""

import numpy as np
import pytest

from volumeevm_addon import VolumeEVMError, density_histogram, otsu_threshold


def otsu_by_definition(array, bins):
    """Otsu's threshold straight from its definition: try every split of the histogram, keep
    the first with the largest between-class variance ``w0 w1 (mu0 - mu1)^2``."""
    counts, edges = np.histogram(array, bins=bins, range=(float(array.min()), float(array.max())))
    centres = (edges[:-1] + edges[1:]) / 2
    best, split = -1.0, None
    for k in range(bins - 1):
        w0, w1 = counts[:k + 1].sum(), counts[k + 1:].sum()
        if w0 == 0 or w1 == 0:
            continue
        mu0 = (counts[:k + 1] * centres[:k + 1]).sum() / w0
        mu1 = (counts[k + 1:] * centres[k + 1:]).sum() / w1
        between = float(w0) * float(w1) * (mu0 - mu1) ** 2
        if between > best * (1 + 1e-12):
            best, split = between, edges[k + 1]
    return float(split)


def test_histogram_of_the_ct_head(data_dir):
    ct = np.load(data_dir / "ct_head_invesalius.npy")
    counts, lo, hi = density_histogram(ct, bins=32)
    assert counts.dtype == np.int64 and counts.shape == (32,)
    assert (lo, hi) == (float(ct.min()), float(ct.max()))
    assert counts.sum() == ct.size
    edges = np.linspace(lo, hi, 33)
    assert counts[0] == np.count_nonzero(ct < edges[1])  # the first bin: air
    assert counts[-1] == np.count_nonzero(ct >= edges[-2])  # the last includes the maximum


def test_histogram_of_a_constant_volume_is_one_full_bin():
    counts, lo, hi = density_histogram(np.full((3, 4, 5), 7, np.int16), bins=8)
    assert (lo, hi) == (7.0, 7.0)
    np.testing.assert_array_equal(counts, [60, 0, 0, 0, 0, 0, 0, 0])


@pytest.mark.parametrize("name", ["ct_head_invesalius", "mr_brainsmall_volpack"])
def test_otsu_on_real_volumes_is_the_definitions(data_dir, name):
    array = np.load(data_dir / f"{name}.npy")
    threshold = otsu_threshold(array)
    assert threshold == pytest.approx(otsu_by_definition(array, 256), rel=1e-12)
    assert array.min() < threshold < array.max()


def test_otsu_splits_two_clusters_and_keeps_a_constant_value():
    values = np.array([1, 2, 2, 3, 7, 8, 8, 9])
    threshold = otsu_threshold(values, bins=8)
    assert threshold == 4.0
    np.testing.assert_array_equal(values[values >= threshold], [7, 8, 8, 9])
    assert otsu_threshold(np.full(10, -3.5)) == -3.5


@pytest.mark.parametrize("function", [density_histogram, otsu_threshold])
@pytest.mark.parametrize("array, bins, match", [
    (np.zeros(0), 4, "array: expected a non-empty array of numbers"),
    (np.array(["a", "b"]), 4, "array: expected a non-empty array of numbers"),
    (np.array([1.0, np.nan]), 4, "array: holds NaN or infinite values"),
    (np.array([1.0, np.inf]), 4, "array: holds NaN or infinite values"),
    (np.arange(4), 0, "bins: a positive integer, got 0"),
    (np.arange(4), 2.5, "bins: a positive integer, got 2.5"),
    (np.arange(4), True, "bins: a positive integer, got True"),
])
def test_bad_input_raises_naming_the_parameter(function, array, bins, match):
    with pytest.raises(VolumeEVMError, match=match):
        function(array, bins=bins)


@pytest.mark.parametrize("name", ["ct_head_invesalius", "mr_brainsmall_volpack",
                                  "micro_nuclei3d_stardist", "ct_skull_cgal"])
def test_lazy_volumes_give_the_in_memory_histogram_and_otsu(data_dir, name):
    """A lazy array (a store's level, possibly larger than memory) is counted chunk by chunk
    (int16, uint8, uint16: their values counted in one pass; float32: range, then counts),
    with the same counts, range and threshold as in memory."""
    import dask.array as da

    array = np.load(data_dir / f"{name}.npy")
    lazy = da.from_array(array, chunks=(37, 50, 29))
    for bins in (32, 256):
        counts, lo, hi = density_histogram(lazy, bins=bins)
        want = density_histogram(array, bins=bins)
        assert np.array_equal(counts, want[0]) and (lo, hi) == want[1:]
        assert counts.dtype == np.int64
    assert otsu_threshold(lazy) == otsu_threshold(array)


def test_lazy_nan_is_refused():
    import dask.array as da

    array = np.zeros((6, 6, 6), np.float32)
    array[5, 5, 5] = np.nan
    with pytest.raises(VolumeEVMError, match="NaN or infinite"):
        density_histogram(da.from_array(array, chunks=3))


def test_a_lazy_arrays_histogram_and_threshold_read_it_once(data_dir):
    """An import asks for both of one store level: its chunks are read once, not twice; a
    new array of the same values is counted again."""
    import dask.array as da

    array = np.load(data_dir / "ct_head_invesalius.npy")
    reads = []

    def read(block):
        reads.append(1)
        return block

    def lazy():
        return da.from_array(array, chunks=(64, 64, 54)).map_blocks(
            read, meta=np.empty((0, 0, 0), array.dtype))

    level = lazy()
    counts, lo, hi = density_histogram(level, bins=32)
    first = len(reads)
    assert first == level.npartitions == 32  # every chunk once
    assert otsu_threshold(level) == otsu_threshold(array)
    assert len(reads) == first
    assert np.array_equal(counts, density_histogram(array, bins=32)[0])
    density_histogram(lazy(), bins=32)
    assert len(reads) == 2 * first
