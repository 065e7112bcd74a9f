"""Face-connected components of an EVM: each one's extreme vertices.

The region is cut into its ordered boxes (slabs, sub-slabs, runs). Two boxes are face-adjacent
when they touch across a plane with a common area: consecutive sub-slabs of one slab, or boxes of
consecutive slabs, whose runs overlap. Within a slab the sub-slabs are sorted and disjoint, and
within a sub-slab the runs are, so every overlap is a contiguous range found by binary search.
Labels then spread along adjacencies (min-label hooking with pointer jumping), and each
component's EVM is the XOR of its boxes' corners.
"""

import numpy as np

from . import _sweep


def _pairs(first, stop):
    """All ``(n, m)`` with ``first[n] <= m < stop[n]``, as two arrays."""
    counts = np.maximum(stop - first, 0)
    n = np.repeat(np.arange(len(first)), counts)
    m = np.repeat(first - (np.cumsum(counts) - counts), counts) + np.arange(counts.sum())
    return n, m


def _overlapping(keys_lo, keys_hi, group, lo, hi):
    """For intervals ``[lo, hi)`` in ``group``, the range of sorted, disjoint intervals (given by
    their packed ``(group, lo)`` and ``(group, hi)`` keys) that overlap each with a positive
    length."""
    first = np.searchsorted(keys_hi, (group << _sweep.BITS) | (lo + _sweep.OFFSET), side="right")
    stop = np.searchsorted(keys_lo, (group << _sweep.BITS) | (hi + _sweep.OFFSET), side="left")
    return first, stop


def face_components(evm):
    """Face-connected components of ``evm``, largest volume first: each one's packed vertex keys
    (sorted), from which :meth:`EVM.components` makes its EVM."""
    lo, hi = evm.boxes()
    if len(lo) == 0:
        return []
    # Sub-slabs: boxes of one slab (same x range) and one y range, runs along z.
    sub_start = np.flatnonzero(np.r_[True, (lo[1:, 0] != lo[:-1, 0]) | (lo[1:, 1] != lo[:-1, 1])])
    sub_stop = np.r_[sub_start[1:], len(lo)]
    sub = np.repeat(np.arange(len(sub_start)), sub_stop - sub_start)
    slab_x = lo[sub_start, 0]
    slab_start = np.flatnonzero(np.r_[True, slab_x[1:] != slab_x[:-1]])
    slab = np.repeat(np.arange(len(slab_start)), np.diff(np.r_[slab_start, len(sub_start)]))
    slab_lo, slab_hi = lo[sub_start[slab_start], 0], hi[sub_start[slab_start], 0]
    sub_lo, sub_hi = lo[sub_start, 1], hi[sub_start, 1]
    sub_keys_lo = (slab << _sweep.BITS) | (sub_lo + _sweep.OFFSET)
    sub_keys_hi = (slab << _sweep.BITS) | (sub_hi + _sweep.OFFSET)
    run_keys_lo = (sub << _sweep.BITS) | (lo[:, 2] + _sweep.OFFSET)
    run_keys_hi = (sub << _sweep.BITS) | (hi[:, 2] + _sweep.OFFSET)

    # Sub-slab pairs that share area across a plane: the next sub-slab of the same slab when the
    # y ranges touch, and the sub-slabs of the next slab (touching in x) whose y ranges overlap.
    touching = (slab[1:] == slab[:-1]) & (sub_hi[:-1] == sub_lo[1:])
    s_same = np.flatnonzero(touching)
    t_same = s_same + 1
    next_slab = slab + 1
    has_next = next_slab < len(slab_start)
    has_next[has_next] &= slab_lo[next_slab[has_next]] == slab_hi[slab[has_next]]
    candidates = np.flatnonzero(has_next)
    first, stop = _overlapping(sub_keys_lo, sub_keys_hi, next_slab[candidates],
                               sub_lo[candidates], sub_hi[candidates])
    n, t_next = _pairs(first, stop)
    s = np.concatenate([s_same, candidates[n]])
    t = np.concatenate([t_same, t_next])

    # Run pairs of each sub-slab pair whose z ranges overlap.
    n, r = _pairs(sub_start[s], sub_stop[s])
    first, stop = _overlapping(run_keys_lo, run_keys_hi, t[n], lo[r, 2], hi[r, 2])
    n, q = _pairs(first, stop)
    u, v = r[n], q

    labels = _connect(len(lo), u, v)
    component = _sweep.unique_inverse(labels)[1]
    sizes = np.bincount(component, weights=np.prod(hi - lo, axis=1))
    rank = np.empty(len(sizes), np.int64)
    rank[np.argsort(-sizes, kind="stable")] = np.arange(len(sizes))
    component = rank[component]

    # Each component's vertices: XOR of its boxes' corners, all components at once.
    corners = np.concatenate([np.where([sx, sy, sz], hi, lo)
                              for sx in (0, 1) for sy in (0, 1) for sz in (0, 1)])
    owner = np.tile(component, 8)
    keys = _sweep.pack(corners)
    order = np.lexsort((keys, owner))
    keys, owner = keys[order], owner[order]
    first = np.flatnonzero(np.r_[True, (keys[1:] != keys[:-1]) | (owner[1:] != owner[:-1])])
    odd = (np.diff(np.r_[first, len(keys)]) & 1) == 1
    keys, owner = keys[first[odd]], owner[first[odd]]
    cuts = np.flatnonzero(np.diff(owner)) + 1
    return np.split(keys, cuts)


def _connect(n, u, v):
    """Connected-component labels of ``n`` nodes with edges ``(u, v)``: the smallest node of
    each."""
    labels = np.arange(n)
    while True:
        low = np.minimum(labels[u], labels[v])
        hooked = labels.copy()
        np.minimum.at(hooked, labels[u], low)
        np.minimum.at(hooked, labels[v], low)
        while True:
            jumped = hooked[hooked]
            if np.array_equal(jumped, hooked):
                break
            hooked = jumped
        if np.array_equal(hooked, labels):
            return labels
        labels = hooked
