"""Exact voxelization of a closed, oriented triangle mesh into a volume's voxel grid.

A CAD tool enters a VolumeEVM as the set of voxels whose centres lie inside it
(``volumeevm.md``, section 2). :func:`voxelize_mesh` computes that set exactly for the mesh
given in float64 coordinates: every decision (is a ray inside a projected triangle, is a
crossing below a voxel centre) is an exact sign, with a cheap floating-point filter and an exact
integer fallback for the few uncertain cases, and a fixed symbolic perturbation breaks every tie.
:func:`check_closed_mesh` is the validation it runs first, usable on its own.

The filter is a compiled kernel (:mod:`._jit`), linear in the (triangle, column) pairs: it
keeps the crossings it is sure of and hands the uncertain pairs to the exact NumPy path. A
second kernel sorts each column's crossings into the runs of non-zero winding number, from
which :func:`voxelize_mesh` fills its mask and :func:`voxelize_mesh_evm` writes the EVM's
vertices directly (no grid: linear in the columns and the runs).
"""

from dataclasses import dataclass

import numpy as np

from .._errors import VolumeEVMError
from .._jit import kernel
from .._memory import check_memory
from . import _sweep
from ._evm import EVM, check_lattice_range
from ._volume import grid_to_world, transform

__all__ = ["MeshCheck", "box_evm", "check_closed_mesh", "tool_to_grid", "voxelize_memory",
           "voxelize_mesh", "voxelize_mesh_evm"]

# Shewchuk's forward error bounds for orient2d / orient3d evaluated in float64 ("Adaptive
# Precision Floating-Point Arithmetic and Fast Robust Geometric Predicates", 1997): if
# |det| > bound the sign of the floating-point determinant is the sign of the exact one.
_EPS = 2.0**-53
_ORIENT2D_BOUND = (3.0 + 16.0 * _EPS) * _EPS
_ORIENT3D_BOUND = (7.0 + 56.0 * _EPS) * _EPS
# The bounds above assume no underflow; determinants smaller than this go to the exact path.
_TINY = 2.0**-900
# Uncertain (triangle, ray) pairs the exact path takes per chunk: bounds its working memory
# (~150 bytes each).
_CHUNK = 1 << 19
# Bytes per (triangle, column) candidate pair, from its test to the EVM, counted (tracemalloc
# does not see the kernels' arrays): a sure crossing's column, start and sign in arrays grown by
# doubling (~51 while one grows), its place in its column's sort and its run ends (~32) and the
# vertices they make (~32); an uncertain pair's row (~72 while it grows) before the exact path.
_PAIR_BYTES = 128
# Largest |coordinate| of the mesh in voxel index space: keeps every product in the predicates
# (up to the cube of a coordinate) far from float64 overflow.
_MAX_INDEX = 1e30


@dataclass(frozen=True)
class MeshCheck:
    """Facts about a mesh that passed :func:`check_closed_mesh` (its return value).

    Attributes
    ----------
    n_vertices, n_faces : int
        Sizes of the input arrays.
    n_edges : int
        Number of distinct undirected edges.
    euler_characteristic : int
        ``n_vertices - n_edges + n_faces`` (2 for a sphere-like shell, 0 for a torus).
    signed_volume : float
        Volume enclosed by the mesh in its own units cubed; positive when the faces are
        oriented outwards, negative for an inside-out mesh.
    """

    n_vertices: int
    n_faces: int
    n_edges: int
    euler_characteristic: int
    signed_volume: float


def check_closed_mesh(vertices, faces):
    """Check that a triangle mesh is a closed, consistently oriented surface.

    The test is combinatorial: every undirected edge must be used as often in one direction
    as in the other. A 2-manifold closed mesh uses each edge once each way; an edge where two
    closed parts touch (used twice each way) is accepted too, because the winding number is
    still well defined there.

    Parameters
    ----------
    vertices : (V, 3) array_like of float
        Vertex coordinates, any units. All must be finite.
    faces : (F, 3) array_like of int
        Triangles as vertex indices in ``[0, V)``; ``(a, b, c)`` counter-clockwise seen from
        outside means an outward normal.

    Returns
    -------
    MeshCheck
        Sizes, Euler characteristic and signed volume of the mesh.

    Raises
    ------
    VolumeEVMError
        If the arrays have the wrong shape or dtype, are empty, hold non-finite coordinates or
        out-of-range indices; if the mesh has open (boundary) edges, used by exactly one face
        ("tool mesh is not closed: 304 open (boundary) edges"); or if some edges are used more
        often in one direction than in the other although by two faces or more (faces flipped
        against their neighbours).

    Notes
    -----
    An inside-out mesh (negative ``signed_volume``) is not an error: :func:`voxelize_mesh`
    counts a point as inside where its winding number is not zero, so reversing every face
    does not change the mask.
    """
    verts, tris = _as_mesh(vertices, faces)
    n_open, n_unpaired, n_edges = _edge_defects(tris)
    if n_open:
        msg = f"tool mesh is not closed: {n_open} open (boundary) edges"
        if n_unpaired:
            msg += f" and {n_unpaired} edges used more often in one direction than the other"
        raise VolumeEVMError(msg + "; fill the holes so that the mesh encloses a volume")
    if n_unpaired:
        raise VolumeEVMError(
            f"tool mesh is not consistently oriented: {n_unpaired} edges are used more often "
            "in one direction than the other (faces flipped against their neighbours); "
            "recalculate the normals so that they all point outwards"
        )
    # About the bounding box centre: no cancellation for a mesh far from the origin.
    centred = verts - (verts.min(axis=0) + verts.max(axis=0)) / 2
    a, b, c = centred[tris[:, 0]], centred[tris[:, 1]], centred[tris[:, 2]]
    volume = float(np.einsum("ij,ij->", a, np.cross(b, c))) / 6.0
    return MeshCheck(
        n_vertices=len(verts),
        n_faces=len(tris),
        n_edges=n_edges,
        euler_characteristic=len(verts) - n_edges + len(tris),
        signed_volume=volume,
    )


