"""The densities of a volume at a glance: a histogram, and Otsu's threshold as a first guess.

The Blender side stores a small histogram on each imported volume (drawn in the sidebar beside
the threshold and the transfer function) and starts the threshold field at Otsu's value.
"""

import numpy as np

from .._errors import VolumeEVMError
from .._jit import kernel
from ._volume import is_lazy

__all__ = ["density_histogram", "otsu_threshold"]


def _value_range(array):
    """``(data, lo, hi)``: the densities, checked (non-empty, finite), and their range. ``data``
    is what :func:`_counts` bins: the array in memory; for a lazy (Dask) array of 8- or 16-bit
    integers, its possible values and how many voxels hold each (:func:`_value_counts`, one
    pass over the chunks); for another lazy array the array itself (its range one pass here,
    the counts another)."""
    if not is_lazy(array):
        array = np.asarray(array)
    if array.size == 0 or not (np.issubdtype(array.dtype, np.integer)
                               or np.issubdtype(array.dtype, np.floating)):
        raise VolumeEVMError(f"array: expected a non-empty array of numbers, got "
                             f"{array.dtype} with shape {array.shape}")
    if is_lazy(array) and array.dtype.kind in "iu" and array.dtype.itemsize <= 2:
        last = _last_counted
        if last[0] is not array:  # the histogram and the threshold of one array: one pass
            values, counts = _value_counts(array)
            present = values[counts > 0]
            last = _last_counted[:] = [array, ((values, counts), float(present[0]),
                                               float(present[-1]))]
        return last[1]
    if is_lazy(array):
        import dask

        lo, hi = (float(v) for v in dask.compute(array.min(), array.max()))
    else:
        lo, hi = float(array.min()), float(array.max())
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise VolumeEVMError(f"array: holds NaN or infinite values (range {lo} .. {hi})")
    return array, lo, hi


_last_counted = [None, None]
"""The lazy integer array counted last and what :func:`_value_range` made of it: an import
asks for the histogram and Otsu's threshold of the same array, read once (the array object
itself is kept, so the same object is the same data)."""


def _value_counts(array):
    """``(values, counts)``: every value of the lazy integer ``array``'s dtype (8 or 16 bits)
    and how many voxels hold it, counted chunk by chunk (:func:`_chunk_sums`)."""
    info = np.iinfo(array.dtype)
    values = np.arange(int(info.min), int(info.max) + 1)

    def count(block):
        counts = np.zeros(len(values), np.int64)
        _count_values(np.ravel(block, order="K"), int(info.min), counts)  # K: no copy
        return counts

    return values, _chunk_sums(array, count)


@kernel
def _count_values(values, lowest, counts):
    """Add one to ``counts[v - lowest]`` for each ``v`` of ``values`` (a compiled loop that
    releases the GIL, so Dask's threads count chunks in parallel; NumPy's ``bincount`` does
    not, and took 110 s for the chunks of a 2048³ store)."""
    for v in values:
        counts[np.int64(v) - lowest] += 1


def _chunk_sums(array, function):
    """The sum over the chunks of the lazy ``array`` of ``function(chunk)`` (an array of
    integers, the same shape for every chunk), on Dask's scheduler (in parallel, or on a
    cluster's workers) and summed in pairs, so a few results are in memory at a time."""
    import dask

    parts = [dask.delayed(function)(block) for block in array.to_delayed().ravel()]
    while len(parts) > 1:
        parts = [dask.delayed(np.add)(*parts[i:i + 2]) if i + 1 < len(parts) else parts[i]
                 for i in range(0, len(parts), 2)]
    return dask.compute(parts[0])[0]


