"""Tests of the exact mesh voxelization (volumeevm_addon/model/_voxelize.py).

The oracle is the generalized winding number (sum of the triangles' solid angles, Van
Oosterom & Strackee 1983), evaluated by brute force over all triangles. It is exactly 0 or 1
away from the surface of a closed mesh, independent of rays and tie rules.
"""

import numpy as np
import pytest

from reader_files import DATA
from volumeevm_addon import EVM, VolumeEVMError, grid_to_world, voxelize_mesh
from volumeevm_addon.model import (
    MeshCheck,
    _voxelize,
    box_evm,
    check_closed_mesh,
    tool_to_grid,
    voxelize_mesh_evm,
)

CLOSED_MESHES = [
    "mesh_tool_fandisk",
    "mesh_tool_rotor",
    "mesh_tool_anchor",
    "mesh_tool_nut",
    "mesh_bunny",
    "mesh_femur",
]


def load_mesh(name):
    with np.load(DATA / f"{name}.npz") as data:
        return data["vertices"], data["faces"]


def rotation(axis, angle):
    """3x3 rotation matrix about ``axis`` by ``angle`` radians (Rodrigues)."""
    x, y, z = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def fit_to_grid(vertices, span, linear=np.eye(3), margin=1.37):
    """A to_grid matrix (``linear`` then scale) and the grid shape holding the mesh.

    The longest side of the transformed mesh is ``span`` voxels; the offset is generic, so
    no voxel centre lies on the surface.
    """
    pts = vertices @ linear.T
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    scale = span / (hi - lo).max()
    matrix = np.eye(4)
    matrix[:3, :3] = scale * linear
    matrix[:3, 3] = margin - scale * lo + np.array([0.0123457, 0.0234568, 0.0345679])
    shape = tuple(int(n) for n in np.ceil(scale * (hi - lo) + 2 * margin))
    return matrix, shape


def apply(matrix, vertices):
    return vertices @ matrix[:3, :3].T + matrix[:3, 3]


