"""Measures of a surface mesh against the voxel region it comes from, for the smooth-mesh
tests and bench: distances to the exact boundary, normals' roughness, marching cubes."""

import numpy as np


def triangles(vertices, polygons):
    """Fan triangles of every polygon, ``(T, 3)`` vertex indices (planar convex faces)."""
    first = np.repeat(polygons.starts, polygons.sizes - 2)
    corner = np.concatenate([np.arange(s + 1, s + m - 1) for s, m in
                             zip(polygons.starts.tolist(), polygons.sizes.tolist())])
    loops = polygons.indices
    return np.stack([loops[first], loops[corner], loops[corner + 1]], axis=1)


def roughness(vertices, faces):
    """How much the normals turn across edges, per unit area: the sum over edges shared by
    exactly two faces (once each way) of the edge's length times the angle between the two
    faces' normals, divided by the total area (radians per lattice unit; about ``2 / r`` on a
    sphere of radius ``r`` for any fine, smooth tessellation, far more on a staircase).

    ``faces`` is ``(T, 3)`` triangles, consistently oriented."""
    p = vertices[faces]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = np.linalg.norm(cross, axis=1)
    normal = cross / np.maximum(area, 1e-300)[:, None]
    u = faces.ravel()
    v = np.roll(faces, -1, axis=1).ravel()
    face = np.repeat(np.arange(len(faces)), 3)
    n = len(vertices)
    keys = u.astype(np.int64) * n + v
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    single = np.ones(len(keys), bool)
    single[order[1:][sorted_keys[1:] == sorted_keys[:-1]]] = False
    single[order[:-1][sorted_keys[1:] == sorted_keys[:-1]]] = False
    opposite = v.astype(np.int64) * n + u
    found = np.minimum(np.searchsorted(sorted_keys, opposite), len(keys) - 1)
    twin = order[found]
    use = single & (sorted_keys[found] == opposite) & single[twin] & (u < v)
    use &= (area[face] > 1e-12) & (area[face[twin]] > 1e-12)
    cosine = np.einsum("ij,ij->i", normal[face[use]], normal[face[twin[use]]])
    angle = np.arccos(np.clip(cosine, -1.0, 1.0))
    length = np.linalg.norm(vertices[v[use]] - vertices[u[use]], axis=1)
    return float((angle * length).sum() / (area.sum() / 2))


def sample_triangles(vertices, faces, spacing, rng):
    """Points on the triangles, about one per ``spacing**2`` of area (at least one each, the
    centroid), uniformly placed."""
    p = vertices[faces]
    area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1) / 2
    counts = np.maximum(np.ceil(area / spacing**2).astype(np.int64), 1)
    which = np.repeat(np.arange(len(faces)), counts)
    r1, r2 = rng.random(len(which)), rng.random(len(which))
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    q = p[which]
    points = q[:, 0] + r1[:, None] * (q[:, 1] - q[:, 0]) + r2[:, None] * (q[:, 2] - q[:, 0])
    return np.concatenate([points, p.mean(axis=1)])


def distance_to_boundary(mask, points):
    """Exact distance (lattice units, voxel ``i`` is ``[i, i+1]``) from each point to the
    boundary of the voxel region ``mask``: the unit faces between a voxel inside and one outside.
    Faces more than one voxel away in any axis are not looked at: a point farther than that
    from every face gets ``inf``."""
    padded = np.pad(mask, 3)
    q = np.asarray(points, np.float64) + 3
    best = np.full(len(q), np.inf)
    base = np.floor(q).astype(np.int64)
    for axis in range(3):
        b, c = (axis + 1) % 3, (axis + 2) % 3
        for da in (-1, 0, 1, 2):
            for db in (-1, 0, 1):
                for dc in (-1, 0, 1):
                    cell = base.copy()
                    cell[:, axis] += da
                    cell[:, b] += db
                    cell[:, c] += dc
                    behind = cell.copy()
                    behind[:, axis] -= 1
                    inside = padded[cell[:, 0], cell[:, 1], cell[:, 2]]
                    face = inside != padded[behind[:, 0], behind[:, 1], behind[:, 2]]
                    gap_b = np.maximum(np.maximum(cell[:, b] - q[:, b],
                                                  q[:, b] - cell[:, b] - 1), 0)
                    gap_c = np.maximum(np.maximum(cell[:, c] - q[:, c],
                                                  q[:, c] - cell[:, c] - 1), 0)
                    d = np.sqrt((q[:, axis] - cell[:, axis]) ** 2 + gap_b**2 + gap_c**2)
                    best = np.where(face, np.minimum(best, d), best)
    return best


def boundary_face_points(mask):
    """The centre and the corners of every unit boundary face of ``mask`` (lattice units)."""
    padded = np.pad(mask, 1)
    points = []
    for axis in range(3):
        change = np.diff(padded.astype(np.int8), axis=axis) != 0
        cells = np.argwhere(change).astype(np.float64)
        # The face between padded cells c and c+1 along axis: lattice plane c (unpadded).
        lo = cells - 1
        lo[:, axis] += 1
        for offset in ([0.5, 0.5], [0, 0], [0, 1], [1, 0], [1, 1]):
            p = lo.copy()
            p[:, (axis + 1) % 3] += offset[0]
            p[:, (axis + 2) % 3] += offset[1]
            points.append(p)
    return np.unique(np.concatenate(points), axis=0)


