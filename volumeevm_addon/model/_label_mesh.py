"""The boundary meshes of several regions of one grid (a label set), made together so that
where two regions touch, their meshes carry the same polygons with opposite orientations.

Each region's own mesh (:mod:`._mesh`) merges its unit faces into rectangles by itself, so a
rectangle of one label can span its contact with a second label and faces beside it, and the
second label's mesh cuts the contact differently. Here every unit face of the grid's planes gets
a *signature*: the regions whose boundary it is, each with its side (``+A`` where the region
ends on the plane, ``-A`` where it starts). For a label map that is ``{p+}`` or ``{p-}`` against
the background and ``{p+, q-}`` between labels ``p`` and ``q``. The faces are merged into
rectangles as in :mod:`._mesh`, by one sweep of all regions at once, but only faces of one
signature together: along each line the maximal runs of one signature, a run recurring with
the same extent and signature on the next line extending its rectangle. Every rectangle then
belongs to each region of its signature, with that region's orientation: the decomposition of a
contact depends on the faces of that contact alone, and is the one rectangle set seen from both
sides.

T-junctions are closed as in :mod:`._mesh`, with one vertex set for all regions: the corners of
every region's rectangles. Each edge takes every such vertex strictly inside it, so two meshes'
copies of a contact rectangle have the same vertices (each mesh keeps only the vertices its
loops use), and each mesh is closed as before: both faces at an edge take the same vertices.

A single region gets exactly its own mesh (:func:`._mesh.boundary_mesh`), array for array: its
signatures are ``+A`` and ``-A`` alone, the faces where it ends and where it starts.

Tagged keys. The sweep keeps all regions' 2-D sections in one sorted set of points ``(B, C,
tag)``, packed like a 3-D key, where the tag is the region's number; a line's row (1-D
section) holds ``(C, tag)`` breakpoints, packed like a 2-D key.
"""

import numpy as np

from .._errors import VolumeEVMError
from .._jit import kernel, parallel_map
from . import _sweep
from ._mesh import (
    _AXES,
    _BLOCK_RECTANGLES,
    _BLOCK_VERTICES,
    _BYTES_PER_RECTANGLE,
    _CYCLIC,
    _MESH_OVERHEAD,
    Polygons,
    _check_memory,
    _corner_keys,
    _lines,
    _loops,
    _vertices_of,
)

_MAX_REGIONS = 1 << _sweep.BITS
"""Tags take :data:`._sweep.BITS` bits: at most this many regions are meshed together."""

_TWO_D = (np.int64(1) << (2 * _sweep.BITS)) - 1
"""Mask of a tagged point's ``(C, tag)`` bits, its row breakpoint."""


@kernel
def _toggle(section, count, start, line, row, length, scratch):
    """Toggle the tagged breakpoints ``row[:length]`` by the points of ``section[start:count]``
    on ``line``; returns the index past them and the row's new length."""
    stop = start
    while stop < count and section[stop] >> (2 * _sweep.BITS) == line:
        stop += 1
    if stop > start:
        length = _sweep.xor_into(row, length, section, start, stop, _TWO_D, scratch)
        row[:length] = scratch[:length]
    return stop, length


@kernel
def _set_member(active, n_active, code, present):
    """Insert (``present``) or remove ``code`` in the sorted ``active[:n_active]``; returns
    the new count."""
    k = 0
    while k < n_active and active[k] < code:
        k += 1
    if present:
        for m in range(n_active, k, -1):
            active[m] = active[m - 1]
        active[k] = code
        return n_active + 1
    for m in range(k, n_active - 1):
        active[m] = active[m + 1]
    return n_active - 1


@kernel
def _same_members(members_a, start_a, length_a, members_b, start_b, length_b):
    """Whether two signatures (slices of member arrays) are equal."""
    if length_a != length_b:
        return False
    for k in range(length_a):
        if members_a[start_a + k] != members_b[start_b + k]:
            return False
    return True