def _counts(data, bins, value_range):
    """``np.histogram`` of ``data`` (:func:`_value_range`) with ``bins`` over ``value_range``:
    the voxels' values, weighted by their counts when ``data`` holds counts (each value falls
    in the bin it falls in as a voxel: the counts of the array in memory, exact in float64 up
    to 2**53 voxels); a lazy array's chunks are binned one by one, the counts summed."""
    if isinstance(data, tuple):
        values, counts = data
        counts, edges = np.histogram(values, bins=bins, range=value_range, weights=counts)
        return counts.astype(np.int64), edges
    if not is_lazy(data):
        return np.histogram(data, bins=bins, range=value_range)
    _, edges = np.histogram(np.zeros(0, data.dtype), bins=bins, range=value_range)
    return _chunk_sums(data, lambda block: np.histogram(block, bins=bins,
                                                        range=value_range)[0]), edges


def _bin_count(bins):
    if isinstance(bins, bool) or not isinstance(bins, (int, np.integer)) or bins < 1:
        raise VolumeEVMError(f"bins: a positive integer, got {bins!r}")
    return int(bins)


def density_histogram(array, *, bins=256):
    """Voxel counts in ``bins`` equal bins over the data range, and that range.

    Parameters
    ----------
    array : ndarray or dask.array.Array
        The densities (any shape, integer or floating point), in the data's own units. A lazy
        array (a store's level) is read chunk by chunk, never whole: once for 8- and 16-bit
        integers (their values counted), else twice (the range, then the counts); the result
        is the one of the same array in memory.
    bins : int, optional
        Number of bins between the smallest and the largest density.

    Returns
    -------
    counts : (bins,) ndarray of np.int64
        Voxels per bin; a constant volume has all of them in the first bin.
    lo, hi : float
        The smallest and the largest density.

    Raises
    ------
    VolumeEVMError
        For an empty or non-numeric ``array``, NaN or infinite densities, or ``bins`` < 1.

    Examples
    --------
    >>> import numpy as np
    >>> from volumeevm_addon import density_histogram
    >>> density_histogram(np.array([0, 1, 1, 2, 3, 3, 3, 4]), bins=4)
    (array([1, 2, 1, 4]), 0.0, 4.0)
    """
    data, lo, hi = _value_range(array)
    bins = _bin_count(bins)
    counts, _ = _counts(data, bins, (lo, hi) if hi > lo else (lo, lo + 1.0))
    return counts.astype(np.int64), lo, hi


def otsu_threshold(array, *, bins=256):
    """Otsu's threshold: the density that best splits a volume's values into two classes.

    The histogram of ``bins`` equal bins is split where the between-class variance is largest;
    the threshold is the upper edge of the last bin of the lower class, so the voxels at or
    above it form the upper class (Otsu, 1979). A starting value for the threshold field.

    Parameters
    ----------
    array : ndarray or dask.array.Array
        The densities (any shape, integer or floating point), in the data's own units; a lazy
        array is read chunk by chunk, as by :func:`density_histogram`.
    bins : int, optional
        Number of histogram bins.

    Returns
    -------
    float
        In the data's own units; the only value of a constant volume.

    Raises
    ------
    VolumeEVMError
        For an empty or non-numeric ``array``, NaN or infinite densities, or ``bins`` < 1.

    References
    ----------
    N. Otsu, "A threshold selection method from gray-level histograms", IEEE Transactions on
    Systems, Man, and Cybernetics 9(1), 62-66, 1979. doi:10.1109/TSMC.1979.4310076

    Examples
    --------
    >>> import numpy as np
    >>> from volumeevm_addon import otsu_threshold
    >>> otsu_threshold(np.array([1, 2, 2, 3, 7, 8, 8, 9]), bins=8)  # the voxels >= 4: 7, 8, 8, 9
    4.0
    """
    data, lo, hi = _value_range(array)
    bins = _bin_count(bins)
    if hi <= lo:
        return lo
    counts, edges = _counts(data, bins, (lo, hi))
    counts = counts.astype(np.float64)
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(counts)
    w1 = w0[-1] - w0
    s0 = np.cumsum(counts * centres)
    with np.errstate(divide="ignore", invalid="ignore"):
        between = w0 * w1 * (s0 / w0 - (s0[-1] - s0) / w1) ** 2
    between = np.nan_to_num(between[:-1], nan=-1.0)
    return float(edges[int(np.argmax(between)) + 1])
