"""Ray casters (EVM space leaping and the navigation variant): what is particular to them -
the navigation variant against the block walk, blocks and leap levels, jitter and
pre-integration, closed forms, modes, shading, the kernels' rays and degenerate input. What
every method keeps (EVM = dense, threads, odd sizes, error bounds against the reference) is in
test_render_contract.py."""

import json
import tracemalloc

import numpy as np
import pytest

from render_helpers import MODES, XRAY, camera, const_tf, reference
from volumeevm_addon import (
    EVM,
    Camera,
    TransferFunction,
    VolumeEVM,
    VolumeEVMError,
    grid_to_world,
)
from volumeevm_addon.model import BLENDER_UNITS_PER_MM as BU
from volumeevm_addon.phantoms import box_chords_mm
from volumeevm_addon.rendering import BACKGROUND_DEPTH, _ray_march, _raycast
from volumeevm_addon.rendering._raycast import _Blocks, render_raycast, render_raycast_navigate
from volumeevm_addon.rendering._rays import camera_rays


@pytest.fixture(scope="module")
def ct(data_dir):
    """The CT head downsampled 4x4x3 (64x64x36), with its JSON spacing."""
    meta = json.loads((data_dir / "ct_head_invesalius.json").read_text())
    a = np.load(data_dir / "ct_head_invesalius.npy")[::4, ::4, ::3]
    sp = np.array(meta["spacing_mm"]) * (4, 4, 3)
    return a, tuple(sp)


@pytest.fixture(scope="module")
def brain(data_dir):
    """brainsmall (VolPack's MR example) cropped to 48x40x32, with its JSON spacing."""
    meta = json.loads((data_dir / "mr_brainsmall_volpack.json").read_text())
    a = np.load(data_dir / "mr_brainsmall_volpack.npy")[40:88, 44:84, 26:58]
    return a, tuple(meta["spacing_mm"])


def skin(ct):
    a, sp = ct
    v = VolumeEVM.from_array(a, -300, spacing=sp)
    return v, grid_to_world(v.spacing, v.origin), TransferFunction.preset("ct_skin")


def bone(ct):
    a, sp = ct
    v = VolumeEVM.from_array(a, 150, spacing=sp)
    return v, grid_to_world(v.spacing, v.origin), TransferFunction.preset("ct_bone")


# ---------------------------------------------------------------------------- exactness
@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
@pytest.mark.parametrize("mode", MODES)
def test_navigation_equals_raycast(ct, kind, mode):
    """Walking the region's sections gives the block walk's image (EVM = dense for both is in
    test_render_contract.py)."""
    v, g, tf = bone(ct)
    cam = camera(kind, g, v, (0.3, -0.5, 0.2), 0.3)
    kw = XRAY if mode == "xray" else {}
    r1, d1 = render_raycast(v, cam, tf, g, mode=mode, **kw)
    assert r1[..., 3].max() > 0.5 and (r1[..., 3] == 0).sum() > 50
    r2, d2 = render_raycast_navigate(v, cam, tf, g, mode=mode, **kw)
    np.testing.assert_allclose(r2, r1, rtol=0, atol=1e-5)
    np.testing.assert_allclose(d2, d1, rtol=1e-6)


@pytest.mark.parametrize("mode", ["over", "under"])
def test_jitter_and_preintegration_keep_the_contract(ct, mode):
    """Space leaping and the navigation variant give the same image with both options (the
    blocks widen their density ranges for segment ends); jitter is the same on every run."""
    v, g, tf = bone(ct)
    cam = camera("PERSP", g, v, (0.3, -0.5, 0.2), 0.3, res=(23, 17))
    opts = {"mode": mode, "jitter": True, "preintegrate": True, "step_mm": 1.5}
    r1, d1 = render_raycast(v, cam, tf, g, **opts)
    r0, d0 = render_raycast(v, cam, tf, g, skip_empty=False, **opts)
    assert r1[..., 3].max() > 0.5
    np.testing.assert_allclose(r1, r0, rtol=0, atol=1e-6)
    np.testing.assert_allclose(d1, d0, rtol=1e-6)
    r2, d2 = render_raycast_navigate(v, cam, tf, g, chunk_rays=101, **opts)
    np.testing.assert_allclose(r2, r1, rtol=0, atol=1e-5)
    np.testing.assert_allclose(d2, d1, rtol=1e-6)
    again, _ = render_raycast(v, cam, tf, g, chunk_rays=50, **opts)
    np.testing.assert_array_equal(again, r1)
    plain, _ = render_raycast(v, cam, tf, g, mode=mode, step_mm=1.5)
    assert np.abs(r1 - plain).max() > 0.01  # the options change the image


