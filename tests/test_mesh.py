"""The EVM boundary mesh: closed, outward, merged, with exact volume and area."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from volumeevm_addon import EVM
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
@given(st.tuples(st.integers(1, 6), st.integers(1, 6), st.integers(1, 6)).flatmap(lambda s: arrays(bool, s)))
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
    shared = [(a, b) for a, b in zip(u, v) if {tuple(vertices[a]), tuple(vertices[b])} == {(1, 1, 0), (1, 1, 1)}]
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
