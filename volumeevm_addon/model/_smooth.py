"""A smooth display surface that stays within half a voxel of the exact boundary mesh.

The exact boundary mesh (:mod:`._mesh`) looks like voxels. For display, its vertices are relaxed
towards a smooth surface, each kept in a box around its own exact position, as in Gibson's
constrained elastic surface nets (S. F. F. Gibson, "Constrained elastic surface nets: generating
smooth surfaces from binary segmented data", MICCAI 1998, doi:10.1007/BFb0056307), where each
node stays in its lattice cell. Here the mesh keeps the exact mesh's vertices, faces and
topology; only the positions change:

1. **The constraint.** Vertex ``i`` at exact position ``p_i`` (a lattice point) stays in the
   closed box ``p_i ± HALF_WIDTH`` (:data:`HALF_WIDTH` = 0.5 voxel along each axis): the box
   whose corners are the centres of the 8 voxels around the lattice point. Two vertices' boxes
   share at most a side, so vertices never cross each other's box.
2. **The relaxation.** :data:`ITERATIONS` Jacobi steps: every vertex moves by :data:`STEP` of
   the way to the weighted mean of its neighbours along the mesh's edges (the ends of its
   outgoing edges, so an edge shared by four faces counts twice), then is clamped to its box.
   A neighbour's weight is the inverse of the edge's exact length: merged faces have edges from
   1 to hundreds of voxels long, and a far corner says little about the surface near a vertex
   (smoother than equal weights, docs/measurements.md). Each step reads the positions of the
   step before only and sums in a fixed order: the result does not depend on the thread count.
3. **Triangles where needed.** A face whose moved vertices are no longer in one plane (off it
   by more than :data:`PLANAR`) is cut: a quadrangle along its shorter diagonal, a polygon with
   more corners (a rectangle with T-junction vertices in its sides, whose fan from a corner
   would have zero-area triangles) into a fan around an added vertex, the mean of its corners.
   Planar faces are kept as they are.

**Why the surface stays within half a voxel.** A point of a smooth triangle is a convex
combination of its corners, and the same combination of their exact positions lies on the exact
face the triangle came from (exact faces are planar and convex, and an added centre is the mean
of its face's exact corners, inside that face). Its displacement is the same combination of the
corners' displacements, each within ``±HALF_WIDTH`` per axis; so every point of the smooth
surface has a point of the exact surface within ``HALF_WIDTH`` per axis, and every point of the
exact surface one of the smooth surface, i.e. the Hausdorff distance is at most
``HALF_WIDTH * sqrt(3)`` (half a voxel diagonal), in lattice units.

Where voxels touch only along an edge or at a point, the exact mesh's shared vertices relax
once for both sheets (a pinch stays a pinch). With ``manifold=True`` (:mod:`._manifold`) the
split copies relax separately, each in the box around its own position (``1e-3`` voxel off the
lattice), so that mesh's smooth surface is within ``HALF_WIDTH + 1e-3`` per axis of the exact
one.

The exact mesh stays what tools and measurements use: this one is for display only (its
enclosed volume differs from the voxel count, by the amounts ``tests/test_smooth_mesh.py``
states).
"""

import numpy as np

from .._jit import kernel
from ._mesh import Polygons, _check_memory

HALF_WIDTH = 0.5
"""How far a vertex may move from its exact position, along each axis (voxels)."""
ITERATIONS = 8
"""Relaxation steps (more make it no smoother on real data: more vertices stop at their box)."""
STEP = 0.5
"""Fraction of the way to the neighbours' mean a vertex moves in one step."""
PLANAR = 1e-4
"""A face whose moved vertices are all within this of their mean plane is kept whole (voxels;
well above float32 rounding at the coordinates Blender keeps)."""

_BYTES_PER_CORNER = 130
"""Peak of smoothing per loop corner of the exact mesh: neighbours and weights, two position
buffers, the triangulated faces (up to three loops per corner); an estimate from the arrays'
sizes."""


@kernel
def _clamped(x, centre, half_width):
    """``x`` clamped to ``centre ± half_width``."""
    return min(max(x, centre - half_width), centre + half_width)


@kernel
def _relaxed(points, indices, starts, sizes, iterations, step, half_width):
    """``points`` moved by ``iterations`` constrained Laplacian steps (module docstring)."""
    n = len(points)
    first = np.zeros(n + 1, np.int64)
    for h in range(len(indices)):
        first[indices[h] + 1] += 1
    for k in range(n):
        first[k + 1] += first[k]
    target = np.empty(len(indices), np.int32)
    filled = first[:-1].copy()
    for p in range(len(starts)):
        end = starts[p] + sizes[p]
        for h in range(starts[p], end):
            u = indices[h]
            target[filled[u]] = indices[h + 1] if h + 1 < end else indices[starts[p]]
            filled[u] += 1
    weight = np.empty(len(indices))
    total = np.zeros(n)
    for u in range(n):
        for k in range(first[u], first[u + 1]):
            v = target[k]
            weight[k] = 1.0 / np.sqrt((points[v, 0] - points[u, 0]) ** 2
                                      + (points[v, 1] - points[u, 1]) ** 2
                                      + (points[v, 2] - points[u, 2]) ** 2)
            total[u] += weight[k]
    current = points.copy()
    following = points.copy()
    for _ in range(iterations):
        for u in range(n):
            if first[u + 1] == first[u]:
                continue
            x = y = z = 0.0
            for k in range(first[u], first[u + 1]):
                v = target[k]
                x += weight[k] * current[v, 0]
                y += weight[k] * current[v, 1]
                z += weight[k] * current[v, 2]
            following[u, 0] = _clamped(current[u, 0] + step * (x / total[u] - current[u, 0]),
                                       points[u, 0], half_width)
            following[u, 1] = _clamped(current[u, 1] + step * (y / total[u] - current[u, 1]),
                                       points[u, 1], half_width)
            following[u, 2] = _clamped(current[u, 2] + step * (z / total[u] - current[u, 2]),
                                       points[u, 2], half_width)
        current, following = following, current
    return current


