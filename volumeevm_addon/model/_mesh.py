"""The boundary of an EVM as a closed, outward polygon mesh with merged faces.

Faces perpendicular to axis A lie in the planes of vertices. With ``S_{i-1}`` and ``S_i`` the
sections before and after plane ``i``, ``S_{i-1} - S_i`` is where the solid ends (outward normal
+A) and ``S_i - S_{i-1}`` where it starts (normal -A). Both are cut into rectangles: along each
line in B their runs along the last axis C, and a run that recurs unchanged on the next lines
extends its rectangle, so one rectangle covers many unit voxel faces. Faces perpendicular to B
and C come from the same sweep on the vertices sorted with B or C first.

The sweeps, the vertices' de-duplication and the loops are compiled kernels (:mod:`.._jit`):
plain loops over sorted keys, linear but for a radix sort by coordinates. Blocks of planes and
of rectangles run on parallel threads; each block's output is joined in order, so the mesh is the
same whatever the thread count.

Rectangles of neighbouring faces are cut at different places, so a corner of one can lie inside
an edge of another (a T-junction). Every such vertex is inserted into the edge it lies on, which
makes the faces n-gons (rectangles with extra collinear vertices) and the mesh closed: each
directed edge ``u -> v`` is matched by exactly one ``v -> u`` per pair of faces that share it.

Non-manifold configurations of the region come out as follows. Where two voxels touch only along
an edge, four faces share that mesh edge (two directed each way), so the mesh stays closed and
consistently oriented but that edge is non-manifold. Where voxels touch only at a point, the
faces of both sheets share that vertex. Nothing is duplicated or split apart to hide these: the
mesh is the exact boundary of the voxel region, and Blender shows such edges and vertices as
non-manifold (Select > Select All by Trait > Non Manifold). :mod:`._manifold` splits them, for
3D printing.

Memory is checked (:func:`volumeevm_addon.system.check_memory`) after each axis's sweep, whose own
working set is a few arrays the size of its vertices: the rectangles found so far give the peak
of making the polygon mesh from them, :data:`_BYTES_PER_RECTANGLE` each (a measured peak,
docs/measurements.md): faces, not vertices, are what the mesh costs.
"""

from dataclasses import dataclass

import numpy as np

from .._jit import kernel, parallel_map
from .._memory import check_memory
from . import _sweep

# Cyclic axis orders "ABC" with e_B x e_C = +e_A, so (B, C) counter-clockwise faces +A.
_CYCLIC = ("xyz", "yzx", "zxy")
_AXES = np.array([["xyz".index(a) for a in order] for order in _CYCLIC])
"""The x, y, z axes of A, B and C in each cyclic order."""

_ENDS = _sweep.TRUTH_TABLES["difference"]
"""Where the solid ends on a plane: in the section before it, not in the one after."""
_STARTS = _sweep.TRUTH_TABLES["reverse difference"]
"""Where it starts: in the section after the plane, not in the one before."""

_BLOCK_VERTICES = 1 << 14
"""Vertices per block of planes swept by one thread."""
_BLOCK_RECTANGLES = 1 << 14
"""Rectangles per block of loops made by one thread."""

_BYTES_PER_RECTANGLE = 250
"""Peak per rectangle of the polygon mesh: rectangle rows, corner keys and their radix sort,
vertex orders along lines, loops (about 4.6 loops per rectangle)."""
_MESH_OVERHEAD = 1 << 20
"""Fixed part of the mesh's working set (small regions)."""
_ADVICE = "build the VolumeEVM with a higher threshold, crop it (clip) or mesh a coarser level"


def _check_memory(needed, what):
    check_memory(needed, f"making the boundary mesh ({what})", source="mesh", advice=_ADVICE)


