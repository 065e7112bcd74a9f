"""Resolution levels: the coarse VolumeEVM (region, densities, geometry), its cache, the auto
level's rule, and render(level=...) against the full level."""

import numpy as np
import pytest

from render_helpers import camera, const_tf
from volumeevm_addon import BLENDER_UNITS_PER_MM as BU
from volumeevm_addon import Camera, VolumeEVM, VolumeEVMError, grid_to_world, render
from volumeevm_addon.metrics import rmse
from volumeevm_addon.model._levels import coarsen
from volumeevm_addon.rendering._levels import auto_factor, level_factor


def blocks(array, f):
    """``array`` padded to whole ``f``-blocks (with zeros) and split into them."""
    shape = -(-np.array(array.shape) // f)
    padded = np.zeros(shape * f, array.dtype)
    padded[tuple(slice(0, n) for n in array.shape)] = array
    return padded.reshape(shape[0], f, shape[1], f, shape[2], f)


@pytest.fixture(scope="module")
def ragged():
    """Random densities on a grid no factor divides, region a ragged threshold of them."""
    rng = np.random.default_rng(3)
    a = rng.random((13, 10, 7)).astype(np.float32)
    return VolumeEVM.from_array(a, 0.55, spacing=(0.8, 1.1, 1.7), origin=(5.0, -2.0, 3.0),
                                orientation=np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1.0]]))