@kernel
def _cut(points, indices, starts, sizes, planar):
    """Each non-planar face cut into triangles (module docstring, step 3).

    Returns the added centres, and the loops, starts and sizes of the faces in the same order
    (a face kept, or its triangles in its place).
    """
    n_polygons = len(starts)
    kind = np.zeros(n_polygons, np.int8)  # 0 kept, 1 and 2 quadrangle cut 0-2 or 1-3, 3 fan
    n_loops = 0
    n_faces = 0
    n_centres = 0
    for p in range(n_polygons):
        s, m = starts[p], sizes[p]
        nx = ny = nz = cx = cy = cz = 0.0
        for h in range(s, s + m):
            a = indices[h]
            b = indices[h + 1] if h + 1 < s + m else indices[s]
            nx += points[a, 1] * points[b, 2] - points[a, 2] * points[b, 1]
            ny += points[a, 2] * points[b, 0] - points[a, 0] * points[b, 2]
            nz += points[a, 0] * points[b, 1] - points[a, 1] * points[b, 0]
            cx += points[a, 0]
            cy += points[a, 1]
            cz += points[a, 2]
        length = max(np.sqrt(nx * nx + ny * ny + nz * nz), 1e-300)
        off = 0.0
        for h in range(s, s + m):
            a = indices[h]
            off = max(off, abs((points[a, 0] - cx / m) * nx + (points[a, 1] - cy / m) * ny
                               + (points[a, 2] - cz / m) * nz) / length)
        if off <= planar:
            n_loops += m
            n_faces += 1
        elif m == 4:
            d02 = d13 = 0.0
            for axis in range(3):
                d02 += (points[indices[s + 2], axis] - points[indices[s], axis]) ** 2
                d13 += (points[indices[s + 3], axis] - points[indices[s + 1], axis]) ** 2
            kind[p] = 1 if d02 <= d13 else 2
            n_loops += 6
            n_faces += 2
        else:
            kind[p] = 3
            n_loops += 3 * m
            n_faces += m
            n_centres += 1
    centres = np.zeros((n_centres, 3))
    out = np.empty(n_loops, np.int32)
    out_starts = np.empty(n_faces, np.int32)
    out_sizes = np.empty(n_faces, np.int32)
    loop = 0
    face = 0
    centre = 0
    for p in range(n_polygons):
        s, m = starts[p], sizes[p]
        if kind[p] == 0:
            out_starts[face], out_sizes[face] = loop, m
            face += 1
            for h in range(s, s + m):
                out[loop] = indices[h]
                loop += 1
        elif kind[p] < 3:
            q = 0 if kind[p] == 1 else 1  # triangles q, q+1, q+2 and q, q+2, q+3
            for t in range(2):
                out_starts[face], out_sizes[face] = loop, 3
                face += 1
                out[loop] = indices[s + q]
                out[loop + 1] = indices[s + (q + 1 + t) % 4]
                out[loop + 2] = indices[s + (q + 2 + t) % 4]
                loop += 3
        else:
            c = len(points) + centre
            for h in range(s, s + m):
                for axis in range(3):
                    centres[centre, axis] += points[indices[h], axis] / m
                out_starts[face], out_sizes[face] = loop, 3
                face += 1
                out[loop] = c
                out[loop + 1] = indices[h]
                out[loop + 2] = indices[h + 1] if h + 1 < s + m else indices[s]
                loop += 3
            centre += 1
    return centres, out, out_starts, out_sizes


def smooth_mesh(vertices, polygons):
    """The exact boundary mesh relaxed into a smooth display surface (module docstring).

    Parameters
    ----------
    vertices : (n, 3) ndarray of np.float64
        The exact mesh's vertices in lattice units (:func:`._mesh.boundary_mesh`, or the
        manifold mesh's).
    polygons : Polygons
        Its faces.

    Returns
    -------
    vertices : (m, 3) ndarray of np.float64
        The ``n`` vertices moved (same order), each within ``HALF_WIDTH`` of its exact
        position along each axis; then one added vertex per face cut into a fan, in face order.
    polygons : Polygons
        The faces in the same order, each kept or replaced by its triangles (same orientation).

    Raises
    ------
    VolumeEVMError
        When smoothing would need more memory than is available.
    """
    if len(polygons) == 0:
        return vertices, polygons
    _check_memory(_BYTES_PER_CORNER * len(polygons.indices),
                  f"smoothing the {len(polygons.indices)} corners of the mesh")
    points = np.ascontiguousarray(vertices, np.float64)
    moved = _relaxed(points, polygons.indices, polygons.starts, polygons.sizes, ITERATIONS, STEP,
                     HALF_WIDTH)
    centres, indices, starts, sizes = _cut(moved, polygons.indices, polygons.starts,
                                           polygons.sizes, PLANAR)
    return np.concatenate([moved, centres]), Polygons(indices, starts, sizes)