@dataclass(frozen=True)
class Polygons:
    """Polygon faces of a mesh as flat loops (Blender's layout).

    Blender's ``Mesh.loops``/``polygons`` take these arrays as they are (``foreach_set``),
    with no Python loop per face. ``len(polygons)`` is the number of faces; iterating gives
    each face's vertex indices.

    Attributes
    ----------
    indices : (L,) ndarray of int
        The vertex index of every loop; polygon ``p`` is
        ``indices[starts[p] : starts[p] + sizes[p]]``, counter-clockwise seen from outside.
    starts : (P,) ndarray of int
        Each polygon's first loop.
    sizes : (P,) ndarray of int
        Each polygon's number of loops (corners).
    """

    indices: np.ndarray
    starts: np.ndarray
    sizes: np.ndarray

    def __len__(self):
        return len(self.sizes)

    def __iter__(self):
        return iter(np.split(self.indices, self.starts[1:]))

    def edges(self):
        """Directed edges of every loop, from each corner to the next.

        Returns
        -------
        u, v : (L,) ndarray
            Edge ``i`` runs from vertex ``u[i]`` to vertex ``v[i]``; in a closed mesh every
            edge appears once each way.
        """
        following = np.arange(1, len(self.indices) + 1)
        last = self.starts + self.sizes - 1
        following[last] = self.starts
        return self.indices, self.indices[following]

    def unique_edges(self):
        """Each undirected edge once, with each loop corner's edge (as Blender stores them).

        :meth:`BoundaryMesh.edges` gives the same for its own mesh without sorting; this is
        for any polygons (the manifold mesh's).

        Returns
        -------
        edges : (E, 2) ndarray of np.int32
            The two vertices of every edge, lower index first, sorted.
        corner_edges : (L,) ndarray of np.int32
            The edge from loop corner ``i`` to the next corner of its polygon.
        """
        u, v = self.edges()
        keys = (np.minimum(u, v).astype(np.int64) << 32) | np.maximum(u, v)
        unique, corner_edges = np.unique(keys, return_inverse=True)
        edges = np.stack([unique >> 32, unique & 0xFFFFFFFF], axis=1).astype(np.int32)
        return edges, corner_edges.reshape(-1).astype(np.int32)


@kernel
def _advance(open_runs, n_open, runs, n_runs, a, b, found, n_found, following):
    """Carry the runs open before line ``b`` on to the runs from ``b`` (sorted, disjoint: run
    ``k`` is ``[runs[2k], runs[2k + 1])``).

    ``open_runs`` rows are ``[lo C, hi C, first B]``. A run with the same C range continues its
    rectangle; the other open runs close at ``b`` (appended to ``found`` as rows ``[A, lo B,
    hi B, lo C, hi C]``; it has room for all) and the other new runs open at ``b``. The next
    open runs are made in ``following`` and copied back to ``open_runs``. Returns the counts of
    found and open rows.
    """
    i = 0
    j = 0
    n = 0
    while i < n_open or j < n_runs:
        if (i < n_open and j < n_runs and open_runs[i, 0] == runs[2 * j]
                and open_runs[i, 1] == runs[2 * j + 1]):
            following[n, 2] = open_runs[i, 2]
            i += 1
        elif j == n_runs or (i < n_open and open_runs[i, 0] <= runs[2 * j]):
            found[n_found, 0] = a
            found[n_found, 1] = open_runs[i, 2]
            found[n_found, 2] = b
            found[n_found, 3] = open_runs[i, 0]
            found[n_found, 4] = open_runs[i, 1]
            n_found += 1
            i += 1
            continue
        else:
            following[n, 2] = b
        following[n, 0] = runs[2 * j]
        following[n, 1] = runs[2 * j + 1]
        n += 1
        j += 1
    for k in range(n):
        open_runs[k, 0], open_runs[k, 1], open_runs[k, 2] = (following[k, 0], following[k, 1],
                                                              following[k, 2])
    return n_found, n


@kernel
def _ordered(found, count):
    """The first ``count`` rectangle rows, which come plane by plane, ordered in each plane by
    lo C, hi C and lo B (a radix sort of those three packed as a key)."""
    out = np.empty((count, 5), np.int64)
    start = 0
    while start < count:
        stop = start
        while stop < count and found[stop, 0] == found[start, 0]:
            stop += 1
        rows = found[start:stop]
        keys = (((rows[:, 3] << _sweep.BITS) | rows[:, 4]) << _sweep.BITS) | rows[:, 1]
        order = _sweep.radix_sort(keys, 0, 3)[1]
        for k in range(stop - start):
            out[start + k] = found[start + order[k]]
        start = stop
    return out


