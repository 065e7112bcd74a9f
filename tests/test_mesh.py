"""The EVM boundary mesh: closed, outward, merged, with exact volume and area."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from volumeevm_addon import EVM, set_kernel_threads
from volumeevm_addon.model import _mesh
from volumeevm_addon.model._mesh import mesh_volume_area


def unit_faces(mask):
    padded = np.pad(mask, 1).astype(np.int8)
    return sum(int(np.count_nonzero(np.diff(padded, axis=axis))) for axis in range(3))


def assert_closed_outward(vertices, polygons, mask):
    u, v = polygons.edges()
    forward = np.sort(u.astype(np.int64) * len(vertices) + v)
    backward = np.sort(v.astype(np.int64) * len(vertices) + u)
    assert np.array_equal(forward, backward), "every directed edge needs its opposite"
    assert not (u == v).any()
    assert len(np.unique(vertices, axis=0)) == len(vertices), "duplicate vertices"
    volume, area = mesh_volume_area(vertices, polygons)
    assert volume == pytest.approx(np.count_nonzero(mask), abs=1e-9)  # positive: outward
    assert area == pytest.approx(unit_faces(mask), abs=1e-9)


@settings(max_examples=150, deadline=None)
@given(st.tuples(st.integers(1, 6), st.integers(1, 6), st.integers(1, 6)).flatmap(
    lambda s: arrays(bool, s)))
def test_mesh_of_random_regions_is_closed_outward_and_exact(mask):
    vertices, polygons = EVM.from_mask(mask).mesh()
    if not mask.any():
        assert len(vertices) == 0 and len(polygons) == 0
        return
    assert_closed_outward(vertices, polygons, mask)


def test_non_manifold_edge_has_four_faces():
    mask = np.zeros((2, 2, 1), bool)
    mask[0, 0, 0] = mask[1, 1, 0] = True
    vertices, polygons = EVM.from_mask(mask).mesh()
    assert_closed_outward(vertices, polygons, mask)
    u, v = polygons.edges()
    shared = [(a, b) for a, b in zip(u, v)
              if {tuple(vertices[a]), tuple(vertices[b])} == {(1, 1, 0), (1, 1, 1)}]
    assert len(shared) == 4


@pytest.mark.parametrize("name,threshold,merged", [
    ("ct_head_invesalius", 300, 0.4),  # bone: the target
    ("ct_head_invesalius", -500, 0.3),  # skin
    ("ct_skull_cgal", 2.9, 0.45),  # small 64^3 grid: shorter runs
    ("mr_brainsmall_volpack", 60, 0.6),  # noisy MRI: many isolated unit faces
])
def test_mesh_of_real_volumes(data_dir, name, threshold, merged):
    mask = np.load(data_dir / f"{name}.npy") >= threshold
    vertices, polygons = EVM.from_mask(mask).mesh()
    assert_closed_outward(vertices, polygons, mask)
    # Merged faces: far fewer polygons than unit voxel faces.
    assert len(polygons) <= merged * unit_faces(mask)


def test_polygons_iterate_as_loops():
    mask = np.ones((2, 1, 1), bool)
    vertices, polygons = EVM.from_mask(mask).mesh()
    loops = list(polygons)
    assert len(loops) == 6 and sum(len(loop) for loop in loops) == 24
    assert sorted(len(loop) for loop in loops) == [4] * 6


def mesh_arrays(mask):
    vertices, polygons = EVM.from_mask(mask).mesh()
    return vertices, polygons.indices, polygons.starts, polygons.sizes


def test_mesh_is_the_same_on_one_thread_and_on_two(data_dir):
    """Blocks of planes and of polygons run in parallel: the result never depends on the thread
    count (the CT head at bone cuts into several blocks of each kind)."""
    mask = np.load(data_dir / "ct_head_invesalius.npy") >= 300
    previous = set_kernel_threads(1)
    try:
        one = mesh_arrays(mask)
        set_kernel_threads(2)
        two = mesh_arrays(mask)
    finally:
        set_kernel_threads(previous)
    for a, b in zip(one, two):
        assert a.dtype == b.dtype and np.array_equal(a, b)


@settings(max_examples=60, deadline=None)
@given(st.tuples(st.integers(1, 7), st.integers(1, 7), st.integers(1, 7)).flatmap(
           lambda s: arrays(bool, s)),
       st.integers(1, 20), st.integers(1, 20))
def test_mesh_does_not_depend_on_how_the_work_is_cut(mask, block_vertices, block_rectangles):
    """Tiny blocks (a plane or a few rectangles each, on two threads) give the same arrays."""
    whole = mesh_arrays(mask)
    previous = set_kernel_threads(2)
    try:
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(_mesh, "_BLOCK_VERTICES", block_vertices)
            patch.setattr(_mesh, "_BLOCK_RECTANGLES", block_rectangles)
            cut = mesh_arrays(mask)
    finally:
        set_kernel_threads(previous)
    for a, b in zip(whole, cut):
        assert a.dtype == b.dtype and np.array_equal(a, b)


def test_unique_edges_are_the_boundary_meshs_edges(data_dir):
    """The sorting edge table of any polygons (the manifold mesh's) gives the boundary mesh the
    same edges as its own along-the-lines table, and each corner the same edge."""
    mesh = _mesh.BoundaryMesh(EVM.from_mask(np.load(data_dir / "ct_skull_cgal.npy") >= 2.9))
    edges, corner_edges = mesh.edges()
    unique, corner_unique = mesh.polygons.unique_edges()
    assert unique.dtype == corner_unique.dtype == np.int32
    np.testing.assert_array_equal(unique, np.unique(np.sort(edges, axis=1), axis=0))
    np.testing.assert_array_equal(unique[corner_unique], np.sort(edges[corner_edges], axis=1))