def test_skip_empty_equals_dense_brain_and_blocks(brain):
    a, sp = brain
    v = VolumeEVM.from_array(a, 40, spacing=sp)
    g = grid_to_world(v.spacing, v.origin)
    tf = TransferFunction.preset("mri", data_range=(0, 202))
    cam = camera("PERSP", g, v, (-0.1, -0.12, 0.08), 0.0, shift_x=0.05)
    r0, d0 = render_raycast(v, cam, tf, g, skip_empty=False, termination=0.95)
    assert r0[..., 3].max() > 0.5
    for block in (1, 3, 8):
        r1, d1 = render_raycast(v, cam, tf, g, termination=0.95, block=block, chunk_rays=97)
        np.testing.assert_allclose(r1, r0, rtol=0, atol=1e-6)
        np.testing.assert_allclose(d1, d0, rtol=1e-6)


def test_default_blocks_grow_with_the_grid_and_keep_the_image(brain):
    """Up to 1024³ voxels the default blocks are 4³; a larger grid gets the next edge whose
    block grid holds at most MAX_BLOCKS blocks (their memory is grid-sized). A small region
    in a 1100³ grid: the default render is the render with 8³ blocks, bit for bit, and its
    memory estimate is that one's, a fraction of what 4³ blocks would need."""
    assert _raycast.leap_block(None, (1024, 1024, 1024)) == 4
    assert _raycast.leap_block(None, (1025, 1024, 1024)) == 8
    assert _raycast.leap_block(None, (4096, 4096, 2048)) == 16
    assert _raycast.leap_block(5, (4096, 4096, 4096)) == 5
    a, sp = brain
    small = VolumeEVM.from_array(a, 40, spacing=sp)
    v = VolumeEVM(EVM.from_mask(small.evm.to_mask(small.shape), offset=(500, 520, 540)),
                  small.table(), shape=(1100, 1100, 1100), spacing=sp)
    g = grid_to_world(v.spacing, v.origin)
    tf = TransferFunction.preset("mri", data_range=(0, 202))
    cam = camera("ORTHO", g, v, (-0.1, -0.12, 0.08), 120 * max(sp) * BU, res=(48, 48))
    r, d = render_raycast(v, cam, tf, g)
    r8, d8 = render_raycast(v, cam, tf, g, block=8)
    assert r[..., 3].max() > 0.5
    np.testing.assert_array_equal(r, r8)
    np.testing.assert_array_equal(d, d8)
    need = {block: _raycast.table_bytes(v, {"block": block}, navigate=False)
            + _raycast._block_view_bytes(v, {"skip_empty": True, "block": block})
            for block in (None, 4, 8)}
    assert need[None] == need[8] < need[4] / 4


