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
  level is chosen by :func:`..rendering._levels.auto_factor`. A majority rule (at least half
  the block) is a little closer on bulk objects but drops thin structures
  (docs/measurements.md).
- **Densities**: the mean of the region's fine voxels in the block (voxels outside the region
  have no density), so a constant region stays exactly constant; summed in float64 in one
  order, the block's x, y, z order (:func:`_block_sums`). Tables are float32 (float64 when the
  fine table is).

Memory follows the region and one slab of the grid, never the whole grid: the fine mask is made
one coarse slab (``f`` fine slices) at a time from the slab's own vertices
(:func:`._evm.mask_slabs`); the table lists voxels in C order, so each slab's densities are one
contiguous stretch of it (no dense copy of the densities); and each coarse slice goes straight
into the coarse region's vertices (:func:`._evm.vertex_keys`) and its means into the coarse
table. The result is the one the grid-sized way gives, bit for bit; one compiled pass over
each slab sums its blocks (the NumPy reductions over the block axes it replaces took three
quarters of the time: 2048³ to level 4, 100 s).
"""

import numbers

import numpy as np

from .._errors import VolumeEVMError
from .._jit import kernel
from .._memory import check_memory
from ._evm import EVM, mask_slabs, vertex_keys

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
    dtype = np.float64 if vevm.table().dtype == np.float64 else np.float32
    check_memory(level_memory(vevm.shape, f, vevm.voxel_count, len(vevm.evm), dtype),
                 f"making level {f}", source="level factor", advice="use a smaller factor")
    table = vevm.table()
    pieces = []

    def coarse_slices():
        """The coarse region slice by slice; each slice's densities go to ``pieces``."""
        start = 0
        for slab in mask_slabs(vevm.evm, vevm.shape, f):
            count = int(np.count_nonzero(slab))
            sums = np.zeros((shape[1], shape[2]), np.float64)
            counts = np.zeros((shape[1], shape[2]), np.int64)
            _block_sums(slab, table[start:start + count], f, sums, counts)
            start += count
            inside = counts > 0
            pieces.append((sums[inside] / counts[inside]).astype(dtype))
            yield inside

    keys = np.concatenate(list(vertex_keys(coarse_slices(), shape)))
    coarse_table = np.concatenate(pieces)
    pieces.clear()
    spacing = np.array(vevm.spacing) * f
    shift = vevm.orientation @ (np.array(vevm.spacing) * (f - 1) / 2.0)
    return (EVM._from_keys(keys), coarse_table, tuple(int(n) for n in shape), tuple(spacing),
            tuple(np.array(vevm.origin) + shift))


@kernel
def _block_sums(slab, values, f, sums, counts):
    """Add the densities of the region voxels of ``slab`` (a fine slab of ``f`` slices at
    most, boolean), ``values`` in the slab's C order, to the ``sums`` and ``counts`` (float64,
    int64) of their coarse voxels ``(y // f, z // f)``: in C order, so each coarse voxel's sum
    is taken over its block's voxels in x, y, z order from 0 — one order, whatever the machine
    (the mean a NumPy reduction over the block's axes gives may differ in the last bit)."""
    k = 0
    for x in range(slab.shape[0]):
        for y in range(slab.shape[1]):
            for z in range(slab.shape[2]):
                if slab[x, y, z]:
                    sums[y // f, z // f] += values[k]
                    counts[y // f, z // f] += 1
                    k += 1


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


def level_memory(shape, factor, voxel_count, vertex_count, dtype=np.float32):
    """Estimated peak bytes of :func:`coarsen`, which goes one coarse slab at a time: no term
    grows with the fine grid beyond one slab of it.

    Counted: two fine mask slabs (``factor`` slices each, a byte a voxel: the one in use and
    the next) and the slice carried between them (:func:`._evm.mask_slabs`); the coarse
    slice's sums, counts, region flags and means (:func:`_block_sums`: 40 bytes a coarse
    cell); a slab's fine vertices
    unpacked (40 bytes each with the temporaries, all ``vertex_count`` of them at worst); the
    coarse vertices' keys (per plane, then joined: 16 bytes each), counted as many as the fine
    vertices: coarse regions had no more in every case measured (0.007 to 0.26 times as many
    on the real volumes of the tests at factors 2 to 5, at most as many on 20,000 small random
    regions); and the coarse table of ``dtype`` twice (slab by slab, then joined), one entry
    per coarse voxel of the region: at most the fine voxel count and the coarse grid's size.
    """
    x, y, z = (int(n) for n in shape)
    coarse = [-(-n // factor) for n in (x, y, z)]
    entries = min(int(voxel_count), coarse[0] * coarse[1] * coarse[2])
    slabs = 2 * factor * y * z + 2 * y * z
    blocks = 40 * coarse[1] * coarse[2]
    return (slabs + blocks + (40 + 16) * int(vertex_count)
            + 2 * np.dtype(dtype).itemsize * entries)
