"""Chunked exact builds: the VolumeEVM of a lazy (Dask) volume, and the regions of a lazy label
map, chunk by chunk.

The EVM of a union of disjoint voxel sets is the XOR of their EVMs (a lattice point's parity is
the XOR of the parities), so each chunk's EVM, found from the chunk's own voxels alone and
shifted to the grid's coordinates, XOR-merged with the others gives exactly the EVM of the
whole region: vertices on a shared chunk plane cancel where the region continues across it.

Each Dask task (:func:`chunk_region`) thresholds one chunk and returns its vertices (sorted
packed keys), its region's densities in the chunk's C order and how many of them each
``(x, y)`` row holds. Chunks are computed a few x-slabs of chunks at a time
(:func:`chunk_slabs`; Dask's scheduler: threads by default, a ``dask.distributed`` cluster
when a ``Client`` exists): a slab's densities are one contiguous stretch of the table (order
"xyz"), placed row by row from the row counts, and the slabs concatenate. The result is
identical to :meth:`VolumeEVM.from_array` on the same data in memory, for any chunk shape.

A label map goes the same way (:func:`labels_chunked`): a task sweeps its chunk for every
label at once (:func:`chunk_labels`), and each label's vertices are the XOR of its chunks',
its voxel count their sum: identical to :meth:`VolumeEVM.from_labels` in memory.

Memory: the chunks in flight (the scheduler's workers, each holding one chunk and what it
derives from it) plus the result (table and vertices) plus one batch of slabs, checked before
starting and after every batch (:func:`volumeevm_addon.system.check_memory`).
"""

import math
import os
import sys

import numpy as np

from .._errors import VolumeEVMError
from .._jit import kernel
from .._memory import check_memory
from . import _sweep
from ._evm import _block_keys
from ._labels import MAX_LABELS, swept_labels

#: Chunks computed per batch, per scheduler worker: enough to keep every worker busy.
TASKS_PER_WORKER = 4

_ADVICE = ("raise the threshold or narrow the density interval, pick a coarser level, or use "
           "smaller chunks")


def chunk_region(block, offset, threshold, upper, source):
    """One chunk's part of the region: what a Dask task returns.

    Parameters
    ----------
    block : (x, y, z) ndarray
        The chunk's densities.
    offset : tuple of 3 int
        Grid index of ``block[0, 0, 0]``.
    threshold, upper : real number or None
        The density interval.
    source : str
        Names the data in messages.

    Returns
    -------
    keys : (k,) ndarray of int64
        Sorted packed keys of the chunk's own EVM in grid coordinates.
    values : (n,) ndarray
        The region's densities in the chunk, in its C order.
    rows : (x, y) ndarray of int64
        How many of them each row (fixed x and y) holds.
    low, high : scalar
        The chunk's smallest and largest density.

    Raises
    ------
    VolumeEVMError
        If the chunk holds NaN or infinite densities, naming ``source`` and the chunk.
    """
    given = block
    block, flipped = _native(block)
    if block.dtype.kind == "f" and not np.isfinite(block).all():
        bad = tuple(int(i) + o for i, o in zip(np.argwhere(~np.isfinite(given))[0], offset))
        raise VolumeEVMError(f"{source}: densities are NaN or infinite in the chunk at voxel "
                             f"{tuple(offset)} (first at voxel {bad}); densities must be finite")
    threshold, upper = _own_type(block.dtype, threshold, upper)
    selected = block >= threshold
    if upper is not None:
        selected &= block <= upper
    ox, oy, oz = (int(o) + _sweep.OFFSET for o in offset)
    mask = selected.view(np.uint8)
    if not flipped:
        keys = _block_keys(mask, 0, block.shape[0] + 1, ox, oy, oz)
    else:  # the vertices of the (z, y, x) mask, their coordinates swapped back
        keys = _block_keys(mask, 0, block.shape[0] + 1, oz, oy, ox)
        bits = 2 * _sweep.BITS
        keys = np.sort(((keys & _sweep.MASK) << bits) | (keys & (_sweep.MASK << _sweep.BITS))
                       | (keys >> bits))
    nx, ny = (block.shape[2], block.shape[1]) if flipped else block.shape[:2]
    rows = np.zeros((nx, ny), np.int64)
    values = np.empty(np.count_nonzero(mask), block.dtype)
    _values_xyz(block, mask, flipped, rows, values)
    return keys, values, rows, block.min(), block.max()


