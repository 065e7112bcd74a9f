"""Label maps: the region of every label of an integer volume, in one sweep of the array.

A label map (0 = background) partitions the grid, and each label ``L`` is the band
``[L, L]``: its EVM holds the lattice points around which an odd number of the 8 cells carry
``L``. One compiled pass over the lattice finds every label's vertices at once (most points sit
inside one label and are passed over after a single comparison of their 8 cells), so a map of
100 labels costs about one ordinary build, not 100. Two labels that touch bound the same
lattice faces: their meshes share those faces exactly (no gap, no overlap).
"""

import warnings

import numpy as np

from .._errors import VolumeEVMError
from .._jit import kernel, parallel_map
from .._memory import check_memory
from . import _sweep

MAX_LABELS = 1 << 16
"""The most labels one map may hold (65536): more is a density volume, not a segmentation."""

_LOOKUP_RANGE = 1 << 22
"""Label values above this are renumbered by sorting first (the lookup table would be large)."""

_BLOCK_VOXELS = 1 << 21
"""Voxels per block of x-slices one thread sweeps."""


@kernel
def _label_block(labels, ids, first, stop, n_ids, ox, oy, oz):
    """Every label's extreme vertices on the lattice planes ``x = first .. stop - 1``.

    ``labels`` is the ``(X, Y, Z)`` map, ``ids[value]`` a label's number (0 .. n_ids - 1)
    or -1 for the background and the labels not asked for. Returns the vertices' label numbers
    and packed keys (plane by plane, each plane in key order, so every label's keys come out
    sorted), and the voxel count of each label over the slices ``first .. stop - 1`` inside the
    grid.

    The two slices around a plane are copied into planes with a ring of zeros (the background
    outside the grid) and compared as they are; only a lattice point whose 8 cells are not all
    the same value looks its labels up and counts them.
    """
    nx, ny, nz = labels.shape
    before = np.zeros((ny + 2, nz + 2), labels.dtype)
    after = np.zeros((ny + 2, nz + 2), labels.dtype)
    counts = np.zeros(n_ids, np.int64)
    cells = np.empty(8, np.int64)  # the 8 values around a point
    numbers = np.empty(8, np.int32)  # the label numbers with an odd count there
    out_ids = np.empty(1024, np.int32)
    out_keys = np.empty(1024, np.int64)
    n = 0
    if first > 0:
        before[1:ny + 1, 1:nz + 1] = labels[first - 1]
    for x in range(first, stop):
        if x < nx:
            for y in range(ny):
                run_value, run = labels[x, y, 0], 0  # counted by runs: an increment per voxel
                for z in range(nz):                  # would wait on the one before it
                    value = labels[x, y, z]
                    after[y + 1, z + 1] = value
                    if value != run_value:
                        if ids[run_value] >= 0:
                            counts[ids[run_value]] += run
                        run_value, run = value, 0
                    run += 1
                if ids[run_value] >= 0:
                    counts[ids[run_value]] += run
        else:
            after[:, :] = 0
        plane = np.int64(x + ox) << (2 * _sweep.BITS)
        for y in range(ny + 1):
            row = plane | (np.int64(y + oy) << _sweep.BITS)
            # A row whose every column of 4 cells is one value has no vertex (two such columns
            # hold 8 of one value or 4 and 4): a pass without branches finds most of them.
            mixed = False
            for z in range(nz + 2):
                value = before[y, z]
                mixed |= ((before[y + 1, z] != value) | (after[y, z] != value)
                          | (after[y + 1, z] != value))
            if not mixed:
                continue
            # Column z of the point's 4 rows is uniform when its 4 cells agree; a point is inside
            # one label when its two columns are uniform with the same value.
            left = before[y, 0]
            left_uniform = (before[y + 1, 0] == left and after[y, 0] == left
                            and after[y + 1, 0] == left)
            for z in range(nz + 1):
                value = before[y, z + 1]
                uniform = (before[y + 1, z + 1] == value and after[y, z + 1] == value
                           and after[y + 1, z + 1] == value)
                same = uniform and left_uniform and value == left
                left, left_uniform = value, uniform
                if same:
                    continue  # inside one label (or the background): 8 cells, even
                cells[0], cells[1] = before[y, z], before[y, z + 1]
                cells[2], cells[3] = before[y + 1, z], before[y + 1, z + 1]
                cells[4], cells[5] = after[y, z], after[y, z + 1]
                cells[6], cells[7] = after[y + 1, z], after[y + 1, z + 1]
                # Most such points lie between two values: each then has the parity of the
                # first one's count (the counts sum to 8).
                first_value, other, count = cells[0], -1, 0
                for i in range(8):
                    if cells[i] == first_value:
                        count += 1
                    elif other < 0:
                        other = cells[i]
                    elif cells[i] != other:
                        count = -1
                        break
                if count > 0:
                    if count % 2 == 0:
                        continue
                    numbers[0], numbers[1], found = ids[first_value], ids[other], 2
                else:
                    found = 0
                    for i in range(8):
                        if cells[i] < 0:
                            continue
                        count = 1
                        for j in range(i + 1, 8):
                            if cells[j] == cells[i]:
                                count += 1
                                cells[j] = -1  # counted: not a value of its own again
                        if count % 2 == 1:
                            numbers[found] = ids[cells[i]]
                            found += 1
                for i in range(found):
                    if numbers[i] < 0:
                        continue
                    if n == len(out_keys):
                        grown_ids = np.empty(2 * n, np.int32)
                        grown_keys = np.empty(2 * n, np.int64)
                        grown_ids[:n] = out_ids[:n]
                        grown_keys[:n] = out_keys[:n]
                        out_ids, out_keys = grown_ids, grown_keys
                    out_ids[n] = numbers[i]
                    out_keys[n] = row | (z + oz)
                    n += 1
        before, after = after, before
    return out_ids[:n].copy(), out_keys[:n].copy(), counts


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
def _group(ids, keys, starts):
    """``keys`` grouped by label number, each group keeping its order (a counting sort);
    ``starts[i]`` is where label ``i``'s group begins (and is moved on while filling)."""
    out = np.empty_like(keys)
    fill = starts.copy()
    for i in range(len(keys)):
        out[fill[ids[i]]] = keys[i]
        fill[ids[i]] += 1
    return out