@pytest.mark.parametrize("f", [2, 3, 4])
def test_coarse_region_and_densities(ragged, f):
    """A coarse voxel is in the region iff any fine voxel of its block is; its density is the
    mean of those fine voxels (computed here densely)."""
    c = ragged.level(f)
    mask = blocks(ragged.evm.to_mask(ragged.shape), f)
    dense = blocks(ragged.to_dense(), f).astype(np.float64)
    counts = mask.sum(axis=(1, 3, 5))
    assert c.shape == tuple(-(-np.array(ragged.shape) // f))
    np.testing.assert_array_equal(c.evm.to_mask(c.shape), counts > 0)
    want = (np.where(mask, dense, 0).sum(axis=(1, 3, 5)) / np.maximum(counts, 1))[counts > 0]
    np.testing.assert_allclose(c.table(), want, rtol=1e-6)
    assert c.table().dtype == np.float32 and c.units == ragged.units


def test_coarse_geometry_keeps_physical_positions(ragged):
    """Spacing times f; the centre of coarse voxel (I, J, K) is the mean of its block's fine
    centres, orientation and all."""
    f = 3
    c = ragged.level(f)
    np.testing.assert_allclose(c.spacing, np.array(ragged.spacing) * f)
    ijk = np.array([[0, 0, 0], [2, 1, 1], [4, 3, 2]])
    fine = ragged.index_to_physical()
    centres = np.array([(fine @ np.r_[f * p + (f - 1) / 2.0, 1.0])[:3] for p in ijk])
    got = (np.c_[ijk, np.ones(3)] @ c.index_to_physical().T)[:, :3]
    np.testing.assert_allclose(got, centres, atol=1e-12)


def test_constant_region_stays_constant_and_thin_structures_survive():
    """Mean densities keep a constant exactly; the any rule keeps a one-voxel plate at level 4
    (one coarse voxel thick) where a majority rule would drop it."""
    plate = np.zeros((32, 32, 32), np.int16)
    plate[:, :, 13] = 700
    v = VolumeEVM.from_array(plate, 500)
    c = v.level(4)
    assert set(np.unique(c.table())) == {700.0}
    np.testing.assert_array_equal(c.evm.to_mask(c.shape)[:, :, 3], True)
    assert c.voxel_count == 8 * 8


def test_levels_are_cached_and_built_on_demand(ragged):
    v = VolumeEVM(ragged.evm, ragged.table(), shape=ragged.shape)
    assert v.cache.keys() == []
    assert v.level(2) is v.level(2)
    assert v.cache.keys() == [("level", 2)]


def test_bad_levels_raise():
    g = np.eye(4)
    cam = Camera.orthographic(np.eye(4), 1.0, resolution_x=8, resolution_y=8)
    for bad in ("half", 0, -2, 1.5, True, None):
        with pytest.raises(VolumeEVMError, match="level"):
            level_factor(bad, (8, 8, 8), g, cam)
    assert level_factor("full", (8, 8, 8), g, cam) == 1 and level_factor(3, (8, 8, 8), g, cam) == 3
    with pytest.raises(VolumeEVMError, match="factor"):
        coarsen(VolumeEVM.from_array(np.ones((4, 4, 4)), 0.5), 1)


def test_auto_factor_rule():
    """Orthographic: the largest power of two whose voxel (largest edge) fits in a pixel;
    perspective: the pixel at the box's nearest axial depth."""
    g = grid_to_world((0.5, 0.5, 1.0), (0.0, 0.0, 0.0))  # largest edge 1 mm
    shape = (200, 200, 100)
    for pixel_mm, want in ((0.9, 1), (1.0, 1), (2.5, 2), (4.0, 4), (7.9, 4), (9.0, 8)):
        cam = Camera.look_at((0, -1, 0), (0, 0, 0), ortho_scale=100 * pixel_mm * BU,
                             resolution_x=100, resolution_y=80)
        assert auto_factor(shape, g, cam) == want, pixel_mm
    # Never coarser than the grid's largest side.
    cam = Camera.orthographic(np.eye(4), 10.0, resolution_x=4, resolution_y=4)
    assert auto_factor((3, 2, 2), grid_to_world((1, 1, 1), (0, 0, 0)), cam) == 2
    # Perspective, 50 mm lens on a 36 mm sensor, 100 px wide: pixel 0.0072 * depth. The box
    # (x from -0.25 to 199.75 mm) nearest the camera at 0.6 BU along +x: depth 0.40025 BU,
    # pixel 2.88 mm: level 2.
    cam = Camera.look_at((0.6, 0.05, 0.05), (0.0, 0.05, 0.05), kind="PERSP", lens_mm=50.0,
                         resolution_x=100, resolution_y=100, clip_start=1e-3)
    assert auto_factor(shape, g, cam) == 2
    cam = Camera.look_at((1.4, 0.05, 0.05), (0.0, 0.05, 0.05), kind="PERSP", lens_mm=50.0,
                         resolution_x=100, resolution_y=100, clip_start=1e-3)
    assert auto_factor(shape, g, cam) == 8  # depth 1.2 BU: pixel 8.6 mm


def test_aligned_box_renders_the_same_at_a_coarser_level():
    """A box whose faces fall on level-2 block faces is the same region at level 2; constant
    opacity: ray casting and splatting give the full level's image (measured 2.5e-8), and
    level="auto" picks the level (0.45 px per largest voxel edge here)."""
    a = np.zeros((40, 40, 40))
    a[10:30, 12:28, 8:32] = 1.0
    v = VolumeEVM.from_array(a, 0.5, spacing=(1.0, 1.2, 0.9))
    g = grid_to_world(v.spacing, v.origin)
    tf = const_tf(0.05)
    cam = camera("ORTHO", g, v, (0.6, -0.9, 0.45), 0.08, res=(30, 30))  # 2.67 mm pixels
    assert auto_factor(v.shape, g, cam) == 2
    for method in ("raycast", "splat"):
        full = render(v, cam, tf, method=method)[0]
        np.testing.assert_allclose(render(v, cam, tf, method=method, level=2)[0], full, atol=1e-6)
        np.testing.assert_array_equal(render(v, cam, tf, method=method, level="auto")[0],
                                      render(v, cam, tf, method=method, level=2)[0])


def test_level_scales_the_step_and_the_reference_ignores_it(ragged):
    v = ragged
    g = grid_to_world(v.spacing, v.origin, v.orientation)
    cam = camera("ORTHO", g, v, (0.02, -0.03, 0.01), 0.025, res=(12, 12))
    tf = const_tf(0.1)
    got = render(v, cam, tf, method="raycast", level=2, step_mm=0.3)[0]
    c = v.level(2)
    want = render(c, cam, tf, method="raycast", step_mm=0.6)[0]
    np.testing.assert_array_equal(got, want)
    assert rmse(got, render(v, cam, tf, method="raycast", step_mm=0.3)[0]) > 1e-4
    np.testing.assert_array_equal(render(v, cam, tf, method="reference", level=2)[0],
                                  render(v, cam, tf, method="reference")[0])