@pytest.mark.parametrize("dtype", [np.int16, np.uint8, np.uint16])
def test_integer_pools_keep_the_image_and_halve_the_table(ct, dtype):
    """8- and 16-bit densities stay in their own type in the sampling table (the type's
    smallest value marks outside the region): the images, shaded included, and the depths are
    those of the same densities as float32, bit for bit; a region holding that smallest value
    falls back to float32."""
    a, sp = ct
    data = {np.int16: a, np.uint16: (a - a.min()).astype(np.uint16),
            np.uint8: ((a - a.min()) // 16).astype(np.uint8)}[dtype]
    v = VolumeEVM.from_array(data, float(np.percentile(data, 80)), spacing=sp)
    f = VolumeEVM(v.evm, v.table().astype(np.float32), shape=v.shape, spacing=sp)
    g = grid_to_world(v.spacing, v.origin)
    tf = TransferFunction.preset("ct_bone", data_range=(float(data.min()), float(data.max())))
    cam = camera("PERSP", g, v, (0.15, -0.2, 0.1), 0.0)
    for shading in (None, True):
        r, d = render_raycast(v, cam, tf, g, shading=shading)
        rf, df = render_raycast(f, cam, tf, g, shading=shading)
        assert r[..., 3].max() > 0.5
        np.testing.assert_array_equal(r, rf)
        np.testing.assert_array_equal(d, df)
    table = v.cache.get(("raycast", "table"), lambda: None)
    assert table.table.dtype == dtype and table.hole == np.iinfo(dtype).min
    per_set = _raycast.table_bytes(v, {}, navigate=False)
    assert per_set < _raycast.table_bytes(f, {}, navigate=False)
    lowest = np.iinfo(dtype).min
    full = VolumeEVM(v.evm, np.r_[lowest, v.table()[1:]].astype(dtype), shape=v.shape)
    pool, hole = _raycast.pool_type(full)
    assert pool == np.float32 and np.isnan(hole)
    r_full, _ = render_raycast(full, cam, tf, g)
    r_full_f, _ = render_raycast(VolumeEVM(v.evm, full.table().astype(np.float32),
                                           shape=v.shape), cam, tf, g)
    np.testing.assert_array_equal(r_full, r_full_f)


@pytest.mark.parametrize("size, reach", [(4, 1), (3, 2), (5, 3)])
def test_blocks_cover_what_samples_can_read(size, reach):
    """Block occupancy (the region voxels within one voxel of the block's cells) and density
    range (those within ``reach`` voxels), brute force over a random region."""
    rng = np.random.default_rng(11)
    shape = (13, 11, 9)
    mask = rng.uniform(size=shape) < 0.05
    dens = rng.uniform(-100, 100, shape)
    v = VolumeEVM(EVM.from_mask(mask), dens[mask], shape=shape)
    blocks = _Blocks(v, size, reach)

    def near(b, grow):  # the densities of region voxels within `grow` of block b's cells
        lo = np.maximum(np.array(b) * size - grow, 0)
        hi = np.minimum((np.array(b) + 1) * size + grow, shape)
        sub = tuple(slice(a, c) for a, c in zip(lo, hi))
        return dens[sub][mask[sub]].astype(np.float32)  # the sampler's precision

    for b in np.ndindex(*blocks.nb):
        assert blocks.occupied[b] == (len(near(b, 1)) > 0)
        inside = near(b, reach)
        if len(inside):
            assert blocks.range_lo[b] == inside.min() and blocks.range_hi[b] == inside.max()
        else:
            assert blocks.range_lo[b] == np.inf and blocks.range_hi[b] == -np.inf


# ---------------------------------------------------------------------------- closed forms

OPTIONS = [{}, {"jitter": True, "preintegrate": True}]


@pytest.mark.parametrize("opts", OPTIONS)
@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_homogeneous_box_closed_form(kind, opts):
    """Region = the whole grid: every segment is inside, the first (jitter) and last are cut at
    the entry and exit, so the opacity is 1 - (1 - a0)^(L / 1 mm) for the exact chord L."""
    shape, sp = (7, 9, 5), (0.7, 0.5, 1.3)
    v = VolumeEVM.from_array(np.full(shape, 5.0), 0, spacing=sp)
    g = grid_to_world(sp, (0, 0, 0))
    cam = camera(kind, g, v, (0.012, -0.01, 0.009), 0.012)
    tf = const_tf(0.15)
    for step in (0.3, None):
        rgba, depth = render_raycast(v, cam, tf, g, step_mm=step, termination=1.0, **opts)
        chord = box_chords_mm(cam, g, (0, 0, 0), shape)
        assert (chord > 0).sum() > 200 and (chord == 0).sum() > 50
        expected = 1 - 0.85 ** chord
        np.testing.assert_allclose(rgba[..., 3], expected, rtol=0, atol=2e-5)
        np.testing.assert_allclose(rgba[..., :3], expected[..., None] * (0.9, 0.6, 0.3),
                                   atol=2e-5)
        rr, dr = reference(v, cam, tf, g)
        hit = chord > 1e-9
        np.testing.assert_allclose(depth[hit], dr[hit], rtol=1e-6)
        assert np.all(depth[~hit] == BACKGROUND_DEPTH)


@pytest.mark.parametrize("opts", OPTIONS)
@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_box_region_closed_form(kind, opts):
    """A box region inside a larger grid: each sample counts the part of its segment that lies
    in region cells, so the chord is exact (steps up to the smallest voxel size) and so is the
    depth of the box's surface. A longer step only approximates it."""
    shape, sp = (12, 10, 9), (0.8, 0.6, 1.1)
    mask = np.zeros(shape, bool)
    mask[3:9, 2:8, 2:7] = True
    dens = np.where(mask, 7.0, -50.0)
    v = VolumeEVM(EVM.from_mask(mask), dens[mask], shape=shape, spacing=sp)
    g = grid_to_world(sp, (0, 0, 0))
    cam = camera(kind, g, v, (0.013, -0.011, 0.01), 0.014)
    tf = const_tf(0.2)
    chord = box_chords_mm(cam, g, (3, 2, 2), (9, 8, 7))
    expected = 1 - 0.8 ** chord
    assert (chord > 0).sum() > 200 and (chord == 0).sum() > 50
    _, dr = reference(v, cam, tf, g)
    hit = chord > 1e-6
    for step in (0.25, None, 0.6):
        rgba, depth = render_raycast(v, cam, tf, g, step_mm=step, termination=1.0, **opts)
        np.testing.assert_allclose(rgba[..., 3], expected, rtol=0, atol=2e-6)
        np.testing.assert_allclose(rgba[..., :3], expected[..., None] * (0.9, 0.6, 0.3),
                                   atol=2e-6)
        np.testing.assert_allclose(depth[hit], dr[hit], rtol=1e-6)
    rgba, _ = render_raycast(v, cam, tf, g, step_mm=1.5, termination=1.0)
    assert np.abs(rgba[..., 3] - expected).max() < 1 - 0.8 ** 1.5


def test_gaussian_blob_against_reference():
    n = 20
    x = np.arange(n) - (n - 1) / 2
    blob = 1000 * np.exp(-(x[:, None, None] ** 2 + x[None, :, None] ** 2
                           + (1.5 * x[None, None, :]) ** 2) / (2 * 4.0 ** 2))
    v = VolumeEVM.from_array(blob, 0, spacing=(1.0, 1.0, 1.5))
    g = grid_to_world(v.spacing, v.origin)
    cam = camera("PERSP", g, v, (0.03, -0.04, 0.025), 0.0)
    tf = TransferFunction([(0, 0.2, 0.4, 1.0, 0.0), (1000, 1.0, 0.8, 0.2, 0.3)])
    rgba, _ = render_raycast(v, cam, tf, g, step_mm=0.25, termination=1.0)
    rr, _ = reference(v, cam, tf, g)
    assert rr[..., 3].max() > 0.8
    assert np.abs(rgba - rr).max() < 2e-4  # measured 5.8e-5 (2.4e-4 at the default step)
    rgba, _ = render_raycast(v, cam, None, g, mode="xray", step_mm=0.25, xray_scale=3e-4)
    rr, _ = reference(v, cam, None, g, mode="xray", xray_scale=3e-4)
    assert rr[..., 3].max() > 0.5
    assert np.abs(rgba - rr).max() < 2e-4  # measured 5.7e-5


# ---------------------------------------------------------------------------- modes
def axis_scene():
    """Random densities, an irregular region; an orthographic camera looking down -z whose
    pixel centres sit on voxel columns (x, y)."""
    rng = np.random.default_rng(7)
    shape, sp = (6, 5, 9), (1.0, 1.0, 1.25)
    dens = rng.uniform(-500, 1500, shape)
    mask = rng.uniform(size=shape) < 0.6
    mask[0, 0, 0] = True
    v = VolumeEVM(EVM.from_mask(mask), dens[mask], shape=shape, spacing=sp)
    g = grid_to_world(sp, (0, 0, 0))
    m = np.eye(4)
    m[:3, 3] = (2.5 * BU, 2.0 * BU, 1.0)
    cam = Camera.orthographic(m, 6 * BU, resolution_x=6, resolution_y=5)
    return v, g, cam, dens, mask


def test_mip_is_the_maximum_along_rays():
    v, g, cam, dens, mask = axis_scene()
    tf = TransferFunction([(-500, 0, 0, 0, 0.0), (1500, 1, 1, 1, 1.0)])
    # With a step of one voxel the samples are the voxel centres of each column.
    rgba, _ = render_raycast(v, cam, tf, g, mode="mip", step_mm=1.25)
    colmax = np.where(mask, dens, -np.inf).max(axis=2)  # (x, y)
    expected = tf.evaluate(colmax.T[::-1])[..., 3]  # image rows run down y
    expected = np.where(np.isfinite(colmax.T[::-1]), expected, 0)
    np.testing.assert_allclose(rgba[..., 3], expected, atol=1e-5)
    # Finer steps never exceed the column maximum (interpolation is a convex combination).
    fine, _ = render_raycast(v, cam, tf, g, mode="mip", step_mm=0.1)
    assert np.all(fine[..., 3] <= expected + 1e-5)


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_mip_against_reference(ct, kind):
    """Each segment's ends and middle are evaluated; a ray that grazes a cell the samples miss
    is the rare large error (measured mean 0.0024 / 0.0016, 99th percentile 0.015 / 0.007)."""
    v, g, tf = bone(ct)
    cam = camera(kind, g, v, (0.3, -0.5, 0.2), 0.3)
    rgba, depth = render_raycast(v, cam, tf, g, mode="mip")
    rr, dr = reference(v, cam, tf, g, mode="mip")
    err = np.abs(rgba - rr).max(axis=-1)
    assert rr[..., 3].mean() > 0.1
    assert err.mean() < 0.005 and np.percentile(err, 99) < 0.03
    assert ((depth < 1e9) != (dr < 1e9)).sum() <= 5


def test_xray_is_exp_of_minus_the_sum():
    v, g, cam, dens, mask = axis_scene()
    rgba, depth = render_raycast(v, cam, None, g, mode="xray", step_mm=1.25, xray_scale=1e-3,
                                 xray_offset=-200.0)
    mu = 1e-3 * np.maximum(dens + 200.0, 0) * mask
    expected = 1 - np.exp(-(mu.sum(axis=2) * 1.25).T[::-1])
    np.testing.assert_allclose(rgba[..., 0], expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(rgba[..., 3], expected, rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------- shading
def test_shading_against_reference_and_navigation(ct):
    v, g, tf = bone(ct)
    cam = camera("ORTHO", g, v, (0.3, -0.5, 0.2), 0.3, res=(30, 24))
    rgba, _ = render_raycast(v, cam, tf, g, shading=True, termination=1.0, step_mm=1.0)
    plain, _ = render_raycast(v, cam, tf, g, termination=1.0, step_mm=1.0)
    rr, _ = reference(v, cam, tf, g, shading=True)
    assert np.abs(rgba - plain)[..., :3].mean() > 0.05  # shading changes the image
    err = np.abs(rgba - rr).max(axis=-1)
    assert err.mean() < 0.004  # measured 0.0019 (0.0058 at the default 1.9 mm step)
    nav, _ = render_raycast_navigate(v, cam, tf, g, shading={"specular": 0.3}, termination=1.0,
                                     step_mm=1.0)
    np.testing.assert_allclose(nav, rgba, atol=1e-5)
    dense, _ = render_raycast(v, cam, tf, g, shading=True, termination=1.0, skip_empty=False,
                              step_mm=1.0)
    np.testing.assert_allclose(dense, rgba, atol=1e-6)


# ---------------------------------------------------------------------------- degenerate
def test_single_voxel_region():
    shape = (5, 4, 3)
    tf = const_tf(0.5)
    g = grid_to_world((1.0, 1.0, 1.0), (0, 0, 0))
    mask = np.zeros(shape, bool)
    mask[2, 1, 1] = True
    one = VolumeEVM(EVM.from_mask(mask), np.array([100.0]), shape=shape)
    cam = camera("PERSP", g, one, (0.01, -0.008, 0.006), 0.0, res=(9, 7))
    for mode in MODES:
        rgba, depth = render_raycast(one, cam, tf, g, mode=mode, step_mm=0.05)
        rr, dr = reference(one, cam, tf, g, mode=mode)
        assert rr[..., 3].max() > 0.1 and not np.isnan(rgba).any()
        assert np.abs(rgba - rr).mean() < 0.01
        np.testing.assert_array_equal(depth < 1e9, dr < 1e9)


def test_bad_input(ct):
    v, g, tf = skin(ct)
    cam = camera("ORTHO", g, v, (0.3, -0.5, 0.2), 0.3, res=(6, 4))
    nan = np.full((4, 6), 1e10)
    nan[1, 2] = np.nan
    for fn in (render_raycast, render_raycast_navigate):
        with pytest.raises(VolumeEVMError, match="depth_in: 1 NaN"):
            fn(v, cam, tf, g, depth_in=nan)
    with pytest.raises(VolumeEVMError, match="depth_in: shape"):
        render_raycast(v, cam, tf, g, depth_in=np.zeros((3, 3)))
    with pytest.raises(VolumeEVMError, match="mode"):
        render_raycast(v, cam, tf, g, mode="sum")
    with pytest.raises(VolumeEVMError, match="step_mm"):
        render_raycast(v, cam, tf, g, step_mm=0)
    with pytest.raises(VolumeEVMError, match="termination"):
        render_raycast(v, cam, tf, g, termination=0)
    with pytest.raises(VolumeEVMError, match="shading"):
        render_raycast(v, cam, tf, g, shading={"glow": 1})
    with pytest.raises(VolumeEVMError, match="tf"):
        render_raycast(v, cam, "bone", g)
    with pytest.raises(VolumeEVMError, match="grid_to_world"):
        render_raycast(v, cam, tf, np.zeros((4, 4)))
    for name in ("jitter", "preintegrate", "skip_empty"):
        with pytest.raises(VolumeEVMError, match=name):
            render_raycast_navigate(v, cam, tf, g, **{name: 1})
        with pytest.raises(VolumeEVMError, match=name):
            render_raycast(v, cam, tf, g, **{name: np.ones(2, bool)})


# ---------------------------------------------------------------------------- kernels
@pytest.mark.parametrize("mode, opts", [
    ("over", {"jitter": True, "preintegrate": True, "shading": True, "step_mm": 1.5}),
    ("under", {"shading": True}), ("xray", XRAY), ("mip", {})])
def test_the_image_does_not_depend_on_tiles(ct, mode, opts):
    """Each ray is cast on its own: small tiles or large, the same bits, and the navigation
    variant the same image (one thread or two: test_render_contract.py)."""
    v, g, tf = bone(ct)
    cam = camera("PERSP", g, v, (0.3, -0.5, 0.2), 0.0, res=(37, 29))
    small = render_raycast(v, cam, tf, g, mode=mode, chunk_rays=64, **opts)
    tiles = render_raycast(v, cam, tf, g, mode=mode, chunk_rays=300, **opts)
    navigated = render_raycast_navigate(v, cam, tf, g, mode=mode, chunk_rays=100, **opts)
    assert small[0][..., 3].max() > 0.5
    for image in (tiles, navigated):
        np.testing.assert_array_equal(image[0], small[0])
        np.testing.assert_array_equal(image[1], small[1])


@pytest.mark.parametrize("kind", ["ORTHO", "PERSP"])
def test_each_kernel_ray_is_the_cameras(ct, kind):
    """The kernels make each pixel's ray themselves: the same rays, clipped the same way, as
    the other renderers' (``camera_rays``)."""
    v, g, _ = bone(ct)
    cam = camera(kind, g, v, (0.3, -0.5, 0.2), 0.3, res=(13, 7), shift_x=0.1, shift_y=-0.05)
    depth_in = np.random.default_rng(3).uniform(0.2, 0.8, cam.shape)
    depth_in[0, :4] = 1e10
    for stop in (None, depth_in):
        rays = camera_rays(cam, g, v.shape, stop)
        view = _raycast._view(cam, g, v.shape, np.asarray(v.spacing), stop)
        for ray in range(13 * 7):
            o, d, w, a0, kz, t0, t1 = _ray_march._pixel_ray(ray, view)
            np.testing.assert_allclose(o, rays.o[ray], rtol=1e-12, atol=1e-9)
            np.testing.assert_allclose(d, rays.d[ray], rtol=1e-12)
            np.testing.assert_allclose(w, rays.dirs[ray], rtol=1e-12, atol=1e-15)
            np.testing.assert_allclose((a0, kz), (rays.a0[ray], rays.kz[ray]), rtol=1e-12,
                                       atol=1e-12)
            np.testing.assert_allclose((t0, t1), (rays.t0[ray], rays.t1[ray]), rtol=1e-12,
                                       atol=1e-9)


def test_leap_levels_are_the_largest_uniform_aligned_cubes():
    """Hierarchical space leaping (brute force over a random block grid): each block's code
    names the largest aligned cube of 2**L blocks holding it that is all invisible (L + 1) or
    all visible (-(L + 1))."""
    rng = np.random.default_rng(5)
    visible = rng.uniform(size=(13, 9, 6)) < 0.05
    visible[4:8, 0:8, 0:4] = True  # a visible interior
    got = _raycast.leap_levels(visible)
    assert got.dtype == np.int8 and got.shape == visible.shape

    def cube(cell, level):  # the blocks of the aligned cube in the grid (rays go nowhere else)
        lo = [(c >> level) << level for c in cell]
        return visible[lo[0]:lo[0] + (1 << level), lo[1]:lo[1] + (1 << level),
                       lo[2]:lo[2] + (1 << level)]

    for cell in np.ndindex(*visible.shape):
        code = int(got[cell])
        assert code != 0 and (code < 0) == visible[cell]
        level = abs(code) - 1
        assert (cube(cell, level) == visible[cell]).all()
        assert not (cube(cell, level + 1) == visible[cell]).all()
    nothing = _raycast.leap_levels(np.zeros((3, 4, 5), bool))
    np.testing.assert_array_equal(nothing, 4)  # one cube of 8 blocks: rays leap past the grid


def test_a_render_needs_little_beyond_its_tables_and_image(ct):
    """Once the tables are cached, a render allocates its image and little else: the rays
    keep their state in the kernels, not in per-ray arrays."""
    v, g, tf = skin(ct)
    cam = camera("PERSP", g, v, (0.3, -0.5, 0.2), 0.0, res=(200, 160))
    render_raycast(v, cam, tf, g, shading=True, jitter=True)  # tables made and cached
    tracemalloc.start()
    rgba, _ = render_raycast(v, cam, tf, g, shading=True, jitter=True)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert rgba[..., 3].max() > 0.5
    image = 200 * 160 * (16 + 4)  # RGBA and depth, float32
    assert peak < image + (1 << 20)  # measured: the image and 0.2 MiB (lookup tables)


def test_shaded_and_unshaded_renders_share_the_dense_table(ct):
    """Shading adds its gradients to the cache beside the one dense table; a render without
    shading afterwards builds nothing more (no second copy of the table)."""
    v, g, tf = bone(ct)
    cam = camera("PERSP", g, v, (0.3, -0.5, 0.2), 0.0, res=(24, 20))
    render_raycast(v, cam, tf, g, shading=True)
    keys, held = sorted(v.cache.keys()), v.size_report()["cache_bytes"]
    assert ("raycast", "table") in keys and ("raycast", "gradients") in keys
    render_raycast(v, cam, tf, g)
    assert sorted(v.cache.keys()) == keys and v.size_report()["cache_bytes"] == held
