"""Plane sweeps over sorted extreme vertices, as compiled kernels (:mod:`.._jit`).

The EVM algorithms of the report sweep the planes of vertices one by one: the section after plane
``i`` is ``S_i = S_{i-1} xor plv_i``, an operation on sections one dimension down gives the result's
section, and the result's plane is ``plv = S_prev xor S_cur``. The kernels here do exactly that,
plane by plane and, inside a section, line by line: sorted point sets merged in linear time
(:func:`xor_into`), a line's points toggling the breakpoints of its row, the 1-D section
(:func:`toggle_line`), and a running parity along a row for inside and outside. On that:
Booleans (:func:`boolean`), the ordered disjoint boxes (:func:`boxes`) and the faces' area
(:func:`plane_area`); the mesh (:mod:`._mesh`) and the clip (:mod:`._evm`) sweep the same way.

Points are packed into int64 *keys* so that sorting keys sorts points lexicographically: each
coordinate takes :data:`BITS` bits (offset to be non-negative), the first from the most
significant bits down. Keys in another axis order come from :func:`radix_sort`, linear in the
number of keys.
"""

import numpy as np

from .._jit import kernel

BITS = 21
OFFSET = 1 << (BITS - 1)
MASK = (1 << BITS) - 1
LIMIT = OFFSET
"""Coordinates must lie in ``[-LIMIT, LIMIT)``: one million lattice steps each way."""

def pack(coords):
    """Pack integer points ``(n, d)`` into int64 keys."""
    coords = np.asarray(coords, dtype=np.int64)
    keys = np.zeros(len(coords), np.int64)
    for j in range(coords.shape[1]):
        keys <<= BITS
        keys |= coords[:, j] + OFFSET
    return keys


def unpack(keys, d):
    """Inverse of :func:`pack`: the points ``(n, d)``."""
    coords = np.empty((len(keys), d), np.int64)
    for j in range(d):
        coords[:, j] = ((keys >> (BITS * (d - 1 - j))) & MASK) - OFFSET
    return coords


@kernel
def radix_sort(keys, lowest, count):
    """Sort packed keys by ``count`` of their coordinates, from the ``lowest``-th counted from
    the least significant (0 is the last coordinate): ``(0, 3)`` sorts 3-D keys fully.

    A stable LSD radix sort: one counting pass per coordinate over the range of values it
    spans, linear in ``len(keys)`` plus that range, where ``np.sort`` compares ``log n`` times
    per key. A coordinate spanning far more values than there are keys (a few vertices far
    apart) is sorted by a stable merge sort instead. Returns ``(sorted keys, position of each
    in keys)``.
    """
    n = len(keys)
    index = np.arange(n)
    if n == 0:
        return keys, index
    out_keys = np.empty(n, np.int64)
    out_index = np.empty(n, np.int64)
    for d in range(count):
        shift = (lowest + d) * BITS
        lo = MASK
        hi = 0
        for key in keys:
            lo = min(lo, (key >> shift) & MASK)
            hi = max(hi, (key >> shift) & MASK)
        if hi - lo > 4 * n + 1024:
            order = np.argsort((keys >> shift) & MASK, kind="mergesort")
            out_keys[:] = keys[order]
            out_index[:] = index[order]
        else:
            place = np.zeros(hi - lo + 2, np.int64)
            for key in keys:
                place[((key >> shift) & MASK) - lo + 1] += 1
            for value in range(hi - lo + 1):
                place[value + 1] += place[value]
            for i in range(n):
                value = ((keys[i] >> shift) & MASK) - lo
                out_keys[place[value]] = keys[i]
                out_index[place[value]] = index[i]
                place[value] += 1
        keys, out_keys = out_keys, keys
        index, out_index = out_index, index
    return keys, index


def unique_inverse(keys):
    """``(distinct sorted values, index of each key's value)``, by one argsort."""
    order = np.argsort(keys)
    ordered = keys[order]
    first = np.r_[True, ordered[1:] != ordered[:-1]] if keys.size else np.zeros(0, bool)
    inverse = np.empty(keys.size, np.int64)
    inverse[order] = np.cumsum(first) - 1
    return ordered[first], inverse


