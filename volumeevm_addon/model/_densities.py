"""The relation v: voxel -> index in a densities table, computed from the EVM alone.

A densities table lists the region's voxels slice by slice along a principal axis A, and inside
a slice line by line (B), then along the line (C) — the table orders are "xyz", "yxz" and "zxy"
(:data:`TABLE_ORDERS`). The report's formula locates a voxel ``(a, b, c)`` without storing any
per-voxel data:

    index = Base_i + (a - a_i) |S_i| + Base_ij + (b - b_ij) L_ij + before_k + (c - c_k)

with slab ``i`` (the section ``S_i`` holds for ``a_i <= a < a_{i+1}``, area ``|S_i|``), sub-slab
``j`` of that section (every line ``b_ij <= b < b_i(j+1)`` has the same runs, total length
``L_ij``), and the run ``k`` of that line that holds ``c``. The slabs, sub-slabs and runs are
the ordered boxes of the EVM (:func:`._sweep.boxes`).
"""

import numpy as np

from .._jit import kernel, parallel_map
from . import _sweep

TABLE_ORDERS = ("xyz", "yxz", "zxy")
"""Traversal order of the densities table for principal axis 0, 1, 2."""


def _exclusive_cumsum(values):
    out = np.zeros(len(values), np.int64)
    np.cumsum(values[:-1], out=out[1:])
    return out


def _within_group(totals, group):
    """Exclusive running sums of ``totals`` restarted at each new value of sorted ``group``."""
    before = _exclusive_cumsum(totals)
    first = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
    return before - np.repeat(before[first], np.diff(np.r_[first, len(group)]))


class TableIndex:
    """Voxel -> table index for one traversal order, from the boxes of the EVM."""

    def __init__(self, evm, order):
        self.order = order
        self.axes = ["xyz".index(a) for a in order]
        lo, hi = (corner[:, self.axes] for corner in evm.boxes(order))
        self.size = int(np.prod(hi - lo, axis=1).sum())
        if self.size == 0:
            return
        length = hi[:, 2] - lo[:, 2]

        slab_first = np.flatnonzero(np.r_[True, lo[1:, 0] != lo[:-1, 0]])
        self.slab_lo = lo[slab_first, 0]
        self.slab_hi = hi[slab_first, 0]
        slab = np.repeat(np.arange(len(slab_first)), np.diff(np.r_[slab_first, len(lo)]))

        sub_first = np.flatnonzero(np.r_[True, (slab[1:] != slab[:-1]) | (lo[1:, 1] != lo[:-1, 1])])
        sub_count = np.diff(np.r_[sub_first, len(lo)])
        sub = np.repeat(np.arange(len(sub_first)), sub_count)
        self.sub_lo = lo[sub_first, 1]
        self.sub_hi = hi[sub_first, 1]
        self.sub_slab = slab[sub_first]
        self.sub_keys = (self.sub_slab << _sweep.BITS) | (self.sub_lo + _sweep.OFFSET)
        self.line_length = np.add.reduceat(length, sub_first)
        rows = (self.sub_hi - self.sub_lo) * self.line_length

        self.slab_area = np.bincount(self.sub_slab, weights=rows, minlength=len(slab_first))
        self.slab_area = self.slab_area.astype(np.int64)
        self.slab_base = _exclusive_cumsum((self.slab_hi - self.slab_lo) * self.slab_area)
        self.sub_base = _within_group(rows, self.sub_slab)

        self.run_keys = (sub << _sweep.BITS) | (lo[:, 2] + _sweep.OFFSET)
        self.run_sub = sub
        self.run_lo = lo[:, 2]
        self.run_hi = hi[:, 2]
        self.run_before = _within_group(length, sub)

    def __call__(self, voxels):
        """Table indices of ``voxels`` (m, 3) given as x, y, z; -1 for voxels outside."""
        v = np.asarray(voxels, dtype=np.int64).reshape(-1, 3)[:, self.axes]
        a, b, c = v[:, 0], v[:, 1], v[:, 2]
        out = np.full(len(v), -1, np.int64)
        if self.size == 0:
            return out
        i = np.searchsorted(self.slab_lo, a, side="right") - 1
        ok = (i >= 0) & (a < self.slab_hi[np.maximum(i, 0)])
        i = np.maximum(i, 0)
        j = np.searchsorted(self.sub_keys, (i << _sweep.BITS) | (b + _sweep.OFFSET),
                            side="right") - 1
        jj = np.maximum(j, 0)
        ok &= (j >= 0) & (self.sub_slab[jj] == i) & (b >= self.sub_lo[jj]) & (b < self.sub_hi[jj])
        k = np.searchsorted(self.run_keys, (jj << _sweep.BITS) | (c + _sweep.OFFSET),
                            side="right") - 1
        kk = np.maximum(k, 0)
        ok &= (k >= 0) & (self.run_sub[kk] == jj) & (c >= self.run_lo[kk]) & (c < self.run_hi[kk])
        index = (
            self.slab_base[i]
            + (a - self.slab_lo[i]) * self.slab_area[i]
            + self.sub_base[jj]
            + (b - self.sub_lo[jj]) * self.line_length[jj]
            + self.run_before[kk]
            + (c - self.run_lo[kk])
        )
        out[ok] = index[ok]
        return out


