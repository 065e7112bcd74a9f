"""The manifold boundary mesh (for 3D printing): every edge with two faces, every vertex one fan,
the surface and the volume kept within epsilon; checked here independently of the kernel."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from volumeevm_addon import EVM, VolumeEVM, read_volume
from volumeevm_addon.model._manifold import EPSILON
from volumeevm_addon.model._mesh import mesh_volume_area

LIVER_LABELS = (84, 85, 127, 255)


def following_corners(polygons):
    following = np.arange(1, len(polygons.indices) + 1)
    following[polygons.starts + polygons.sizes - 1] = polygons.starts
    return following


def polygon_areas(vertices, polygons):
    """Each polygon's area (the length of its Newell area vector)."""
    u, v = polygons.edges()
    area = np.add.reduceat(np.cross(vertices[u], vertices[v]), polygons.starts)
    return np.linalg.norm(area, axis=1) / 2


def assert_two_manifold(vertices, polygons):
    """Every undirected edge in exactly two faces, once each way; every vertex one fan of faces
    (its corners form one cycle through shared edges); no two vertices at one point."""
    u, v = polygons.edges()
    n = len(vertices)
    assert not (u == v).any(), "degenerate edge"
    keys = u.astype(np.int64) * n + v
    order = np.argsort(keys)
    assert (np.diff(keys[order]) != 0).all(), "a directed edge in two faces"
    opposite = v.astype(np.int64) * n + u
    found = np.minimum(np.searchsorted(keys[order], opposite), len(keys) - 1)
    assert (keys[order][found] == opposite).all(), "an edge without its opposite: not closed"
    # Around a vertex, the corner after h is the one after h's opposite edge in that face.
    turn = following_corners(polygons)[order[found]]
    corners = len(keys)
    graph = coo_matrix((np.ones(corners), (np.arange(corners), turn)), shape=(corners, corners))
    fans, fan = connected_components(graph, directed=False)
    assert np.array_equal(np.unique(u), np.arange(n)), "unused vertex"
    assert fans == n, f"{fans - n} vertices with more than one fan"
    assert len(np.unique(vertices, axis=0)) == n, "two vertices at one point"


def assert_near_lattice(manifold, plain, epsilon=EPSILON):
    """Every vertex is within ``epsilon`` (per axis) of a vertex of the plain mesh, or of the
    middle of an edge of it between its two polygon neighbours (a vertex added to a doubled
    edge); without the added ones, the polygons visit the plain mesh's points in its order."""
    (vertices, polygons), (lattice, plain_polygons) = manifold, plain
    points = np.round(vertices)
    keys = lambda p: (p[:, 0] * 4096 + p[:, 1]) * 4096 + p[:, 2]  # noqa: E731
    near = (np.abs(vertices - points) <= epsilon * (1 + 1e-9)).all(axis=1)
    copy = near & np.isin(keys(points + 1), keys(lattice + 1))
    corner_copy = copy[polygons.indices]
    kept = polygons.indices[corner_copy]
    sizes = np.add.reduceat(corner_copy.astype(int), polygons.starts)
    assert np.array_equal(sizes, plain_polygons.sizes)
    assert np.array_equal(points[kept], lattice[plain_polygons.indices])
    added = np.flatnonzero(~corner_copy)
    following = following_corners(polygons)
    previous = np.empty_like(following)
    previous[following] = np.arange(len(following))
    assert corner_copy[following[added]].all() and corner_copy[previous[added]].all()
    ends = points[polygons.indices[following[added]]] + points[polygons.indices[previous[added]]]
    off = np.abs(vertices[polygons.indices[added]] - ends / 2)
    assert off.max(initial=0) <= epsilon * (1 + 1e-9)


def volume_bound(vertices, polygons, epsilon=EPSILON):
    """The stated bound on the change of volume: epsilon times each face's area times its
    number of moved vertices (off the lattice)."""
    moved = (vertices != np.round(vertices)).any(axis=1)
    per_face = np.add.reduceat(moved[polygons.indices].astype(float), polygons.starts)
    return epsilon * float(polygon_areas(vertices, polygons) @ per_face)


def assert_manifold_mesh(mask):
    """The manifold mesh of ``mask``: 2-manifold, near the plain one, outward, its volume the
    voxel count within the bound. Returns it."""
    evm = EVM.from_mask(mask)
    manifold, plain = evm.mesh(manifold=True), evm.mesh()
    assert_two_manifold(*manifold)
    assert_near_lattice(manifold, plain)
    volume, _ = mesh_volume_area(*manifold)
    voxels = np.count_nonzero(mask)
    assert abs(volume - voxels) <= volume_bound(*manifold) + 1e-9 * voxels
    return manifold


def contact(kind):
    """Two voxels touching only along an edge, or only at a point."""
    mask = np.zeros((2, 2, 2), bool)
    mask[0, 0, 0] = True
    mask[1, 1, 0 if kind == "edge" else 1] = True
    return mask


@pytest.mark.parametrize("kind", ["edge", "point"])
def test_plain_mesh_is_not_manifold_where_voxels_touch(kind):
    """The check fails on the exact boundary mesh of a contact (so it can fail)."""
    message = "edge in two faces" if kind == "edge" else "more than one fan"
    with pytest.raises(AssertionError, match=message):
        assert_two_manifold(*EVM.from_mask(contact(kind)).mesh())


