"""The boundary mesh made 2-manifold, for 3D printing: non-manifold edges and vertices split.

The boundary mesh (:mod:`._mesh`) is the exact surface of the voxel region, which is not a
manifold where two voxels touch only along an edge (four faces at that edge, two directed each
way) or only at a point (two or more cones of faces share the vertex). Slicers expect every edge
to have exactly two faces and every vertex one fan of faces around it; this module makes such a
mesh from the boundary mesh, in four steps:

1. **Edges are paired the way the solid is.** Looking along a non-manifold edge, the two voxels
   that touch only along it lie in diagonally opposite quadrants. A face at the edge, with
   outward normal ``n`` and traversed along ``d``, has its solid voxel in the quadrant
   ``n x d - n``; each face is paired with the opposite face of the same voxel, so each voxel
   keeps its own two faces (the solid is split apart along the edge, as if its voxels were
   face-connected only).
2. **Each fan of faces around a vertex gets its own copy of the vertex.** With every directed
   edge paired, the corners at a vertex fall into cycles (from a corner, across its outgoing
   edge to the paired face, then that face's corner at the same vertex); each cycle is a fan.
3. **Copies move by :data:`EPSILON` so that they are distinct points** (slicers and Blender's
   importers merge coincident vertices). A vertex with two or more fans moves each copy by
   ``EPSILON`` along each axis, with the sign of the sum of the octants of the fan's faces'
   solid voxels: into a voxel that touches the others at that point only, away from a gap. A
   vertex with one fan stays on the lattice.
4. **A non-manifold edge whose two ends keep one copy each** (the solid joins again at both
   ends, e.g. two diagonal voxels between two full layers) would become two edges between the
   same two vertices. A vertex is then added to each such edge, at its middle moved by
   ``EPSILON`` towards its voxel along both other axes, in both faces of the edge.

Moved vertices leave their faces' planes by at most ``EPSILON``, so the surface moves by less
than ``EPSILON * sqrt(3)`` lattice units, and the enclosed volume changes by less than
``EPSILON`` times the sum, over the faces, of the face's area times its number of moved
vertices (the volume's derivative with respect to a vertex is a third of the area vectors of its
triangles). Polygons keep the order and orientation of :func:`._mesh.boundary_mesh`'s; those
with moved vertices are slightly non-planar (exporters triangulate them).
"""

import numpy as np

from .._jit import kernel
from ._mesh import BoundaryMesh, Polygons, _check_memory

EPSILON = 1e-3
"""How far (lattice units, per axis) a split vertex moves off the lattice. Blender and STL keep
coordinates as float32: at 1000 voxels from the origin two copies ``2 * EPSILON`` apart are still
about 30 float32 steps apart, while 1e-3 voxel (0.5 um at 0.5 mm spacing) is far below what any
printer resolves."""

_BYTES_PER_CORNER = 100
"""Peak of the split per loop corner of the boundary mesh: the tracemalloc peak on the CT head
at bone and at skin, noise (55 bytes) and a checkerboard (73), rounded up."""


@kernel
def _same(rows, i, j):
    """Whether rows ``i`` and ``j`` of an ``(m, 3)`` array are equal."""
    return rows[i, 0] == rows[j, 0] and rows[i, 1] == rows[j, 1] and rows[i, 2] == rows[j, 2]