def voxelize_mesh(vertices, faces, shape, to_grid):
    """Voxels of a grid whose centres lie inside a closed triangle mesh, computed exactly.

    Parameters
    ----------
    vertices : (V, 3) array_like of float
        Vertex coordinates in mesh units (converted to float64).
    faces : (F, 3) array_like of int
        Triangles as vertex indices; the mesh must pass :func:`check_closed_mesh`.
    shape : tuple of 3 int
        ``(X, Y, Z)``, the number of voxels of the target grid along x, y, z.
    to_grid : (4, 4) array_like of float
        Affine matrix (last row ``0, 0, 0, 1``) taking mesh coordinates (column vectors) to
        voxel index space, where voxel ``(i, j, k)`` has its centre at ``(i, j, k)``. May
        rotate, scale non-uniformly and mirror (negative determinant).

    Returns
    -------
    mask : (X, Y, Z) ndarray of bool
        Indexed ``[x, y, z]``; True where the voxel centre is inside the mesh, i.e. where the
        winding number of the mesh around it is not zero. A cavity bounded by an inner shell
        of opposite orientation is outside; overlapping components give their union.

    Raises
    ------
    VolumeEVMError
        For the input errors of :func:`check_closed_mesh`; for a bad ``shape`` or
        ``to_grid`` (also one that puts vertices more than 1e30 voxels away from the grid);
        if the transformed mesh lies wholly outside the volume, i.e. its bounding
        box in index space misses the box ``[-0.5, X - 0.5] x [-0.5, Y - 0.5] x [-0.5, Z - 0.5]``.
        A mesh that meets that box but contains no voxel centre gives an all-False mask.
        When the voxelization would need more memory than is available
        (:func:`voxelize_memory`, :func:`._memory.check_memory`), before allocating the grid.

    Notes
    -----
    The mesh voxelized is the one whose vertices are ``to_grid`` applied to ``vertices`` in
    float64; from there on the result is exact. Rays run along +z through the voxel centre
    columns ``(i, j)``; for each triangle the columns in its projected bounding box are tested
    with exact 2D orientation signs, each crossing gets the sign of the triangle's normal z
    component (times the sign of ``det(to_grid)``), and the signed crossings below each centre
    add up to its winding number.

    **Tie rule.** A voxel centre ``c`` counts as inside if and only if the point
    ``c + (e, e**2, d)`` is inside, for infinitesimals ``0 < e**2 << e << d``: a centre on the
    surface is inside when the solid continues from it towards +z; where the surface is
    parallel to z there, towards +x; where it is also parallel to x, towards +y. An
    axis-aligned box ``[x0, x1] x [y0, y1] x [z0, z1]`` therefore contains exactly the centres
    with ``x0 <= i < x1``, ``y0 <= j < y1``, ``z0 <= k < z1``. The perturbation is symbolic
    (simulation of simplicity), so a ray through a shared edge or vertex crosses the surface
    exactly as often as a ray in general position.

    Cost grows linearly with the number of (triangle, column) pairs in the triangles'
    projected bounding boxes plus the number of voxels (filling the mask): compiled kernels
    test the pairs one by one and sort the crossings column by column; the few uncertain pairs
    go to the exact path in chunks of bounded memory.

    References
    ----------
    J. R. Shewchuk, "Adaptive precision floating-point arithmetic and fast robust geometric
    predicates", Discrete Comput. Geom. 18 (1997) 305-363, :doi:`10.1007/PL00009321`.
    H. Edelsbrunner and E. P. Mücke, "Simulation of simplicity", ACM Trans. Graph. 9 (1990)
    66-104, :doi:`10.1145/77635.77639`.

    Examples
    --------
    >>> import numpy as np
    >>> v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    >>> f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    >>> to_grid = np.diag([4.0, 4.0, 4.0, 1.0])  # the tetrahedron spans 4 voxels
    >>> int(voxelize_mesh(v, f, (5, 5, 5), to_grid).sum())  # centres with i + j + k < 4
    20
    """
    shape = _as_shape(shape)
    ptr, ends = _winding_runs(vertices, faces, shape, to_grid, dense=True)
    return _fill_runs(ptr, ends, shape).view(bool)