@kernel
def _plane_rectangles(keys, start, stop, section):
    """The face rectangles on the planes of ``keys[start:stop]`` (whole planes of sorted keys).

    ``section`` is the 2-D section before the first of them (sorted packed ``(B, C)`` keys).
    Plane by plane, the section after it is ``before xor plane``; a sweep of both sections'
    lines in B keeps the rows (1-D sections along C) of both, whose differences are the face
    runs from that line on. A run with the same C range as on the line before continues its
    rectangle, so every rectangle is a maximal run that recurs on consecutive lines.

    Returns
    -------
    ends, starts : (m, 5) int64
        Rows ``[A, lo B, hi B, lo C, hi C]`` (offset coordinates) where the solid ends (outward
        normal +A) and where it starts (-A), each ordered by plane, lo C, hi C and lo B.
    """
    plane_mask = (np.int64(1) << (2 * _sweep.BITS)) - 1
    size = len(section) + stop - start + 2  # bounds every section, row and run list
    before = np.empty(size, np.int64)
    before[:len(section)] = section
    n_before = len(section)
    after = np.empty(size, np.int64)
    row_before = np.empty(size, np.int64)
    row_after = np.empty(size, np.int64)
    scratch = np.empty(size, np.int64)
    end_runs = np.empty(size, np.int64)
    start_runs = np.empty(size, np.int64)
    open_ends = np.empty((size, 3), np.int64)
    open_starts = np.empty((size, 3), np.int64)
    following = np.empty((size, 3), np.int64)
    ends = np.empty((64, 5), np.int64)
    starts = np.empty((64, 5), np.int64)
    n_ends = 0
    n_starts = 0
    i = start
    while i < stop:
        a = keys[i] >> (2 * _sweep.BITS)
        j = i
        while j < stop and keys[j] >> (2 * _sweep.BITS) == a:
            j += 1
        n_after = _sweep.xor_into(before, n_before, keys, i, j, plane_mask, after)
        length_before = 0
        length_after = 0
        open_e = 0
        open_s = 0
        p = 0
        q = 0
        while p < n_before or q < n_after:
            # The next line of either section: its points toggle the rows' breakpoints.
            if q == n_after or (p < n_before and before[p] < after[q]):
                b = before[p] >> _sweep.BITS
            else:
                b = after[q] >> _sweep.BITS
            p, length_before = _sweep.toggle_line(before, n_before, p, b, row_before,
                                                  length_before, scratch)
            q, length_after = _sweep.toggle_line(after, n_after, q, b, row_after, length_after,
                                                 scratch)
            # The face runs from this line on: where the solid ends, and where it starts.
            runs_e = _sweep.combine_rows(row_before, length_before, row_after, length_after, _ENDS,
                                         end_runs) // 2
            runs_s = _sweep.combine_rows(row_before, length_before, row_after, length_after,
                                         _STARTS, start_runs) // 2
            if n_ends + open_e > len(ends):
                ends = _sweep.with_room(ends, n_ends, open_e)
            n_ends, open_e = _advance(open_ends, open_e, end_runs, runs_e, a, b, ends, n_ends,
                                      following)
            if n_starts + open_s > len(starts):
                starts = _sweep.with_room(starts, n_starts, open_s)
            n_starts, open_s = _advance(open_starts, open_s, start_runs, runs_s, a, b,
                                        starts, n_starts, following)
        before, after = after, before
        n_before = n_after
        i = j
    return _ordered(ends, n_ends), _ordered(starts, n_starts)


@kernel
def _section_after(keys, start, stop, section):
    """The 2-D section after the planes of ``keys[start:stop]``, from the one before them."""
    plane_mask = (np.int64(1) << (2 * _sweep.BITS)) - 1
    current = np.empty(len(section) + stop - start, np.int64)
    current[:len(section)] = section
    n = len(section)
    scratch = np.empty_like(current)
    i = start
    while i < stop:
        j = i
        while j < stop and keys[j] >> (2 * _sweep.BITS) == keys[i] >> (2 * _sweep.BITS):
            j += 1
        n = _sweep.xor_into(current, n, keys, i, j, plane_mask, scratch)
        current, scratch = scratch, current
        i = j
    return current[:n].copy()