def box(lo, hi):
    """Closed box mesh [lo, hi] with outward faces: (8, 3) vertices, (12, 3) faces."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    vertices = lo + corners * (hi - lo)
    faces = np.array([
        [0, 1, 3], [0, 3, 2],  # x = lo
        [4, 6, 7], [4, 7, 5],  # x = hi
        [0, 4, 5], [0, 5, 1],  # y = lo
        [2, 3, 7], [2, 7, 6],  # y = hi
        [0, 2, 6], [0, 6, 4],  # z = lo
        [1, 5, 7], [1, 7, 3],  # z = hi
    ])
    return vertices, faces


def merge(*meshes):
    """Concatenate meshes into one vertex and face array."""
    vertices, faces, offset = [], [], 0
    for v, f in meshes:
        vertices.append(v)
        faces.append(f + offset)
        offset += len(v)
    return np.concatenate(vertices), np.concatenate(faces)


def half_open_box_mask(shape, lo, hi):
    """Centres (i, j, k) with lo <= (i, j, k) < hi: the documented rule for a box."""
    idx = np.indices(shape)
    lo = np.asarray(lo, float).reshape(3, 1, 1, 1)
    hi = np.asarray(hi, float).reshape(3, 1, 1, 1)
    return np.all((idx >= lo) & (idx < hi), axis=0)


# --- brute-force oracle ----------------------------------------------------------------------

def winding_numbers(tri, points, chunk=1 << 21):
    """Generalized winding number of triangles ``tri`` (F, 3, 3) at ``points`` (P, 3).

    Van Oosterom-Strackee: tan(omega / 2) = a.(b x c) / (|a||b||c| + (a.b)|c| + (b.c)|a| +
    (c.a)|b|) with a, b, c the corners relative to the point; w = sum(omega) / (4 pi). The
    dot products are expanded (a.b = A.B - q.(A + B) + q.q) so that they become one matrix
    product per chunk of points.
    """
    centre = tri.reshape(-1, 3).mean(axis=0)
    tri, points = tri - centre, points - centre
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n_tri = len(tri)
    normal = np.cross(b - a, c - a)
    coeff = np.concatenate([normal, -2 * a, -2 * b, -2 * c, -(a + b), -(b + c), -(c + a)]).T
    const = np.concatenate([
        -np.einsum("fi,fi->f", a, normal),
        *(np.einsum("fi,fi->f", u, v)
          for u, v in ((a, a), (b, b), (c, c), (a, b), (b, c), (c, a))),
    ])
    out = np.empty(len(points))
    per = max(1, chunk // n_tri)
    for first in range(0, len(points), per):
        q = points[first:first + per]
        r = q @ coeff
        r += const
        r[:, n_tri:] += np.einsum("pi,pi->p", q, q)[:, None]
        det = -r[:, :n_tri]
        lengths = np.sqrt(r[:, n_tri:4 * n_tri])
        la, lb, lc = np.split(lengths, 3, axis=1)
        ab, bc, ca = np.split(r[:, 4 * n_tri:], 3, axis=1)
        den = la * lb * lc + ab * lc + bc * la + ca * lb
        out[first:first + per] = np.arctan2(det, den).sum(axis=1) / (2 * np.pi)
    return out


def near_surface(tri, shape):
    """Centres c such that a segment from c to a 6-neighbour may meet a triangle.

    If the segment [c, c + e_a] meets triangle T, T's bounding box holds a point with the
    other two coordinates of c and coordinate a in [c_a, c_a + 1]: both ends are marked by
    the bounding box widened by 1 along axis a. Two 6-adjacent centres that are not marked
    are therefore on the same side of the surface.
    """
    near = np.zeros(shape, bool)
    size = np.asarray(shape)
    for axis in range(3):
        widen = np.eye(3)[axis]
        lo = np.maximum(np.ceil(tri.min(axis=1) - widen), 0).astype(np.int64)
        hi = np.minimum(np.floor(tri.max(axis=1) + widen), size - 1).astype(np.int64)
        width = np.maximum(hi - lo + 1, 0)
        count = width.prod(axis=1)
        tri_of = np.repeat(np.arange(len(tri)), count)
        local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
        w = width[tri_of]
        i = lo[tri_of, 0] + local % w[:, 0]
        j = lo[tri_of, 1] + (local // w[:, 0]) % w[:, 1]
        k = lo[tri_of, 2] + local // (w[:, 0] * w[:, 1])
        near[i, j, k] = True
    return near


def component_labels(free):
    """Label of each free voxel: the smallest flat index of its 6-connected component."""
    big = np.iinfo(np.int64).max
    label = np.where(free, np.arange(free.size).reshape(free.shape), big)
    while True:
        new = label.copy()
        for axis in range(3):
            for src, dst in ((slice(1, None), slice(None, -1)), (slice(None, -1), slice(1, None))):
                a = [slice(None)] * 3
                b = [slice(None)] * 3
                a[axis], b[axis] = dst, src
                np.minimum(new[tuple(a)], label[tuple(b)], out=new[tuple(a)])
        new[~free] = big
        if np.array_equal(new, label):
            return label
        label = new


def assert_matches_winding_number(vertices, faces, shape, matrix):
    """voxelize_mesh equals |winding number| > 0.5 at every voxel centre.

    The oracle is evaluated by brute force at every centre near the surface (see
    ``near_surface``) and at one centre of each connected region of the rest, where the mask
    must be constant. Returns the mask.
    """
    mask = voxelize_mesh(vertices, faces, shape, matrix)
    assert mask.shape == shape and mask.dtype == np.bool_
    tri = apply(matrix, vertices)[faces]
    near = near_surface(tri, shape)
    label = component_labels(~near).reshape(-1)
    far = np.flatnonzero(~near.reshape(-1))
    # A region's label is the flat index of its first voxel: that voxel represents it.
    points = np.concatenate([np.flatnonzero(near.reshape(-1)), np.unique(label[far])])
    w = winding_numbers(tri, np.stack(np.unravel_index(points, shape), axis=1).astype(float))
    # Generic placement: no centre is on or within rounding distance of the surface, where
    # the oracle is not an integer; none is excluded.
    assert np.abs(w - np.round(w)).max() < 1e-6
    expected = np.zeros(mask.size, bool)
    expected[points] = np.abs(w) > 0.5
    expected[far] = expected[label[far]]
    expected = expected.reshape(shape)
    mismatch = np.argwhere(mask != expected)
    assert len(mismatch) == 0, f"{len(mismatch)} voxels differ, first {mismatch[:5].tolist()}"
    assert 0 < mask.sum() < mask.size
    return mask


# --- equality with the oracle on all closed meshes --------------------------------------------

# Longest side in voxels at two resolutions: the big meshes get smaller grids so that the
# brute force (points x triangles) stays affordable.
SPANS = {
    "mesh_tool_fandisk": (14, 23),
    "mesh_tool_rotor": (24, 37),
    "mesh_tool_anchor": (24, 37),
    "mesh_tool_nut": (24, 37),
    "mesh_bunny": (9, 13),
    "mesh_femur": (20, 31),
}
TILT = rotation([1.0, 2.0, 3.0], 0.7)


@pytest.mark.parametrize("name", CLOSED_MESHES)
@pytest.mark.parametrize("level", [0, 1])
def test_matches_winding_number(name, level):
    vertices, faces = load_mesh(name)
    matrix, shape = fit_to_grid(vertices, SPANS[name][level])
    assert_matches_winding_number(vertices, faces, shape, matrix)


@pytest.mark.parametrize("name", CLOSED_MESHES)
def test_matches_winding_number_rotated_stretched(name):
    vertices, faces = load_mesh(name)
    linear = TILT @ np.diag([1.0, 0.8, 1.3])
    matrix, shape = fit_to_grid(vertices, SPANS[name][0] * 1.2, linear)
    assert_matches_winding_number(vertices, faces, shape, matrix)


def test_mirroring_transform_mirrors_mask():
    vertices, faces = load_mesh("mesh_tool_rotor")
    matrix, shape = fit_to_grid(vertices, 30, TILT)
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    mirror[0, 3] = shape[0] - 1
    mask = voxelize_mesh(vertices, faces, shape, matrix)
    mirrored = voxelize_mesh(vertices, faces, shape, mirror @ matrix)
    assert mask.sum() > 100
    np.testing.assert_array_equal(mirrored, mask[::-1])
    # The mirrored result is also right, not just mirrored.
    assert_matches_winding_number(vertices, faces, shape, mirror @ matrix)


def test_inside_out_mesh_gives_same_mask():
    vertices, faces = load_mesh("mesh_tool_nut")
    matrix, shape = fit_to_grid(vertices, 20)
    reversed_faces = faces[:, ::-1]
    assert check_closed_mesh(vertices, reversed_faces).signed_volume < 0
    np.testing.assert_array_equal(
        voxelize_mesh(vertices, reversed_faces, shape, matrix),
        voxelize_mesh(vertices, faces, shape, matrix),
    )


# --- ties: centres exactly on faces, edges and corners ----------------------------------------

def test_unit_cube_on_lattice_is_half_open():
    # The unit cube mapped to [2, 5] x [3, 7] x [1, 3]: centres lie on its faces, edges
    # (including the face diagonals of the triangulation) and corners.
    vertices, faces = box([0, 0, 0], [1, 1, 1])
    matrix = np.diag([3.0, 4.0, 2.0, 1.0])
    matrix[:3, 3] = [2, 3, 1]
    shape = (8, 9, 5)
    mask = voxelize_mesh(vertices, faces, shape, matrix)
    np.testing.assert_array_equal(mask, half_open_box_mask(shape, [2, 3, 1], [5, 7, 3]))
    assert mask.sum() == 3 * 4 * 2


def test_boxes_with_edges_on_rays():
    # Both diagonals of every face and boxes touching the grid border.
    shape = (7, 6, 5)
    for lo, hi in [([1, 1, 1], [4, 4, 4]), ([0, 0, 0], [7, 6, 5]), ([-2, 3, 2], [2, 9, 3])]:
        vertices, faces = box(lo, hi)
        for tris in (faces, other_diagonals(faces)):
            mask = voxelize_mesh(vertices, tris, shape, np.eye(4))
            np.testing.assert_array_equal(mask, half_open_box_mask(shape, lo, hi))
        # The same box with every face split through its centre: more edges and vertices on rays.
        vertices2, faces2 = split_faces(vertices, faces)
        mask = voxelize_mesh(vertices2, faces2, shape, np.eye(4))
        np.testing.assert_array_equal(mask, half_open_box_mask(shape, lo, hi))


def other_diagonals(faces):
    """The box faces of ``box`` triangulated along their other diagonals."""
    quads = faces.reshape(6, 2, 3)
    a, b, c, d = quads[:, 0, 0], quads[:, 0, 1], quads[:, 0, 2], quads[:, 1, 2]
    return np.concatenate([np.stack([a, b, d], 1), np.stack([b, c, d], 1)])


def split_faces(vertices, faces):
    """Split each triangle into three around its centroid (the surface stays the same)."""
    centroids = vertices[faces].mean(axis=1)
    index = len(vertices) + np.arange(len(faces))
    a, b, c = faces.T
    new = np.concatenate([np.stack([a, b, index], 1), np.stack([b, c, index], 1),
                          np.stack([c, a, index], 1)])
    return np.concatenate([vertices, centroids]), new


def test_slanted_face_through_centres():
    # Wedge 0 <= y <= 4, 0 <= x <= 4, 0 <= z <= x: top face z = x has normal (-1, 0, 1); a
    # centre on it is outside (the solid does not continue towards +z).
    vertices = np.array([[0, 0, 0], [4, 0, 0], [4, 0, 4], [0, 4, 0], [4, 4, 0], [4, 4, 4]], float)
    faces = np.array([
        [0, 1, 2], [3, 5, 4],  # y = 0, y = 4
        [0, 4, 1], [0, 3, 4],  # z = 0
        [1, 4, 5], [1, 5, 2],  # x = 4
        [0, 5, 3], [0, 2, 5],  # z = x
    ])
    assert check_closed_mesh(vertices, faces).signed_volume == pytest.approx(32.0)
    shape = (6, 6, 6)
    i, j, k = np.indices(shape)
    expected = (0 <= j) & (j < 4) & (i < 4) & (0 <= k) & (k < i)
    np.testing.assert_array_equal(voxelize_mesh(vertices, faces, shape, np.eye(4)), expected)
    assert expected.sum() == 4 * (0 + 1 + 2 + 3)


def test_vertical_slanted_face_through_centres():
    # Prism over the triangle (0,0), (4,0), (4,4), 0 <= z <= 4. Its face x = y is parallel to
    # z with outward normal (-1, 1, 0): the tie rule looks towards +x, into the solid.
    tri = np.array([[0, 0], [4, 0], [4, 4]], float)
    vertices = np.concatenate([np.c_[tri, np.zeros(3)], np.c_[tri, np.full(3, 4.0)]])
    faces = np.array([
        [0, 2, 1], [3, 4, 5],  # bottom, top
        [0, 1, 4], [0, 4, 3],  # y = 0
        [1, 2, 5], [1, 5, 4],  # x = 4
        [2, 0, 3], [2, 3, 5],  # x = y
    ])
    assert check_closed_mesh(vertices, faces).signed_volume == pytest.approx(32.0)
    shape = (6, 6, 6)
    i, j, k = np.indices(shape)
    expected = (0 <= j) & (j <= i) & (i < 4) & (k < 4)
    np.testing.assert_array_equal(voxelize_mesh(vertices, faces, shape, np.eye(4)), expected)
    assert expected.sum() == 10 * 4


def test_tetrahedron_corner_on_centres():
    # A corner where six faces of a split cube meet, on a ray column, and centres on the
    # slanted faces of a tetrahedron.
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    shape = (7, 7, 7)
    mask = voxelize_mesh(vertices, faces, shape, np.diag([6.0, 6.0, 6.0, 1.0]))
    i, j, k = np.indices(shape)
    np.testing.assert_array_equal(mask, i + j + k < 6)


def lattice_polyhedra(rng, count, shape):
    """Random integer images of an octahedron, a cube and a tetrahedron, merged.

    Vertices are lattice points and face normals are small integer vectors, so many voxel
    centres lie exactly on faces, edges and vertices, and rays graze edges and vertices.
    Overlapping parts and coplanar faces of different parts occur.
    """
    octahedron = (np.concatenate([np.eye(3), -np.eye(3)]),
                  np.array([[0, 1, 2], [1, 3, 2], [3, 4, 2], [4, 0, 2],
                            [1, 0, 5], [3, 1, 5], [4, 3, 5], [0, 4, 5]]))
    cube = box([-1, -1, -1], [1, 1, 1])
    tetrahedron = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float),
                   np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]))
    parts = []
    while len(parts) < count:
        linear = rng.integers(-2, 3, size=(3, 3)).astype(float)
        if abs(np.linalg.det(linear)) < 0.5:
            continue
        v, f = (octahedron, cube, tetrahedron)[len(parts) % 3]
        offset = rng.integers(2, np.asarray(shape) - 2).astype(float)
        # A negative determinant turns the part inside out: reverse its faces to keep it outward.
        f = f if np.linalg.det(linear) > 0 else f[:, ::-1]
        parts.append((v @ linear.T + offset, f))
    return merge(*parts)


@pytest.mark.parametrize("seed", range(4))
def test_lattice_polyhedra_match_perturbed_winding_number(seed):
    # The documented rule says a centre c is inside iff c + (e, e**2, d) is, 0 < e**2 << e << d.
    # With integer vertices in a small grid every face normal n (cross product of two edges)
    # has |n_i| <= 64 and every plane offset n.c - n.v0 is an integer, so e = 1e-6, d = 1e-3
    # realise that order and move no centre across a face it is not on: the oracle at
    # c + (e, e**2, d) is the rule.
    rng = np.random.default_rng(seed)
    shape = (12, 11, 10)
    vertices, faces = lattice_polyhedra(rng, 6, shape)
    check_closed_mesh(vertices, faces)
    mask = voxelize_mesh(vertices, faces, shape, np.eye(4))
    centres = np.stack(np.unravel_index(np.arange(mask.size), shape), axis=1).astype(float)
    w = winding_numbers(vertices[faces], centres + [1e-6, 1e-12, 1e-3])
    assert np.abs(w - np.round(w)).max() < 1e-6
    np.testing.assert_array_equal(mask, (np.abs(w) > 0.5).reshape(shape))
    # And the ties really happen: many centres lie exactly on the surface.
    with np.errstate(invalid="ignore"):  # undefined at a vertex: NaN
        on_surface = ~(np.abs(winding_numbers(vertices[faces], centres) - np.round(w)) < 1e-6)
    assert on_surface.sum() > 50


# --- topology: genus, nesting, components -----------------------------------------------------

def test_rotor_hole_is_empty():
    vertices, faces = load_mesh("mesh_tool_rotor")
    assert check_closed_mesh(vertices, faces).euler_characteristic == 0  # genus 1
    matrix, shape = fit_to_grid(vertices, 40)
    mask = voxelize_mesh(vertices, faces, shape, matrix)
    # The ring lies in the mesh's y-z plane: the line through the centre of its bounding box
    # along x is outside, and the ring is inside on both sides of it along y and along z.
    centre = apply(matrix, (vertices.min(axis=0) + vertices.max(axis=0)) / 2)
    j, k = np.round(centre[1:]).astype(int)
    assert not mask[:, j, k].any()
    ring_y, ring_z = mask[:, :, k].any(axis=0), mask[:, j, :].any(axis=0)
    assert ring_y[:j].any() and ring_y[j + 1:].any() and ring_z[:k].any() and ring_z[k + 1:].any()


def test_nested_shells_reversed_inner_is_hollow():
    outer = box([1, 1, 1], [9, 9, 9])
    inner_v, inner_f = box([3, 4, 3], [6, 7, 8])
    shape = (10, 10, 10)
    vertices, faces = merge(outer, (inner_v, inner_f[:, ::-1]))
    check_closed_mesh(vertices, faces)
    mask = voxelize_mesh(vertices, faces, shape, np.eye(4))
    expected = half_open_box_mask(shape, [1, 1, 1], [9, 9, 9]) & ~half_open_box_mask(
        shape, [3, 4, 3], [6, 7, 8]
    )
    np.testing.assert_array_equal(mask, expected)
    # Same orientation for both shells: winding number 2 inside the inner one, still inside.
    vertices, faces = merge(outer, (inner_v, inner_f))
    mask = voxelize_mesh(vertices, faces, shape, np.eye(4))
    np.testing.assert_array_equal(mask, half_open_box_mask(shape, [1, 1, 1], [9, 9, 9]))


def test_nested_shells_of_real_mesh_generic_position():
    vertices, faces = load_mesh("mesh_tool_fandisk")
    centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
    small = centre + 0.3 * (vertices - centre)
    hollow_v, hollow_f = merge((vertices, faces), (small, faces[:, ::-1]))
    matrix, shape = fit_to_grid(vertices, 15)
    full = voxelize_mesh(vertices, faces, shape, matrix)
    core = voxelize_mesh(small, faces, shape, matrix)
    hollow = assert_matches_winding_number(hollow_v, hollow_f, shape, matrix)
    assert core.sum() > 0
    # Winding number 1 - 1 = 0 where both contain a centre (the cavity); the small copy
    # pokes out of the non-convex fandisk, and there the winding number is -1: inside.
    np.testing.assert_array_equal(hollow, full ^ core)
    assert (core & full).sum() > 0 and (hollow & core).sum() > 0


def test_thin_slabs_at_a_centre_plane():
    # Slabs 1e-12 voxels thick around, above and below the plane of centres k = 3.
    shape = (6, 5, 7)
    for z0, z1, expected in [
        (3 - 1e-12, 3 + 1e-12, [1.5, 0.5, 3, 4.5, 3.5, 4]),
        (3.0, 3 + 1e-12, [1.5, 0.5, 3, 4.5, 3.5, 4]),
        (3 - 1e-12, 3.0, None),
        (3 + 1e-12, 3 + 2e-12, None),
    ]:
        vertices, faces = box([1.5, 0.5, z0], [4.5, 3.5, z1])
        mask = voxelize_mesh(vertices, faces, shape, np.eye(4))
        if expected is None:
            assert not mask.any()
        else:
            np.testing.assert_array_equal(
                mask, half_open_box_mask(shape, expected[:3], expected[3:]))
            assert mask.sum() == 3 * 3


def test_parts_sharing_an_edge_and_degenerate_faces():
    # Two boxes welded along the edge x = y = 3: that edge is used twice in each direction,
    # which is still a closed, oriented surface. A zero-area face (repeated vertex) is ignored.
    vertices, faces = merge(box([1, 1, 1], [3, 3, 4]), box([3, 3, 1], [5, 6, 4]))
    welded, index = np.unique(vertices, axis=0, return_inverse=True)
    faces = np.concatenate([index.reshape(-1)[faces], [[0, 0, 1]]])
    info = check_closed_mesh(welded, faces)
    assert info.n_vertices == 14 and info.signed_volume == pytest.approx(12 + 18)
    shape = (7, 7, 5)
    expected = half_open_box_mask(shape, [1, 1, 1], [3, 3, 4]) | half_open_box_mask(
        shape, [3, 3, 1], [5, 6, 4])
    np.testing.assert_array_equal(voxelize_mesh(welded, faces, shape, np.eye(4)), expected)


def test_many_components():
    rng = np.random.default_rng(7)
    shape = (30, 25, 20)
    meshes, expected = [], np.zeros(shape, bool)
    for _ in range(40):
        lo = rng.uniform(-3, np.array(shape) - 2)
        hi = lo + rng.uniform(0.3, 6, size=3)
        meshes.append(box(lo, hi))
        expected |= half_open_box_mask(shape, lo, hi)
    vertices, faces = merge(*meshes)  # some boxes overlap: the mask is their union
    mask = voxelize_mesh(vertices, faces, shape, np.eye(4))
    np.testing.assert_array_equal(mask, expected)
    # Real meshes side by side, one of them overlapping another.
    rotor, nut = load_mesh("mesh_tool_rotor"), load_mesh("mesh_tool_nut")
    nut = ((nut[0] - nut[0].mean(axis=0)) / 46.0, nut[1])
    parts = [rotor, (rotor[0] + [0.6, 0, 0], rotor[1]), (nut[0] + [0.3, 0.2, 0.1], nut[1])]
    vertices, faces = merge(*parts)
    matrix, shape = fit_to_grid(vertices, 22)
    mask = assert_matches_winding_number(vertices, faces, shape, matrix)
    union = np.zeros(shape, bool)
    for v, f in parts:
        union |= voxelize_mesh(v, f, shape, matrix)
    np.testing.assert_array_equal(mask, union)


def test_mesh_partly_outside_grid():
    vertices, faces = load_mesh("mesh_femur")
    matrix, shape = fit_to_grid(vertices, 30)
    full = voxelize_mesh(vertices, faces, shape, matrix)
    shifted = matrix.copy()
    shifted[:3, 3] -= [7, 3, 12]
    part = voxelize_mesh(vertices, faces, shape, shifted)
    np.testing.assert_array_equal(part[: shape[0] - 7, : shape[1] - 3, : shape[2] - 12],
                                  full[7:, 3:, 12:])
    assert not part[shape[0] - 7:].any()


# --- validation -----------------------------------------------------------------------------

def test_check_closed_mesh_reports_facts():
    vertices, faces = load_mesh("mesh_femur")
    info = check_closed_mesh(vertices, faces)
    assert isinstance(info, MeshCheck)
    assert (info.n_vertices, info.n_faces, info.n_edges) == (3897, 7798, 11697)
    assert info.euler_characteristic == -2
    v, f = box([0, 0, 0], [2, 3, 4])
    assert check_closed_mesh(v, f).signed_volume == pytest.approx(24.0)


def test_open_mesh_raises():
    vertices, faces = load_mesh("mesh_open_mech_holes_shark")
    with pytest.raises(VolumeEVMError, match=r"not closed: 304 open \(boundary\) edges"):
        check_closed_mesh(vertices, faces)
    with pytest.raises(VolumeEVMError, match="304 open"):
        voxelize_mesh(vertices, faces, (10, 10, 10), np.diag([9.0, 9.0, 9.0, 1.0]))


def test_inconsistent_orientation_raises():
    vertices, faces = load_mesh("mesh_tool_rotor")
    faces = faces.copy()
    faces[[5, 17]] = faces[[5, 17], ::-1]
    with pytest.raises(VolumeEVMError, match="not consistently oriented: 6 edges"):
        check_closed_mesh(vertices, faces)


def test_bad_input_raises():
    vertices, faces = box([0, 0, 0], [1, 1, 1])
    eye = np.eye(4)
    nan = vertices.copy()
    nan[3, 1] = np.nan
    cases = [
        ((nan, faces), "1 of 8 vertices with NaN"),
        ((vertices, faces + 1), "6 faces with vertex indices outside"),
        ((vertices, faces - 3), "faces with vertex indices outside"),
        ((vertices[:0], faces[:0]), "empty: 0 vertices and 0 faces"),
        ((vertices, faces[:0]), "empty"),
        ((vertices[:, :2], faces), r"vertices must have shape \(V, 3\)"),
        ((vertices, faces[:, :2]), r"faces must have shape \(F, 3\)"),
        ((vertices, faces.astype(float)), "faces must be integer"),
    ]
    for (v, f), message in cases:
        with pytest.raises(VolumeEVMError, match=message):
            check_closed_mesh(v, f)
        with pytest.raises(VolumeEVMError, match=message):
            voxelize_mesh(v, f, (4, 4, 4), eye)
    perspective = eye.copy()
    perspective[3, 2] = 1.0
    for shape, matrix, message in [
        ((4, 4), eye, "shape must be three positive integers"),
        ((4, 0, 4), eye, "shape must be three positive integers"),
        ((4, 4, 4), eye[:3], "4x4 matrix"),
        ((4, 4, 4), perspective, "affine"),
        ((4, 4, 4), np.diag([1.0, 0.0, 1.0, 1.0]), "singular"),
        ((4, 4, 4), np.full((4, 4), np.nan), "NaN"),
    ]:
        with pytest.raises(VolumeEVMError, match=message):
            voxelize_mesh(vertices, faces, shape, matrix)


def test_wholly_outside_raises():
    vertices, faces = load_mesh("mesh_tool_anchor")
    matrix, shape = fit_to_grid(vertices, 10)
    for shift in ([shape[0] + 10.0, 0, 0], [0, -30.0, 0], [0, 0, 100.0]):
        moved = matrix.copy()
        moved[:3, 3] += shift
        with pytest.raises(VolumeEVMError, match="wholly outside the volume"):
            voxelize_mesh(vertices, faces, shape, moved)


def test_chunking_does_not_change_result(monkeypatch):
    # Small chunks split the (triangle, column) pairs of single big triangles across chunks.
    vertices, faces = load_mesh("mesh_tool_anchor")
    matrix, shape = fit_to_grid(vertices, 30, TILT)
    big_v, big_f = box([1, 1, 1], [shape[0] - 1, shape[1] - 2.5, 9])
    vertices, faces = merge((apply(matrix, vertices), faces), (big_v, big_f))
    whole = voxelize_mesh(vertices, faces, shape, np.eye(4))
    monkeypatch.setattr(_voxelize, "_CHUNK", 97)
    np.testing.assert_array_equal(voxelize_mesh(vertices, faces, shape, np.eye(4)), whole)
    assert whole.sum() > 1000


def test_extreme_coordinates_stay_exact():
    # Subnormal and tiny corner coordinates (exact fallback with ~1000-bit integers) and
    # corners 1e25 voxels away.
    vertices, faces = box([1e-300, -1e-300, 5e-324], [4, 3 - 2.0**-50, 2 + 1e-15])
    mask = voxelize_mesh(vertices, faces, (6, 5, 4), np.eye(4))
    np.testing.assert_array_equal(mask, half_open_box_mask((6, 5, 4), [1, 0, 1], [4, 3, 3]))
    corners, faces = box([0, 0, 0], [1, 1, 1])
    vertices = np.where(corners == 0, -1e25, 2.5)
    mask = voxelize_mesh(vertices, faces, (6, 5, 4), np.eye(4))
    np.testing.assert_array_equal(mask, half_open_box_mask((6, 5, 4), [0, 0, 0], [2.5, 2.5, 2.5]))
    with pytest.raises(VolumeEVMError, match="1e\\+40 voxels away"):
        voxelize_mesh(vertices * 1e15, faces, (6, 5, 4), np.eye(4))


def test_small_mesh_between_centres_is_empty():
    vertices, faces = box([0.2, 0.2, 0.2], [0.8, 0.8, 0.8])
    mask = voxelize_mesh(vertices, faces, (3, 3, 3), np.eye(4))
    assert mask.shape == (3, 3, 3) and not mask.any()


# ---------------------------------------------------------------------- EVM on the tool's box
@pytest.mark.parametrize("name", ["mesh_tool_nut", "mesh_tool_fandisk"])
def test_evm_on_the_tool_box_equals_the_whole_grid(name):
    """A tool in a bigger grid, partly outside it: same voxels as voxelizing the whole grid."""
    vertices, faces = load_mesh(name)
    matrix, shape = fit_to_grid(vertices, 30, rotation((1, 2, 3), 0.7))
    matrix[:3, 3] += (17.25, -9.5, 6.0)  # sticks out of the grid at y < 0
    grid = (60, 40, 50)
    expected = EVM.from_mask(voxelize_mesh(vertices, faces, grid, matrix))
    assert voxelize_mesh_evm(vertices, faces, grid, matrix) == expected
    assert not expected.is_empty()
    with pytest.raises(VolumeEVMError, match="wholly outside"):
        far = matrix.copy()
        far[:3, 3] += 500
        voxelize_mesh_evm(vertices, faces, grid, far)


def test_box_evm_follows_the_tie_rule_of_a_box_mesh():
    for lo, hi in [((1.0, 2.0, 0.5), (6.0, 4.0, 3.5)), ((-3.2, 1.7, 2.0), (4.9, 9.0, 2.6)),
                   ((0.4, 0.4, 0.4), (0.6, 0.6, 0.6))]:
        vertices, faces = box(lo, hi)
        expected = EVM.from_mask(voxelize_mesh(vertices, faces, (8, 8, 8), np.eye(4)))
        assert box_evm(lo, hi, (8, 8, 8)) == expected


def test_tool_to_grid_undoes_the_volumes_placement():
    """A tool placed in the world lands in the volume's index space: the inverse of the
    volume's grid_to_world after the tool's placement, affine exactly."""
    orientation = rotation((0, 0, 1), 0.3)
    volume = np.eye(4)
    volume[:3, :3] = rotation((1, 1, 0), 0.4) * 1.5
    volume[:3, 3] = (0.1, -0.2, 0.05)
    tool = np.eye(4)
    tool[:3, :3], tool[:3, 3] = rotation((1, 2, 3), 0.7), (0.02, 0.01, -0.03)
    spacing, origin = (0.9, 0.8, 1.5), (-30.0, -20.0, 50.0)
    to_grid = tool_to_grid(tool, spacing, origin, orientation, matrix_world=volume)
    assert to_grid.dtype == np.float64
    assert to_grid[3].tolist() == [0.0, 0.0, 0.0, 1.0]
    world = grid_to_world(spacing, origin, orientation, volume)
    points = np.array([[0.0, 0.0, 0.0, 1.0], [0.01, -0.02, 0.005, 1.0]])
    np.testing.assert_allclose(world @ (to_grid @ points.T), tool @ points.T, atol=1e-12)
    # A tool 4 mm along x of a 2 mm grid at the origin: 2 voxels along x.
    moved = np.eye(4)
    moved[0, 3] = 0.004
    np.testing.assert_allclose(tool_to_grid(moved, (2.0, 2.0, 2.0), (0.0, 0.0, 0.0))[:3, 3],
                               (2.0, 0.0, 0.0), atol=1e-12)


@pytest.mark.parametrize("tool, volume, match", [
    (np.eye(3), None, r"tool_matrix: a finite 4x4 matrix, got shape \(3, 3\)"),
    (np.full((4, 4), np.nan), None, "tool_matrix: a finite 4x4 matrix"),
    (np.eye(4), np.diag([1.0, 0.0, 1.0, 1.0]), "matrix_world: the volume's placement cannot be "
                                               "inverted"),
])
def test_tool_to_grid_refuses_bad_placements(tool, volume, match):
    with pytest.raises(VolumeEVMError, match=match):
        tool_to_grid(tool, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), matrix_world=volume)