@pytest.mark.parametrize("kind", ["edge", "point"])
def test_contacts_split_into_two_cubes_moved_apart(kind):
    """Two cubes: the corners they share are there once per cube, moved by epsilon along each
    axis towards that cube's centre; the other corners stay where they are."""
    mask = contact(kind)
    vertices, polygons = assert_manifold_mesh(mask)
    expected = []
    for voxel in np.argwhere(mask):
        for corner in voxel + np.indices((2, 2, 2)).reshape(3, -1).T:
            shared = all(np.all(np.abs(corner - other - 0.5) <= 0.5) for other in np.argwhere(mask))
            expected.append(corner + (EPSILON * np.sign(voxel + 0.5 - corner) if shared else 0))
    expected = np.array(sorted(map(tuple, expected)))
    np.testing.assert_allclose(np.array(sorted(map(tuple, vertices))), expected, rtol=0, atol=1e-12)
    assert len(polygons) == 12


def test_every_configuration_around_a_vertex():
    """All 256 ways to fill the eight voxels around a vertex."""
    for bits in range(1, 256):
        mask = ((bits >> np.arange(8)) & 1).astype(bool).reshape(2, 2, 2)
        assert_manifold_mesh(mask)


def test_diagonal_voxels_between_full_layers_get_middle_vertices():
    """The two voxels touching along an edge join again at both its ends, which keep one copy
    each: each voxel's side of the edge gets a middle vertex, moved into that voxel."""
    mask = np.zeros((2, 2, 3), bool)
    mask[:, :, 0] = mask[:, :, 2] = True
    mask[0, 0, 1] = mask[1, 1, 1] = True
    vertices, _ = assert_manifold_mesh(mask)
    middles = vertices[(np.round(2 * vertices) % 2 == 1).any(axis=1)]
    expected = [[1 - EPSILON, 1 - EPSILON, 1.5], [1 + EPSILON, 1 + EPSILON, 1.5]]
    np.testing.assert_allclose(middles[np.argsort(middles[:, 0])], expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("size", [2, 7])
def test_checkerboard(size):
    """Every voxel touches its diagonal neighbours along edges and at points only."""
    x, y, z = np.indices((size, size, size))
    vertices, _ = assert_manifold_mesh((x + y + z) % 2 == 0)
    corners = np.count_nonzero((x + y + z) % 2 == 0) * 8
    assert len(vertices) == corners  # no voxel shares a corner any more


@pytest.mark.parametrize("fill", [0.2, 0.5, 0.8])
def test_noise(fill):
    rng = np.random.default_rng(int(fill * 10))
    assert_manifold_mesh(rng.random((24, 20, 16)) < fill)


@settings(max_examples=150, deadline=None)
@given(st.tuples(*[st.integers(1, 6)] * 3).flatmap(lambda s: arrays(bool, s)))
def test_random_regions(mask):
    if not mask.any():
        vertices, polygons = EVM.from_mask(mask).mesh(manifold=True)
        assert len(vertices) == 0 and len(polygons) == 0
        return
    assert_manifold_mesh(mask)


def test_a_manifold_region_is_left_as_it_is():
    mask = np.zeros((5, 5, 5), bool)
    mask[1:4, 1:4, 1:4] = True
    mask[2, 2, 3] = False
    evm = EVM.from_mask(mask)
    vertices, polygons = evm.mesh(manifold=True)
    plain_vertices, plain_polygons = evm.mesh()
    np.testing.assert_array_equal(vertices[polygons.indices],
                                  plain_vertices[plain_polygons.indices])
    np.testing.assert_array_equal(polygons.sizes, plain_polygons.sizes)


@pytest.mark.parametrize("name,threshold", [
    ("ct_head_invesalius", 300),  # bone
    ("ct_head_invesalius", -500),  # skin
    ("ct_skull_cgal", 2.9),
    ("mr_t1_itk_kmeans", 60),
    ("mr_brainsmall_volpack", 60),
    ("micro_nuclei3d_stardist", 250),
])
def test_real_volumes(data_dir, name, threshold):
    assert_manifold_mesh(np.load(data_dir / f"{name}.npy") >= threshold)


def test_liver_labels_in_physical_units(data_dir):
    """Each label of the liver label map as its own VolumeEVM: manifold in mm, every copy still
    a distinct point in float32 Blender units (what Blender and STL keep), volume in mm^3."""
    labels = np.load(data_dir / "seg_liver_cgal.npy")
    spacing = (0.617, 0.617, 1.333)
    for label in LIVER_LABELS:
        vevm = VolumeEVM.from_array(labels, label, upper=label, spacing=spacing,
                                    origin=(-135.0, -108.0, 20.0))
        vertices, polygons = vevm.mesh(manifold=True)
        assert_two_manifold(vertices, polygons)
        assert len(np.unique((vertices * 0.001).astype(np.float32), axis=0)) == len(vertices)
        lattice, _ = vevm.evm.mesh(manifold=True)
        np.testing.assert_allclose(vertices, vevm.corner_positions(lattice), rtol=0, atol=1e-9)
        volume, _ = mesh_volume_area(vertices, polygons)
        voxels = np.count_nonzero(labels == label)
        bound = volume_bound(lattice, polygons) + 1e-9 * voxels
        assert abs(volume / np.prod(spacing) - voxels) <= bound


def test_slicer_chest_ct_and_its_segments(data_dir):
    """The 3D Slicer files: the chest CT at bone and each segment of its segmentation."""
    chest = read_volume(data_dir / "slicer" / "CTChest4.nrrd").array
    assert_manifold_mesh(chest >= 300)
    segments = read_volume(data_dir / "slicer" / "Segmentation.seg.nrrd").array
    for label in np.unique(segments)[1:]:
        assert_manifold_mesh(segments == label)