@kernel
def _signature_runs(before, n_before, after, n_after, state, active, runs, members):
    """The face runs of one line: its rows before and after the plane (tagged breakpoints) cut
    into maximal runs of one non-empty signature.

    A member is ``2 * tag + side``: side 0 where the region is in the row before and not after
    (it ends, outward normal +A), 1 the reverse. ``state[tag]`` (bit 0 before, bit 1 after) is
    all zero on entry and on return. Rows ``runs[k]`` are ``[lo C, hi C, first member, member
    count]``, members in ``members``; both grow. Returns ``(runs, members, run count)``.
    """
    i = 0
    j = 0
    n_active = 0
    n_runs = 0
    n_members = 0
    open_run = False
    while i < n_before or j < n_after:
        c = before[i] >> _sweep.BITS if j == n_after or (
            i < n_before and before[i] < after[j]) else after[j] >> _sweep.BITS
        changed = False
        while i < n_before or j < n_after:
            if i < n_before and j < n_after and before[i] == after[j]:
                # A breakpoint of both rows (most are: a plane changes a row in few places).
                tag = before[i] & _sweep.MASK
                if before[i] >> _sweep.BITS != c:
                    break
                if state[tag] == 0 or state[tag] == 3:  # in both rows or neither: no face
                    state[tag] ^= 3
                    i += 1
                    j += 1
                    continue
            from_before = j == n_after or (i < n_before and before[i] < after[j])
            point = before[i] if from_before else after[j]
            if point >> _sweep.BITS != c:
                break
            tag = point & _sweep.MASK
            old = state[tag]
            state[tag] ^= 1 if from_before else 2
            if old == 1 or old == 2:
                n_active = _set_member(active, n_active, 2 * tag + old - 1, False)
            if state[tag] == 1 or state[tag] == 2:
                n_active = _set_member(active, n_active, 2 * tag + state[tag] - 1, True)
            changed = True
            if from_before:
                i += 1
            else:
                j += 1
        if not changed or (open_run and _same_members(members, runs[n_runs - 1, 2],
                                                      runs[n_runs - 1, 3], active, 0, n_active)):
            continue
        if open_run:
            runs[n_runs - 1, 1] = c
            open_run = False
        if n_active > 0:
            runs = _sweep.with_room(runs, n_runs, 1)
            members = _sweep.with_room(members, n_members, n_active)
            runs[n_runs, 0], runs[n_runs, 2], runs[n_runs, 3] = c, n_members, n_active
            members[n_members:n_members + n_active] = active[:n_active]
            n_members += n_active
            n_runs += 1
            open_run = True
    return runs, members, n_runs


@kernel
def _close(found, n_found, rectangles, n_rectangles, members, start, length, a, first_b, b,
           lo_c, hi_c):
    """Append the rectangle ``[A, first B, B, lo C, hi C]`` to ``rectangles``, and once per
    member of its signature as rows ``[member, A, lo B, hi B, lo C, hi C, rectangle]`` to
    ``found``; returns both and their counts."""
    rectangles = _sweep.with_room(rectangles, n_rectangles, 1)
    rectangles[n_rectangles, 0], rectangles[n_rectangles, 1] = a, first_b
    rectangles[n_rectangles, 2], rectangles[n_rectangles, 3] = b, lo_c
    rectangles[n_rectangles, 4] = hi_c
    found = _sweep.with_room(found, n_found, length)
    for k in range(length):
        found[n_found, 0] = members[start + k]
        found[n_found, 1:6] = rectangles[n_rectangles]
        found[n_found, 6] = n_rectangles
        n_found += 1
    return found, n_found, rectangles, n_rectangles + 1