def _blocks(keys):
    """The tasks of :func:`_plane_rectangles` for all planes of sorted 3-D ``keys``: blocks of
    whole planes of about :data:`_BLOCK_VERTICES` vertices, each with the section before it
    (carried from block to block by a first, serial pass)."""
    if len(keys) == 0:
        return []
    plane_starts = np.flatnonzero(np.r_[True, np.diff(keys >> (2 * _sweep.BITS)) != 0])
    first_planes = np.unique(np.searchsorted(plane_starts,
                                             np.arange(0, len(keys), _BLOCK_VERTICES)))
    cuts = plane_starts[first_planes[first_planes < len(plane_starts)]].tolist() + [len(keys)]
    sections = [np.zeros(0, np.int64)]
    for start, stop in zip(cuts[:-2], cuts[1:-1]):
        sections.append(_section_after(keys, start, stop, sections[-1]))
    return [(keys, start, stop, section) for start, stop, section in zip(cuts, cuts[1:], sections)]


@kernel
def _corner_keys(rectangles, axes, flip):
    """Packed x, y, z keys of the rectangles' corners, 4 per rectangle in loop order.

    ``rectangles`` rows are ``[A, lo B, hi B, lo C, hi C]`` (offset coordinates) and ``axes``
    the x, y, z axes of A, B and C. Counter-clockwise in (B, C) faces +A; ``flip`` reverses it.
    """
    shift_a, shift_b, shift_c = (2 - axes) * _sweep.BITS
    keys = np.empty(4 * len(rectangles), np.int64)
    for r in range(len(rectangles)):
        a = rectangles[r, 0] << shift_a
        lo_b, hi_b = rectangles[r, 1] << shift_b, rectangles[r, 2] << shift_b
        lo_c, hi_c = rectangles[r, 3] << shift_c, rectangles[r, 4] << shift_c
        first, step = (4 * r + 3, -1) if flip else (4 * r, 1)
        keys[first] = a | lo_b | lo_c
        keys[first + step] = a | hi_b | lo_c
        keys[first + 2 * step] = a | hi_b | hi_c
        keys[first + 3 * step] = a | lo_b | hi_c
    return keys


@kernel
def _vertices_of(corners):
    """The distinct corner keys, sorted (the mesh's vertices), and each corner's vertex."""
    keys, index = _sweep.radix_sort(corners, 0, 3)
    corner_vertex = np.empty(len(keys), np.int32)
    count = 0
    for k in range(len(keys)):
        if count == 0 or keys[k] != keys[count - 1]:
            keys[count] = keys[k]
            count += 1
        corner_vertex[index[k]] = count - 1
    return keys[:count].copy(), corner_vertex


@kernel
def _lines(vertices):
    """The sorted vertex keys along the lines parallel to each axis.

    ``order[axis]`` lists the vertices line by line, ascending along the line; ``rank[axis, v]``
    is vertex ``v``'s place in it. Along z that is the x, y, z order of the keys; a stable pass
    by z gives the (z, x, y) order, lines along y, and then one by y the (y, z, x) order.
    """
    n = len(vertices)
    order = np.empty((3, n), np.int32)
    rank = np.empty((3, n), np.int32)
    order[2] = np.arange(n)
    along_y, order[1] = _sweep.radix_sort(vertices, 0, 1)
    order[0] = order[1][_sweep.radix_sort(along_y, 1, 1)[1]]
    for axis in range(3):
        for k in range(n):
            rank[axis, order[axis, k]] = k
    return order, rank


