"""Plane sweeps over sorted extreme vertices, evaluated for all planes at once with NumPy.

The EVM algorithms of the report sweep the planes of vertices one by one: the section after plane
``i`` is ``S_i = S_{i-1} xor plv_i``, an operation on sections one dimension down gives the result's
section, and the result's plane is ``plv = S_prev xor S_cur``. A Python loop over planes (and over
lines inside each plane) is slow, so this module evaluates the same recurrences for every plane
at once:

- The section valid on slab ``i`` holds the point ``(b, c)`` exactly when an odd number of the
  vertices on the line ``(., b, c)`` lie at or before plane ``i``. Pairing the sorted vertices of
  each line (its *brinks*) gives the slabs each point belongs to, so all sections come out of one
  sort and one ``np.repeat`` (:func:`sections`).
- Sections are lower-dimensional EVMs tagged with their slab index (a *group*); the recursion goes
  down to 1-D, where inside/outside is a running parity (:func:`combine_1d`).
- Going back up, a result section on slab ``[c_j, c_{j+1})`` contributes its points at both ends;
  the XOR (odd multiplicity) of all contributions is ``plv = S_prev xor S_cur`` for every plane
  (:func:`extrude`).

Points are packed into int64 *keys* so that sorting keys sorts points lexicographically: each
coordinate takes :data:`BITS` bits (offset to be non-negative) and a group id takes the bits above
them. A d-dimensional key with group ``g`` is ``g, c1, ..., cd`` from the most significant bits down.
"""

import numpy as np

BITS = 21
OFFSET = 1 << (BITS - 1)
MASK = (1 << BITS) - 1
LIMIT = OFFSET
"""Coordinates must lie in ``[-LIMIT, LIMIT)``: one million lattice steps each way."""

OPERATIONS = {
    "union": lambda a, b: a | b,
    "intersection": lambda a, b: a & b,
    "difference": lambda a, b: a & (1 - b),
    "xor": lambda a, b: a ^ b,
    "reverse difference": lambda a, b: b & (1 - a),
}


def pack(coords, group=None):
    """Pack integer points ``(n, d)`` (and an optional group id per point) into int64 keys."""
    coords = np.asarray(coords, dtype=np.int64)
    keys = np.zeros(len(coords), np.int64) if group is None else np.array(group, np.int64)
    for j in range(coords.shape[1]):
        keys <<= BITS
        keys |= coords[:, j] + OFFSET
    return keys


def unpack(keys, d):
    """Inverse of :func:`pack`: ``(group, coords (n, d))``."""
    keys = np.array(keys, dtype=np.int64)
    coords = np.empty((len(keys), d), np.int64)
    for j in range(d - 1, -1, -1):
        coords[:, j] = (keys & MASK) - OFFSET
        keys >>= BITS
    return keys, coords


def coordinate(keys, d, j):
    """Coordinate ``j`` (0-based) of d-dimensional keys, without unpacking the others."""
    return ((keys >> (BITS * (d - 1 - j))) & MASK) - OFFSET


def unique_sorted(keys):
    """Distinct values of an already sorted array (no sort; ``np.unique`` would sort again)."""
    if keys.size < 2:
        return keys
    return keys[np.r_[True, keys[1:] != keys[:-1]]]


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


def xor(a, b):
    """Symmetric difference of two sorted key sets (the EVM of the regularized XOR)."""
    if a.size == 0:
        return b
    if b.size == 0:
        return a
    return parity(np.concatenate([a, b]), runs=True)


def leading(keys, d):
    """The ``(group, first coordinate)`` part of d-dimensional keys, as 1-D grouped keys."""
    return keys >> (BITS * (d - 1))


def sections(keys, d, slabs):
    """Sections of grouped d-D EVMs on the given slabs, for all slabs at once.

    Parameters
    ----------
    keys : (n,) int64
        Sorted keys of grouped d-dimensional EVMs (d >= 2).
    slabs : (m,) int64
        Sorted, unique ``(group, first coordinate)`` keys (see :func:`leading`) that include every
        plane of ``keys``; slab ``j`` runs from ``slabs[j]`` to ``slabs[j + 1]`` in the same group.

    Returns
    -------
    (k,) int64
        Sorted keys of grouped (d-1)-D EVMs: the section on slab ``j`` has group ``j``.
    """
    if keys.size == 0:
        return keys
    shift = BITS * (d - 1)
    rest_mask = (1 << shift) - 1
    group = keys >> (shift + BITS)
    # Re-key as (group, rest, first) so that the vertices of each line come out adjacent and in
    # order: consecutive pairs are the brinks along the first axis.
    lines = (group << (shift + BITS)) | ((keys & rest_mask) << BITS) | ((keys >> shift) & MASK)
    lines.sort()
    lo, hi = lines[0::2], lines[1::2]
    line_group = (lo >> (shift + BITS)) << BITS
    first = np.searchsorted(slabs, line_group | (lo & MASK))
    stop = np.searchsorted(slabs, line_group | (hi & MASK))
    counts = stop - first
    slab = np.repeat(first - (np.cumsum(counts) - counts), counts) + np.arange(counts.sum())
    out = (slab << shift) | np.repeat((lo >> BITS) & rest_mask, counts)
    out.sort()
    return out


