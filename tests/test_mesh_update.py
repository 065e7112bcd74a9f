"""The boundary mesh updated where a region changed equals the mesh made from scratch, array for
array (vertices, polygons, Blender's edges), and carries per-vertex values to the new vertices."""

import numpy as np
import pytest

from volumeevm_addon import EVM, VolumeEVM
from volumeevm_addon.model import BoundaryMesh, box_evm


def _ball(shape, centre, radius):
    x, y, z = np.ogrid[: shape[0], : shape[1], : shape[2]]
    c = np.asarray(centre, float)
    return EVM.from_mask((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 < radius ** 2)


def _assert_same(mesh, evm):
    fresh = BoundaryMesh(evm)
    np.testing.assert_array_equal(mesh.vertices, fresh.vertices)
    for name in ("indices", "starts", "sizes"):
        np.testing.assert_array_equal(getattr(mesh.polygons, name), getattr(fresh.polygons, name))
    for got, expected in zip(mesh.edges(), fresh.edges(), strict=True):
        np.testing.assert_array_equal(got, expected)
    vertices, polygons = evm.mesh()
    np.testing.assert_array_equal(mesh.vertices, vertices)
    np.testing.assert_array_equal(mesh.polygons.indices, polygons.indices)


@pytest.fixture(scope="module")
def bone(data_dir):
    head = np.load(data_dir / "ct_head_invesalius.npy")
    return VolumeEVM.from_array(np.ascontiguousarray(head[64:192, 48:176, 30:80]), 300)


def test_updates_on_random_drags_equal_fresh_meshes(bone):
    """A drill, an implant and a box dragged around the CT crop (a voxel or a few at a time,
    sometimes far): every update equals the mesh made from scratch."""
    shape = bone.shape
    rng = np.random.default_rng(5)
    drill, implant = np.array([40.0, 30, 25]), np.array([70.0, 90, 20])
    box_lo = np.array([10, 12, 5])
    mesh = BoundaryMesh(bone.evm)
    for step in range(24):
        far = step % 8 == 7
        drill += rng.integers(-15, 16, 3) if far else rng.integers(-2, 3, 3)
        implant += rng.integers(-2, 3, 3) * (step % 3 == 0)
        box_lo += rng.integers(-1, 2, 3) * (step % 4 == 1)
        region = ((bone.evm & box_evm(box_lo, box_lo + (100, 100, 40), shape))
                  - _ball(shape, drill, 9)
                  | _ball(shape, implant, 5))
        updated = mesh.updated(region)
        _assert_same(updated, region)
        if updated is mesh:  # the same region
            continue
        # Positions follow their vertices: the old ones carried, the new ones left to fill.
        carried, fresh = updated.carry(mesh.vertices)
        carried[fresh] = updated.points(fresh)
        np.testing.assert_array_equal(carried, updated.vertices)
        mesh = updated


def test_no_change_empty_and_whole_changes():
    mask = np.zeros((8, 9, 7), bool)
    mask[2:6, 1:8, 1:5] = True
    cube = EVM.from_mask(mask)
    mesh = BoundaryMesh(cube)
    assert mesh.updated(EVM.from_mask(mask)) is mesh
    empty = BoundaryMesh(EVM())
    assert len(empty) == 0 and len(empty.polygons) == 0 and empty.edges()[0].shape == (0, 2)
    _assert_same(empty.updated(cube), cube)
    gone = mesh.updated(EVM())
    assert len(gone) == 0 and len(gone.polygons) == 0
    other = EVM.from_mask(~mask)  # every face changes
    _assert_same(mesh.updated(other), other)
