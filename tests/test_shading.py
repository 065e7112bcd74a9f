"""Shading's gradient estimator (volumeevm_addon.rendering._gradients): the 3x3x3 Sobel over
region voxels, its boundary policy (outside voxels never read), its compiled twin in the
navigation ray caster, the normals it gives a sphere; and the fade of shading where the gradient
is small, in every method."""

import itertools

import numpy as np
import pytest

from render_helpers import camera
from volumeevm_addon import TransferFunction, VolumeEVM, grid_to_world, render
from volumeevm_addon.rendering import _gradients
from volumeevm_addon.rendering._gradients import region_gradients
from volumeevm_addon.rendering._ray_march import _hood_gradients

WEIGHTS = np.array([1.0, 2.0, 1.0])


def stated_rule(f, inside, v, ax):
    """The estimator as the module docstring states it, voxel by voxel: the 9 lines along
    ``ax`` through the 3x3 neighbours across, weighted 1 2 1 x 1 2 1, missing lines left out."""
    if not inside[v]:
        return 0.0
    others = [a for a in range(3) if a != ax]
    step = np.eye(3, dtype=int)[ax]
    total = used = 0.0
    for di, dj in itertools.product((-1, 0, 1), repeat=2):
        centre = np.array(v)
        centre[others[0]] += di
        centre[others[1]] += dj

        def at(p):
            p = tuple(p)
            ok = all(0 <= p[a] < f.shape[a] for a in range(3)) and inside[p]
            return ok, f[p] if ok else np.nan
        (mp, fp), (m0, f0), (mm, fm) = at(centre + step), at(centre), at(centre - step)
        w = WEIGHTS[di + 1] * WEIGHTS[dj + 1]
        if mp and mm:
            d = (fp - fm) / 2
        elif mp and m0:
            d = fp - f0
        elif mm and m0:
            d = f0 - fm
        else:
            continue
        total += w * d
        used += w
    return total / used if used else 0.0


def gradients(f, inside, dtype=np.float64):
    """region_gradients of the grid ``f`` (region ``inside``), padded as the renderers pad it."""
    pad = np.pad(np.where(inside, f, 0).astype(dtype), 1)
    out = np.zeros((3,) + f.shape, dtype)
    region_gradients(pad, np.pad(inside, 1), out)
    return out


def test_estimator_is_the_stated_rule():
    """On a random region of random densities, every voxel's gradient is the stated rule's:
    Sobel inside, renormalised over the lines the region has at its edge (0 outside)."""
    rng = np.random.default_rng(3)
    f = rng.uniform(-500, 1500, (7, 6, 5))
    inside = rng.uniform(size=f.shape) < 0.6
    got = gradients(f, inside)
    want = np.array([[[[stated_rule(f, inside, (i, j, k), ax) for k in range(5)]
                       for j in range(6)] for i in range(7)] for ax in range(3)])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)
    # Deep inside a full region it is the Sobel operator / 32 (index units).
    full = gradients(f, np.ones(f.shape, bool))
    sobel = np.einsum("i,j,k->ijk", [-1.0, 0.0, 1.0], WEIGHTS, WEIGHTS) / 32.0
    assert full[0, 3, 2, 2] == pytest.approx((f[2:5, 1:4, 1:4] * sobel).sum(), rel=1e-12)


def test_linear_field_exact_and_outside_never_read():
    """A linear field's gradient is exact at every region voxel, at its edges too, and the
    densities outside the region change nothing (the boundary policy: never read)."""
    i, j, k = np.meshgrid(*[np.arange(n) for n in (9, 8, 7)], indexing="ij")
    f = 3.0 * i - 2.0 * j + 0.5 * k
    rng = np.random.default_rng(4)
    inside = rng.uniform(size=f.shape) < 0.7
    got = gradients(f, inside)
    has_line = np.abs(got).sum(axis=0) > 0
    assert has_line[inside].mean() > 0.95
    for ax, slope in enumerate((3.0, -2.0, 0.5)):
        np.testing.assert_allclose(got[ax][inside & has_line], slope, rtol=1e-12)
    garbage = np.where(inside, f, rng.uniform(-1e4, 1e4, f.shape))
    pad = np.pad(garbage, 1)
    out = np.zeros_like(got)
    region_gradients(pad, np.pad(inside, 1), out)
    np.testing.assert_array_equal(out, got)


@pytest.mark.parametrize("slab_voxels", [1, 1 << 18])
def test_table_gradients_are_the_grids(data_dir, monkeypatch, slab_voxels):
    """Shear-warp's gradients, made on x-slabs of the region (one slice a slab with
    ``slab_voxels=1``, the default sizes otherwise), equal bit for bit those of the whole padded
    float32 grid at the region's voxels, in the table's order: the CT head's bone and skin and
    random regions of every size."""
    monkeypatch.setattr(_gradients, "_SLAB_VOXELS", slab_voxels)
    monkeypatch.setattr(_gradients, "_SLAB_SLICES", 1 if slab_voxels == 1 else 8)
    head = np.load(data_dir / "ct_head_invesalius.npy")[::2, ::2, :]
    rng = np.random.default_rng(7)
    cases = [(head, 300), (head, -300)] + [
        (rng.normal(0, 1, tuple(rng.integers(1, 30, 3))).astype(np.float32), rng.normal())
        for _ in range(30)]
    for array, threshold in cases:
        vevm = VolumeEVM.from_array(array, threshold)
        if vevm.evm.is_empty():
            continue
        inside = vevm.evm.to_mask(vevm.shape)
        want = gradients(array, inside, np.float32)
        got = _gradients.table_gradients(vevm)
        np.testing.assert_array_equal(got, want[:, inside])