def extrude(keys, d, slabs):
    """Inverse of :func:`sections`: grouped d-D EVMs from their sections on ``slabs``.

    A section on slab ``[s_j, s_{j+1})`` is the prism's cross-section; its points stand at both
    ends, and the points that cancel in pairs are the planes where consecutive sections agree.
    """
    shift = BITS * (d - 1)
    slab = keys >> shift
    rest = keys & ((1 << shift) - 1)
    # Both halves are sorted (slab starts grow with the slab index): a two-run merge.
    return parity(np.concatenate([(slabs[slab] << shift) | rest, (slabs[slab + 1] << shift) | rest]),
                  runs=True)


def combine_1d(a, b, operations):
    """Boolean operations on grouped 1-D EVMs (sorted breakpoints per group), all groups at once.

    Inside/outside of each operand is the parity of the breakpoints passed so far. Every group of
    an EVM has an even number of breakpoints, so a running count over all groups restarts at
    "outside" at each group's end, and a single cumulative sum serves every group. Returns one
    result per name in ``operations``, from a single merge of the operands.
    """
    keys = np.concatenate([a, b])
    if keys.size == 0:
        return [keys for _ in operations]
    source = np.concatenate([np.ones(a.size, np.int8), np.full(b.size, 2, np.int8)])
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    source = source[order]
    first = np.empty(keys.size, bool)
    first[0] = True
    np.not_equal(keys[1:], keys[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    toggles = np.bitwise_or.reduceat(source, starts)
    keys = keys[starts]
    inside_a = np.cumsum(toggles & 1, dtype=np.int64) & 1
    inside_b = np.cumsum(toggles >> 1, dtype=np.int64) & 1
    results = []
    for operation in operations:
        result = OPERATIONS[operation](inside_a, inside_b)
        before = np.concatenate([[0], result[:-1]])
        results.append(keys[result != before])
    return results


def merged_slabs(a, b, d):
    """The union of the planes of two grouped d-D EVMs, as sorted slab keys."""
    return unique_sorted(np.sort(np.concatenate([leading(a, d), leading(b, d)]), kind="stable"))


def boolean(a, b, d, operation):
    """Boolean operation on grouped d-D EVMs given as sorted keys.

    The sweep of the report, all planes at once: sections of both operands on the merged planes,
    the operation one dimension down on every pair of sections, and the result's planes from its
    consecutive sections.
    """
    if d == 1:
        return combine_1d(a, b, [operation])[0]
    slabs = merged_slabs(a, b, d)
    result = boolean(sections(a, d, slabs), sections(b, d, slabs), d - 1, operation)
    return extrude(result, d, slabs)


def boxes(keys, d):
    """Decompose grouped d-D EVMs into ordered, disjoint boxes.

    Slabs between the EVM's own planes, then sub-slabs between the lines of each section, down to
    runs along the last axis (the ordered union of disjoint boxes of the EVM literature).

    Returns
    -------
    group : (n,) int64
        The group of each box.
    lo, hi : (n, d) int64
        Box corners, ``lo`` inclusive and ``hi`` exclusive, ordered lexicographically.
    """
    levels = []
    for level in range(d, 1, -1):
        slabs = unique_sorted(leading(keys, level))
        levels.append(slabs)
        keys = sections(keys, level, slabs)
    group = keys[0::2] >> BITS
    lo = [(keys[0::2] & MASK) - OFFSET]
    hi = [(keys[1::2] & MASK) - OFFSET]
    for slabs in reversed(levels):
        lo.insert(0, (slabs[group] & MASK) - OFFSET)
        hi.insert(0, (slabs[group + 1] & MASK) - OFFSET)
        group = slabs[group] >> BITS
    return group, np.stack(lo, axis=1), np.stack(hi, axis=1)