# ------------------------------------------------------------------- runs and other orders
@kernel
def scanline_runs(lo, hi, slices, lines):
    """The region's runs per scanline from the EVM's ordered boxes, in a table's order.

    ``lo``, ``hi`` (m, 3): the boxes of :meth:`EVM.boxes` in the table order, columns
    permuted to (slice, scanline, column): slabs of boxes sharing a slice range, split in
    sub-slabs sharing a scanline range, split in runs. The table lists each slice's voxels
    scanline by scanline, each scanline run by run, so a running count gives every run's
    position. Returns ``(starts, run_lo, run_hi, pos)``: scanline ``a`` of slice ``s`` has
    the runs ``starts[s·lines + a] .. starts[s·lines + a + 1] - 1``, run ``r`` covers the
    columns ``run_lo[r] .. run_hi[r] - 1`` and its first voxel is ``pos[r]`` in the table.
    """
    m = lo.shape[0]
    starts = np.zeros(slices * lines + 1, np.int64)
    for k in range(m):
        for s in range(lo[k, 0], hi[k, 0]):
            for a in range(lo[k, 1], hi[k, 1]):
                starts[s * lines + a + 1] += 1
    for line in range(slices * lines):
        starts[line + 1] += starts[line]
    total = starts[slices * lines]
    run_lo = np.empty(total, np.int32)
    run_hi = np.empty(total, np.int32)
    pos = np.empty(total, np.int64)
    fill = starts[:-1].copy()
    at = 0
    k = 0
    while k < m:
        slab = k
        while slab < m and lo[slab, 0] == lo[k, 0] and hi[slab, 0] == hi[k, 0]:
            slab += 1
        for s in range(lo[k, 0], hi[k, 0]):
            u = k
            while u < slab:
                v = u
                while v < slab and lo[v, 1] == lo[u, 1] and hi[v, 1] == hi[u, 1]:
                    v += 1
                for a in range(lo[u, 1], hi[u, 1]):
                    w = fill[s * lines + a]
                    for r in range(u, v):
                        run_lo[w] = lo[r, 2]
                        run_hi[w] = hi[r, 2]
                        pos[w] = at
                        at += hi[r, 2] - lo[r, 2]
                        w += 1
                    fill[s * lines + a] = w
                u = v
        k = slab
    return starts, run_lo, run_hi, pos


def run_count(evm, order):
    """How many runs the scanlines of ``order`` hold (:func:`scanline_runs`): each ordered box
    adds one per (slice, scanline) it spans. From the boxes alone, for memory estimates."""
    lo, hi = evm.boxes(order)
    a, b = "xyz".index(order[0]), "xyz".index(order[1])
    return int(np.sum((hi[:, a] - lo[:, a]) * (hi[:, b] - lo[:, b])))


_SLAB_SLICES = 16
"""Slices of the other order per task of :func:`reordered_table` (cut by size, not threads)."""


def reordered_table(evm, table, shape, axis, out=None):
    """``table`` (the densities in the order ``TABLE_ORDERS[0]``, or any per-voxel values)
    listed in the order of ``axis`` (1 or 2), into ``out`` when given, without a grid: memory
    is the new table and the scanline runs.

    The runs of the stored order are read scanline ``(x, y)`` by scanline; slabs of the other
    order's slices (y for "yxz", z for "zxy") are filled in parallel, each voxel going to its
    slice's cursor, which visits x then y then z as the other order lists them."""
    nx, ny, nz = (int(n) for n in shape)
    lo, hi = (np.ascontiguousarray(corner, dtype=np.int64) for corner in evm.boxes("xyz"))
    starts, run_lo, run_hi, pos = scanline_runs(lo, hi, nx, ny)
    slices = (ny, nz)[axis - 1]
    base = np.zeros(slices + 1, np.int64)
    np.cumsum(_slice_counts(starts, run_lo, run_hi, ny, slices, axis), out=base[1:])
    out = np.empty_like(table) if out is None else out
    parallel_map(lambda s0: _fill_slices(starts, run_lo, run_hi, pos, table, base, s0,
                                         min(s0 + _SLAB_SLICES, slices), nx, ny, axis, out),
                 [(s0,) for s0 in range(0, slices, _SLAB_SLICES)])
    return out


@kernel
def _slice_counts(starts, run_lo, run_hi, lines, slices, axis):
    """Region voxels per slice of the order of ``axis``: per y (1) or per z (2)."""
    counts = np.zeros(slices, np.int64)
    for line in range(starts.size - 1):
        for r in range(starts[line], starts[line + 1]):
            if axis == 1:
                counts[line % lines] += run_hi[r] - run_lo[r]
            else:
                for z in range(run_lo[r], run_hi[r]):
                    counts[z] += 1
    return counts


@kernel
def _fill_slices(starts, run_lo, run_hi, pos, table, base, s0, s1, nx, ny, axis, out):
    """Slices ``s0 .. s1 - 1`` of the order of ``axis`` into ``out``, from the stored order's
    runs: scanlines (x, y) in x, y order, so each slice receives its voxels in its own order."""
    cursor = base[s0:s1].copy()
    for x in range(nx):
        for y in range(s0 if axis == 1 else 0, s1 if axis == 1 else ny):
            line = x * ny + y
            for r in range(starts[line], starts[line + 1]):
                if axis == 1:  # "yxz": the scanline is a line of slice y
                    at = cursor[y - s0]
                    for i in range(run_hi[r] - run_lo[r]):
                        out[at + i] = table[pos[r] + i]
                    cursor[y - s0] = at + run_hi[r] - run_lo[r]
                else:  # "zxy": each voxel of the scanline in slice z is next in line x
                    for z in range(max(run_lo[r], s0), min(run_hi[r], s1)):
                        out[cursor[z - s0]] = table[pos[r] + z - run_lo[r]]
                        cursor[z - s0] += 1