@kernel
def _loops(corner_vertex, first, stop, axis_b, axis_c, order, rank):
    """Loops of the rectangles ``first .. stop - 1``, whose edges alternate along B and C.

    Each edge gives its start vertex, then the vertices strictly inside it (the T-junctions,
    found between its ends in the order along its line) in its direction. Returns
    ``(loops, sizes, slots)``: with each loop corner, the slot ``axis * n + k`` of the edge
    from it to the next corner, the edge along ``axis`` from the vertex at place ``k`` of that
    axis's line order to the next one (:func:`_numbered_edges` numbers them).
    """
    n = rank.shape[1]
    sizes = np.empty(stop - first, np.int32)
    total = 0
    for r in range(first, stop):
        size = 0
        for e in range(4):
            axis = axis_b if e % 2 == 0 else axis_c
            size += abs(rank[axis, corner_vertex[4 * r + (e + 1) % 4]]
                        - rank[axis, corner_vertex[4 * r + e]])
        sizes[r - first] = size
        total += size
    loops = np.empty(total, np.int32)
    slots = np.empty(total, np.int32)
    w = 0
    for r in range(first, stop):
        for e in range(4):
            axis = axis_b if e % 2 == 0 else axis_c
            here = rank[axis, corner_vertex[4 * r + e]]
            there = rank[axis, corner_vertex[4 * r + (e + 1) % 4]]
            if there > here:
                for k in range(here, there):
                    loops[w] = order[axis, k]
                    slots[w] = axis * n + k
                    w += 1
            else:
                for k in range(here, there, -1):
                    loops[w] = order[axis, k]
                    slots[w] = axis * n + k - 1
                    w += 1
    return loops, sizes, slots


@kernel
def _merge_vertices(keys, uses, added):
    """The vertex keys after some corners left (``uses`` already lowered) and ``added`` came.

    ``keys`` are the sorted vertex keys and ``uses`` their corner counts; a vertex whose count
    fell to 0 goes, a new corner key not among them comes. Returns the new sorted keys, their
    counts, each old vertex's new index (-1 if gone) and each added corner's vertex.
    """
    order_keys, order = _sweep.radix_sort(added.copy(), 0, 3)
    new_keys = np.empty(len(keys) + len(added), np.int64)
    new_uses = np.empty(len(keys) + len(added), np.int32)
    old_vertex = np.empty(len(keys), np.int32)
    added_vertex = np.empty(len(added), np.int32)
    n = 0
    i = 0
    k = 0
    while i < len(keys) or k < len(added):
        if k == len(added) or (i < len(keys) and keys[i] < order_keys[k]):
            key = keys[i]
        else:
            key = order_keys[k]
        count = 0
        if i < len(keys) and keys[i] == key:
            count = uses[i]
            old_vertex[i] = n if count > 0 or (k < len(added) and order_keys[k] == key) else -1
            i += 1
        while k < len(added) and order_keys[k] == key:
            added_vertex[order[k]] = n
            count += 1
            k += 1
        if count > 0:
            new_keys[n] = key
            new_uses[n] = count
            n += 1
    return new_keys[:n].copy(), new_uses[:n].copy(), old_vertex, added_vertex


@kernel
def _carried(came_from, values, n):
    """``values`` (a row per old vertex) moved to the new vertices ``came_from`` names, and the
    new vertices no old one became (their rows are left unset)."""
    out = np.empty((n, values.shape[1]), values.dtype)
    fresh = np.ones(n, np.bool_)
    for i in range(len(came_from)):
        if came_from[i] >= 0:
            out[came_from[i]] = values[i]
            fresh[came_from[i]] = False
    return out, np.nonzero(fresh)[0]


@kernel
def _numbered_edges(slots, order, n):
    """The edges of the used ``slots`` (see :func:`_loops`), numbered by slot: their two
    vertices, and each loop corner's edge number."""
    number = np.zeros(3 * n + 1, np.int32)
    for slot in slots:
        number[slot + 1] = 1
    for slot in range(3 * n):
        number[slot + 1] += number[slot]
    edges = np.empty((number[3 * n], 2), np.int32)
    for axis in range(3):
        for k in range(n - 1):
            slot = axis * n + k
            if number[slot + 1] != number[slot]:
                edges[number[slot], 0], edges[number[slot], 1] = order[axis, k], order[axis, k + 1]
    corner_edges = np.empty(len(slots), np.int32)
    for k in range(len(slots)):
        corner_edges[k] = number[slots[k]]
    return edges, corner_edges


