"""Resolution levels: the coarse VolumeEVM (region, densities, geometry), its cache, the auto
level's rule, and render(level=...) against the full level."""

import tracemalloc

import numpy as np
import pytest

from render_helpers import camera, const_tf
from volumeevm_addon import EVM, Camera, VolumeEVM, VolumeEVMError, grid_to_world, render
from volumeevm_addon.metrics import rmse
from volumeevm_addon.model import BLENDER_UNITS_PER_MM as BU
from volumeevm_addon.model._evm import mask_slabs
from volumeevm_addon.model._levels import coarsen, level_memory
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


def grid_sized_coarsen(vevm, f):
    """The coarsening by its definition on the whole grid (the oracle of the slab-by-slab
    one): a coarse voxel is in the region when a fine voxel of its block is, its density the
    mean of those, summed in float64 in the block's x, y, z order (``cumsum``: one addition
    after another; the voxels outside the region add zeros, which change no sum)."""
    fine = np.array(vevm.shape)
    shape = -(-fine // f)
    dtype = np.float64 if vevm.table().dtype == np.float64 else np.float32
    mask = vevm.evm.to_mask(vevm.shape)
    dense = np.zeros(vevm.shape, np.float64)
    dense[mask] = vevm.table()
    in_block_order = (blocks(dense, f).transpose(0, 2, 4, 1, 3, 5)
                      .reshape(*shape, f ** 3))
    sums = np.cumsum(in_block_order, axis=-1)[..., -1]
    counts = blocks(mask, f).sum(axis=(1, 3, 5))
    inside = counts > 0
    spacing = np.array(vevm.spacing) * f
    shift = vevm.orientation @ (np.array(vevm.spacing) * (f - 1) / 2.0)
    return (EVM.from_mask(inside), (sums[inside] / counts[inside]).astype(dtype),
            tuple(int(n) for n in shape), tuple(spacing), tuple(np.array(vevm.origin) + shift))


def assert_same_level(vevm, f):
    """``vevm.level(f)`` equals the grid-sized coarsening's VolumeEVM in every field, bit for
    bit (vertices, table values and dtype, shape, spacing, origin and the rest)."""
    evm, table, shape, spacing, origin = grid_sized_coarsen(vevm, f)
    got = coarsen(vevm, f)
    assert got[0] == evm and np.array_equal(got[0].vertices, evm.vertices)
    assert got[1].dtype == table.dtype and np.array_equal(got[1], table)
    assert got[2:] == (shape, spacing, origin)
    want = VolumeEVM(evm, table, shape=shape, spacing=spacing, origin=origin,
                     orientation=vevm.orientation, units=vevm.units, threshold=vevm.threshold,
                     upper=vevm.upper)
    level = vevm.level(f)
    assert level.evm == want.evm and level.voxel_count == want.voxel_count
    assert level.table().dtype == want.table().dtype
    assert np.array_equal(level.table(), want.table())
    for field in ("shape", "spacing", "origin", "units", "threshold", "upper"):
        assert getattr(level, field) == getattr(want, field), field
        assert type(getattr(level, field)) is type(getattr(want, field)), field
    assert np.array_equal(level.orientation, want.orientation)


@pytest.mark.parametrize("name,threshold,upper", [
    ("ct_head_invesalius", 300, None), ("ct_head_invesalius", -500, 200),
    ("mr_t1_itk_kmeans", 60, None), ("mr_brainsmall_volpack", 40, None),
    ("micro_nuclei3d_stardist", 200, None), ("ct_skull_cgal", 2.9, None),
    ("seg_liver_cgal", 84, 85)])
def test_slab_by_slab_levels_equal_the_grid_sized_ones_on_real_volumes(data_dir, name,
                                                                         threshold, upper):
    vevm = VolumeEVM.from_array(np.load(data_dir / f"{name}.npy"), threshold, upper,
                                spacing=(0.7, 0.9, 1.3), origin=(4.0, -1.0, 2.5))
    for f in (2, 3, 4, 5):
        assert_same_level(vevm, f)


def test_slab_by_slab_levels_equal_the_grid_sized_ones_on_random_regions():
    """Odd shapes (down to one voxel thick), every table type, sparse to full regions."""
    rng = np.random.default_rng(18)
    dtypes = (np.float32, np.float64, np.uint16, np.int16, np.uint8)
    for trial in range(40):
        shape = tuple(int(n) for n in rng.integers(1, 24, 3))
        a = (rng.random(shape) * 1000).astype(dtypes[trial % len(dtypes)])
        if a.max() == a.min():
            continue
        threshold = float(np.quantile(a, rng.choice([0.0, 0.5, 0.9, 0.99])))
        rotation = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0.0]])
        vevm = VolumeEVM.from_array(a, threshold, spacing=tuple(rng.random(3) + 0.1),
                                    origin=tuple(rng.random(3) * 10), orientation=rotation)
        for f in range(2, min(5, max(shape)) + 1):
            assert_same_level(vevm, f)


@pytest.mark.parametrize("thickness", [1, 2, 3, 5, 7, 40])
def test_mask_slabs_are_the_mask_slab_by_slab(thickness):
    """Vertices before the grid fold in, those past it drop out, as in to_mask."""
    rng = np.random.default_rng(thickness)
    evm = EVM.from_mask(rng.random((19, 11, 9)) < 0.4, offset=(-3, -2, -1))
    for shape in ((13, 8, 9), (19, 11, 9), (25, 4, 3)):
        slabs = list(mask_slabs(evm, shape, thickness))
        assert [len(s) for s in slabs[:-1]] == [thickness] * (len(slabs) - 1)
        np.testing.assert_array_equal(np.concatenate(slabs), evm.to_mask(shape))


def test_level_memory_follows_the_region_and_bounds_the_allocations():
    """A small region in a 400³ grid: the estimate is a fraction of a mask of the grid (what the
    coarsening needed before) and at least what tracemalloc measures (NumPy's allocations and
    the compiled kernels')."""
    rng = np.random.default_rng(5)
    box = rng.random((30, 41, 23)) < 0.7
    evm = EVM.from_mask(box, offset=(100, 200, 300))
    vevm = VolumeEVM(evm, rng.random(evm.volume()).astype(np.float32), shape=(400, 400, 400))
    for f in (2, 3):
        coarsen(vevm, f)  # kernels compiled, keys cached
        tracemalloc.start()
        try:
            coarsen(vevm, f)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        estimate = level_memory(vevm.shape, f, vevm.voxel_count, len(evm))
        assert peak <= estimate < 400 ** 3 / 5, (f, peak, estimate)


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