def marching_cubes(mask):
    """Marching cubes (scikit-image, Lewiner) of the mask at 0.5, in lattice units (voxel
    centres at ``i + 0.5``): vertices and triangles."""
    import warnings

    from skimage.measure import marching_cubes as skimage_marching_cubes

    with warnings.catch_warnings():  # scikit-image 0.26 sets an array's shape (NumPy 2.5)
        warnings.filterwarnings("ignore", "Setting the shape", DeprecationWarning)
        verts, faces, _, _ = skimage_marching_cubes(np.pad(mask, 1).astype(np.float32), 0.5)
    return verts - 0.5, faces


def _closest_on_triangles(p, a, b, c):
    """The closest point to each ``p`` on the triangle ``a, b, c`` (rows; Ericson, Real-Time
    Collision Detection, 5.1.5), for any triangle, degenerate ones included."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denominator = va + vb + vc
        v, w = vb / denominator, vc / denominator
        out = a + ab * v[:, None] + ac * w[:, None]
        # Edges (when outside the face region) and vertices, in Ericson's order reversed so
        # that the first region that holds wins.
        edge_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        out = np.where(edge_bc[:, None], b + (c - b) * t[:, None], out)
        edge_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        out = np.where(edge_ac[:, None], a + ac * (d2 / (d2 - d6))[:, None], out)
        edge_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        out = np.where(edge_ab[:, None], a + ab * (d1 / (d1 - d3))[:, None], out)
    out = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, out)
    # Degenerate triangles (zero area): the nearest of their three edges' closest points.
    flat = ~np.isfinite(out).all(axis=1)
    if flat.any():
        ends = [(a, b), (b, c), (a, c)]
        best = np.full(flat.sum(), np.inf)
        for s, e in ends:
            d = e[flat] - s[flat]
            t = np.clip(np.einsum("ij,ij->i", p[flat] - s[flat], d)
                        / np.maximum(np.einsum("ij,ij->i", d, d), 1e-300), 0, 1)
            q = s[flat] + d * t[:, None]
            better = np.linalg.norm(p[flat] - q, axis=1) < best
            best = np.where(better, np.linalg.norm(p[flat] - q, axis=1), best)
            out[np.flatnonzero(flat)[better]] = q[better]
    return out


def distance_to_triangles(points, vertices, faces, spacing=0.25, radius=1.5, seed=0):
    """Exact distance from each point to the nearest of the triangles that have a sample (at
    ``spacing``, inside them and along their edges) within ``radius`` of it: an upper bound of
    the distance to the mesh, equal to it when the nearest triangle is among those (``inf``
    when none is)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    p = vertices[faces]
    area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1) / 2
    counts = np.maximum(np.ceil(area / spacing**2).astype(np.int64), 1)
    which = np.repeat(np.arange(len(faces)), counts)
    r1, r2 = rng.random(len(which)), rng.random(len(which))
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    q = p[which]
    samples = [q[:, 0] + r1[:, None] * (q[:, 1] - q[:, 0]) + r2[:, None] * (q[:, 2] - q[:, 0])]
    owners = [which]
    for s, e in ((0, 1), (1, 2), (2, 0)):  # and along the edges (thin triangles)
        steps = np.ceil(np.linalg.norm(p[:, e] - p[:, s], axis=1) / spacing).astype(np.int64) + 1
        owner = np.repeat(np.arange(len(faces)), steps)
        t = np.arange(len(owner)) - np.repeat(np.cumsum(steps) - steps, steps)
        t = t / np.repeat(steps, steps)
        samples.append(p[owner, s] + (p[owner, e] - p[owner, s]) * t[:, None])
        owners.append(owner)
    samples, which = np.concatenate(samples), np.concatenate(owners)
    near = cKDTree(samples).query_ball_point(points, radius)
    point = np.repeat(np.arange(len(points)), [len(n) for n in near])
    pairs = np.unique(np.stack([point, which[np.concatenate(near).astype(np.int64)]], 1), axis=0)
    best = np.full(len(points), np.inf)
    for chunk in np.array_split(pairs, max(1, len(pairs) // 500_000)):
        t = p[chunk[:, 1]]
        d = np.linalg.norm(points[chunk[:, 0]] - _closest_on_triangles(points[chunk[:, 0]], t[:, 0],
                                                                       t[:, 1], t[:, 2]), axis=1)
        np.minimum.at(best, chunk[:, 0], d)
    return best


def enclosed_volume(vertices, tris):
    """The volume a closed, outward triangle mesh encloses (divergence theorem)."""
    p0, p1, p2 = (vertices[tris[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->", p0, np.cross(p1, p2)) / 6.0)