def _native(block):
    """The chunk as a C-contiguous array in the axis order nearest its memory order: ``(x, y,
    z)``, or ``(z, y, x)`` (``flipped``) when x varies fastest, as in a transposed view of an
    OME-Zarr store's ``(z, y, x)`` chunks, which would otherwise be copied axis by axis."""
    flipped = abs(block.strides[0]) < abs(block.strides[2])
    return np.ascontiguousarray(block.T if flipped else block), flipped


def _own_type(dtype, threshold, upper):
    """The density interval in the densities' own integer type where that selects the same
    voxels: ``v >= t`` is ``v >= ceil(t)`` and ``v <= u`` is ``v <= floor(u)`` for integers, and
    comparing integers of up to 32 bits with a float is exact, as is comparing like types. The
    comparison then runs on the integers as they are instead of converting the chunk to float
    (about 5 times faster for int16). Bounds outside the type's range, 64-bit integers (whose
    comparison with a float is rounded) and floats are left as they are."""
    if dtype.kind not in "iu" or dtype.itemsize > 4:
        return threshold, upper
    info = np.iinfo(dtype)
    bounds = []
    for bound, exact in ((threshold, math.ceil), (upper, math.floor)):
        if bound is not None and info.min <= exact(bound) <= info.max:
            bound = dtype.type(exact(bound))
        bounds.append(bound)
    return tuple(bounds)


@kernel
def _values_xyz(block, mask, flipped, rows, values):
    """The selected densities of a :func:`_native` chunk in ``(x, y, z)`` C order into
    ``values``, and into ``rows[x, y]`` how many each row holds, in two passes over the chunk
    in its memory order: the counts, then each density put at its row's next place."""
    na, nb, nc = block.shape
    if flipped:  # rows[x, y] sums the mask along a: added plane by plane
        across = np.zeros((nb, nc), np.int64)
        for a in range(na):
            for b in range(nb):
                for c in range(nc):
                    across[b, c] += mask[a, b, c]
        rows[:, :] = across.T
    else:
        for a in range(na):
            for b in range(nb):
                count = 0
                for c in range(nc):
                    count += mask[a, b, c]
                rows[a, b] = count
    nx, ny = rows.shape
    place = np.empty(nx * ny, np.int64)
    total = 0
    for x in range(nx):
        for y in range(ny):
            place[x * ny + y] = total
            total += rows[x, y]
    for a in range(na):
        for b in range(nb):
            for c in range(nc):
                if mask[a, b, c]:
                    row = c * ny + b if flipped else a * ny + b
                    values[place[row]] = block[a, b, c]
                    place[row] += 1


def chunked_build_memory(chunks, dtype, voxel_count, *, workers=None):
    """Estimated peak bytes of :meth:`VolumeEVM.from_volume` on a lazy volume.

    The chunks in flight (each scheduler worker holds its chunk, a contiguous copy, the mask,
    the chunk's densities and vertex keys) plus twice the region's densities table (the result
    so far and the next batch's, as the build checks after every batch). The region's extreme
    vertices are not counted: a region's vertices are few beside its voxels.

    Parameters
    ----------
    chunks : tuple of 3 int
        The largest chunk's shape.
    dtype : numpy dtype or str
        The densities' type.
    voxel_count : int
        Voxels in the region (an estimate before building, e.g. from a coarser level).
    workers : int, optional
        Chunks computed at once; default: what the Dask scheduler runs (a ``dask.distributed``
        cluster's threads when a ``Client`` exists, else the local threads).

    Returns
    -------
    int
        Bytes.

    Examples
    --------
    >>> chunked_build_memory((64, 64, 64), "uint16", 10**6, workers=2)
    12388608
    """
    if workers is None:
        import dask

        workers = _workers(dask)
    chunk_voxels = math.prod(chunks)
    in_flight = workers * (3 * chunk_voxels * np.dtype(dtype).itemsize + 10 * chunk_voxels)
    return int(in_flight + 2 * voxel_count * np.dtype(dtype).itemsize)


