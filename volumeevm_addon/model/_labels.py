"""Label maps: the region of every label of an integer volume, in one sweep of the array.

A label map (0 = background) partitions the grid, and each label ``L`` is the band
``[L, L]``: its EVM holds the lattice points around which an odd number of the 8 cells carry
``L``. One compiled pass over the lattice finds every label's vertices at once: a vectorized
pass marks the few points where some label may have an odd count (most points sit inside one
label, or on a face between two), and only those are visited one by one. A map of 100 labels
costs about one ordinary build, not 100. Two labels that touch bound the same
lattice faces: their meshes share those faces exactly (no gap, no overlap).
"""

import sys
import warnings

import numpy as np

from .._errors import VolumeEVMError
from .._jit import kernel, kernel_threads, parallel_map
from .._memory import check_memory
from . import _sweep
from ._volume import is_lazy

MAX_LABELS = 1 << 16
"""The most labels one map may hold (65536): more is a density volume, not a segmentation."""

_LOOKUP_RANGE = 1 << 22
"""Label values above this are renumbered by sorting first (the lookup table would be large)."""

_BLOCK_VOXELS = 1 << 21
"""Voxels per block of x-slices one thread sweeps."""


_LITTLE_ENDIAN = sys.byteorder == "little"
"""Whether the first byte of a word is its least significant (how :func:`_marked` reads)."""

_DE_BRUIJN = 0x03F79D71B4CB0A89
"""A de Bruijn sequence: multiplied by a power of two ``2**i``, its top 6 bits are distinct."""

_BIT_OF = np.zeros(64, np.int64)
_BIT_OF[[(_DE_BRUIJN << i) % (1 << 64) >> 58 for i in range(64)]] = np.arange(64)
"""``i`` for the top 6 bits of ``_DE_BRUIJN * 2**i``: the lowest set bit of a word in O(1)."""


@kernel
def _marked(flags, rows, places):
    """The marked points of the first ``rows`` rows of ``flags`` (uint8, 0 or 1, rows of a
    multiple of 8 bytes), row by row in increasing order: their rows go to ``places[0]``,
    their columns to ``places[1]``; returns their count.

    Eight bytes are read as one word: a word of zeros (most of them) costs one test, and a
    marked byte is found from the word's lowest set bit without testing the bytes around it.
    """
    per_row = flags.shape[1] // 8
    words = flags.reshape(flags.size).view(np.uint64)
    count = 0
    for row in range(rows):
        for w in range(per_row):
            word = words[row * per_row + w]
            while word:
                low = word & (~word + np.uint64(1))  # the lowest set bit
                byte = _BIT_OF[(low * np.uint64(_DE_BRUIJN)) >> np.uint64(58)] >> 3
                places[0, count] = row
                places[1, count] = 8 * w + (byte if _LITTLE_ENDIAN else 7 - byte)
                count += 1
                word &= ~(np.uint64(0xFF) * low)
    return count