def _groups(evm):
    """The face rectangles of a region, in the mesh's six groups: per axis (x, y, z) where the
    solid ends (+A), then where it starts (-A), each ordered by plane, lo C, hi C, lo B."""
    tasks = parallel_map(lambda order: _blocks(evm.keys(order)), [(order,) for order in _CYCLIC])
    found = iter(parallel_map(_plane_rectangles, [task for axis in tasks for task in axis]))
    groups, count = [], 0
    for order, axis in zip(_CYCLIC, tasks):
        blocks = [next(found) for _ in axis]
        ends, starts = (np.concatenate([block[side] for block in blocks]
                                       or [np.zeros((0, 5), np.int64)])
                        for side in (0, 1))
        groups += [ends, starts]
        count += len(ends) + len(starts)
        _check_memory(_BYTES_PER_RECTANGLE * count + _MESH_OVERHEAD,
                      f"{len(ends) + len(starts)} face runs perpendicular to axis {order[0]}")
    return groups


def _touching(rectangles, lo, hi):
    """Which rectangles ``[A, lo B, hi B, lo C, hi C]`` meet the closed box from ``lo`` to
    ``hi`` (its A, B and C coordinates) in B and C, edges and corners included."""
    return ((rectangles[:, 1] <= hi[1]) & (rectangles[:, 2] >= lo[1])
            & (rectangles[:, 3] <= hi[2]) & (rectangles[:, 4] >= lo[2]))


def _dirty_rectangles(keys, lo, hi):
    """The rectangles of the planes ``lo`` to ``hi`` (offset coordinates) of the region of
    ``keys`` (sorted in a cyclic order), as :func:`_plane_rectangles` gives them: the section
    before them swept from the first plane, then their own sweep."""
    start, stop = np.searchsorted(keys >> (2 * _sweep.BITS), (lo, hi + 1))
    return _plane_rectangles(keys, start, stop,
                             _section_after(keys, 0, start, np.zeros(0, np.int64)))