def _winding_runs(vertices, faces, shape, to_grid, *, dense):
    """The runs of :func:`voxelize_mesh`'s voxels, column by column, after its checks.

    Returns ``(ptr, ends)``: column ``c = i * Y + j`` runs from ``ends[ptr[c]]`` to
    ``ends[ptr[c] + 1]`` (exclusive), and so on to ``ends[ptr[c + 1] - 1]``. ``dense`` says
    whether the caller then fills a grid (counted in the memory check).
    """
    verts, tris = _as_mesh(vertices, faces)
    matrix = _as_affine(to_grid)
    check_closed_mesh(verts, tris)

    linear = matrix[:3, :3]
    pts = transform(verts, linear.T, matrix[:3, 3])
    reach = float(np.abs(pts).max())
    if not reach <= _MAX_INDEX:
        raise VolumeEVMError(
            f"to_grid maps the tool mesh {reach:.3g} voxels away from the grid origin "
            f"(at most {_MAX_INDEX:.0e} is supported); check its scale"
        )
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    extent = np.asarray(shape, np.float64) - 0.5
    if np.any(hi <= -0.5) or np.any(lo >= extent):
        raise VolumeEVMError(
            "tool mesh lies wholly outside the volume: in voxel index space it spans "
            f"{_box_text(lo, hi)} while the volume spans "
            f"{_box_text(np.full(3, -0.5), extent)}"
        )
    # A mirroring transform turns outward normals inward: undo it in the crossing signs.
    orientation = 1 if np.linalg.det(linear) > 0 else -1
    return _column_runs(pts[tris], shape, orientation, dense)


def _as_mesh(vertices, faces):
    """Validated float64 (V, 3) vertices and int64 (F, 3) faces."""
    verts = np.asarray(vertices)
    tris = np.asarray(faces)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise VolumeEVMError(f"vertices must have shape (V, 3), got {verts.shape}")
    if tris.ndim != 2 or tris.shape[1] != 3:
        raise VolumeEVMError(f"faces must have shape (F, 3) (triangles), got {tris.shape}")
    if not np.issubdtype(verts.dtype, np.number) or np.issubdtype(verts.dtype, np.complexfloating):
        raise VolumeEVMError(f"vertices must be real numbers, got dtype {verts.dtype}")
    if not np.issubdtype(tris.dtype, np.integer):
        raise VolumeEVMError(f"faces must be integer vertex indices, got dtype {tris.dtype}")
    if len(verts) == 0 or len(tris) == 0:
        raise VolumeEVMError(
            f"tool mesh is empty: {len(verts)} vertices and {len(tris)} faces"
        )
    verts = np.ascontiguousarray(verts, np.float64)
    bad = int(np.count_nonzero(~np.isfinite(verts).all(axis=1)))
    if bad:
        raise VolumeEVMError(
            f"tool mesh has {bad} of {len(verts)} vertices with NaN or infinite coordinates"
        )
    out_of_range = int(np.count_nonzero(((tris < 0) | (tris >= len(verts))).any(axis=1)))
    if out_of_range:
        raise VolumeEVMError(
            f"tool mesh has {out_of_range} faces with vertex indices outside "
            f"[0, {len(verts)}) (indices range over [{tris.min()}, {tris.max()}])"
        )
    return verts, np.ascontiguousarray(tris, np.int64)


def _as_shape(shape):
    """The grid shape as a tuple of three positive ints."""
    arr = np.asarray(shape)
    if arr.shape != (3,) or not np.issubdtype(arr.dtype, np.integer) or np.any(arr < 1):
        raise VolumeEVMError(f"shape must be three positive integers (X, Y, Z), got {shape!r}")
    return tuple(int(n) for n in arr)


def _as_affine(to_grid):
    """The transform as a float64 (4, 4) affine matrix with an invertible linear part."""
    matrix = np.asarray(to_grid, dtype=np.float64)
    if matrix.shape != (4, 4):
        raise VolumeEVMError(f"to_grid must be a 4x4 matrix, got shape {matrix.shape}")
    if not np.isfinite(matrix).all():
        raise VolumeEVMError("to_grid holds NaN or infinite entries")
    if not np.array_equal(matrix[3], [0.0, 0.0, 0.0, 1.0]):
        raise VolumeEVMError(
            f"to_grid must be affine (last row 0, 0, 0, 1), got last row {matrix[3].tolist()}"
        )
    if np.linalg.det(matrix[:3, :3]) == 0.0:
        raise VolumeEVMError("to_grid is singular: it flattens the tool mesh (determinant 0)")
    return matrix


def _box_text(lo, hi):
    """A box as text, e.g. ``[-0.5, 9.5] x [...] x [...]``."""
    return " x ".join(f"[{a:.6g}, {b:.6g}]" for a, b in zip(lo, hi))


def _edge_defects(tris):
    """Counts of open edges, unpaired edges and distinct edges of a triangle mesh.

    An undirected edge used by one face is open; one used by two faces or more, but more often
    in one direction than in the other, is unpaired. Edges of a face with a repeated vertex
    that join a vertex to itself are ignored.
    """
    start = tris.reshape(-1)
    end = tris[:, [1, 2, 0]].reshape(-1)
    keep = start != end
    start, end = start[keep], end[keep]
    low, high = np.minimum(start, end), np.maximum(start, end)
    key = low * (int(tris.max()) + 1) + high
    edges, inverse = np.unique(key, return_inverse=True)
    inverse = inverse.reshape(-1)
    forward = np.bincount(inverse[start < end], minlength=len(edges))
    uses = np.bincount(inverse, minlength=len(edges))
    backward = uses - forward
    n_open = int(np.count_nonzero(uses == 1))
    n_unpaired = int(np.count_nonzero((uses >= 2) & (forward != backward)))
    return n_open, n_unpaired, len(edges)