def checked_labels(array, source):
    """The label map as a 3-D integer ndarray, refused unless it is one.

    Raises
    ------
    VolumeEVMError
        For anything but a 3-D, non-empty array of non-negative integers, naming ``source``:
        floating-point labels (cast whole-numbered floats with ``array.astype(np.int32)``),
        booleans (a mask: :meth:`EVM.from_mask`) and negative labels.
    """
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
    if array.dtype.kind == "i" and int(array.min()) < 0:
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
    array = checked_labels(array, source)
    wanted = _wanted(labels)
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
    # Vertices are not known before the sweep: check what it keeps per slice and per label.
    check_memory(2 * 4 * (ny + 2) * (nz + 2) + 12 * len(ids), "sweeping the label map",
                 source=source, advice="pick fewer labels with labels=, or crop the volume")
    step = max(1, _BLOCK_VOXELS // max(1, ny * nz))
    blocks = parallel_map(_label_block, [(array, ids, x, min(x + step, nx + 1), len(candidates),
                                          _sweep.OFFSET, _sweep.OFFSET, _sweep.OFFSET)
                                         for x in range(0, nx + 1, step)])
    vertex_ids = np.concatenate([b[0] for b in blocks])
    keys = np.concatenate([b[1] for b in blocks])
    counts = np.sum([b[2] for b in blocks], axis=0)
    del blocks
    if wanted is not None:
        missing = np.setdiff1d(wanted, candidates[counts > 0])
        if len(missing):
            warnings.warn(f"{source}: labels {missing.tolist()} have no voxels", UserWarning,
                          stacklevel=3)
    starts = np.concatenate([[0], np.cumsum(np.bincount(vertex_ids, minlength=len(candidates)))])
    grouped = _group(vertex_ids, keys, starts.astype(np.int64))
    return {int(label): (grouped[starts[i]:starts[i + 1]].copy(), int(counts[i]))
            for i, label in enumerate(candidates) if counts[i] > 0}


def _wanted(labels):
    """The labels asked for as sorted unique int64 (None: all)."""
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


def labels_present(array, source="array"):
    """The labels a map holds, 0 (the background) left out: sorted int64.

    One counting pass for labels up to 2**22, a sort otherwise.

    Raises
    ------
    VolumeEVMError
        For what :func:`checked_labels` refuses.
    """
    array = checked_labels(array, source)
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
    wanted = _wanted(labels)
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
        merged.update(label_regions(array, present, source=f"{source}: layer {number}"))
    if wanted is not None:
        missing = sorted(set(wanted.tolist()) - set(merged))
        if missing:
            warnings.warn(f"{source}: labels {missing} have no voxels", UserWarning, stacklevel=3)
    return dict(sorted(merged.items()))
