"""Coarser resolution levels of a VolumeEVM: model no more than a view needs.

A volume much finer than the image's pixels costs time (every voxel is visited) and aliases
(voxels narrower than a pixel make moiré). Level ``f`` (an integer factor >= 2) renders it from
a coarser VolumeEVM instead, built on demand and kept in the VolumeEVM's cache (:meth:`.level`):

- **Grid**: coarse voxel ``(I, J, K)`` is the block of fine voxels ``[fI, fI + f) x [fJ, fJ + f)
  x [fK, fK + f)``; the coarse grid is ``ceil(shape / f)``, its spacing ``f`` times the fine one
  and its origin at the centre of block ``(0, 0, 0)`` (fine index ``(f - 1) / 2``), so physical
  positions agree: the coarse box covers the fine one (more at the far end when ``f`` does not
  divide the shape).
- **Region**: a coarse voxel is in the region when *any* of its block's fine voxels is. Thin
  structures (a one-voxel plate or shell) survive at every level, thickened to one coarse
  voxel; the silhouette grows by less than one coarse voxel, i.e. less than a pixel when the
  level is chosen by :func:`auto_factor`. The other choice, a majority rule (at least half the
  block), was measured against it (ray casting, RMSE of the level's image to the full level's):
  on bulk objects it is a little closer (CT head at level 2: 0.037 against 0.042; Marschner–Lobb
  81³: 0.048 against 0.052; shear-warp on the CT: 0.039 against 0.034), but it drops thin
  structures: a one-voxel plate 64³ at level 4 vanishes (RMSE 0.23, nothing drawn) where the
  any rule draws it thickened (0.11); a shell likewise (0.26 against 0.17).
- **Densities**: the mean of the region's fine voxels in the block (voxels outside the region
  have no density), so a constant region stays exactly constant. Tables are float32 (float64
  when the fine table is).

The coarse region is made from the region's mask one coarse slab (``f`` fine slices) at a time;
the table lists voxels in C order, so each slab's densities are one contiguous stretch of it and
no dense copy of the densities is made.
"""

import numbers

import numpy as np

from .._errors import VolumeEVMError
from .._memory import check_memory
from ._evm import EVM

__all__ = ["coarsen", "checked_factor", "level_memory"]


def coarsen(vevm, factor):
    """The region and densities of ``vevm`` at ``factor`` times coarser voxels (see the module
    notes); :meth:`VolumeEVM.level` makes the VolumeEVM of them.

    Parameters
    ----------
    vevm : VolumeEVM
    factor : int
        Fine voxels per coarse voxel along each axis: an integer from 2 to the grid's largest
        side (a larger factor would merge the whole grid into one voxel all the same).

    Returns
    -------
    evm : EVM
        The coarse region.
    table : ndarray
        Its densities in the table's order (float32, float64 when the fine table is).
    shape, spacing, origin : tuple of 3
        The coarse grid: ``ceil(shape / factor)``, ``spacing * factor``, the centre of the
        first block.

    Raises
    ------
    VolumeEVMError
        For a factor that is not such an integer, or when the level would need more memory
        than is available (:func:`volumeevm_addon.system.check_memory`).
    """
    f = checked_factor(factor, vevm.shape)
    fine = np.array(vevm.shape)
    shape = -(-fine // f)
    check_memory(level_memory(vevm.shape, f, vevm.voxel_count, len(vevm.evm)), f"making level {f}",
                 source="level factor", advice="use a smaller factor")
    dtype = np.float64 if vevm.table().dtype == np.float64 else np.float32
    mask = vevm.evm.to_mask(vevm.shape)
    table = vevm.table()
    start = 0
    coarse_mask = np.zeros(shape, bool)
    coarse_table = []
    padded = shape * f
    for i in range(shape[0]):
        # One coarse slab: f fine slices padded to whole blocks, summed block by block.
        block_mask = np.zeros((f, padded[1], padded[2]), bool)
        block_sum = np.zeros((f, padded[1], padded[2]), np.float64)
        x0, x1 = i * f, min((i + 1) * f, fine[0])
        slab = mask[x0:x1]
        count = int(np.count_nonzero(slab))
        block_mask[: x1 - x0, : fine[1], : fine[2]] = slab
        block_sum[: x1 - x0, : fine[1], : fine[2]][slab] = table[start:start + count]
        start += count
        split = (f, shape[1], f, shape[2], f)
        counts = block_mask.reshape(split).sum(axis=(0, 2, 4))
        sums = block_sum.reshape(split).sum(axis=(0, 2, 4))
        inside = counts > 0
        coarse_mask[i] = inside
        coarse_table.append(sums[inside] / counts[inside])
    spacing = np.array(vevm.spacing) * f
    shift = vevm.orientation @ (np.array(vevm.spacing) * (f - 1) / 2.0)
    return (EVM.from_mask(coarse_mask), np.concatenate(coarse_table).astype(dtype),
            tuple(int(n) for n in shape), tuple(spacing), tuple(np.array(vevm.origin) + shift))


def checked_factor(factor, shape):
    """``factor`` as an int, refused unless it is an integer from 2 to the grid's largest side.

    Raises
    ------
    VolumeEVMError
        Naming the level factor and the accepted range.
    """
    if (isinstance(factor, (bool, np.bool_)) or not isinstance(factor, numbers.Integral)
            or factor < 2):
        raise VolumeEVMError(f"level factor must be an integer >= 2, got {factor!r}")
    if factor > max(shape):
        raise VolumeEVMError(
            f"level factor {factor} is larger than the grid's largest side ({max(shape)} voxels); "
            f"use a factor from 2 to {max(shape)}"
        )
    return int(factor)


def level_memory(shape, factor, voxel_count, vertex_count):
    """Estimated peak bytes of :func:`coarsen`: the fine mask, one coarse slab's blocks, the table.

    The region's fine mask (its prefix-XOR grid and the boolean copy: 2 bytes a voxel, and
    int64 copies of the ``vertex_count`` vertices that place it: 100 bytes each), the
    blocks of one coarse slab (``factor`` fine slices padded to whole blocks, a boolean and a
    float64 each, with as much again for the block sums) and the coarse table in float64 while
    it is gathered (one entry per coarse voxel of the region, at most the fine voxel count or
    the coarse grid's size; 8 bytes twice).
    """
    x, y, z = (int(n) for n in shape)
    coarse = [-(-n // factor) for n in (x, y, z)]
    padded = [n * factor for n in coarse]
    entries = min(int(voxel_count), coarse[0] * coarse[1] * coarse[2])
    return (2 * (x + 1) * (y + 1) * (z + 1) + 100 * int(vertex_count)
            + 2 * 9 * factor * padded[1] * padded[2] + 16 * entries)