@kernel
def _plane_rectangles(keys, tags, start, stop, section, n_tags):
    """The rectangles of every region on the planes of ``keys[start:stop]`` (whole planes of
    the regions' sorted keys, ``tags`` their regions), from the tagged section before them.

    Plane by plane as :func:`._mesh._plane_rectangles`: the section after is ``before xor
    plane``, a sweep of both sections' lines keeps their rows, each line's signature runs come
    from :func:`_signature_runs`, and a run with the same C range and signature as an open
    rectangle extends it (else that one closes). ``keys`` are sorted by plane only (a plane's
    points are sorted here). Returns the rectangles, rows ``[A, lo B, hi B, lo C, hi C]``
    (offset coordinates), and rows ``[member, A, lo B, hi B, lo C, hi C, rectangle]``, one per
    member of each one's signature.
    """
    plane_mask = (np.int64(1) << (2 * _sweep.BITS)) - 1
    size = len(section) + stop - start + 2
    before = np.empty(size, np.int64)
    before[:len(section)] = section
    n_before = len(section)
    after = np.empty(size, np.int64)
    points = np.empty(size, np.int64)
    row_before = np.empty(size, np.int64)
    row_after = np.empty(size, np.int64)
    scratch = np.empty(size, np.int64)
    state = np.zeros(n_tags, np.int8)
    active = np.empty(n_tags * 2 + 1, np.int64)
    runs = np.empty((64, 4), np.int64)
    members = np.empty(64, np.int64)
    open_rows = np.empty((64, 5), np.int64)  # [lo C, hi C, first B, first member, count]
    open_members = np.empty(64, np.int64)
    following = np.empty((64, 5), np.int64)
    following_members = np.empty(64, np.int64)
    found = np.empty((64, 7), np.int64)
    n_found = 0
    rectangles = np.empty((64, 5), np.int64)
    n_rectangles = 0
    i = start
    while i < stop:
        a = keys[i] >> (2 * _sweep.BITS)
        j = i
        while j < stop and keys[j] >> (2 * _sweep.BITS) == a:
            points[j - i] = ((keys[j] & plane_mask) << _sweep.BITS) | tags[j]
            j += 1
        points[:j - i] = np.sort(points[:j - i])
        n_after = _sweep.xor_into(before, n_before, points, 0, j - i, np.int64(-1), after)
        length_before = 0
        length_after = 0
        n_open = 0
        p = 0
        q = 0
        while p < n_before or q < n_after:
            if q == n_after or (p < n_before and before[p] < after[q]):
                b = before[p] >> (2 * _sweep.BITS)
            else:
                b = after[q] >> (2 * _sweep.BITS)
            p, length_before = _toggle(before, n_before, p, b, row_before, length_before, scratch)
            q, length_after = _toggle(after, n_after, q, b, row_after, length_after, scratch)
            runs, members, n_runs = _signature_runs(row_before, length_before, row_after,
                                                    length_after, state, active, runs, members)
            # Open rectangles meet this line's runs, both sorted by lo C and disjoint.
            following = _sweep.with_room(following, 0, n_open + n_runs)
            n_next = 0
            n_next_members = 0
            o = 0
            r = 0
            while o < n_open or r < n_runs:
                if (o < n_open and r < n_runs and open_rows[o, 0] == runs[r, 0]
                        and open_rows[o, 1] == runs[r, 1]
                        and _same_members(open_members, open_rows[o, 3], open_rows[o, 4],
                                          members, runs[r, 2], runs[r, 3])):
                    following[n_next, 2] = open_rows[o, 2]
                    o += 1
                elif r == n_runs or (o < n_open and open_rows[o, 0] <= runs[r, 0]):
                    found, n_found, rectangles, n_rectangles = _close(
                        found, n_found, rectangles, n_rectangles, open_members, open_rows[o, 3],
                        open_rows[o, 4], a, open_rows[o, 2], b, open_rows[o, 0], open_rows[o, 1])
                    o += 1
                    continue
                else:
                    following[n_next, 2] = b
                following[n_next, 0], following[n_next, 1] = runs[r, 0], runs[r, 1]
                following_members = _sweep.with_room(following_members, n_next_members, runs[r, 3])
                following[n_next, 3], following[n_next, 4] = n_next_members, runs[r, 3]
                for k in range(runs[r, 3]):
                    following_members[n_next_members + k] = members[runs[r, 2] + k]
                n_next_members += runs[r, 3]
                n_next += 1
                r += 1
            open_rows, following = following, open_rows
            open_members, following_members = following_members, open_members
            n_open = n_next
        before, after = after, before
        n_before = n_after
        i = j
    return rectangles[:n_rectangles].copy(), found[:n_found].copy()


@kernel
def _section_after(keys, tags, start, stop, section):
    """The tagged 2-D section after the planes of ``keys[start:stop]``."""
    plane_mask = (np.int64(1) << (2 * _sweep.BITS)) - 1
    current = np.empty(len(section) + stop - start, np.int64)
    current[:len(section)] = section
    n = len(section)
    scratch = np.empty_like(current)
    points = np.empty(stop - start, np.int64)
    i = start
    while i < stop:
        j = i
        while j < stop and keys[j] >> (2 * _sweep.BITS) == keys[i] >> (2 * _sweep.BITS):
            points[j - i] = ((keys[j] & plane_mask) << _sweep.BITS) | tags[j]
            j += 1
        points[:j - i] = np.sort(points[:j - i])
        n = _sweep.xor_into(current, n, points, 0, j - i, np.int64(-1), scratch)
        current, scratch = scratch, current
        i = j
    return current[:n].copy()