@kernel
def _pair_and_fan(vertices, indices, starts, sizes):
    """Pair the directed edges and number the fans of corners around each vertex.

    Corner ``h`` starts the directed edge ``u -> v`` of its polygon (whose outward normal is
    the sign of its Newell area vector). Its pair is the corner starting ``v -> u``: the only
    one, or of two (a non-manifold edge) the one whose solid voxel lies in the same quadrant
    ``n x d - n``. The corner after ``h`` around ``u`` is then the one after its pair in that
    polygon, and each cycle of that is a fan.

    Returns
    -------
    fan : (L,) int32
        Each corner's fan, numbered vertex by vertex (in corner order within one).
    fan_vertex : (F,) int32
        Each fan's vertex.
    direction : (F, 3) int64
        Per fan, the sum of the octants (-1 or +1 per axis) of its faces' solid voxels at the
        vertex: a corner's voxel beside its outgoing edge, and the one beside its incoming edge
        when that is another (a T-junction in a straight side). Zero for the fan of a vertex
        with one fan (it does not move).
    twin, quadrant : (L,) int32, (L, 3) int8
        Each corner's paired corner, and the side (-1, 0 or +1 per axis) of its edge's voxel.
    shared : (L,) bool
        Which corners start an edge of a non-manifold edge (two edges each way).
    """
    n_corners = len(indices)
    following = np.empty(n_corners, np.int32)
    target = np.empty(n_corners, np.int32)  # the vertex each corner's edge goes to
    step = np.zeros((n_corners, 3), np.int8)
    quadrant = np.zeros((n_corners, 3), np.int8)
    normal = np.zeros(3, np.int8)
    for p in range(len(starts)):
        area = np.zeros(3)
        for h in range(starts[p], starts[p] + sizes[p]):
            following[h] = h + 1 if h + 1 < starts[p] + sizes[p] else starts[p]
            a, b = indices[h], indices[following[h]]
            target[h] = b
            for axis in range(3):
                step[h, axis] = np.sign(vertices[b, axis] - vertices[a, axis])
                area[axis] += (vertices[a, (axis + 1) % 3] * vertices[b, (axis + 2) % 3]
                               - vertices[a, (axis + 2) % 3] * vertices[b, (axis + 1) % 3])
        for axis in range(3):
            normal[axis] = np.sign(area[axis])
        for h in range(starts[p], starts[p] + sizes[p]):
            for axis in range(3):  # n x d - n
                j, k = (axis + 1) % 3, (axis + 2) % 3
                quadrant[h, axis] = normal[j] * step[h, k] - normal[k] * step[h, j] - normal[axis]
    # The corners at each vertex (a counting sort by vertex).
    first = np.zeros(len(vertices) + 1, np.int64)
    for h in range(n_corners):
        first[indices[h] + 1] += 1
    for k in range(len(vertices)):
        first[k + 1] += first[k]
    at_vertex = np.empty(n_corners, np.int32)
    filled = first[:-1].copy()
    for h in range(n_corners):
        at_vertex[filled[indices[h]]] = h
        filled[indices[h]] += 1
    twin = np.full(n_corners, -1, np.int32)
    shared = np.zeros(n_corners, np.bool_)
    for h in range(n_corners):
        u, v = indices[h], target[h]
        found = 0
        for k in range(first[v], first[v + 1]):
            g = at_vertex[k]
            if target[g] == u:
                found += 1
                if twin[h] < 0 or _same(quadrant, g, h):
                    twin[h] = g
        shared[h] = found > 1
    previous = np.empty(n_corners, np.int32)
    previous[following] = np.arange(n_corners, dtype=np.int32)
    fan = np.full(n_corners, -1, np.int32)
    fan_vertex = np.empty(n_corners, np.int32)
    fans = np.zeros(len(vertices), np.int32)
    count = 0
    for h in at_vertex:
        if fan[h] >= 0:
            continue
        fan_vertex[count] = indices[h]
        fans[indices[h]] += 1
        g = h
        while fan[g] < 0:
            fan[g] = count
            g = following[twin[g]]
        count += 1
    # The directions, needed where a vertex has more than one fan only.
    direction = np.zeros((count, 3), np.int64)
    for g in range(n_corners):
        if fans[indices[g]] < 2:
            continue
        e = previous[g]
        same_voxel = True  # a corner of a rectangle, not a T-junction
        for axis in range(3):
            direction[fan[g], axis] += step[g, axis] + quadrant[g, axis]
            same_voxel &= quadrant[e, axis] - step[e, axis] == step[g, axis] + quadrant[g, axis]
        if not same_voxel:
            for axis in range(3):
                direction[fan[g], axis] += quadrant[e, axis] - step[e, axis]
    return fan, fan_vertex[:count].copy(), direction, twin, quadrant, shared


def split_non_manifold(vertices, polygons, epsilon=EPSILON):
    """The closed, outward boundary mesh of a voxel region made 2-manifold (module docstring).

    Parameters
    ----------
    vertices : (n, 3) ndarray of np.float64
        Lattice points, as :func:`._mesh.boundary_mesh` gives them.
    polygons : Polygons
        Its faces (axis-aligned, counter-clockwise seen from outside, closed).
    epsilon : float
        How far split vertices move along each axis, lattice units.

    Returns
    -------
    vertices : (m, 3) ndarray of np.float64
        Each vertex once per fan of faces around it (copies moved by ``epsilon``), then the
        vertices added in the middle of edges.
    polygons : Polygons
        The same faces in the same order, with the copies, and the added vertices in their
        edges.

    Raises
    ------
    VolumeEVMError
        When the split would need more memory than is available.
    """
    if len(polygons) == 0:
        return vertices, polygons
    _check_memory(_BYTES_PER_CORNER * len(polygons.indices),
                  f"splitting the edges and vertices of {len(polygons.indices)} corners")
    fan, fan_vertex, direction, twin, quadrant, shared = _pair_and_fan(
        vertices, polygons.indices, polygons.starts, polygons.sizes)
    split = np.bincount(fan_vertex, minlength=len(vertices))[fan_vertex] > 1
    points = vertices[fan_vertex] + epsilon * np.where(split[:, None], np.sign(direction), 0)
    # Non-manifold edges still doubled (both ends kept one copy): a moved middle vertex in each.
    pairs = np.flatnonzero(shared & (np.arange(len(twin)) < twin))
    ends = np.sort(np.stack([fan[pairs], fan[twin[pairs]]]), axis=0)
    _, inverse, counts = np.unique(ends[0].astype(np.int64) * len(points) + ends[1],
                                   return_inverse=True, return_counts=True)
    doubled = pairs[counts[inverse] > 1]
    if len(doubled) == 0:
        return points, Polygons(fan, polygons.starts, polygons.sizes)
    ends = vertices[polygons.indices[doubled]] + vertices[polygons.indices[twin[doubled]]]
    middles = ends / 2 + epsilon * quadrant[doubled]
    added = np.arange(len(points), len(points) + len(doubled), dtype=np.int32)
    at = np.concatenate([doubled, twin[doubled]])
    order = np.argsort(at, kind="stable")
    indices = np.insert(fan, at[order] + 1, np.concatenate([added, added])[order])
    polygon = np.repeat(np.arange(len(polygons)), polygons.sizes)
    sizes = polygons.sizes + np.bincount(polygon[at], minlength=len(polygons)).astype(np.int32)
    starts = (np.cumsum(sizes, dtype=np.int64) - sizes).astype(np.int32)
    return np.concatenate([points, middles]), Polygons(indices, starts, sizes)


def manifold_mesh(evm, epsilon=EPSILON):
    """The boundary mesh of ``evm`` made 2-manifold (:func:`split_non_manifold`)."""
    mesh = BoundaryMesh(evm)
    return split_non_manifold(mesh.vertices, mesh.polygons, epsilon)