def build_chunked(array, threshold, upper, source, progress=None):
    """The sorted vertex keys and the densities table (order "xyz") of the region of a lazy
    ``(X, Y, Z)`` Dask array, chunk by chunk; ``progress(done, total)`` after each chunk (see
    :meth:`VolumeEVM.from_volume`).

    Returns
    -------
    keys : (k,) ndarray of int64
    table : (n,) ndarray of the array's dtype
    low, high : scalar
        The data's range (for the message about an empty region).

    Raises
    ------
    VolumeEVMError
        If a chunk holds NaN or infinite densities or the memory would not suffice.
    """
    keys, tables = [], []
    low = high = None
    # A worker holds its chunk, a contiguous copy, the mask, the densities and the keys.
    per_voxel = 3 * array.dtype.itemsize + 10
    slabs = chunk_slabs(array, chunk_region, (threshold, upper, source), per_voxel,
                        lambda: sum(t.nbytes for t in tables) + sum(k.nbytes for k in keys),
                        "building the VolumeEVM", source, _ADVICE, progress)
    for slab in slabs:
        tables.append(_slab_table(slab, array.numblocks[1:], array.dtype))
        keys.append(_sweep.parity(np.concatenate([r[0] for r in slab]), runs=True))
        lows, highs = [r[3] for r in slab], [r[4] for r in slab]
        low = min(lows + ([] if low is None else [low]))
        high = max(highs + ([] if high is None else [high]))
    keys = _sweep.parity(np.concatenate(keys), runs=True)
    return keys, _concatenated(tables, array.dtype), low, high


def chunk_labels(block, offset, wanted, source):
    """One chunk's part of a label map (a Dask task): ``label -> (keys, voxel count)`` of the
    chunk alone, its keys in grid coordinates (:func:`._labels.swept_labels`).

    Raises
    ------
    VolumeEVMError
        If the chunk holds negative labels or too many, naming ``source`` and the chunk.
    """
    return swept_labels(np.ascontiguousarray(block), wanted, offset,
                        source=f"{source}: the chunk at voxel {tuple(offset)}")


def labels_chunked(array, wanted, source):
    """:func:`._labels.label_regions` of a lazy ``(X, Y, Z)`` Dask label map, chunk by chunk:
    each label's keys are the XOR of its chunks' keys, merged slab by slab, and its voxel
    count their sum. ``wanted`` are the labels asked for (:func:`._labels.wanted_labels`).

    Returns
    -------
    dict
        ``label -> (keys, voxel_count)`` in increasing label order, as
        :func:`._labels.label_regions` gives it (without its warning).

    Raises
    ------
    VolumeEVMError
        If a chunk holds negative labels, the map more than :data:`._labels.MAX_LABELS`
        labels, or the memory would not suffice.
    """
    keys, counts = {}, {}  # label -> its slabs' keys (each slab's merged), its voxel count
    # A worker holds its chunk, a contiguous copy, and label numbers and keys of up to a
    # vertex per voxel, grouped once.
    per_voxel = 2 * array.dtype.itemsize + 20
    slabs = chunk_slabs(array, chunk_labels, (wanted, source), per_voxel,
                        lambda: sum(k.nbytes for parts in keys.values() for k in parts),
                        "building the label map's VolumeEVMs", source,
                        "pick fewer labels with labels=, or use smaller chunks")
    for slab in slabs:
        found = {}
        for regions in slab:
            for label, (part, count) in regions.items():
                found.setdefault(label, []).append(part)
                counts[label] = counts.get(label, 0) + count
        for label, parts in found.items():
            keys.setdefault(label, []).append(_sweep.parity(np.concatenate(parts), runs=True))
        if len(keys) > MAX_LABELS:
            raise VolumeEVMError(
                f"{source}: more than the {MAX_LABELS} labels a label map may hold; pick the "
                f"labels you need with labels=, or build density bands with VolumeEVM.from_volume")
    return {label: (_sweep.parity(np.concatenate(keys.pop(label)), runs=True), counts[label])
            for label in sorted(keys)}


