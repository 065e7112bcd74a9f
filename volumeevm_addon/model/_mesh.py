"""The boundary of an EVM as a closed, outward polygon mesh with merged faces.

Faces perpendicular to axis A lie in the planes of vertices. With ``S_{i-1}`` and ``S_i`` the
sections before and after plane ``i``, ``S_{i-1} - S_i`` is where the solid ends (outward normal
+A) and ``S_i - S_{i-1}`` where it starts (normal -A). Both are 2-D EVMs; each is cut into
rectangles (slabs between its own lines, runs along the last axis), so one rectangle covers many
unit voxel faces. Faces perpendicular to B and C come from the same sweep on the vertices sorted
with B or C first.

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

Memory is checked (:func:`volumeevm_addon.check_memory`) before each stage allocates, from the sizes
known by then: each axis's rectangles from its count of face runs, then the polygon mesh from
the count of rectangles. The bytes per run and per rectangle are tracemalloc peaks measured on
real and synthetic regions (CT head at two thresholds, noise, checkerboard, ball; see
``bench/bench_memory.py``), rounded up. The peak is about 600 bytes per extreme vertex for CT
data, but a checkerboard has a few hundred vertices and 10⁵ faces: faces, not vertices, are what
the mesh costs.
"""

from dataclasses import dataclass

import numpy as np

from .._memory import check_memory
from . import _sweep

# Cyclic axis orders "ABC" with e_B x e_C = +e_A, so (B, C) counter-clockwise faces +A.
_CYCLIC = ("xyz", "yzx", "zxy")

_BYTES_PER_RUN = 250
"""Peak of cutting one face run into rectangles: positions, merge sort keys, corners."""
_BYTES_PER_RECTANGLE = 700
"""Peak per rectangle of the polygon mesh: corner keys, T-junction orders, loops (about 4.5
loops per rectangle)."""
_MESH_OVERHEAD = 1 << 20
"""Fixed part of the mesh's working set (small regions)."""
_ADVICE = "build the VolumeEVM with a higher threshold, crop it (clip) or mesh a coarser level"


def _check_memory(needed, what):
    check_memory(needed, f"making the boundary mesh ({what})", source="mesh", advice=_ADVICE)


@dataclass(frozen=True)
class Polygons:
    """Polygon faces of a mesh as flat loops (Blender's layout).

    ``indices`` holds the vertex index of every loop; polygon ``p`` is
    ``indices[starts[p] : starts[p] + sizes[p]]``, counter-clockwise seen from outside.
    """

    indices: np.ndarray
    starts: np.ndarray
    sizes: np.ndarray

    def __len__(self):
        return len(self.sizes)

    def __iter__(self):
        return iter(np.split(self.indices, self.starts[1:]))

    def edges(self):
        """Directed edges ``(u, v)`` of every loop, as two int arrays."""
        following = np.arange(1, len(self.indices) + 1)
        last = self.starts + self.sizes - 1
        following[last] = self.starts
        return self.indices, self.indices[following]


def boundary_rectangles(evm):
    """Outward boundary rectangles of an EVM.

    Returns
    -------
    (m, 4, 3) int64
        Rectangle corners (lattice coordinates), counter-clockwise seen from outside.
    """
    rectangles = []
    for order in _CYCLIC:
        axes = ["xyz".index(a) for a in order]
        keys = evm.keys(order)
        planes = _sweep.unique_sorted(_sweep.leading(keys, 3))
        after = _sweep.sections(keys, 3, planes)  # section after plane i has group i
        before = after + (np.int64(1) << (2 * _sweep.BITS))  # the same, as group i + 1
        # One sweep of the consecutive sections gives both face sets as runs on the merged
        # lines: solid ends (before - after, normal +A) and starts (after - before, normal -A).
        lines = _sweep.merged_slabs(before, after, 2)
        ends, starts = _sweep.combine_1d(_sweep.sections(before, 2, lines),
                                         _sweep.sections(after, 2, lines),
                                         ["difference", "reverse difference"])
        count = (len(ends) + len(starts)) // 2
        _check_memory(sum(r.nbytes for r in rectangles) + _BYTES_PER_RUN * count + _MESH_OVERHEAD,
                      f"{count} face runs perpendicular to axis {order[0]}")
        for runs, flip in ((ends, False), (starts, True)):
            line = runs[0::2] >> _sweep.BITS
            lo = np.stack([lines[line] & _sweep.MASK, runs[0::2] & _sweep.MASK], axis=1) - _sweep.OFFSET
            hi = np.stack([lines[line + 1] & _sweep.MASK, runs[1::2] & _sweep.MASK], axis=1) - _sweep.OFFSET
            plane, lo, hi = _merge_runs(lines[line] >> _sweep.BITS, lo, hi)
            a = (planes[plane] & _sweep.MASK) - _sweep.OFFSET
            corners = np.empty((len(a), 4, 3), np.int64)
            corners[:, :, axes[0]] = a[:, None]
            corners[:, :, axes[1]] = np.stack([lo[:, 0], hi[:, 0], hi[:, 0], lo[:, 0]], axis=1)
            corners[:, :, axes[2]] = np.stack([lo[:, 1], lo[:, 1], hi[:, 1], hi[:, 1]], axis=1)
            rectangles.append(corners[:, ::-1] if flip else corners)
    return np.concatenate(rectangles)


