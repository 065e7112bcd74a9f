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

The methods with a grid compute them with :func:`region_gradients`: the reference on
its padded float64 grid, ray casting into its padded float32 tables, splatting on the three
slices around a sheet; the same arithmetic compiled per voxel (:func:`voxel_gradient`) gives
them to shear-warp, on slabs of the region (:func:`table_gradients`), and to the navigation
variant of ray casting, on each sample's 4x4x4 neighbourhood.
"""

import numpy as np

from .._jit import kernel, parallel_map
from ..model._evm import mask_slabs

__all__ = ["region_gradients", "table_gradients", "voxel_gradient"]

_SLAB_VOXELS = 1 << 18
"""Voxels per slab of the computation (bounds its temporaries, a few MB)."""
_SLAB_SLICES = 8
"""Fewest slices per slab of :func:`table_gradients` (its slices are computed in parallel)."""


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


def table_gradients(vevm, out=None):
    """The gradients of the region's voxels, ``(3, N)`` float32 in the order of
    ``vevm.table(0)``, into ``out`` when given.

    Computed on x-slabs of the grid (:func:`.._evm.mask_slabs`) holding the densities, plus
    one slice on either side, a voxel at a time (:func:`voxel_gradient`, in parallel over
    slices): memory is the result and a slab, never the grid; the values are bit for bit
    :func:`region_gradients`' on the whole padded float32 grid."""
    nx, ny, nz = (int(n) for n in vevm.shape)
    table = vevm.table(0)
    out = np.empty((3, len(table)), np.float32) if out is None else out
    thickness = max(_SLAB_SLICES, 4 * _SLAB_VOXELS // (ny * nz))
    density = np.zeros((thickness + 2, ny + 2, nz + 2), np.float32)
    region = np.zeros(density.shape, bool)  # slice 0: the slice before the slab
    slabs = mask_slabs(vevm.evm, vevm.shape, thickness)
    mask, at = next(slabs), 0
    while mask is not None:
        following = next(slabs, None)
        counts = np.count_nonzero(mask, axis=(1, 2))
        t, n = len(mask), int(counts.sum())
        density[1:t + 1, 1:-1, 1:-1][mask] = table[at:at + n]
        region[1:t + 1, 1:-1, 1:-1] = mask
        region[t + 1] = False
        if following is not None:
            after = following[0]
            density[t + 1, 1:-1, 1:-1][after] = table[at + n:at + n + np.count_nonzero(after)]
            region[t + 1, 1:-1, 1:-1] = after
        starts = at + np.r_[0, np.cumsum(counts)]
        flat, flat_in = density.ravel(), region.ravel()
        parallel_map(lambda x: _slice_gradients(flat, flat_in, x + 1, ny, nz, out, starts[x]),
                     [(x,) for x in range(t) if counts[x]])
        density[0], region[0] = density[t], region[t]
        mask, at = following, at + n
    return out


@kernel
def _slice_gradients(density, region, x, ny, nz, out, at):
    """The gradients of the region voxels of slice ``x`` of a flat padded slab into ``out[:,
    at:]``, in C order."""
    sy = nz + 2
    sx = (ny + 2) * sy
    k = at
    for y in range(1, ny + 1):
        for h in range(x * sx + y * sy + 1, x * sx + y * sy + nz + 1):
            if region[h]:
                out[0, k] = voxel_gradient(density, region, h, sx, sy, 1)
                out[1, k] = voxel_gradient(density, region, h, sy, sx, 1)
                out[2, k] = voxel_gradient(density, region, h, 1, sx, sy)
                k += 1


@kernel
def voxel_gradient(density, region, h, step, first, second):
    """One axis of the gradient at voxel ``h`` of a flat grid (``step`` apart along the axis,
    ``first`` and ``second`` along the other two, the lower axis first): the estimator of
    :func:`region_gradients` with its arithmetic, in float32 (the 9 lines' differences weighted
    ``1 2 1`` along ``first``, then along ``second``, over the weights used)."""
    if not region[h]:
        return np.float32(0)
    two = np.float32(2)
    total, used = np.float32(0), np.float32(0)
    for j in range(3):
        across = h + (j - 1) * second
        d0, u0 = _line_difference(density, region, across - first, step)
        d1, u1 = _line_difference(density, region, across, step)
        d2, u2 = _line_difference(density, region, across + first, step)
        weight = two if j == 1 else np.float32(1)
        if j == 0:
            total, used = (d0 + two * d1) + d2, (u0 + two * u1) + u2
        else:
            total = total + weight * ((d0 + two * d1) + d2)
            used = used + weight * ((u0 + two * u1) + u2)
    return total / max(used, np.float32(1))


@kernel
def _line_difference(density, region, h, step):
    """The difference along ``step`` of the line through voxel ``h`` and 1, or 0 and 0 where
    it is missing (the module docstring)."""
    plus, middle, minus = region[h + step], region[h], region[h - step]
    if plus and minus:
        return np.float32(0.5) * (density[h + step] - density[h - step]), np.float32(1)
    if plus and middle:
        return density[h + step] - density[h], np.float32(1)
    if minus and middle:
        return density[h] - density[h - step], np.float32(1)
    return np.float32(0), np.float32(0)