def chunk_slabs(array, task, arguments, per_voxel, held, what, source, advice, progress=None):
    """The results of ``task(block, offset, *arguments)`` for every chunk of the lazy array,
    one x-slab of chunks at a time (a tuple in ``(y, z)`` chunk order), x-slab by x-slab;
    ``progress(done, total)`` after each chunk (:func:`_computed`).

    Chunks are computed a few x-slabs at a time on Dask's scheduler (threads, or the
    ``dask.distributed`` cluster of a ``Client``). Memory: ``per_voxel`` bytes per voxel of a
    chunk for each chunk in flight, checked before the first chunk; after every batch, also
    twice ``held()`` (what the caller keeps so far, and the next batch's results as large
    again at most). ``what`` and ``advice`` go into the message.

    Raises
    ------
    VolumeEVMError
        If the memory would not suffice (or as ``task`` raises).
    """
    import dask

    workers = _workers(dask)
    chunk_voxels = int(np.prod([max(c) for c in array.chunks]))
    in_flight = workers * per_voxel * chunk_voxels
    check_memory(in_flight, f"{what} with {workers} chunks in flight", source=source,
                 advice=advice)
    starts = [np.r_[0, np.cumsum(c)] for c in array.chunks]
    blocks = array.to_delayed()
    delayed_task = dask.delayed(task, pure=True)
    per_slab = blocks.shape[1] * blocks.shape[2]
    per_batch = max(1, (TASKS_PER_WORKER * workers) // per_slab)
    done = 0
    for first in range(0, blocks.shape[0], per_batch):
        slabs = range(first, min(first + per_batch, blocks.shape[0]))
        tasks = [delayed_task(blocks[i, j, k],
                              (int(starts[0][i]), int(starts[1][j]), int(starts[2][k])),
                              *arguments)
                 for i in slabs for j in range(blocks.shape[1]) for k in range(blocks.shape[2])]
        results = _computed(dask, tasks, progress, done, blocks.size, task.__name__)
        done += len(tasks)
        for n in range(len(slabs)):
            yield results[n * per_slab:(n + 1) * per_slab]
        del results
        check_memory(2 * held() + in_flight, f"{what} chunk by chunk", source=source,
                     advice=advice)


def _computed(dask, tasks, progress, done, total, name):
    """``dask.compute(*tasks)``, calling ``progress(done + n, total)`` as the n-th task ends.

    The local schedulers call back on this thread as each chunk's task ends; a distributed
    cluster does not call back, so the calls come when the batch ends."""
    if progress is None:
        return dask.compute(*tasks)
    from dask.callbacks import Callback

    ended = [done]

    def task_ended(key, *_):
        if str(key[0] if isinstance(key, tuple) else key).startswith(f"{name}-"):
            ended[0] += 1
            progress(ended[0], total)

    with Callback(posttask=task_ended):
        results = dask.compute(*tasks)
    for n in range(ended[0] + 1, done + len(tasks) + 1):
        progress(n, total)
    return results


def _workers(dask):
    """How many chunks the scheduler computes at once (a distributed cluster's threads, else
    the local threads)."""
    if "distributed" in sys.modules:  # a user who made a Client imported it
        from distributed import default_client

        try:
            return max(1, sum(default_client().nthreads().values()))
        except ValueError:  # no client
            pass
    return int(dask.config.get("num_workers", None) or os.cpu_count() or 1)


def _slab_table(slab, grid, dtype):
    """The densities of one x-slab of chunks in table order "xyz".

    ``slab`` holds the :func:`chunk_region` results of the slab's chunks, ``(y, z)`` chunk
    order. Rows ``(x, y)`` follow one another in the table; inside a row the chunks' pieces
    follow in z order. Each piece's place comes from the row counts.
    """
    ny, nz = grid
    # rows[x, y, k]: densities of row (x, y) in the k-th chunk along z
    rows = np.stack([np.concatenate([slab[j * nz + k][2] for j in range(ny)], axis=1)
                     for k in range(nz)], axis=2)
    starts = np.zeros(rows.size, np.int64)
    np.cumsum(rows.ravel()[:-1], out=starts[1:])
    starts = starts.reshape(rows.shape)
    table = np.empty(int(rows.sum()), dtype)
    y0 = 0
    for j in range(ny):
        height = slab[j * nz][2].shape[1]
        for k in range(nz):
            _, values, counts, _, _ = slab[j * nz + k]
            if not len(values):
                continue
            _place_rows(values, counts, starts[:, y0:y0 + height, k], table)
        y0 += height
    return table


@kernel
def _place_rows(values, rows, starts, table):
    """Copy a chunk's densities, ``rows[x, y]`` of them for each row in turn, to
    ``table[starts[x, y]:]``."""
    n = 0
    for x in range(rows.shape[0]):
        for y in range(rows.shape[1]):
            start = starts[x, y]
            for i in range(rows[x, y]):
                table[start + i] = values[n + i]
            n += rows[x, y]


def _concatenated(tables, dtype):
    """One table from the slabs' tables, each dropped once copied (the new table's pages are
    touched as it fills, so the peak stays near one table, not two)."""
    table = np.empty(sum(len(t) for t in tables), dtype)
    start = 0
    while tables:
        part = tables.pop(0)
        table[start:start + len(part)] = part
        start += len(part)
        del part
    return table
