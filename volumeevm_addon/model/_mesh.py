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
non-manifold (Select > Select All by Trait > Non Manifold).

Memory is checked (:func:`volumeevm_addon.check_memory`) after each axis's sweep, whose own
working set is a few arrays the size of its vertices: the rectangles found so far give the peak
of making the polygon mesh from them, :data:`_BYTES_PER_RECTANGLE` each. That figure is the
tracemalloc peak (which sees the kernels' arrays too) measured on real and synthetic regions
(CT head at two thresholds, an MRI, noise, a ball, a checkerboard: 170 to 210 bytes), rounded
up. The peak is about 200 bytes per extreme vertex for CT data, but a checkerboard has a few
hundred vertices and 10⁵ faces: faces, not vertices, are what the mesh costs.
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
        open_runs[k, 0], open_runs[k, 1], open_runs[k, 2] = following[k, 0], following[k, 1], following[k, 2]
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
            p, length_before = _sweep.toggle_line(before, n_before, p, b, row_before, length_before, scratch)
            q, length_after = _sweep.toggle_line(after, n_after, q, b, row_after, length_after, scratch)
            # The face runs from this line on: where the solid ends, and where it starts.
            runs_e = _sweep.combine_rows(row_before, length_before, row_after, length_after, _ENDS,
                                         end_runs) // 2
            runs_s = _sweep.combine_rows(row_before, length_before, row_after, length_after, _STARTS,
                                         start_runs) // 2
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
    first_planes = np.unique(np.searchsorted(plane_starts, np.arange(0, len(keys), _BLOCK_VERTICES)))
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
    ``(loops, sizes)``.
    """
    sizes = np.empty(stop - first, np.int32)
    total = 0
    for r in range(first, stop):
        size = 0
        for e in range(4):
            axis = axis_b if e % 2 == 0 else axis_c
            size += abs(rank[axis, corner_vertex[4 * r + (e + 1) % 4]] - rank[axis, corner_vertex[4 * r + e]])
        sizes[r - first] = size
        total += size
    loops = np.empty(total, np.int32)
    w = 0
    for r in range(first, stop):
        for e in range(4):
            axis = axis_b if e % 2 == 0 else axis_c
            here = rank[axis, corner_vertex[4 * r + e]]
            there = rank[axis, corner_vertex[4 * r + (e + 1) % 4]]
            step = 1 if there > here else -1
            for k in range(here, there, step):
                loops[w] = order[axis, k]
                w += 1
    return loops, sizes


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
    tasks = parallel_map(lambda order: _blocks(evm.keys(order)), [(order,) for order in _CYCLIC])
    found = iter(parallel_map(_plane_rectangles, [task for axis in tasks for task in axis]))
    groups, count = [], 0
    for axes, order, axis in zip(_AXES, _CYCLIC, tasks):
        blocks = [next(found) for _ in axis]
        ends, starts = (np.concatenate([block[side] for block in blocks] or [np.zeros((0, 5), np.int64)])
                        for side in (0, 1))
        groups += [(ends, axes, False), (starts, axes, True)]
        count += len(ends) + len(starts)
        _check_memory(_BYTES_PER_RECTANGLE * count + _MESH_OVERHEAD,
                      f"{len(ends) + len(starts)} face runs perpendicular to axis {order[0]}")
    if count == 0:
        empty = np.zeros(0, np.int32)
        return np.zeros((0, 3)), Polygons(empty, empty, empty)
    corners = np.concatenate([_corner_keys(rectangles, axes, flip) for rectangles, axes, flip in groups])
    vertices, corner_vertex = _vertices_of(corners)
    del corners
    order, rank = _lines(vertices)
    tasks, first = [], 0
    for rectangles, axes, _ in groups:
        stop = first + len(rectangles)
        tasks += [(corner_vertex, start, min(start + _BLOCK_RECTANGLES, stop), axes[1], axes[2], order, rank)
                  for start in range(first, stop, _BLOCK_RECTANGLES)]
        first = stop
    blocks = parallel_map(_loops, tasks)
    sizes = np.concatenate([block[1] for block in blocks])
    starts = (np.cumsum(sizes, dtype=np.int64) - sizes).astype(np.int32)
    polygons = Polygons(np.concatenate([block[0] for block in blocks]), starts, sizes)
    return _sweep.unpack(vertices, 3).astype(np.float64), polygons


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
