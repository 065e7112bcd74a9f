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