def _tagged_keys(evms, order):
    """All regions' keys in the cyclic ``order``, sorted by plane (one counting pass), and each
    key's region."""
    keys = [evm.keys(order) for evm in evms]
    tags = np.repeat(np.arange(len(evms), dtype=np.int64), [len(k) for k in keys])
    ordered, index = _sweep.radix_sort(np.concatenate(keys), 2, 1)
    return ordered, tags[index]


def _blocks(evms, order):
    """The tasks of :func:`_plane_rectangles` for one axis order: blocks of whole planes of
    about :data:`._mesh._BLOCK_VERTICES` vertices, each with the tagged section before it."""
    keys, tags = _tagged_keys(evms, order)
    if len(keys) == 0:
        return []
    plane_starts = np.flatnonzero(np.r_[True, np.diff(keys >> (2 * _sweep.BITS)) != 0])
    first_planes = np.unique(np.searchsorted(plane_starts,
                                             np.arange(0, len(keys), _BLOCK_VERTICES)))
    cuts = plane_starts[first_planes[first_planes < len(plane_starts)]].tolist() + [len(keys)]
    sections = [np.zeros(0, np.int64)]
    for start, stop in zip(cuts[:-2], cuts[1:-1]):
        sections.append(_section_after(keys, tags, start, stop, sections[-1]))
    return [(keys, tags, start, stop, section, len(evms))
            for start, stop, section in zip(cuts, cuts[1:], sections)]


@kernel
def _by_member(rows, n_members):
    """Rows ``[member, A, lo B, hi B, lo C, hi C, rectangle]`` (plane by plane) grouped by
    member, each group ordered by plane, lo C, hi C, lo B as :func:`._mesh._ordered` orders a
    region's own; returns their rectangle column in that order and where each member's group
    starts."""
    starts = np.zeros(n_members + 1, np.int64)
    for r in range(len(rows)):
        starts[rows[r, 0] + 1] += 1
    for m in range(n_members):
        starts[m + 1] += starts[m]
    grouped = np.empty(len(rows), np.int64)
    fill = starts[:-1].copy()
    for r in range(len(rows)):  # a counting sort keeps each member's rows plane by plane
        grouped[fill[rows[r, 0]]] = r
        fill[rows[r, 0]] += 1
    out = np.empty(len(rows), np.int64)
    first = 0
    while first < len(rows):  # then each member's plane by lo C, hi C, lo B
        row = rows[grouped[first]]
        last = first
        while (last < len(rows) and rows[grouped[last], 0] == row[0]
               and rows[grouped[last], 1] == row[1]):
            last += 1
        keys = np.empty(last - first, np.int64)
        for k in range(first, last):
            r = rows[grouped[k]]
            keys[k - first] = (((r[4] << _sweep.BITS) | r[5]) << _sweep.BITS) | r[2]
        order = _sweep.radix_sort(keys, 0, 3)[1]
        for k in range(last - first):
            out[first + k] = rows[grouped[first + order[k]], 6]
        first = last
    return out, starts


def _sweeps(evms):
    """The rectangles of all regions, per axis (x, y, z): the distinct rectangles, rows
    ``[A, lo B, hi B, lo C, hi C]``, and each region's, as indices into them in :mod:`._mesh`'s
    order (where the region ends, then where it starts, each by plane, lo C, hi C, lo B):
    ``(rectangles, members)``, ``members[m]`` those of member ``2 * region + side``."""
    tasks = [_blocks(evms, order) for order in _CYCLIC]
    found = iter(parallel_map(_plane_rectangles, [task for axis in tasks for task in axis]))
    axes, count = [], 0
    for order, axis in zip(_CYCLIC, tasks):
        blocks = [next(found) for _ in axis]
        offsets = np.cumsum([0] + [len(block[0]) for block in blocks])
        rows = np.concatenate([block[1] + np.array([0, 0, 0, 0, 0, 0, offset])  # global numbers
                               for block, offset in zip(blocks, offsets)]
                              or [np.zeros((0, 7), np.int64)])
        count += len(rows)
        _check_memory(_BYTES_PER_RECTANGLE * count + _MESH_OVERHEAD,
                      f"{len(rows)} face runs of {len(evms)} regions perpendicular to axis "
                      f"{order[0]}")
        rectangles = np.concatenate([block[0] for block in blocks] or [np.zeros((0, 5), np.int64)])
        index, starts = _by_member(rows, 2 * len(evms))
        axes.append((rectangles, [index[starts[m]:starts[m + 1]] for m in range(2 * len(evms))]))
    return axes


