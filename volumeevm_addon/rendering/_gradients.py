"""Per-voxel gradients for shading: a 3x3x3 Sobel estimator over the region's voxels, one rule
for every renderer.

Central differences of noisy data (CT) are mostly noise: lit by them, thin structures look
grainy and show the voxels' stair-steps. The estimator here averages, along each axis, the
differences of the 9 lines of the 3x3x3 neighbourhood parallel to it, weighted ``1 2 1`` in
each of the two other axes (weights 1, 2 and 4: the Sobel operator), divided by the sum of the
weights used: the gradient per index unit, exact for a linear field, with about 1/7 of the
central difference's noise variance (``Σw² / (Σw)² = 36/256`` of it for independent noise).

The boundary policy: voxels outside the region are never read (the policy "clamp" of
:mod:`._reference`). A line's difference is the central one ``(f(+1) - f(-1)) / 2`` where both
its ends are region voxels, the one-sided difference towards the one that is where only one is
and the line's middle voxel is too, and missing otherwise; missing lines are left out of the
average (their weights too). A voxel with no line is 0, and so is every voxel outside the
region. With only the voxel's own line this is the central difference rule (one-sided at the
region's edge). So a VolumeEVM, which stores only its region's densities, has the gradients of
the dense grid with the region as a mask. The renderers interpolate these per-voxel gradients
like the densities and light the samples with them (:mod:`._shading`).

Every method computes them with :func:`region_gradients`, on the grid it has: the reference on
its padded float64 grid, ray casting into its padded float32 tables, shear-warp on the dense
grid once per principal axis, splatting on the three slices around a sheet; the navigation
variant of ray casting on each sample's 4x4x4 neighbourhood with the same arithmetic, compiled
(``_ray_march._hood_gradient``).
"""

import numpy as np

__all__ = ["region_gradients"]

_SLAB_VOXELS = 1 << 18
"""Voxels per slab of the computation (bounds its temporaries, a few MB)."""


def region_gradients(density, region, out):
    """Index-space gradients (the module's estimator) at the core of padded grids, into ``out``.

    Parameters
    ----------
    density : (..., X + 2, Y + 2, Z + 2) ndarray
        Densities padded by one voxel along the last three axes; leading axes, if any, are
        independent grids (a batch). Values at voxels outside the region are not read. The
        gradients are computed in its dtype.
    region : ndarray
        The same shape: greater than 0 (True) at region voxels.
    out : (3, ..., X, Y, Z) ndarray
        Receives the gradient along each of the last three axes at the core voxels (0 at
        voxels outside the region). Written a slab of the first grid axis at a time, so the
        temporaries stay small beside the grid.
    """
    nx = density.shape[-3] - 2
    slab = max(1, _SLAB_VOXELS // (density.size // density.shape[-3]))
    core = (Ellipsis, slice(1, -1), slice(1, -1), slice(1, -1))
    for x0 in range(0, nx, slab):
        x1 = min(nx, x0 + slab)
        f = density[..., x0:x1 + 2, :, :]
        inside = region[..., x0:x1 + 2, :, :] > 0
        for ax in range(3):
            diff, used = _line_differences(f, inside, ax)
            for other in range(3):  # the 1 2 1 weights across, the lower axis first
                if other != ax:
                    diff, used = _smoothed(diff, other), _smoothed(used, other)
            out[ax, ..., x0:x1, :, :] = np.where(inside[core], diff / np.maximum(used, 1), 0)


def _line_differences(f, inside, ax):
    """The difference along axis ``ax`` (of the last three) of the line through each voxel
    whose index along ``ax`` is in the core, and 1 where it is not missing (0 and 0 where it
    is), both in ``f``'s dtype (module docstring)."""
    plus, middle, minus = _along(ax, 2, None), _along(ax, 1, -1), _along(ax, 0, -2)
    fp, f0, fm = f[plus], f[middle], f[minus]
    mp, m0, mm = inside[plus], inside[middle], inside[minus]
    diff = np.where(mp & mm, 0.5 * (fp - fm),
                    np.where(mp & m0, fp - f0, np.where(mm & m0, f0 - fm, 0)))
    used = ((mp & mm) | (m0 & (mp | mm))).astype(f.dtype)
    return diff.astype(f.dtype, copy=False), used


def _smoothed(values, ax):
    """``values`` weighted ``1 2 1`` along axis ``ax`` (of the last three), which loses its two
    end voxels: ``(v[i - 1] + 2 v[i]) + v[i + 1]``."""
    return values[_along(ax, 0, -2)] + 2 * values[_along(ax, 1, -1)] + values[_along(ax, 2, None)]


def _along(ax, lo, hi):
    """The index taking ``lo:hi`` along axis ``ax`` of the last three, all of the others."""
    index = [Ellipsis, slice(None), slice(None), slice(None)]
    index[1 + ax] = slice(lo, hi)
    return tuple(index)