def test_navigation_kernel_is_the_same_arithmetic():
    """The navigation ray caster's compiled estimator on a 4x4x4 neighbourhood gives, bit for
    bit, region_gradients' float32 gradients at the 8 inner voxels."""
    rng = np.random.default_rng(5)
    for trial in range(50):
        hood = rng.uniform(-1000, 3000, (4, 4, 4)).astype(np.float32)
        hood_in = rng.uniform(size=(4, 4, 4)) < (0.4 + 0.6 * trial / 50)
        hood = np.where(hood_in, hood, np.float32(0))
        want = np.zeros((3, 2, 2, 2), np.float32)
        region_gradients(hood, hood_in, want)
        flat, flat_in = hood.ravel(), hood_in.ravel()
        got = [_hood_gradients(flat, flat_in, 16, 4, 1), _hood_gradients(flat, flat_in, 4, 16, 1),
               _hood_gradients(flat, flat_in, 1, 16, 4)]
        np.testing.assert_array_equal(np.array(got, np.float32), want.reshape(3, 8))


def sphere_angles(noise, region_radius):
    """Degrees between the estimated normals and the true ones (radial) over the surface of a
    ball (density 1000 inside, 0 outside, a 3-voxel ramp at radius 10, plus Gaussian noise of
    ``noise``), at region voxels within 1.5 voxels of the surface."""
    n, c = 33, 16.0
    i, j, k = np.meshgrid(*[np.arange(n)] * 3, indexing="ij")
    r = np.sqrt((i - c) ** 2 + (j - c) ** 2 + (k - c) ** 2)
    f = 1000.0 * np.clip((10.0 - r) / 3.0 + 0.5, 0.0, 1.0)
    f += np.random.default_rng(1).normal(0.0, noise, f.shape)
    inside = r < region_radius
    g = gradients(f, inside)
    surface = inside & (np.abs(r - 10.0) < 1.5)
    radial = -np.stack([i - c, j - c, k - c]) / np.maximum(r, 1e-9)
    cos = (g * radial).sum(axis=0)[surface] / np.linalg.norm(g, axis=0)[surface]
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


@pytest.mark.parametrize("noise, region_radius, mean, p95, worst", [
    (0.0, 14.0, 1.0, 2.0, 3.0),  # measured 0.60, 1.65, 2.21 (central differences 1.9, 6.7, 9.7)
    (40.0, 14.0, 4.0, 8.0, 15.0),  # measured 3.06, 6.43, 11.5 (central: 7.7, 16.3, 34.9)
    (40.0, 10.5, 4.0, 8.0, 15.0),  # edge cuts the ramp: measured 3.45, 7.07, 13.6 (8.2, 17.7, 46)
])
def test_sphere_normals_within_angle(noise, region_radius, mean, p95, worst):
    """A ball's normals: within the stated angles of the radial direction, noise-free and with
    noise of 4% of the edge's contrast, also where the region's edge cuts the surface (lines
    renormalised over the region)."""
    angles = sphere_angles(noise, region_radius)
    assert angles.size > 1500
    assert angles.mean() < mean and np.percentile(angles, 95) < p95 and angles.max() < worst


METHODS = [("reference", {}), ("raycast", {"termination": 1.0}),
           ("raycast_navigate", {"termination": 1.0}), ("splat", {"termination": 1.0}),
           ("shear_warp", {"termination": 1.0}),
           ("shear_warp", {"termination": 1.0, "classification": "post"})]


@pytest.mark.parametrize("method, options", METHODS)
def test_noise_is_not_lit(method, options):
    """Shading fades where the gradient is small against the transfer function's range: a
    block of density 500 with noise of 2 (gradients below fade_from · 1000 = 5 per voxel) is
    lit evenly, as if facing the light (ambient + diffuse = 1: the unshaded image), while a
    step of 300 through it is shaded."""
    rng = np.random.default_rng(6)
    dens = 500.0 + rng.normal(0.0, 2.0, (14, 12, 10))
    vevm = VolumeEVM.from_array(dens, 0.0, spacing=(1.0, 1.0, 1.0))
    g = grid_to_world(vevm.spacing, vevm.origin)
    tf = TransferFunction([(0, 0.9, 0.6, 0.3, 0.05), (1000, 0.9, 0.6, 0.3, 0.05)])
    cam = camera("PERSP", g, vevm, (0.014, -0.03, 0.012), 0.0, res=(24, 20))
    kw = dict(method=method, **options)
    shaded = render(vevm, cam, tf, shading=True, **kw)[0]
    plain = render(vevm, cam, tf, **kw)[0]
    assert (plain[..., 3] > 0.3).sum() > 100
    np.testing.assert_allclose(shaded, plain, rtol=0, atol=2e-6)
    dens[:, :, 5:] += 300.0
    stepped = VolumeEVM.from_array(dens, 0.0, spacing=(1.0, 1.0, 1.0))
    lit = render(stepped, cam, tf, shading=True, **kw)[0]
    unlit = render(stepped, cam, tf, **kw)[0]
    assert np.abs(lit - unlit)[..., :3].max() > 0.02