@kernel
def _compacted(loops, stamp, local, number):
    """The vertices a region's ``loops`` use (global indices, sorted) and the loops in them.

    ``stamp`` and ``local`` are scratch arrays of a slot per global vertex, shared by the
    regions: a vertex is new to region ``number`` when its stamp is not ``number`` yet.
    """
    used = np.empty(len(loops), np.int64)
    n = 0
    for v in loops:
        if stamp[v] != number:
            stamp[v] = number
            used[n] = v
            n += 1
    used = np.sort(used[:n])
    for k in range(n):
        local[used[k]] = k
    out = np.empty(len(loops), np.int32)
    for k in range(len(loops)):
        out[k] = local[loops[k]]
    return used, out


def label_meshes(evms):
    """The closed, outward boundary meshes of regions of one grid, agreeing where they touch.

    Parameters
    ----------
    evms : sequence of EVM
        The regions (disjoint for a label map; they may overlap).

    Returns
    -------
    list of (vertices, polygons)
        Per region, as :func:`._mesh.boundary_mesh` gives them: lattice points sorted in x, y, z
        order, and rectangles with the vertices on their edges inserted, ordered per axis
        where the region ends, then where it starts, each by plane, lo C, hi C, lo B. Where two
        regions share faces, their polygons there are the same, with opposite orientations.

    Raises
    ------
    VolumeEVMError
        When the meshes would need more memory than is available.
    """
    if len(evms) > _MAX_REGIONS:
        raise VolumeEVMError(f"regions: at most {_MAX_REGIONS} are meshed together")
    axes = _sweeps(evms)
    corners = np.concatenate([_corner_keys(rectangles, _AXES[axis], False)
                              for axis, (rectangles, _) in enumerate(axes)])
    empty = np.zeros(0, np.int32)
    if len(corners) == 0:
        return [(np.zeros((0, 3)), Polygons(empty, empty, empty)) for _ in evms]
    keys, corner_vertex = _vertices_of(corners)
    corner_vertex = corner_vertex.reshape(-1, 4)
    offsets = np.cumsum([0] + [len(rectangles) for rectangles, _ in axes])
    order, rank = _lines(keys)
    # Each region's rectangles in its six groups, their corners in its loop order: the
    # distinct rectangle's, reversed where the region starts (the opposite orientation).
    loop_corners, tasks, owners, first = [], [], [], 0
    for number in range(len(evms)):
        for axis, (_, members) in enumerate(axes):
            for side in (0, 1):
                rectangles = members[2 * number + side] + offsets[axis]
                loop_corners.append(corner_vertex[rectangles, ::-1] if side else
                                    corner_vertex[rectangles])
                end = first + len(rectangles)
                for start in range(first, end, _BLOCK_RECTANGLES):
                    tasks.append((start, min(start + _BLOCK_RECTANGLES, end), _AXES[axis]))
                    owners.append(number)
                first = end
    loop_corners = np.concatenate(loop_corners).ravel()
    blocks = parallel_map(_loops, [(loop_corners, start, stop, axes_[1], axes_[2], order, rank)
                                   for start, stop, axes_ in tasks])
    stamp, local = np.full(len(keys), -1, np.int64), np.empty(len(keys), np.int32)
    meshes = []
    for number in range(len(evms)):
        mine = [block for block, owner in zip(blocks, owners) if owner == number]
        if not mine:
            meshes.append((np.zeros((0, 3)), Polygons(empty, empty, empty)))
            continue
        loops = np.concatenate([block[0] for block in mine])
        sizes = np.concatenate([block[1] for block in mine])
        used, indices = _compacted(loops, stamp, local, number)
        starts = (np.cumsum(sizes, dtype=np.int64) - sizes).astype(np.int32)
        meshes.append((_sweep.unpack(keys[used], 3).astype(np.float64),
                       Polygons(indices, starts, sizes)))
    return meshes