class BoundaryMesh:
    """The boundary mesh of a region, kept with what it is made of, so that the mesh of a
    region differing from it in a small box is made by :meth:`updated` without sweeping the
    whole region again.

    The mesh is the one :func:`boundary_mesh` describes. It is made of six groups of face
    rectangles (per axis, where the solid ends and where it starts), their corners' vertices
    (distinct keys, sorted, and how many corners use each) and the loops. When the region
    changes inside the cells ``lo`` to ``hi``, only the faces on the planes ``lo[A]`` to
    ``hi[A]`` of each axis A can change: those planes' rectangles are swept again (the
    vertices' keys in the other axis orders follow by a merge with the changed vertices) and
    replace the old ones; the vertices follow by a merge (the corners that left and came),
    and the loops, which take every vertex on their edges, are made again. The result equals
    the mesh made from scratch, array for array.

    Parameters
    ----------
    evm : EVM
        The region.

    Attributes
    ----------
    evm : EVM
        The region this is the mesh of.
    polygons : Polygons
        The faces, as :func:`boundary_mesh` orders them.
    came_from : (m,) ndarray of np.int32 or None
        For a mesh made by :meth:`updated`: each vertex of the mesh it was made from, its
        index here (-1 where it is gone); None for a mesh made from scratch.

    Raises
    ------
    VolumeEVMError
        When the mesh would need more memory than is available.

    Examples
    --------
    >>> import numpy as np
    >>> from volumeevm_addon import EVM
    >>> mask = np.zeros((6, 6, 6), bool); mask[1:5, 1:5, 1:5] = True
    >>> cube = BoundaryMesh(EVM.from_mask(mask))
    >>> len(cube.polygons), len(cube)  # 6 faces, 8 corners
    (6, 8)
    >>> mask[2, 2, 4] = False  # a notch in the top face
    >>> notched = cube.updated(EVM.from_mask(mask))
    >>> len(notched.polygons), notched.came_from.tolist()  # where the cube's corners went
    (14, [0, 1, 2, 3, 16, 17, 18, 19])
    >>> fresh = BoundaryMesh(EVM.from_mask(mask))
    >>> bool(np.array_equal(notched.polygons.indices, fresh.polygons.indices))
    True
    """

    def __init__(self, evm):
        self._orders = [evm.keys(order) for order in _CYCLIC]
        self.came_from = None
        groups = _groups(evm)
        if not any(len(g) for g in groups):
            self._set(evm, groups, np.zeros(0, np.int64), np.zeros(0, np.int32),
                      np.zeros(0, np.int32))
            return
        keys, corner_vertex = _vertices_of(self._corners(groups))
        uses = np.bincount(corner_vertex, minlength=len(keys)).astype(np.int32)
        self._set(evm, groups, keys, uses, corner_vertex)

    @staticmethod
    def _corners(groups):
        """The packed corner keys of the groups' rectangles, 4 per rectangle in loop order."""
        return np.concatenate([_corner_keys(rectangles, _AXES[g // 2], g % 2 == 1)
                               for g, rectangles in enumerate(groups)])

    def _set(self, evm, groups, keys, uses, corner_vertex):
        """Make the loops of the groups' rectangles from their corners' vertices."""
        self.evm, self._groups, self._keys, self._uses = evm, groups, keys, uses
        self._corner_vertex = corner_vertex
        self._lines = self._vertices = self._edges = None
        if len(keys) == 0:
            empty = np.zeros(0, np.int32)
            self.polygons = Polygons(empty, empty, empty)
            return
        order, rank = self._lines = _lines(keys)
        tasks, first = [], 0
        for g, rectangles in enumerate(groups):
            axes, stop = _AXES[g // 2], first + len(rectangles)
            tasks += [(corner_vertex, start, min(start + _BLOCK_RECTANGLES, stop), axes[1],
                       axes[2], order, rank)
                      for start in range(first, stop, _BLOCK_RECTANGLES)]
            first = stop
        blocks = parallel_map(_loops, tasks)
        sizes = np.concatenate([block[1] for block in blocks])
        starts = (np.cumsum(sizes, dtype=np.int64) - sizes).astype(np.int32)
        self.polygons = Polygons(np.concatenate([block[0] for block in blocks]), starts, sizes)
        self._slots = [block[2] for block in blocks]

    def __len__(self):
        return len(self._keys)

    @property
    def vertices(self):
        """Lattice points (voxel corners), ``(n, 3)`` float64, sorted in x, y, z order."""
        if self._vertices is None:
            self._vertices = self.points(slice(None))
        return self._vertices

    def carry(self, values):
        """Per-vertex ``values`` of the mesh this one was :meth:`updated` from, moved to this
        mesh's vertices (positions, colours: whatever the vertex keeps).

        Parameters
        ----------
        values : (m, k) ndarray
            A row per vertex of the old mesh, in its vertex order.

        Returns
        -------
        out : (n, k) ndarray
            A row per vertex here, of ``values``' dtype.
        fresh : (f,) ndarray of np.int64
            The vertices that are new here: their rows of ``out`` are left for the caller.
        """
        return _carried(self.came_from, values, len(self))

    def points(self, indices):
        """The lattice points of some vertices, without making all of :attr:`vertices`.

        Parameters
        ----------
        indices : array_like of int, or slice
            Any index into :attr:`vertices`.

        Returns
        -------
        (k, 3) ndarray of np.float64
        """
        return _sweep.unpack(np.atleast_1d(self._keys[indices]), 3).astype(np.float64)

    def updated(self, evm):
        """The mesh of ``evm``, made from this one where the two regions agree.

        Parameters
        ----------
        evm : EVM
            Another region of the same lattice (typically this one edited in a small box).

        Returns
        -------
        BoundaryMesh
            Equal to ``BoundaryMesh(evm)``; this one itself if the regions are equal (then
            nothing moved, and its :attr:`came_from` still refers to the mesh before it).

        Raises
        ------
        VolumeEVMError
            When the mesh would need more memory than is available.
        """
        changed = _sweep.xor(self._orders[0], evm.keys())  # EVM(old ^ new) = EVM(old) ^ EVM(new)
        if len(changed) == 0:
            return self
        if len(self._keys) == 0:
            return BoundaryMesh(evm)
        # Faces change on the planes of old ^ new only: per axis, lo to hi (offset coordinates).
        lo, hi = _sweep.key_bounds(changed)
        orders = [evm.keys()] + [
            _sweep.xor(old, _sweep.radix_sort(_sweep.pack(_sweep.unpack(changed, 3)[:, axes]),
                                              0, 3)[0])
            for old, axes in zip(self._orders[1:], _AXES[1:])]
        dirty = parallel_map(_dirty_rectangles,
                             [(orders[axis], lo[axis], hi[axis]) for axis in range(3)])
        # On those planes, a rectangle whose closed extent misses the closed box of the change
        # (in B and C) has the same runs on its lines and the lines around it: it stays.
        groups, corners, left, came, first = [], [], [], [], 0
        for g, old in enumerate(self._groups):
            axes, side = _AXES[g // 2], g % 2
            r0, r1 = np.searchsorted(old[:, 0], (lo[axes[0]], hi[axes[0]] + 1))
            new = dirty[g // 2][side]
            old_touch, new_touch = (_touching(rectangles, lo[axes], hi[axes])
                                    for rectangles in (old[r0:r1], new))
            groups.append(np.concatenate([old[:r0], new, old[r1:]]))
            vertex = self._corner_vertex[first:first + 4 * len(old)].reshape(-1, 4)
            corners.append((vertex[:r0], vertex[r0:r1][~old_touch], new_touch, vertex[r1:]))
            left.append(vertex[r0:r1][old_touch].ravel())
            came.append(_corner_keys(new[new_touch], axes, side == 1))
            first += 4 * len(old)
        _check_memory(_BYTES_PER_RECTANGLE * sum(len(g) for g in groups) + _MESH_OVERHEAD,
                      "the updated face runs")
        uses = self._uses - np.bincount(np.concatenate(left),
                                        minlength=len(self._keys)).astype(np.int32)
        keys, uses, old_vertex, added_vertex = _merge_vertices(self._keys, uses,
                                                               np.concatenate(came))
        corner_vertex, added = [], 0
        for before, kept, touch, after in corners:
            middle = np.empty((len(touch), 4), np.int32)
            middle[~touch] = old_vertex[kept]
            middle[touch] = added_vertex[added:added + 4 * np.count_nonzero(touch)].reshape(-1, 4)
            added += 4 * np.count_nonzero(touch)
            corner_vertex += [old_vertex[before].ravel(), middle.ravel(), old_vertex[after].ravel()]
        mesh = BoundaryMesh.__new__(BoundaryMesh)
        mesh._orders, mesh.came_from = orders, old_vertex
        mesh._set(evm, groups, keys, uses, np.concatenate(corner_vertex))
        return mesh

    def edges(self):
        """The mesh's edges, as Blender stores them: each once, with each loop corner's edge.

        Returns
        -------
        edges : (E, 2) ndarray of np.int32
            The two vertices of every edge (axis by axis, along the lines); made on first use.
        corner_edges : (L,) ndarray of np.int32
            The edge from loop corner ``i`` to the next corner of its polygon.
        """
        if self._edges is None:
            if self._lines is None:
                self._edges = np.zeros((0, 2), np.int32), np.zeros(0, np.int32)
            else:
                self._edges = _numbered_edges(np.concatenate(self._slots), self._lines[0],
                                              len(self))
        return self._edges


def boundary_mesh(evm):
    """Closed, outward polygon mesh of the region's boundary, in lattice units.

    Returns
    -------
    vertices : (n, 3) float64
        Lattice coordinates (voxel corners), without duplicates, sorted in x, y, z order.
    polygons : Polygons
        Merged rectangles with T-junction vertices inserted: per axis (x, y, z) the faces where
        the solid ends (+A), then where it starts (-A), each by plane, lo C, hi C, lo B.
    """
    mesh = BoundaryMesh(evm)
    return mesh.vertices, mesh.polygons


def mesh_volume_area(vertices, polygons):
    """Enclosed volume and surface area of a closed polygon mesh (fan triangulation)."""
    loops = polygons.indices
    first = np.repeat(polygons.starts, polygons.sizes)
    following = polygons.edges()[1]
    p0 = vertices[loops[first]]
    p1 = vertices[loops]
    p2 = vertices[following]
    cross = np.cross(p1 - p0, p2 - p0)
    volume = np.einsum("ij,ij->", p0, cross) / 6.0
    area = np.linalg.norm(cross, axis=1).sum() / 2.0
    return volume, area