def _merge_runs(group, lo, hi):
    """Merge rectangles that continue one another across consecutive slabs.

    The 2-D decomposition cuts every run at every line of the face's EVM, even where the run
    itself goes on unchanged; rectangles with the same group and C-range whose B-ranges touch
    are joined into one.
    """
    order = np.lexsort((lo[:, 0], hi[:, 1], lo[:, 1], group))
    group, lo, hi = group[order], lo[order], hi[order]
    continues = np.zeros(len(group), bool)
    continues[1:] = (
        (group[1:] == group[:-1])
        & (lo[1:, 1] == lo[:-1, 1])
        & (hi[1:, 1] == hi[:-1, 1])
        & (lo[1:, 0] == hi[:-1, 0])
    )
    first = np.flatnonzero(~continues)
    last = np.append(first[1:], len(group))[: len(first)] - 1
    merged_hi = hi[first].copy()
    merged_hi[:, 0] = hi[last, 0]
    return group[first], lo[first], merged_hi


def boundary_mesh(evm):
    """Closed, outward polygon mesh of the region's boundary, in lattice units.

    Returns
    -------
    vertices : (n, 3) float64
        Lattice coordinates (voxel corners), without duplicates.
    polygons : Polygons
        Merged rectangles with T-junction vertices inserted.
    """
    corners = boundary_rectangles(evm)
    _check_memory(corners.nbytes + _BYTES_PER_RECTANGLE * len(corners) + _MESH_OVERHEAD,
                  f"{len(corners)} rectangles")
    if len(corners) == 0:
        empty = np.zeros(0, np.int32)
        return np.zeros((0, 3)), Polygons(empty, empty, empty)
    keys, corner_index = _sweep.unique_inverse(_sweep.pack(corners.reshape(-1, 3)))
    vertices = _sweep.unpack(keys, 3)[1]
    corner_index = corner_index.reshape(-1, 4)
    start = corner_index.ravel()
    end = np.roll(corner_index, -1, axis=1).ravel()

    # For each axis, the vertices sorted along lines parallel to it: the vertices strictly
    # between an edge's ends are a contiguous run of that order.
    n = len(vertices)
    along = np.argmax(vertices[end] != vertices[start], axis=1)
    line_order = np.empty(3 * n, np.int64)
    position = np.empty(len(start), np.int64)
    counts = np.empty(len(start), np.int64)
    steps = np.empty(len(start), np.int64)
    for axis, order in enumerate(_CYCLIC):
        axes = ["xyz".index(a) for a in order]
        line_keys = _sweep.pack(vertices[:, [axes[1], axes[2], axes[0]]])
        order_along = np.argsort(line_keys)
        rank = np.empty(n, np.int64)
        rank[order_along] = np.arange(n)
        line_order[axis * n : (axis + 1) * n] = order_along
        mine = along == axis
        position[mine] = axis * n + rank[start[mine]]
        distance = rank[end[mine]] - rank[start[mine]]
        counts[mine] = np.abs(distance)  # the start vertex and the |distance| - 1 inside
        steps[mine] = np.sign(distance)

    # Each edge contributes its start vertex and then the vertices inside it, in its direction.
    total = counts.sum()
    offsets = np.cumsum(counts) - counts
    edge = np.repeat(np.arange(len(counts)), counts)
    t = np.arange(total) - offsets[edge]
    loops = np.where(t == 0, start[edge], line_order[position[edge] + steps[edge] * t])
    sizes = counts.reshape(-1, 4).sum(axis=1)
    starts = np.cumsum(sizes) - sizes
    polygons = Polygons(loops.astype(np.int32), starts.astype(np.int32), sizes.astype(np.int32))
    return vertices.astype(np.float64), polygons


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