def _column_runs(tri_pts, shape, orientation, dense):
    """Runs of voxel centres with non-zero winding number (see :func:`_winding_runs`).

    Parameters
    ----------
    tri_pts : (F, 3, 3) ndarray of float64
        Triangle corners in voxel index space, ``[face, corner, axis]``.
    shape : tuple of 3 int
        Grid shape ``(X, Y, Z)``.
    orientation : {1, -1}
        -1 if the faces' winding was reversed by a mirroring transform.
    dense : bool
        Whether a grid of ``shape`` will be filled (for the memory check).
    """
    nx, ny, nz = shape
    # Columns (i, j) whose ray can meet each triangle: integer points of the projected
    # bounding box inside the grid. Triangles wholly above the top centre cannot change any
    # centre's winding number.
    lo = np.ceil(tri_pts[:, :, :2].min(axis=1))
    hi = np.floor(tri_pts[:, :, :2].max(axis=1))
    lo = np.maximum(lo, 0.0)
    hi = np.minimum(hi, [nx - 1.0, ny - 1.0])
    width = np.maximum(hi - lo + 1.0, 0.0).astype(np.int64)
    count = width[:, 0] * width[:, 1]
    useful = (count > 0) & (tri_pts[:, :, 2].min(axis=1) <= nz - 1)
    tri_pts = np.ascontiguousarray(tri_pts[useful])
    width, lo = width[useful], lo[useful].astype(np.int64)
    pairs = int(count[useful].sum())
    check_memory(voxelize_memory(shape, pairs, dense),
                 f"voxelizing into a grid of shape {shape}", source="tool mesh",
                 advice="voxelize into a smaller grid or use a smaller tool")
    column, start, sign, unsure = _sure_crossings(tri_pts, lo, width, ny, nz)
    columns, starts, signs = [column], [start], [sign]
    for first in range(0, len(unsure), _CHUNK):
        tri, i, j = unsure[first:first + _CHUNK].T
        i, j, sign, start = _crossings(tri_pts, tri, i, j, nz)
        below = start < nz  # a crossing at the top changes no centre's winding number
        columns.append(i[below] * ny + j[below])
        starts.append(start[below])
        signs.append(sign[below])
    # Upward ray from inside an outward shell leaves through a face with normal z > 0, so a
    # crossing at or below the centre with normal z < 0 adds +1 to the centre's winding number.
    step = -orientation * np.concatenate(signs).astype(np.int64)
    return _runs_of(np.concatenate(columns), np.concatenate(starts), step, nx * ny, nz)


@kernel
def _orient2d_filtered(ax, ay, bx, by, px, py):
    """orient2d(a, b, p) in float64 and its sign when that value decides it (else 0)."""
    left = (ax - px) * (by - py)
    right = (ay - py) * (bx - px)
    det = left - right
    if abs(det) > max(_ORIENT2D_BOUND * (abs(left) + abs(right)), _TINY):
        return (1 if det > 0 else -1), det
    return 0, det


@kernel
def _below_sure(tri, px, py, qz, sign):
    """Whether the crossing of column (px, py) with triangle ``tri`` (oriented ``sign``) is
    surely at or below height ``qz`` (1), surely above it (-1), or too close to tell (0):
    the float64 :func:`_orient3d` and its error bound."""
    adx, ady, adz = tri[0, 0] - px, tri[0, 1] - py, tri[0, 2] - qz
    bdx, bdy, bdz = tri[1, 0] - px, tri[1, 1] - py, tri[1, 2] - qz
    cdx, cdy, cdz = tri[2, 0] - px, tri[2, 1] - py, tri[2, 2] - qz
    bc1, bc2 = bdx * cdy, bdy * cdx
    ca1, ca2 = cdx * ady, cdy * adx
    ab1, ab2 = adx * bdy, ady * bdx
    det = adz * (bc1 - bc2) + bdz * (ca1 - ca2) + cdz * (ab1 - ab2)
    permanent = ((abs(bc1) + abs(bc2)) * abs(adz) + (abs(ca1) + abs(ca2)) * abs(bdz)
                 + (abs(ab1) + abs(ab2)) * abs(cdz))
    if not abs(det) > max(_ORIENT3D_BOUND * permanent, _TINY):
        return 0
    return 1 if sign * det < 0 else -1