@kernel
def _label_block(labels, ids, first, stop, n_ids, ox, oy, oz):
    """Every label's extreme vertices on the lattice planes ``x = first .. stop - 1``.

    ``labels`` is the ``(X, Y, Z)`` map, ``ids[value]`` a label's number (0 .. n_ids - 1)
    or -1 for the background and the labels not asked for. Returns the vertices' label numbers
    and packed keys (plane by plane, each plane in key order, so every label's keys come out
    sorted), and the voxel count of each label over the slices ``first .. stop - 1`` inside the
    grid.

    The two slices around a plane are copied into planes with a ring of zeros (the background
    outside the grid). The plane's lattice points are first marked in one pass without
    branches, which the compiler turns into vector instructions: a point may be a vertex
    unless its 8 cells hold one value, or two values with an even count each. The few marked
    points (about the vertices) are then visited one by one: two values there are both odd,
    so both labels have a vertex there; three or more (where labels meet along an edge or at
    a corner) are counted. Voxels are counted by runs along z, found the same way.
    """
    nx, ny, nz = labels.shape
    before = np.zeros((ny + 2, nz + 2), labels.dtype)
    after = np.zeros((ny + 2, nz + 2), labels.dtype)
    flags = np.zeros((ny + 1, 8 * ((nz + 8) // 8)), np.uint8)  # room for nz + 1 marks a row
    places = np.empty((2, flags.size), np.int64)
    counts = np.zeros(n_ids + 1, np.int64)  # counts[0]: the background and labels not asked for
    cells = np.empty(8, np.int64)  # the 8 values around a point
    odd = np.empty(8, np.int64)  # the values with an odd count there
    out_ids = np.empty(1024, np.int32)
    out_keys = np.empty(1024, np.int64)
    n = 0
    if first > 0:
        for y in range(ny):
            before[y + 1, 1:nz + 1] = labels[first - 1, y]
    for x in range(first, stop):
        if x < nx:
            for y in range(ny):
                for z in range(nz):
                    after[y + 1, z + 1] = labels[x, y, z]
                for z in range(nz - 1):  # the runs' last voxels
                    flags[y, z] = labels[x, y, z] != labels[x, y, z + 1]
                flags[y, nz - 1] = 1
                flags[y, nz] = 0
            start = 0
            for i in range(_marked(flags, ny, places)):
                y, z = places[0, i], places[1, i]
                counts[ids[labels[x, y, z]] + 1] += z + 1 - start
                start = 0 if z == nz - 1 else z + 1
        else:
            after[:, :] = 0
        for y in range(ny + 1):
            for z in range(nz + 1):
                c0, c1 = before[y, z], before[y, z + 1]
                c2, c3 = before[y + 1, z], before[y + 1, z + 1]
                c4, c5 = after[y, z], after[y, z + 1]
                c6, c7 = after[y + 1, z], after[y + 1, z + 1]
                other = c1 if c1 != c0 else c0  # a value other than c0, if there is one
                other = c2 if c2 != c0 else other
                other = c3 if c3 != c0 else other
                other = c4 if c4 != c0 else other
                other = c5 if c5 != c0 else other
                other = c6 if c6 != c0 else other
                other = c7 if c7 != c0 else other
                e1, e2, e3, e4 = c1 == c0, c2 == c0, c3 == c0, c4 == c0
                e5, e6, e7 = c5 == c0, c6 == c0, c7 == c0
                uniform = e1 & e2 & e3 & e4 & e5 & e6 & e7
                c0_even = e1 ^ e2 ^ e3 ^ e4 ^ e5 ^ e6 ^ e7  # c0 is counted 1 + sum(e) times
                two = ((e1 | (c1 == other)) & (e2 | (c2 == other)) & (e3 | (c3 == other))
                       & (e4 | (c4 == other)) & (e5 | (c5 == other)) & (e6 | (c6 == other))
                       & (e7 | (c7 == other)))
                flags[y, z] = (not uniform) & ((not two) | (not c0_even))
        marked = _marked(flags, ny + 1, places)
        if len(out_keys) < n + 8 * marked:  # room for 8 labels at each marked point
            size = max(2 * len(out_keys), n + 8 * marked)
            grown_ids, grown_keys = np.empty(size, np.int32), np.empty(size, np.int64)
            grown_ids[:n], grown_keys[:n] = out_ids[:n], out_keys[:n]
            out_ids, out_keys = grown_ids, grown_keys
        plane = np.int64(x + ox) << (2 * _sweep.BITS)
        for i in range(marked):
            y, z = places[0, i], places[1, i]
            key = plane | ((y + oy) << _sweep.BITS) | (z + oz)
            cells[0], cells[1] = before[y, z], before[y, z + 1]
            cells[2], cells[3] = before[y + 1, z], before[y + 1, z + 1]
            cells[4], cells[5] = after[y, z], after[y, z + 1]
            cells[6], cells[7] = after[y + 1, z], after[y + 1, z + 1]
            other = cells[0]
            for j in range(1, 8):
                if cells[j] != cells[0]:
                    other = cells[j]
            two = True
            for j in range(1, 8):
                two &= (cells[j] == cells[0]) | (cells[j] == other)
            if two:  # both odd (a point of one value, or of two even ones, is not marked)
                odd[0], odd[1], found = cells[0], other, 2
            else:
                found = 0
                for j in range(8):
                    if cells[j] < 0:
                        continue
                    count = 1
                    for k in range(j + 1, 8):
                        if cells[k] == cells[j]:
                            count += 1
                            cells[k] = -1  # counted: not a value of its own again
                    if count % 2 == 1:
                        odd[found] = cells[j]
                        found += 1
            for j in range(found):
                number = ids[odd[j]]
                out_ids[n] = number
                out_keys[n] = key
                n += number >= 0
        before, after = after, before
    return out_ids[:n].copy(), out_keys[:n].copy(), counts[1:].copy()


@kernel
def _present(labels, size):
    """How many voxels carry each value ``0 .. size - 1`` (one pass, no copy)."""
    counts = np.zeros(size, np.int64)
    nx, ny, nz = labels.shape
    for x in range(nx):
        for y in range(ny):
            for z in range(nz):
                counts[labels[x, y, z]] += 1
    return counts


@kernel
def _group(ids, keys, n_ids):
    """``keys`` grouped by label number (0 .. n_ids - 1), each group keeping its order (a
    counting sort), and the ``n_ids + 1`` places where the groups start and the last ends."""
    starts = np.zeros(n_ids + 1, np.int64)
    for number in ids:
        starts[number + 1] += 1
    for i in range(n_ids):
        starts[i + 1] += starts[i]
    out = np.empty_like(keys)
    fill = starts.copy()
    for i in range(len(keys)):
        out[fill[ids[i]]] = keys[i]
        fill[ids[i]] += 1
    return out, starts


def checked_labels(array, source):
    """The label map as a 3-D integer ndarray, refused unless it is one.

    A lazy (Dask) array is checked for its shape and type and returned as it is: its chunks
    are checked as they are swept (:mod:`._chunked`).

    Raises
    ------
    VolumeEVMError
        For anything but a 3-D, non-empty array of non-negative integers, naming ``source``:
        floating-point labels (cast whole-numbered floats with ``array.astype(np.int32)``),
        booleans (a mask: :meth:`EVM.from_mask`) and negative labels.
    """
    lazy = is_lazy(array)
    if not lazy:
        array = np.asarray(array)
    if array.ndim != 3 or array.size == 0:
        raise VolumeEVMError(f"{source}: a label map must be a non-empty 3-D array, got shape "
                             f"{array.shape}")
    if array.dtype.kind not in "iu":
        hint = {"b": "a boolean mask is one region: use EVM.from_mask",
                "f": "labels are categories, not densities: if the values are whole numbers, "
                     "cast them with array.astype(np.int32)"}.get(array.dtype.kind, "")
        raise VolumeEVMError(f"{source}: a label map must hold integers, got dtype {array.dtype}"
                             + (f" ({hint})" if hint else ""))
    if not lazy and array.dtype.kind == "i" and int(array.min()) < 0:
        raise VolumeEVMError(f"{source}: a label map holds labels >= 0 (0 = background), but "
                             f"{np.count_nonzero(array < 0)} voxels are negative "
                             f"(min {array.min()})")
    return array


def label_regions(array, labels=None, *, source="array"):
    """Every label's extreme vertices and voxel count, in one sweep of ``array``.

    Parameters
    ----------
    array : (X, Y, Z) ndarray of int
        The label map, checked by :func:`checked_labels`.
    labels : int or iterable of int, optional
        The labels wanted (default: every label present but 0).
    source : str
        Names the data in messages.

    Returns
    -------
    dict
        ``label -> (keys, voxel_count)`` for the wanted labels that have voxels, in increasing
        label order; ``keys`` are the label's EVM keys (:mod:`._sweep`), sorted.

    Raises
    ------
    VolumeEVMError
        For a map :func:`checked_labels` refuses, bad ``labels``, more than
        :data:`MAX_LABELS` labels, or no memory for the result.

    Warns
    -----
    UserWarning
        Naming the wanted labels that have no voxel (the others are built all the same).
    """
    wanted = wanted_labels(labels)
    regions = swept_labels(array, wanted, source=source)
    warn_missing(wanted, regions, source)
    return regions


def swept_labels(array, wanted, offset=(0, 0, 0), *, source="array"):
    """:func:`label_regions` of ``array`` placed at grid index ``offset`` (a chunk of a larger
    map: its vertices in the grid's coordinates), for the labels ``wanted``
    (:func:`wanted_labels`), without a warning for the wanted labels it lacks."""
    array = checked_labels(array, source)
    hi = int(array.max())
    lookup = hi < _LOOKUP_RANGE
    if lookup:
        values = np.arange(hi + 1)  # number v is value v
        if len(values) > MAX_LABELS:  # a wide range: number only the values present
            values = values[_present(array, hi + 1) > 0]
    else:  # values spread too far for a lookup table: renumber them by sorting
        values, inverse = np.unique(array, return_inverse=True)
        inverse = inverse.reshape(array.shape).astype(np.int32)
        if values[0] != 0:  # number 0 stays the background (the zeros around the grid)
            values, inverse = np.concatenate([[0], values]), inverse + 1
        array = inverse
    candidates = values[values != 0] if wanted is None else np.intersect1d(values, wanted)
    if len(candidates) > MAX_LABELS:
        raise VolumeEVMError(
            f"{source}: {len(candidates)} labels, more than the {MAX_LABELS} a label map may hold; "
            f"pick the labels you need with labels=, or build density bands with "
            f"VolumeEVM.from_array"
        )
    # Each candidate's number, by its value's place in the lookup (-1: not built).
    ids = np.full(int(values[-1]) + 1 if lookup else len(values), -1, np.int32)
    places = candidates if lookup else np.searchsorted(values, candidates)
    ids[places] = np.arange(len(candidates), dtype=np.int32)
    nx, ny, nz = array.shape
    # Vertices are not known before the sweep: check what each thread keeps (two padded slices,
    # a plane of marks and their places) and the counts per label.
    plane = (ny + 2) * (nz + 9)
    check_memory(kernel_threads() * plane * (2 * array.dtype.itemsize + 17) + 12 * len(ids),
                 "sweeping the label map", source=source,
                 advice="pick fewer labels with labels=, or crop the volume")
    step = max(1, _BLOCK_VOXELS // max(1, ny * nz))
    ox, oy, oz = (int(o) + _sweep.OFFSET for o in offset)
    blocks = parallel_map(_label_block, [(array, ids, x, min(x + step, nx + 1), len(candidates),
                                          ox, oy, oz) for x in range(0, nx + 1, step)])
    vertex_ids = np.concatenate([b[0] for b in blocks])
    keys = np.concatenate([b[1] for b in blocks])
    counts = np.sum([b[2] for b in blocks], axis=0)
    del blocks
    grouped, starts = _group(vertex_ids, keys, len(candidates))
    return {int(label): (grouped[starts[i]:starts[i + 1]].copy(), int(counts[i]))
            for i, label in enumerate(candidates) if counts[i] > 0}


def wanted_labels(labels):
    """The labels asked for as sorted unique int64 (None: all); refuses anything else."""
    if labels is None:
        return None
    if np.iterable(labels) and not isinstance(labels, (str, bytes, np.ndarray)):
        labels = list(labels)
    wanted = np.atleast_1d(np.asarray(labels))
    if wanted.dtype.kind not in "iu" or wanted.ndim != 1:
        raise VolumeEVMError(f"labels must be one or more integers > 0, got {labels!r}")
    wanted = np.unique(wanted.astype(np.int64))
    if len(wanted) == 0 or (wanted <= 0).any():
        raise VolumeEVMError(f"labels must be one or more integers > 0 (0 is the background), "
                             f"got {labels!r}")
    return wanted


def warn_missing(wanted, regions, source):
    """Warn naming the labels ``wanted`` (None: all) that have no region in ``regions``."""
    if wanted is not None:
        missing = sorted(set(wanted.tolist()) - set(regions))
        if missing:
            warnings.warn(f"{source}: labels {missing} have no voxels", UserWarning, stacklevel=4)


def labels_present(array, source="array"):
    """The labels a map holds, 0 (the background) left out: sorted int64.

    One counting pass for labels up to 2**22, a sort otherwise. A lazy (Dask) array is
    counted chunk by chunk: one chunk in memory at a time, never the whole map.

    Raises
    ------
    VolumeEVMError
        For what :func:`checked_labels` refuses.
    """
    array = checked_labels(array, source)
    if is_lazy(array):
        found = [labels_present(np.asarray(array.blocks[index]), source)
                 for index in np.ndindex(*array.numblocks)]
        return np.unique(np.concatenate(found))
    hi = int(array.max())
    if hi < _LOOKUP_RANGE:
        values = np.flatnonzero(_present(array, hi + 1))
    else:
        values = np.unique(array).astype(np.int64)
    return values[values != 0]


def layered_regions(maps, labels=None, *, source="array"):
    """:func:`label_regions` of label maps that hold different labels of one grid (a
    segmentation's layers), merged: one sweep per map.

    Parameters
    ----------
    maps : sequence of (X, Y, Z) ndarray of int
        The label maps; a label may appear in one of them only.
    labels, source
        As for :func:`label_regions`.

    Returns
    -------
    dict
        ``label -> (keys, voxel_count)``, as :func:`label_regions` gives it.

    Raises
    ------
    VolumeEVMError
        As :func:`label_regions`, or if the maps differ in shape or share a label.

    Warns
    -----
    UserWarning
        Naming the wanted labels that have no voxel in any map.
    """
    if len(maps) == 1:
        return label_regions(maps[0], labels, source=source)
    if len({np.shape(m) for m in maps}) > 1:
        raise VolumeEVMError(f"{source}: the layers of a label map must share one shape")
    wanted = wanted_labels(labels)
    merged = {}
    for number, array in enumerate(maps):
        present = labels_present(array, f"{source}: layer {number}")
        if wanted is not None:
            present = np.intersect1d(present, wanted)
        if len(present) == 0:
            continue
        shared = sorted(set(present.tolist()) & set(merged))
        if shared:
            raise VolumeEVMError(f"{source}: labels {shared} are in more than one layer")
        merged.update(swept_labels(array, present, source=f"{source}: layer {number}"))
    warn_missing(wanted, merged, source)
    return dict(sorted(merged.items()))
