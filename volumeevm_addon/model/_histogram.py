"""The densities of a volume at a glance: a histogram, and Otsu's threshold as a first guess.

The Blender side stores a small histogram on each imported volume (drawn in the sidebar beside
the threshold and the transfer function) and starts the threshold field at Otsu's value.
"""

import numpy as np

from .._errors import VolumeEVMError
from ._volume import is_lazy

__all__ = ["density_histogram", "otsu_threshold"]


def _value_range(array):
    """``(array, lo, hi)``: the densities and their range, checked (non-empty, finite). A lazy
    (Dask) array stays lazy: its range is one pass over its chunks, in parallel, a few chunks
    in memory at a time."""
    if not is_lazy(array):
        array = np.asarray(array)
    if array.size == 0 or not (np.issubdtype(array.dtype, np.integer)
                               or np.issubdtype(array.dtype, np.floating)):
        raise VolumeEVMError(f"array: expected a non-empty array of numbers, got "
                             f"{array.dtype} with shape {array.shape}")
    if is_lazy(array):
        import dask

        lo, hi = (float(v) for v in dask.compute(array.min(), array.max()))
    else:
        lo, hi = float(array.min()), float(array.max())
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise VolumeEVMError(f"array: holds NaN or infinite values (range {lo} .. {hi})")
    return array, lo, hi


def _counts(array, bins, value_range):
    """``np.histogram(array, bins, range=value_range)``; a lazy array's counts are summed
    chunk by chunk (Dask's histogram: each value falls in the same bin, so the counts are
    those of the whole array in memory)."""
    if not is_lazy(array):
        return np.histogram(array, bins=bins, range=value_range)
    import dask.array as da

    counts, edges = da.histogram(array, bins=bins, range=value_range)
    return counts.compute(), edges


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
        array (a store's level) is read chunk by chunk, twice (its range, then the counts),
        never whole; the result is the one of the same array in memory.
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
    array, lo, hi = _value_range(array)
    bins = _bin_count(bins)
    counts, _ = _counts(array, bins, (lo, hi) if hi > lo else (lo, lo + 1.0))
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
    array, lo, hi = _value_range(array)
    bins = _bin_count(bins)
    if hi <= lo:
        return lo
    counts, edges = _counts(array, bins, (lo, hi))
    counts = counts.astype(np.float64)
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(counts)
    w1 = w0[-1] - w0
    s0 = np.cumsum(counts * centres)
    with np.errstate(divide="ignore", invalid="ignore"):
        between = w0 * w1 * (s0 / w0 - (s0[-1] - s0) / w1) ** 2
    between = np.nan_to_num(between[:-1], nan=-1.0)
    return float(edges[int(np.argmax(between)) + 1])