@kernel
def _sure_crossings(tri_pts, lo, width, ny, nz):
    """The crossings of the columns in each triangle's box that the float64 filter decides.

    The steps of :func:`_crossings` for one pair at a time: the three edge signs (inside when
    all agree), the crossing height from the barycentric weights, the first centre at or above
    it, checked by orient3d at that centre and the one below. Returns ``column`` (``i * ny +
    j``), ``start``, ``sign`` of the sure crossings below the top (``start < nz``) and the
    ``(triangle, i, j)`` rows of the uncertain pairs, for the exact path.
    """
    column = np.empty(256, np.int64)
    start = np.empty(256, np.int64)
    signs = np.empty(256, np.int8)
    unsure = np.empty((16, 3), np.int64)
    n = 0
    m = 0
    for t in range(len(tri_pts)):
        tri = tri_pts[t]
        ax, ay, az = tri[0, 0], tri[0, 1], tri[0, 2]
        bx, by, bz = tri[1, 0], tri[1, 1], tri[1, 2]
        cx, cy, cz = tri[2, 0], tri[2, 1], tri[2, 2]
        z_lo, z_hi = min(az, bz, cz), max(az, bz, cz)
        for jj in range(width[t, 1]):
            j = lo[t, 1] + jj
            py = float(j)
            for ii in range(width[t, 0]):
                i = lo[t, 0] + ii
                px = float(i)
                # Edge a->b gives the weight of c, b->c of a, c->a of b.
                w_a = w_b = 0.0
                sign, w_c = _orient2d_filtered(ax, ay, bx, by, px, py)
                sure = sign != 0
                if sure:
                    s, w_a = _orient2d_filtered(bx, by, cx, cy, px, py)
                    sure = s != 0
                    if sure and s != sign:
                        continue
                if sure:
                    s, w_b = _orient2d_filtered(cx, cy, ax, ay, px, py)
                    sure = s != 0
                    if sure and s != sign:
                        continue
                if sure:
                    total = w_a + w_b + w_c
                    height = (w_a * az + w_b * bz + w_c * cz) / total if total != 0.0 else az
                    first = min(max(np.ceil(min(max(height, z_lo), z_hi)), 0.0), float(nz))
                    if first == nz:  # above the top centre, if orient3d is sure of it
                        if _below_sure(tri, px, py, nz - 1.0, sign) == -1:
                            continue  # no centre's winding changes
                        sure = False
                    else:
                        sure = _below_sure(tri, px, py, first, sign) == 1 and (
                            first == 0.0 or _below_sure(tri, px, py, first - 1.0, sign) == -1)
                    if sure:
                        if n == len(column):
                            column = _grown(column, n)
                            start = _grown(start, n)
                            signs = _grown(signs, n)
                        column[n] = i * ny + j
                        start[n] = int(first)
                        signs[n] = sign
                        n += 1
                if not sure:
                    if m == len(unsure):
                        unsure = _grown(unsure, m)
                    unsure[m, 0], unsure[m, 1], unsure[m, 2] = t, i, j
                    m += 1
    return column[:n].copy(), start[:n].copy(), signs[:n].copy(), unsure[:m].copy()


@kernel
def _grown(array, count):
    """``array`` with twice the room, its first ``count`` rows kept."""
    grown = np.empty((2 * len(array),) + array.shape[1:], array.dtype)
    grown[:count] = array[:count]
    return grown


@kernel
def _runs_of(column, start, step, n_columns, nz):
    """Each column's runs of non-zero winding number from its crossings (any order).

    A crossing adds ``step`` to the winding number of the centres from ``start`` up. Column
    by column (a counting sort, then an insertion sort of its few crossings by start), the
    running winding number gives the runs' ends; a run still open at the top ends at ``nz``.
    Returns ``(ptr, ends)`` as :func:`_winding_runs` does.
    """
    ptr = np.zeros(n_columns + 1, np.int64)
    for c in column:
        ptr[c + 1] += 1
    for c in range(n_columns):
        ptr[c + 1] += ptr[c]
    fill = ptr[:-1].copy()
    heights = np.empty(len(column), np.int64)
    steps = np.empty(len(column), np.int64)
    for k in range(len(column)):
        c = column[k]
        heights[fill[c]] = start[k]
        steps[fill[c]] = step[k]
        fill[c] += 1
    ends = np.empty(2 * len(column), np.int64)
    out = np.zeros(n_columns + 1, np.int64)
    n = 0
    for c in range(n_columns):
        first, stop = ptr[c], ptr[c + 1]
        for k in range(first + 1, stop):
            height, value = heights[k], steps[k]
            q = k
            while q > first and heights[q - 1] > height:
                heights[q], steps[q] = heights[q - 1], steps[q - 1]
                q -= 1
            heights[q], steps[q] = height, value
        winding = 0
        inside = False
        k = first
        while k < stop:
            height = heights[k]
            while k < stop and heights[k] == height:
                winding += steps[k]
                k += 1
            if (winding != 0) != inside:
                ends[n] = height
                n += 1
                inside = not inside
        if inside:
            ends[n] = nz
            n += 1
        out[c + 1] = n
    return out, ends[:n].copy()


