"""Per-voxel gradients for shading: central differences over the region's voxels, one rule for
every renderer.

Along each axis, a voxel's gradient (per index unit) is the central difference
``(f(v + 1) - f(v - 1)) / 2`` where both neighbours are region voxels, the one-sided difference
towards the one that is where only one is, and 0 where neither is; it is 0 at voxels outside the
region. Voxels outside the region are never read (the boundary policy "clamp" of
:mod:`._reference`), so a VolumeEVM, which stores only its region's densities, has the gradients
of the dense grid with the region as a mask. The renderers interpolate these per-voxel gradients
like the densities and light the samples with them (:mod:`._shading`).

Every method computes them with :func:`region_gradients`, on the grid it has: the reference on
its padded float64 grid, ray casting into its padded float32 tables, its navigation variant on
each sample's 4x4x4 neighbourhood, shear-warp on the dense grid once per principal axis,
splatting on the three slices around a sheet.
"""

import numpy as np

__all__ = ["region_gradients"]

_SLAB_VOXELS = 1 << 18
"""Voxels per slab of the computation (bounds its temporaries, ~1 MB each)."""


def region_gradients(density, region, out):
    """Index-space gradients over region voxels at the core of padded grids, into ``out``.

    Parameters
    ----------
    density : (..., X + 2, Y + 2, Z + 2) ndarray
        Densities padded by one voxel along the last three axes; leading axes, if any, are
        independent grids (a batch). Values at voxels outside the region are not read. The
        differences are computed in its dtype.
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
        f0 = f[core]
        for ax in range(3):
            plus, minus = [slice(1, -1)] * 3, [slice(1, -1)] * 3
            plus[ax], minus[ax] = slice(2, None), slice(0, -2)
            plus, minus = (Ellipsis, *plus), (Ellipsis, *minus)
            fp, fm = f[plus], f[minus]
            mp, mm = inside[plus], inside[minus]
            g = np.where(mp & mm, 0.5 * (fp - fm),
                         np.where(mp, fp - f0, np.where(mm, f0 - fm, 0)))
            out[ax, ..., x0:x1, :, :] = np.where(inside[core], g, 0)