def parity(keys, runs=False):
    """The keys that occur an odd number of times, sorted: XOR of point multisets.

    ``runs=True`` says ``keys`` is a concatenation of a few sorted runs, which a stable sort
    merges in linear time.
    """
    keys = np.sort(keys, kind="stable" if runs else None)
    if keys.size < 2:
        return keys
    first = np.empty(keys.size, bool)
    first[0] = True
    np.not_equal(keys[1:], keys[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    counts = np.diff(np.append(starts, keys.size))
    return keys[starts[(counts & 1) == 1]]


@kernel
def xor_into(a, length, b, start, stop, mask, out):
    """``out = a[:length] xor (b[start:stop] & mask)`` for sorted sets (a linear merge in
    which a key found in both cancels); returns its length. ``out`` has room for both."""
    i = 0
    j = start
    n = 0
    while i < length or j < stop:
        if j == stop or (i < length and a[i] < b[j] & mask):
            out[n] = a[i]
            i += 1
        elif i == length or b[j] & mask < a[i]:
            out[n] = b[j] & mask
            j += 1
        else:
            i += 1
            j += 1
            continue
        n += 1
    return n


@kernel
def same_end(keys, start, stop, shift):
    """The first index from ``start`` (at most ``stop``) whose key differs from ``keys[start]``
    in the bits from ``shift`` up: the end of its plane (``shift = 2 * BITS``) or line."""
    j = start
    while j < stop and keys[j] >> shift == keys[start] >> shift:
        j += 1
    return j


@kernel
def with_room(out, count, more):
    """``out`` with room for ``more`` rows after its first ``count`` (doubled when short)."""
    if count + more <= len(out):
        return out
    grown = np.empty((2 * (count + more),) + out.shape[1:], out.dtype)
    grown[:count] = out[:count]
    return grown


@kernel
def _xor(a, b):
    out = np.empty(len(a) + len(b), np.int64)
    return out[:xor_into(a, len(a), b, 0, len(b), np.int64(-1), out)]


def xor(a, b):
    """Symmetric difference of two sorted key sets (the EVM of the regularized XOR)."""
    if a.size == 0:
        return b
    if b.size == 0:
        return a
    return _xor(a, b)


TRUTH_TABLES = {"union": 0b1110, "intersection": 0b1000, "difference": 0b0100, "xor": 0b0110,
                "reverse difference": 0b0010}
"""Each operation as a truth table: bit ``2 * in_a + in_b`` says whether a point is in the
result."""


@kernel
def toggle_line(section, count, start, line, row, length, scratch):
    """Toggle the breakpoints ``row[:length]`` by the points of ``section[start:count]`` on
    ``line`` (the 2-D keys' first coordinate; none if the next point is on another line);
    returns the index past them and the row's new length. ``scratch`` has room for the row."""
    stop = start
    while stop < count and section[stop] >> BITS == line:
        stop += 1
    if stop > start:
        length = xor_into(row, length, section, start, stop, MASK, scratch)
        row[:length] = scratch[:length]
    return stop, length


@kernel
def combine_rows(a, length_a, b, length_b, table, out):
    """The breakpoints of ``table`` applied to two 1-D EVMs (sorted breakpoints); returns the
    count written to ``out``."""
    i = 0
    j = 0
    inside = 0
    in_a = 0
    in_b = 0
    n = 0
    while i < length_a or j < length_b:
        c = a[i] if j == length_b or (i < length_a and a[i] < b[j]) else b[j]
        if i < length_a and a[i] == c:
            in_a ^= 1
            i += 1
        if j < length_b and b[j] == c:
            in_b ^= 1
            j += 1
        now = (table >> (2 * in_a + in_b)) & 1
        if now != inside:
            out[n] = c
            n += 1
            inside = now
    return n


@kernel
def _combine_sections(a, count_a, b, count_b, table, out):
    """The 2-D EVM (sorted ``(B, C)`` keys) of ``table`` applied to two 2-D EVMs, by a sweep of
    their lines: each line's rows (1-D sections) combine in 1-D, and the result's points on a
    line are the change of its row there. Returns ``(out, count)``; ``out`` grows as needed."""
    size = count_a + count_b + 2
    row_a, row_b = np.empty(size, np.int64), np.empty(size, np.int64)
    row, previous, scratch = (np.empty(size, np.int64), np.empty(size, np.int64),
                              np.empty(size, np.int64))
    length_a = 0
    length_b = 0
    length_previous = 0
    n = 0
    i = 0
    j = 0
    while i < count_a or j < count_b:
        line = a[i] >> BITS if j == count_b or (i < count_a and a[i] < b[j]) else b[j] >> BITS
        i, length_a = toggle_line(a, count_a, i, line, row_a, length_a, scratch)
        j, length_b = toggle_line(b, count_b, j, line, row_b, length_b, scratch)
        length = combine_rows(row_a, length_a, row_b, length_b, table, row)
        changed = xor_into(previous, length_previous, row, 0, length, MASK, scratch)
        out = with_room(out, n, changed)
        for k in range(changed):
            out[n + k] = (line << BITS) | scratch[k]
        n += changed
        previous[:length] = row[:length]
        length_previous = length
    return out, n


@kernel
def boolean(a, b, table):
    """A Boolean operation (its :data:`TRUTH_TABLES` entry) on two EVMs given as sorted 3-D
    keys: the sweep of the report. Plane by plane both sections advance by their planes'
    points, the operation applies to them in 2-D, and the result's points on the plane are the
    change of its section there. Returns the result's sorted keys."""
    plane_bits = 2 * BITS
    plane_mask = (np.int64(1) << plane_bits) - 1
    section_a, section_b = np.empty(len(a) + 1, np.int64), np.empty(len(b) + 1, np.int64)
    scratch = np.empty(len(a) + len(b) + 1, np.int64)
    result = np.empty(len(a) + len(b) + 16, np.int64)
    previous = np.empty_like(result)
    changes = np.empty_like(result)
    out = np.empty(len(a) + len(b) + 16, np.int64)
    count_a = 0
    count_b = 0
    length_previous = 0
    n = 0
    i = 0
    j = 0
    while i < len(a) or j < len(b):
        plane = (a[i] >> plane_bits if j == len(b) or (i < len(a) and a[i] < b[j])
                 else b[j] >> plane_bits)
        if i < len(a) and a[i] >> plane_bits == plane:
            stop = same_end(a, i, len(a), plane_bits)
            count_a = xor_into(section_a, count_a, a, i, stop, plane_mask, scratch)
            section_a[:count_a] = scratch[:count_a]
            i = stop
        if j < len(b) and b[j] >> plane_bits == plane:
            stop = same_end(b, j, len(b), plane_bits)
            count_b = xor_into(section_b, count_b, b, j, stop, plane_mask, scratch)
            section_b[:count_b] = scratch[:count_b]
            j = stop
        result, length = _combine_sections(section_a, count_a, section_b, count_b, table, result)
        changes = with_room(changes, 0, length + length_previous)
        changed = xor_into(previous, length_previous, result, 0, length, plane_mask, changes)
        out = with_room(out, n, changed)
        for k in range(changed):
            out[n + k] = (plane << plane_bits) | changes[k]
        n += changed
        previous = with_room(previous, 0, length)
        previous[:length] = result[:length]
        length_previous = length
    return out[:n].copy()


@kernel
def _boxes_into(keys, lo, hi):
    """Write the ordered boxes of :func:`boxes` to ``lo`` and ``hi`` as far as they have room
    (offset coordinates); returns how many boxes there are."""
    plane_bits = 2 * BITS
    plane_mask = (np.int64(1) << plane_bits) - 1
    # Working arrays grow with the largest section, not with all the vertices.
    section, scratch = np.empty(64, np.int64), np.empty(64, np.int64)
    row, row_scratch = np.empty(64, np.int64), np.empty(64, np.int64)
    count = 0
    m = 0
    i = 0
    while i < len(keys):
        a = keys[i] >> plane_bits
        j = same_end(keys, i, len(keys), plane_bits)
        section = with_room(section, m, j - i)
        scratch = with_room(scratch, 0, m + j - i)
        m = xor_into(section, m, keys, i, j, plane_mask, scratch)
        section[:m] = scratch[:m]
        row = with_room(row, 0, m)
        row_scratch = with_room(row_scratch, 0, m)
        i = j
        length = 0
        p = 0
        while p < m:  # empty after the last plane
            b = section[p] >> BITS
            p, length = toggle_line(section, m, p, b, row, length, row_scratch)
            for k in range(0, length, 2):
                if count < len(lo):
                    lo[count, 0], lo[count, 1], lo[count, 2] = a, b, row[k]
                    hi[count, 0], hi[count, 2] = keys[i] >> plane_bits, row[k + 1]
                    hi[count, 1] = section[p] >> BITS
                count += 1
    return count


def boxes(keys):
    """Decompose an EVM (sorted 3-D keys) into ordered, disjoint boxes.

    Slabs between the EVM's own planes, then sub-slabs between the lines of each slab's
    section, down to runs along the last axis (the ordered union of disjoint boxes of the EVM
    literature), in one sweep; a first sweep counts them, so that the result is all the memory
    it takes.

    Returns
    -------
    lo, hi : (n, 3) int64
        Box corners (lattice coordinates, in the keys' axis order), ``lo`` inclusive and ``hi``
        exclusive, ordered lexicographically.
    """
    count = _boxes_into(keys, np.empty((0, 3), np.int64), np.empty((0, 3), np.int64))
    lo, hi = np.empty((count, 3), np.int64), np.empty((count, 3), np.int64)
    _boxes_into(keys, lo, hi)
    lo -= OFFSET
    hi -= OFFSET
    return lo, hi


@kernel
def plane_area(keys):
    """The total area of the planes' 2-D EVMs (sorted 3-D keys read plane by plane): by a sweep
    of each plane's lines, the length of its row (1-D section) times the distance to the next."""
    row, scratch = np.empty(len(keys) + 1, np.int64), np.empty(len(keys) + 1, np.int64)
    total = 0
    i = 0
    while i < len(keys):
        j = same_end(keys, i, len(keys), 2 * BITS)
        length = 0
        p = i
        while p < j:
            line = keys[p] >> BITS
            p, length = toggle_line(keys, j, p, line, row, length, scratch)
            if p < j:
                for k in range(0, length, 2):
                    total += (row[k + 1] - row[k]) * ((keys[p] >> BITS) - line)
        i = j
    return total


@kernel
def key_bounds(keys):
    """The smallest and largest offset coordinates of 3-D keys, per axis (one pass, where a
    NumPy reduction along the short axis of the vertices is slow)."""
    lo = np.full(3, MASK)
    hi = np.zeros(3, np.int64)
    for key in keys:
        for axis in range(3):
            value = (key >> ((2 - axis) * BITS)) & MASK
            lo[axis] = min(lo[axis], value)
            hi[axis] = max(hi[axis], value)
    return lo, hi