@kernel
def _fill_runs(ptr, ends, shape):
    """The grid of ``shape`` with the runs ``(ptr, ends)`` set (uint8 0 or 1)."""
    nx, ny, nz = shape
    grid = np.zeros((nx, ny, nz), np.uint8)
    for c in range(nx * ny):
        for k in range(ptr[c], ptr[c + 1], 2):
            grid[c // ny, c % ny, ends[k]:ends[k + 1]] = 1
    return grid


@kernel
def _run_keys(ptr, ends, shape, origin):
    """The EVM keys of the region of runs ``(ptr, ends)`` in the grid of ``shape`` placed at
    ``origin`` (offset lattice coordinates), sorted.

    Lattice point (x, y, z) is a vertex when an odd number of the 4 columns around its line,
    (x - 1, y - 1) to (x, y), have a run end at z (the EVM is the XOR of the region's shifted
    copies, and a column's run ends are where its voxels toggle along z): a merge of those
    columns' ends (each strictly increasing), line by line, plane by plane.
    """
    nx, ny, _ = shape
    heads = np.empty(4, np.int64)
    stops = np.empty(4, np.int64)
    keys = np.empty(256, np.int64)
    n = 0
    for x in range(nx + 1):
        for y in range(ny + 1):
            lists = 0
            for cx in range(max(x - 1, 0), min(x + 1, nx)):
                for cy in range(max(y - 1, 0), min(y + 1, ny)):
                    c = cx * ny + cy
                    if ptr[c] < ptr[c + 1]:
                        heads[lists], stops[lists] = ptr[c], ptr[c + 1]
                        lists += 1
            line = ((x + origin[0]) << (2 * _sweep.BITS)) | ((y + origin[1]) << _sweep.BITS)
            while lists:
                z = ends[heads[0]]
                for k in range(1, lists):
                    z = min(z, ends[heads[k]])
                odd = False
                k = 0
                while k < lists:
                    if ends[heads[k]] == z:
                        odd = not odd
                        heads[k] += 1
                        if heads[k] == stops[k]:
                            lists -= 1
                            heads[k], stops[k] = heads[lists], stops[lists]
                            continue
                    k += 1
                if odd:
                    if n == len(keys):
                        keys = _grown(keys, n)
                    keys[n] = line | (z + origin[2])
                    n += 1
    return keys[:n].copy()


def voxelize_memory(shape, pairs, dense=True):
    """Estimated peak bytes of :func:`voxelize_mesh` for a grid and its candidate pairs.

    ``pairs`` (triangle, column) candidates bound the crossings. A dense grid costs a byte a
    voxel (``dense``; :func:`voxelize_mesh_evm` makes none), its columns three run offsets
    each; each candidate costs what its crossing or its place in the uncertain list takes
    (``_PAIR_BYTES``), and a chunk of uncertain pairs on the exact path about 150 bytes each.
    The mesh check before it allocates in proportion to the mesh, which is already in memory,
    and is not counted.
    """
    nx, ny, nz = (int(n) for n in shape)
    grid = nx * ny * nz if dense else 0
    return grid + 24 * nx * ny + _PAIR_BYTES * pairs + 150 * min(pairs, _CHUNK)


def _crossings(tri_pts, tri, i, j, nz):
    """Exact crossings of the rays of columns ``(i, j)`` with triangles ``tri``.

    Returns, for the pairs whose (perturbed) ray passes through the triangle: i, j, the sign
    of the triangle's projected orientation (+1 counter-clockwise seen from +z)
    and ``start``, the first centre index k with the crossing at or below it (``ceil`` of the
    crossing height, clipped to ``[0, nz]``).
    """
    px = i.astype(np.float64)
    py = j.astype(np.float64)
    # Edge a->b: its orientation sign with the ray is the weight sign of corner c, and so on.
    corners = ((0, 1), (1, 2), (2, 0))
    weights = [None, None, None]
    sign = None
    for u, v in corners:
        p_u, p_v = tri_pts[tri, u], tri_pts[tri, v]
        s, det = _orient2d(p_u[:, 0], p_u[:, 1], p_v[:, 0], p_v[:, 1], px, py)
        inside = s != 0 if sign is None else s == sign
        tri, px, py, i, j = tri[inside], px[inside], py[inside], i[inside], j[inside]
        weights = [w if w is None else w[inside] for w in weights]
        weights[3 - u - v] = det[inside]
        sign = s[inside] if sign is None else sign[inside]

    a, b, c = tri_pts[tri, 0], tri_pts[tri, 1], tri_pts[tri, 2]
    # Approximate crossing height from barycentric weights forced to their exact sign.
    w = np.stack(weights)
    w = np.where(np.sign(w) == sign, w, 0.0)
    total = w.sum(axis=0)
    z_corner = np.stack([a[:, 2], b[:, 2], c[:, 2]])
    with np.errstate(invalid="ignore", divide="ignore"):
        height = np.where(total != 0.0, (w * z_corner).sum(axis=0) / total, a[:, 2])
    height = np.clip(height, z_corner.min(axis=0), z_corner.max(axis=0))
    start = np.clip(np.ceil(height), 0.0, float(nz))
    # start is right iff (start == nz or crossing <= start) and (start == 0 or
    # crossing > start - 1), where crossing <= q  <=>  sign * orient3d(a, b, c, (i, j, q)) <= 0.
    det_up, bound_up = _orient3d(a, b, c, px, py, start)
    det_down, bound_down = _orient3d(a, b, c, px, py, start - 1.0)
    ok_up = (start == nz) | ((np.abs(det_up) > bound_up) & (sign * det_up < 0))
    ok_down = (start == 0) | ((np.abs(det_down) > bound_down) & (sign * det_down > 0))
    start = start.astype(np.int64)
    unsure = np.flatnonzero(~(ok_up & ok_down))
    if len(unsure):
        start[unsure] = _exact_start(a[unsure], b[unsure], c[unsure], px[unsure], py[unsure], nz)
    return i, j, sign, start


def _orient2d(ax, ay, bx, by, px, py):
    """Exact sign of orient2d(a, b, p) for p nudged by (e, e**2), and its float64 value.

    Returns ``(sign, det)``: sign is +1 if ``p + (e, e**2)`` is left of the directed line
    a->b, -1 if right, 0 only if ``a == b``; det is the floating-point determinant.
    """
    left = (ax - px) * (by - py)
    right = (ay - py) * (bx - px)
    det = left - right
    bound = np.maximum(_ORIENT2D_BOUND * (np.abs(left) + np.abs(right)), _TINY)
    sign = np.sign(det).astype(np.int8)
    unsure = np.flatnonzero(~(np.abs(det) > bound))
    if len(unsure):
        sign[unsure] = _orient2d_exact(
            ax[unsure], ay[unsure], bx[unsure], by[unsure], px[unsure], py[unsure]
        )
    return sign, det


def _orient2d_exact(ax, ay, bx, by, px, py):
    """Exact, symbolically perturbed sign of orient2d(a, b, p) in integer arithmetic."""
    iax, iay, ibx, iby, ipx, ipy = _exact_ints(ax, ay, bx, by, px, py)
    det = (iax - ipx) * (iby - ipy) - (iay - ipy) * (ibx - ipx)
    sign = (det > 0).astype(np.int8) - (det < 0).astype(np.int8)
    # d det / d px = ay - by, d det / d py = bx - ax: the sign of the first non-zero term of
    # det + e (ay - by) + e**2 (bx - ax). Float subtraction of distinct values is never zero.
    tie = np.sign(np.where(ay != by, ay - by, bx - ax)).astype(np.int8)
    return np.where(sign != 0, sign, tie)


def _orient3d(a, b, c, px, py, qz):
    """Float64 orient3d(a, b, c, q) for ``q = (px, py, qz)`` and its error bound.

    Positive when q lies below the plane of a, b, c seen counter-clockwise from +z.
    """
    adx, ady, adz = a[:, 0] - px, a[:, 1] - py, a[:, 2] - qz
    bdx, bdy, bdz = b[:, 0] - px, b[:, 1] - py, b[:, 2] - qz
    cdx, cdy, cdz = c[:, 0] - px, c[:, 1] - py, c[:, 2] - qz
    bc1, bc2 = bdx * cdy, bdy * cdx
    ca1, ca2 = cdx * ady, cdy * adx
    ab1, ab2 = adx * bdy, ady * bdx
    det = adz * (bc1 - bc2) + bdz * (ca1 - ca2) + cdz * (ab1 - ab2)
    permanent = (
        (np.abs(bc1) + np.abs(bc2)) * np.abs(adz)
        + (np.abs(ca1) + np.abs(ca2)) * np.abs(bdz)
        + (np.abs(ab1) + np.abs(ab2)) * np.abs(cdz)
    )
    return det, np.maximum(_ORIENT3D_BOUND * permanent, _TINY)


def _exact_start(a, b, c, px, py, nz):
    """``ceil`` of the exact crossing height of column (px, py) with triangle abc, clipped."""
    (iax, iay, iaz, ibx, iby, ibz, icx, icy, icz, ipx, ipy), scale = _exact_ints(
        a[:, 0], a[:, 1], a[:, 2], b[:, 0], b[:, 1], b[:, 2], c[:, 0], c[:, 1], c[:, 2],
        px, py, with_scale=True,
    )
    w_a = (ibx - ipx) * (icy - ipy) - (iby - ipy) * (icx - ipx)
    w_b = (icx - ipx) * (iay - ipy) - (icy - ipy) * (iax - ipx)
    w_c = (iax - ipx) * (iby - ipy) - (iay - ipy) * (ibx - ipx)
    # height = num / den exactly (the scale cancels as s**3 / s**3).
    num = w_a * iaz + w_b * ibz + w_c * icz
    den = (w_a + w_b + w_c) * scale
    flip = den < 0
    num = np.where(flip, -num, num)
    den = np.where(flip, -den, den)
    start = -((-num) // den)
    return np.minimum(np.maximum(start, 0), nz).astype(np.int64)


def _exact_ints(*arrays, with_scale=False):
    """Float64 arrays as exact Python-int object arrays sharing one power-of-two scale.

    Each value x becomes ``x * scale`` with ``scale = 2**s`` (s >= 0) the smallest that makes
    all of them integers. Returns the converted arrays (and ``scale`` if asked).
    """
    values = np.concatenate([np.ravel(x) for x in arrays])
    mantissa, exponent = np.frexp(values)
    mantissa = (mantissa * 2.0**53).astype(np.int64)
    exponent = exponent.astype(np.int64) - 53
    nonzero = mantissa != 0
    shift = -min(int(exponent[nonzero].min()) if nonzero.any() else 0, 0)
    exponent = np.where(nonzero, exponent + shift, 0)
    ints = mantissa.astype(object) << exponent.astype(object)
    out = np.split(ints, np.cumsum([np.size(x) for x in arrays])[:-1])
    return (out, 1 << shift) if with_scale else out


def voxelize_mesh_evm(vertices, faces, shape, to_grid):
    """The EVM of :func:`voxelize_mesh`'s voxels, computed on the tool's bounding box only.

    A tool usually covers a small part of the grid; its runs and their EVM are made for the
    sub-grid of the tool's bounding box and placed with an integer offset (no grid is filled). The
    vertices are mapped to index space exactly as :func:`voxelize_mesh` maps them and then moved by
    a non-negative integer no larger than their smallest coordinates; that subtraction is exact in
    float64, and the voxelization is invariant under integer translations (the tie rule perturbs
    every centre alike), so the voxels are the same as on the whole grid.

    Parameters
    ----------
    vertices, faces, shape, to_grid
        As for :func:`voxelize_mesh`; besides, ``shape`` must fit the EVM's coordinate range
        (at most 1048575 voxels along each axis).

    Returns
    -------
    EVM
        The voxels of ``voxelize_mesh(vertices, faces, shape, to_grid)``, empty when the mesh
        meets the grid but holds no voxel centre.

    Raises
    ------
    VolumeEVMError
        As :func:`voxelize_mesh`, and for a ``shape`` beyond the EVM's coordinate range.

    Examples
    --------
    >>> v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    >>> f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    >>> to_grid = np.diag([4.0, 4.0, 4.0, 1.0])
    >>> voxelize_mesh_evm(v, f, (5, 5, 5), to_grid).volume()
    20
    """
    verts, tris = _as_mesh(vertices, faces)
    shape = _as_shape(shape)
    check_lattice_range((0, 0, 0), shape, f"shape {shape}")
    matrix = _as_affine(to_grid)
    pts = transform(verts, matrix[:3, :3].T, matrix[:3, 3])  # as voxelize_mesh computes them
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    extent = np.asarray(shape, np.float64) - 0.5
    # Past 1e15 (< 2**53) a float64 may be coarser than 1 and the shift would round: whole grid.
    if np.any(hi <= -0.5) or np.any(lo >= extent) or not np.abs(pts).max() <= 1e15:
        return _runs_evm(verts, tris, shape, matrix, np.zeros(3, np.int64))  # result or error
    offset = np.clip(np.floor(lo), 0, None).astype(np.int64)
    top = np.minimum(np.floor(hi).astype(np.int64) + 1, shape)
    if np.any(top <= offset):  # meets the grid but holds no voxel centre
        check_closed_mesh(verts, tris)  # an open mesh is still refused
        return EVM()
    return _runs_evm(pts - offset, tris, tuple(int(n) for n in top - offset), np.eye(4), offset)


def _runs_evm(vertices, faces, shape, to_grid, offset):
    """The EVM of :func:`voxelize_mesh`'s voxels in the grid ``shape`` placed at lattice cell
    ``offset``, from their runs (no grid)."""
    ptr, ends = _winding_runs(vertices, faces, _as_shape(shape), to_grid, dense=False)
    origin = np.asarray(offset, np.int64) + _sweep.OFFSET
    return EVM._from_keys(_run_keys(ptr, ends, np.asarray(shape, np.int64), origin))


def box_evm(lo, hi, shape):
    """The EVM of the voxels whose centres lie in the axis-aligned box ``[lo, hi]`` (index space).

    The tie rule of :func:`voxelize_mesh` for a box: centre ``i`` is inside when
    ``lo <= i < hi`` on every axis, so the voxels are ``ceil(lo) <= i < ceil(hi)``, clipped to
    the grid; their EVM is the box's 8 corners. A box tool (or clip box) needs no mesh.

    Parameters
    ----------
    lo, hi : (3,) array_like of float
        Opposite corners of the box in voxel index space (voxel centres at integers).
    shape : tuple of 3 int
        The grid the voxels are clipped to.

    Returns
    -------
    EVM
        Empty when the box holds no voxel centre of the grid.

    Examples
    --------
    >>> box_evm((0.5, 0.0, -3.0), (2.0, 2.0, 9.0), (4, 4, 4)).volume()  # 1 x 2 x 4 voxels
    8
    """
    low = np.clip(np.ceil(np.asarray(lo, np.float64)), 0, shape).astype(np.int64)
    high = np.clip(np.ceil(np.asarray(hi, np.float64)), 0, shape).astype(np.int64)
    if np.any(high <= low):
        return EVM()
    ends = np.stack([low, high])
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    return EVM(ends[corners, [0, 1, 2]])


def tool_to_grid(tool_matrix, spacing, origin, orientation=None, *, matrix_world=None):
    """4x4 matrix from a tool's local coordinates to a volume's voxel-centre indices.

    The ``to_grid`` of :func:`voxelize_mesh` for a tool mesh placed in the same world as the
    volume: the inverse of :func:`~volumeevm_addon.grid_to_world` after the tool's placement.

    Parameters
    ----------
    tool_matrix : (4, 4) array_like
        The tool's placement, local coordinates to world (Blender units): its ``matrix_world``.
    spacing, origin, orientation
        The volume's grid, as for :func:`~volumeevm_addon.grid_to_world`.
    matrix_world : (4, 4) array_like, optional
        The volume object's placement (default: the identity).

    Returns
    -------
    (4, 4) ndarray of np.float64
        Affine exactly: its last row is ``(0, 0, 0, 1)`` (the inverse may leave rounding there).

    Raises
    ------
    VolumeEVMError
        When ``tool_matrix`` is not a finite 4x4 matrix, or the volume's placement cannot be
        inverted (a scale of 0).

    Examples
    --------
    >>> import numpy as np
    >>> from volumeevm_addon.model import tool_to_grid
    >>> moved = np.eye(4)
    >>> moved[:3, 3] = (0.004, 0.0, 0.0)  # the tool 4 mm along x (Blender units)
    >>> tool_to_grid(moved, (2.0, 2.0, 2.0), (0.0, 0.0, 0.0)) @ (0.0, 0.0, 0.0, 1.0)
    array([2., 0., 0., 1.])
    """
    tool = np.asarray(tool_matrix, dtype=np.float64)
    if tool.shape != (4, 4) or not np.isfinite(tool).all():
        raise VolumeEVMError(f"tool_matrix: a finite 4x4 matrix, got shape {tool.shape}")
    world = grid_to_world(spacing, origin, orientation, matrix_world)
    if not np.isfinite(world).all() or np.linalg.det(world) == 0.0:
        raise VolumeEVMError("matrix_world: the volume's placement cannot be inverted (a scale "
                             "of 0?)")
    to_grid = np.linalg.inv(world) @ tool
    to_grid[3] = (0.0, 0.0, 0.0, 1.0)
    return to_grid
