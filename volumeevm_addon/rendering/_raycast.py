"""Ray casting of a VolumeEVM: the EVM as space-leaping structure, and the report's navigation
variant.

Both casters implement the optical model of the dense reference (:mod:`._reference`) in float32
with a fixed step, fast:

- **Rays** come from :meth:`Camera.rays` and are clipped to the volume's box (index space
  ``-0.5 .. n - 0.5``), to the camera's clip range and to ``depth_in``. From the entry point
  ``t0`` each ray carries samples on a fixed lattice: sample ``k`` stands for the segment
  ``[t0 + k·Δ, t0 + (k + 1)·Δ]`` of ``step_mm`` millimetres (physical length: anisotropic
  spacing is accounted for) and is taken at its midpoint; the last segment is cut at the ray's
  far end (so ``depth_in`` and the far clip cut exactly) and its opacity corrected for its
  shorter length. Opacity is corrected for the step, ``α' = 1 - (1 - α)^(Δ/Δ0)``.
- **Reconstruction** (boundary policy "clamp"): the density at a sample's midpoint is the
  trilinear interpolation of its 8 neighbours that are in the region, with the weights of the
  others dropped and the rest renormalised. Gradients (for shading) are per-voxel 3x3x3
  Sobel estimates over region voxels (:mod:`._gradients`), interpolated the same way, as in
  the reference.
- **Coverage**: as in the reference, only the parts of a ray inside region cells count. Each
  sample's segment is cut where it crosses cell boundaries (at most one per axis for steps up
  to the smallest voxel size) and only the pieces in region cells (all among the midpoint's 8
  neighbours, whose readability is at hand) count: the opacity is corrected for that length.
  The region's surface is therefore placed exactly (a homogeneous region gives the closed form
  ``1 - (1 - α)^(L/Δ0)`` for its exact chord ``L``) and so is the output depth.
- **Jitter** (``jitter=True``, against banding at coarse steps): the lattice of each ray moves
  back by its pixel's fraction of a step (a hash of the pixel, fixed); the first segment, from
  the entry point, is shorter, so entry and exit stay exact.
- **Classification** after interpolation (post-classification) through a lookup table of the
  transfer function (straight colour and step-corrected opacity), linearly interpolated.
  With ``preintegrate=True`` (over, under) a segment wholly in region cells is classified by
  the densities at its two ends through the pre-integrated table of the transfer function for
  the step (:meth:`TransferFunction.preintegrated_table`, 256², over the range of the data and
  the function, bilinear), shaded with the gradient at its middle. A shorter first or last
  segment takes the table's entry for a full step with its opacity corrected for its length
  (exact for the opacity: the optical depth of a ramp is proportional to its length; the colour
  keeps its ratio to the opacity; its error is the table's resolution, docs/measurements.md).
  Segments the region's surface cuts keep the point-sampled middle with the coverage correction.
- **Modes**: ``"over"`` front to back with early ray termination (``termination``),
  ``"under"`` back to front, ``"xray"`` (``T = exp(-Σ μ Δ)``, μ per mm), ``"mip"`` (maximum
  density along the ray over points in region cells, classified without length correction;
  each segment's two ends and middle are evaluated, as the reference does), with the
  reference's conventions.
- **Depth out**: axial depth where the first visible segment enters the region
  (:mod:`._depth`: opacity per unit length at least ``VISIBLE_ALPHA``; X-ray: attenuation;
  MIP: the sample holding the maximum among samples in region cells, if its class is
  visible); ``1e10`` where there is none.

Space leaping (``skip_empty=True``)
-----------------------------------
The EVM's ordered boxes, grown by one voxel (a segment may reach into a neighbouring cell), are
rasterised into a coarse grid of blocks of ``block``³ cells. A block is *visible* when it holds
such a voxel and (over, under) the transfer function is not transparent on the block's density
range, widened by one voxel and one lookup-table step (every value a sample in the block can
interpolate), or (X-ray) some density attenuates. Rays start at the region's bounding box (grown
by one voxel), and a sample whose midpoint lies in an invisible block makes its ray leap to the
first lattice sample past the block's exit, or past the largest aligned cube of ``2**L``
invisible blocks holding it (hierarchical leaping, :func:`leap_levels`; in a cube of visible
blocks, the samples are marched without a look at their blocks). Skipped samples would add
exact zeros, so the image equals ``skip_empty=False`` (every lattice sample in the volume's
box, read from the sampling table alone, no look at the EVM's blocks) up to float rounding,
which is the exactness contract.

Navigation (``render_raycast_navigate``)
----------------------------------------
The report's baseline: the same caster, but every density is located through the EVM: the 8
neighbours of each sample (the 64 around it with shading) go through the relation v (that of
:meth:`VolumeEVM.index`, from the EVM's boxes by binary search) into the densities table,
``-1`` meaning "outside, not readable". No sampling table is made (the space-leaping block
grid is shared with :func:`render_raycast`). Slow by design; the same image as
:func:`render_raycast`, bit for bit.

Each ray is a loop of its own in a compiled kernel (:mod:`._ray_march`), which holds its state
in registers: a render allocates its image and little else. The image is cut into square
tiles of at most ``chunk_rays`` pixels, cast on all threads (:func:`.._jit.parallel_map`); no
ray depends on another, so the image does not depend on the tiles or the number of threads.
The sampling table (the densities, as float32 with NaN outside the region, or for 8- and 16-bit
data in their own type with a value no region voxel holds outside it; float32 gradients when
shading) is block-sparse (:class:`_SamplingTable`): only the blocks of 8³ voxels of the padded
grid that hold region voxels, with a one-voxel apron so that every sample reads one block, are
stored, and a block index (int32 over the grid of blocks, -1 for empty) leads to them; the
samples are those of the dense table, bit for bit. It, the navigation variant's float32
densities and the space-leaping blocks are built on first use straight from the EVM's boxes and
the densities table (no grid-sized array), and kept in the VolumeEVM's cache, ``vevm.cache``: 1
to 4 bytes per voxel of the stored blocks (:func:`pool_type`; 12 more with gradients) and 4 per
block of the grid;
:func:`tables_to_build` tells whether a render would build them, :func:`table_bytes` what
building them costs.

References
----------
M. Levoy, "Efficient ray tracing of volume data", ACM TOG 9(3), 1990 (front-to-back
compositing, early ray termination, hierarchical space leaping).
J. Rodríguez, D. Ayala, "VolumeEVM: a new surface/volume integrated model", UPC technical
report (density location through the EVM).
"""

import functools
import math

import numpy as np

from .._jit import kernel, parallel_map
from ..model._densities import TABLE_ORDERS, TableIndex
from ._camera import BACKGROUND_DEPTH
from ._checks import (
    RAY_STEPS_PER_VOXEL,
    checked_step_mm,
    checked_view,
    flag,
    positive_integer,
)
from ._gradients import region_gradients
from ._method import MemoryModel, Method, keyword_options, step_quality, step_samples
from ._modes import finish_mode
from ._optics import optics
from ._ray_march import (
    BLOCK_VOXELS,
    RELATION_FIELDS,
    TABLE_BLOCK,
    Lattice,
    View,
    Volume,
    march_rays,
)
from ._shading import checked_shading

__all__ = ["render_raycast", "render_raycast_navigate", "RAYCAST_METHOD", "NAVIGATE_METHOD"]

BLOCK = 4
"""The default edge (voxels) of the space-leaping blocks. Measured on the CT head and
brainsmall (512² and 256², both cameras, steps of 2, 1 and 1/2 voxel): 4 is as fast as 8 or up
to 17 % faster (fewer samples in transparent space beside what is seen)."""

MAX_BLOCKS = 1 << 24
"""The most space-leaping blocks the default edge makes (a 1024³ grid in blocks of 4³). The
blocks are grid-sized (:data:`_LEAP_BLOCK_BYTES` kept, :data:`_BLOCK_VIEW_BYTES` per view): in
blocks of 4³ a 2048³ grid would need 7.3 GiB for them, more than its sampling table, so larger
grids get the next edge that keeps them under this count (8³ at 2048³: 0.9 GiB)."""


def leap_block(block, shape):
    """The edge of the space-leaping blocks a render of a grid of ``shape`` uses: ``block``
    when given, else :data:`BLOCK`, doubled while the grid would hold more than
    :data:`MAX_BLOCKS` blocks. The image does not depend on it (up to float rounding, as
    ``skip_empty`` does not), only the render's memory and speed.

    >>> leap_block(None, (1024, 1024, 1024)), leap_block(None, (2048, 2048, 2048))
    (4, 8)
    >>> leap_block(3, (2048, 2048, 2048))
    3
    """
    if block is not None:
        return block
    edge = BLOCK
    while math.prod(-(-int(n) // edge) for n in shape) > MAX_BLOCKS:
        edge *= 2
    return edge


# ---------------------------------------------------------------------------- tables
def _box_rows(vevm):
    """The EVM's boxes of order "xyz" (:meth:`EVM.boxes`) and where their densities sit in the
    densities table of that order: voxel ``(a, b, c)`` of box ``k`` is entry ``rows[k, 0] +
    (a - lo[k, 0])·rows[k, 1] + (b - lo[k, 1])·rows[k, 2] + c - lo[k, 2]`` (the relation v,
    :class:`..model._densities.TableIndex`, per box). Returns ``lo, hi, rows``, (m, 3) int64."""
    index = TableIndex(vevm.evm, TABLE_ORDERS[0])
    lo, hi = (np.asarray(c, dtype=np.int64) for c in vevm.evm.boxes(TABLE_ORDERS[0]))
    sub = np.asarray(index.run_sub, dtype=np.int64)
    slab = np.asarray(index.sub_slab, dtype=np.int64)[sub]
    rows = np.stack([index.slab_base[slab] + index.sub_base[sub] + index.run_before,
                     index.slab_area[slab], index.line_length[sub]], axis=1).astype(np.int64)
    return lo, hi, rows


def _box_chunks(lo, hi, parts):
    """Boxes ``0 .. m`` cut into at most ``parts`` runs of about equal voxel counts, as
    ``(first, stop)`` pairs (tasks of :func:`.._jit.parallel_map`)."""
    ends = np.cumsum(np.prod(hi - lo, axis=1))
    cuts = np.searchsorted(ends, np.linspace(0, ends[-1], parts + 1)[1:-1], side="right")
    bounds = np.unique(np.r_[0, cuts, len(lo)])
    return list(zip(bounds[:-1].tolist(), bounds[1:].tolist()))


def _rasterised(first, stop, shape):
    """The 3-D bool grid of ``shape`` set in the union of the boxes ``first <= cell < stop``
    ((m, 3) each)."""
    grid = np.zeros(tuple(int(s) for s in shape), np.bool_)
    _mark_boxes(first, stop, grid)
    return grid


@kernel
def _mark_boxes(first, stop, grid):
    """Set the cells of the boxes ``first <= cell < stop`` in ``grid``."""
    for k in range(len(first)):
        for i in range(first[k, 0], stop[k, 0]):
            for j in range(first[k, 1], stop[k, 1]):
                for m in range(first[k, 2], stop[k, 2]):
                    grid[i, j, m] = True


class _SamplingTable:
    """The block-sparse sampling table ray casting reads (:data:`._ray_march.Volume`): the
    densities of the grid padded by one voxel each side, ``hole`` outside the region, stored
    only in the blocks of :data:`._ray_march.TABLE_BLOCK`³ padded voxels that hold a region
    voxel in the block or its apron; a sample reads every other voxel as density and weight 0,
    as it read the dense complex64 table ``density·r + i·r`` this replaces (so samples are
    identical, bit for bit). The pool keeps densities of 8 and 16 bits in their own type
    (:func:`pool_type`: half the memory of float32 for the int16 and uint16 of CT and
    microscopy), else float32. Memory follows the region: 1 to 4 bytes per voxel of the stored
    blocks (:data:`._ray_march.BLOCK_VOXELS` each) and 4 per block of the grid.

    ``index`` (int32, flat, strides ``strides``): each block's place in the pool, -1 when not
    stored; ``shape``: blocks per axis; ``table``: the pool, flat; ``hole``: its value outside
    the region. Written straight from the EVM's boxes and the densities table (no grid-sized
    array)."""

    def __init__(self, vevm):
        lo, hi, rows = _box_rows(vevm)
        self.shape = tuple(int(n) // TABLE_BLOCK + 1 for n in vevm.shape)
        stored = _rasterised(lo // TABLE_BLOCK, hi // TABLE_BLOCK + 1, self.shape)
        count = int(np.count_nonzero(stored))
        index = np.full(self.shape, -1, np.int32)
        index[stored] = np.arange(count, dtype=np.int32)
        del stored
        self.index = index.ravel()
        self.strides = (self.shape[1] * self.shape[2], self.shape[2], 1)
        dens = vevm.table(0)
        dtype, self.hole = pool_type(vevm)
        self.table = np.full(BLOCK_VOXELS * count, self.hole, dtype)
        parallel_map(_fill_table, [(lo, hi, rows, dens, first, stop, self.index, self.strides,
                                    self.table) for first, stop in _box_chunks(lo, hi, 16)])

    def gradients(self):
        """The per-voxel gradients shading reads (:func:`.region_gradients`), three float32
        per voxel of the pool (flat, the table's block order): each block's voxels and one
        more voxel around them are gathered from the table (:func:`_gather`), and
        :func:`.region_gradients` takes batches of blocks, so the gradients are those of the
        dense table, bit for bit. Kept apart from the table, so that renders with and without
        shading share the table."""
        count = len(self.table) // BLOCK_VOXELS
        edge = TABLE_BLOCK + 1
        grad = np.zeros((count, edge, edge, edge, 3), np.float32)
        blocks = np.argwhere(self.index.reshape(self.shape) >= 0)
        for first in range(0, count, _GATHER_BLOCKS):
            stop = min(count, first + _GATHER_BLOCKS)
            window = np.zeros((2, stop - first) + (edge + 2,) * 3, np.float32)
            _gather(self.table, self.hole, self.index, self.strides, self.shape,
                    blocks[first:stop], window)
            region_gradients(window[0], window[1], np.moveaxis(grad[first:stop], -1, 0))
        return grad.ravel()


def pool_type(vevm):
    """The sampling table's type and its value outside the region, ``(dtype, hole)``, for a
    VolumeEVM's densities: their own integer type and that type's smallest value when they are
    of 8 or 16 bits and none of them is that value (so ``hole`` marks no region voxel), else
    float32 and NaN (densities are finite). Kept in ``vevm.cache``: the memory check and the
    table ask, and the answer takes a pass over the densities."""
    return vevm.cache.get(("raycast", "pool_type"), lambda: _pool_type(vevm.table(0)))


def _pool_type(densities):
    """:func:`pool_type` of a densities table."""
    dtype = densities.dtype
    if dtype.kind in "iu" and dtype.itemsize <= 2 and len(densities):
        lowest = np.iinfo(dtype).min
        if densities.min() > lowest:
            return dtype, dtype.type(lowest)
    return np.dtype(np.float32), np.float32(np.nan)


_GATHER_BLOCKS = 1024
"""Blocks per batch of the gradients' computation (a window of 11 MB)."""


@kernel
def _fill_table(lo, hi, rows, dens, first, stop, index, strides, table):
    """Write the densities of boxes ``first .. stop - 1`` (:func:`_box_rows`) into the pool
    ``table`` (:class:`_SamplingTable`): each voxel into the block holding it in the padded
    grid and, on a block's first face along an axis, into the apron of the block before."""
    size, edge = TABLE_BLOCK, TABLE_BLOCK + 1
    for k in range(first, stop):
        for a in range(lo[k, 0], hi[k, 0]):
            for b in range(lo[k, 1], hi[k, 1]):
                start = (rows[k, 0] + (a - lo[k, 0]) * rows[k, 1] + (b - lo[k, 1]) * rows[k, 2]
                         - lo[k, 2])
                for c in range(lo[k, 2], hi[k, 2]):
                    d = dens[start + c]
                    for i in range(2):
                        bx = (a + 1) // size - i
                        lx = a + 1 - bx * size
                        if lx > size:
                            break
                        for j in range(2):
                            by = (b + 1) // size - j
                            ly = b + 1 - by * size
                            if ly > size:
                                break
                            for m in range(2):
                                bz = (c + 1) // size - m
                                lz = c + 1 - bz * size
                                if lz > size:
                                    break
                                slot = index[bx * strides[0] + by * strides[1] + bz]
                                table[np.int64(slot) * BLOCK_VOXELS + (lx * edge + ly) * edge
                                      + lz] = d


@kernel
def _gather(table, hole, index, strides, shape, blocks, window):
    """Into ``window`` (2, m, E + 2, E + 2, E + 2) (``E`` = :data:`._ray_march.TABLE_BLOCK` +
    1): the densities (``window[0]``) and region flags (``window[1]``) of the voxels of the
    stored ``blocks`` (m, 3) and one voxel around them, from the pool ``table``; zeros where
    the padded grid has no voxel, the block holding one is not stored or the voxel is NaN or
    ``hole`` (outside the region)."""
    size, edge = TABLE_BLOCK, TABLE_BLOCK + 1
    for s in range(len(blocks)):
        for u in range(edge + 2):
            px = blocks[s, 0] * size - 1 + u
            bx = px // size
            if px < 0 or bx >= shape[0]:
                continue
            for v in range(edge + 2):
                py = blocks[s, 1] * size - 1 + v
                by = py // size
                if py < 0 or by >= shape[1]:
                    continue
                for w in range(edge + 2):
                    pz = blocks[s, 2] * size - 1 + w
                    bz = pz // size
                    if pz < 0 or bz >= shape[2]:
                        continue
                    slot = index[bx * strides[0] + by * strides[1] + bz]
                    if slot < 0:
                        continue
                    d = table[np.int64(slot) * BLOCK_VOXELS
                              + ((px - bx * size) * edge + py - by * size) * edge + pz - bz * size]
                    if d == d and d != hole:
                        window[0, s, u, v, w] = np.float32(d)
                        window[1, s, u, v, w] = np.float32(1)


# ---------------------------------------------------------------------------- blocks
class _NavigationTables:
    """What the navigation variant reads instead of sampling tables: ``densities``, the densities
    table of order "xyz" as float32 (the kernels' type), and ``relation`` (int64), the arrays
    of the relation v (:class:`..model._densities.TableIndex`, :data:`._ray_march.
    RELATION_FIELDS`) one after another, array ``i`` at ``relation_at[i] .. relation_at[i + 1]``:
    about 4 bytes per region voxel and 60 per box of the EVM."""

    def __init__(self, vevm):
        index = TableIndex(vevm.evm, TABLE_ORDERS[0])
        arrays = [np.asarray(getattr(index, name), dtype=np.int64) for name in RELATION_FIELDS]
        self.densities = np.asarray(vevm.table(0)).astype(np.float32)
        self.relation = np.concatenate(arrays)
        self.relation_at = tuple(int(i) for i in np.cumsum([0] + [len(a) for a in arrays]))


class _Blocks:
    """Coarse occupancy of the region (from the EVM's boxes) with per-block density ranges.

    Block ``b`` holds the cells ``b·B .. (b + 1)·B - 1``; it is occupied when a region voxel
    lies within one voxel of them, and its range covers the densities of the region voxels
    within ``reach`` voxels of them (1: what trilinear interpolation at a sample in the block
    can read; more for pre-integration, whose segment ends lie up to half a step away).
    """

    def __init__(self, vevm, size, reach=1):
        self.size = size
        self.last = None  # (what decides visibility, leap levels) of the last view (leaping)
        shape = np.array(vevm.shape, dtype=np.int64)
        self.nb = -(-shape // size)
        lo, hi, rows = _box_rows(vevm)
        # The boxes, grown by one voxel (a sample's segment may reach a neighbouring cell), in
        # blocks.
        self.occupied = _rasterised(np.maximum(lo - 1, 0) // size,
                                    np.minimum(hi, shape - 1) // size + 1, self.nb)
        self.bbox = np.stack([lo.min(axis=0), hi.max(axis=0)]) if len(lo) else None
        # Density ranges per block: every region voxel within `reach` voxels of the block's
        # cells (:func:`_block_ranges`).
        self.range_lo = np.full(tuple(int(b) for b in self.nb), np.inf, np.float32)
        self.range_hi = np.full(tuple(int(b) for b in self.nb), -np.inf, np.float32)
        _block_ranges(lo, hi, rows, vevm.table(0), size, reach, self.range_lo, self.range_hi)

    def leaping(self, lattice, mode, tf, lut_step, compositing):
        """``lattice`` (:data:`._ray_march.Lattice`) with space leaping over these blocks for
        a view's ``mode`` and ``tf`` (:meth:`visible`, :func:`leap_levels`). The levels of the
        last view are kept with what decides the visibility (the mode, the table step, X-ray's
        parameters and the transfer function's control points): the views of one transfer
        function share them without computing the visibility again."""
        nb = [int(b) for b in self.nb]
        xray = (compositing.xray_scale, compositing.xray_offset)
        key = (mode, float(lut_step), xray,
               tf.points.tobytes() if mode in ("over", "under") else None)
        last = self.last  # read once: another thread may render with this VolumeEVM too
        if last is None or last[0] != key:
            visible = self.visible(mode, tf, lut_step, *xray)
            last = self.last = (key, leap_levels(visible).ravel())
        return lattice._replace(leap=True, levels=last[1],
                                block_strides=((nb[1] + 2) * (nb[2] + 2), nb[2] + 2, 1),
                                bbox_lo=_floats(self.bbox[0]), bbox_hi=_floats(self.bbox[1]))

    def visible(self, mode, tf, lut_step, xray_scale, xray_offset):
        """Whether rays must sample each block (3-D bool), over the grid of blocks padded by
        one invisible block on each side."""
        vis = self.occupied.copy()
        if mode in ("over", "under"):
            # Only occupied blocks are classified; each has a density range (reach >= 1).
            vis[vis] = ~tf.transparent_between(self.range_lo[vis] - lut_step,
                                               self.range_hi[vis] + lut_step)
        elif mode == "xray":
            vis &= (self.range_hi > xray_offset) & (xray_scale > 0)
        return np.pad(vis, 1)


def leap_levels(visible):
    """Hierarchical space leaping (Levoy 1990): per block of the 3-D bool grid ``visible``, the
    largest aligned cube of ``2**L`` blocks holding it whose blocks are all invisible (``L +
    1``: a ray leaps past the whole cube) or all visible (``-(L + 1)``: a ray marches through it
    without looking at its blocks), as int8.

    The pyramids of "all invisible" and "all visible" over pairs of cells along each axis
    (blocks past the grid's end count as either: rays never reach them), then coarse to fine:
    a block takes the code of its coarsest uniform cube.
    """
    none, every = [~visible], [visible]
    while max(none[-1].shape) > 1:
        none.append(_all_pairs(none[-1]))
        every.append(_all_pairs(every[-1]))
    levels = np.zeros(none[-1].shape, np.int8)
    for level in reversed(range(len(none))):
        shape = none[level].shape
        for axis in range(3):  # the coarser codes down to this level's cells
            levels = levels.repeat(2, axis=axis)[(slice(None),) * axis + (slice(shape[axis]),)]
        levels = np.where(levels != 0, levels, np.where(
            none[level], level + 1, np.where(every[level], -(level + 1), 0))).astype(np.int8)
    return levels


def _all_pairs(flags):
    """Whether both cells of each pair along each axis are set (a 3-D bool grid half the size,
    rounded up; a cell past the end counts as set)."""
    padded = np.ones(tuple(n + n % 2 for n in flags.shape), bool)
    padded[tuple(slice(n) for n in flags.shape)] = flags
    x, y, z = (n // 2 for n in padded.shape)
    return padded.reshape(x, 2, y, 2, z, 2).all(axis=(1, 3, 5))


@kernel
def _block_ranges(lo_box, hi_box, rows, dens, size, reach, lo, hi):
    """Per block of ``size``³ cells, the smallest and largest density as float32 (into ``lo``
    and ``hi``, which start at +inf and -inf) of the region voxels within ``reach`` voxels of
    its cells along every axis: one pass over the region's boxes (:func:`_box_rows`) and the
    densities table ``dens``, row by row: each block along a row takes the extremes of the
    row's voxels ``b·size - reach .. (b + 1)·size + reach - 1`` and passes them to the blocks
    ``(i - reach) // size .. (i + reach) // size`` of the row's other two coordinates."""
    bx, by, bz = lo.shape
    for k in range(len(lo_box)):
        z_lo, z_hi = lo_box[k, 2], hi_box[k, 2]
        for x in range(lo_box[k, 0], hi_box[k, 0]):
            x0, x1 = max(x - reach, 0) // size, min((x + reach) // size, bx - 1)
            for y in range(lo_box[k, 1], hi_box[k, 1]):
                y0, y1 = max(y - reach, 0) // size, min((y + reach) // size, by - 1)
                start = (rows[k, 0] + (x - lo_box[k, 0]) * rows[k, 1]
                         + (y - lo_box[k, 1]) * rows[k, 2] - z_lo)
                for m in range(max(z_lo - reach, 0) // size,
                               min((z_hi - 1 + reach) // size, bz - 1) + 1):
                    least, most = np.float32(np.inf), np.float32(-np.inf)
                    for z in range(max(m * size - reach, z_lo),
                                   min((m + 1) * size + reach, z_hi)):
                        d = np.float32(dens[start + z])
                        least = min(least, d)
                        most = max(most, d)
                    for i in range(x0, x1 + 1):
                        for j in range(y0, y1 + 1):
                            if least < lo[i, j, m]:
                                lo[i, j, m] = least
                            if most > hi[i, j, m]:
                                hi[i, j, m] = most


def _reach(spacing, step_mm, preintegrate):
    """Voxels from a sample's cell whose densities the sample may read: 1 (trilinear
    interpolation), more with pre-integration, whose segment ends lie half a step away."""
    if not preintegrate:
        return 1
    return int(np.floor(1.5 + 0.5 * step_mm / float(np.min(spacing))))


def tables_to_build(vevm, options, *, navigate):
    """1 when the render would build tables (the sampling tables, or with ``navigate``
    the float32 densities and the relation v; the space-leaping blocks with ``skip_empty``)
    that are not cached for ``vevm`` yet, else 0. Changes nothing: it only looks at the cache.

    ``options`` are the renderer's keywords (``mode`` included).
    """
    if vevm.evm.is_empty():
        return 0
    mode = options.get("mode", "over")
    shaded = mode in ("over", "under") and options.get("shading") not in (None, False)
    spacing = np.asarray(vevm.spacing, dtype=np.float64)
    step_mm = checked_step_mm(options.get("step_mm"), spacing, RAY_STEPS_PER_VOXEL)
    preintegrate = bool(options.get("preintegrate", False)) and mode in ("over", "under")
    tables, blocks = _cache_keys(spacing, navigate, shaded, options.get("skip_empty", True),
                                 leap_block(options.get("block"), vevm.shape), step_mm,
                                 preintegrate)
    keys = tables + (() if blocks is None else (blocks,))
    return int(not all(key in vevm.cache for key in keys))


_BOX_BYTES = 224
"""Per box of the EVM, while the tables are built: the relation v (:class:`TableIndex`, about
150 bytes with its temporaries) and the boxes' table rows (:func:`_box_rows`, 24)."""
_LEAP_BLOCK_BYTES = 10
"""Per space-leaping block, while the blocks are built: the float32 density ranges and the
occupancy (:func:`_rasterised`)."""
_TABLE_BLOCK_BYTES = 9
"""Per block of the grid of the sampling table, while it is built: the int32 index, the bool
grid of stored blocks and the pool numbers."""
_GATHER_BYTES = 64 << 20
"""The gradients' working set: a batch's window (:data:`_GATHER_BLOCKS`) and the temporaries
of :func:`.region_gradients` on it (measured: 35 MiB)."""


def table_bytes(vevm, options, *, navigate):
    """Estimated peak bytes of building the tables a render with ``options`` (the renderer's
    keywords) reads, none cached: the sampling table's pool (its type's bytes per voxel of the
    stored blocks, :func:`pool_type`, 12 more with shading's gradients; the stored blocks are
    counted from the EVM's boxes,
    no grid is made) and its block index, or with ``navigate`` the float32 densities and the
    relation v; the space-leaping blocks with ``skip_empty``; the construction's temporaries
    (per box of the EVM and per block)."""
    if vevm.evm.is_empty():
        return 0
    boxes = len(vevm.evm.boxes(TABLE_ORDERS[0])[0])
    needed = boxes * _BOX_BYTES
    if navigate:
        needed += int(vevm.voxel_count) * 4 + boxes * 8 * len(RELATION_FIELDS)
    else:
        lo, hi = vevm.evm.boxes(TABLE_ORDERS[0])
        shape = tuple(int(n) // TABLE_BLOCK + 1 for n in vevm.shape)
        stored = int(np.count_nonzero(_rasterised(lo // TABLE_BLOCK, hi // TABLE_BLOCK + 1,
                                                  shape)))
        shaded = (options.get("mode", "over") in ("over", "under")
                  and options.get("shading") not in (None, False))
        per_voxel = pool_type(vevm)[0].itemsize + (12 if shaded else 0)
        needed += stored * BLOCK_VOXELS * per_voxel + math.prod(shape) \
            * _TABLE_BLOCK_BYTES + (stored * 24 + _GATHER_BYTES if shaded else 0)
    if options.get("skip_empty", True):
        # A block of 0 is the render's to refuse.
        block = max(1, int(leap_block(options.get("block"), vevm.shape)))
        needed += math.prod(-(-int(n) // block) for n in vevm.shape) * _LEAP_BLOCK_BYTES
    return int(needed)


def _cache_keys(spacing, navigate, shaded, skip_empty, block, step_mm, preintegrate):
    """The ``vevm.cache`` keys of the tables a render reads, ``(tables, blocks)``: the keys of
    the sampling tables (:class:`_SamplingTable`, and its gradients when ``shaded``;
    :class:`_NavigationTables` when ``navigate``) and of the space-leaping blocks (None without
    ``skip_empty``). One function for the render and :func:`tables_to_build`, so that the
    memory check sees the same cache the render uses."""
    if navigate:
        tables = (("raycast", "navigation"),)
    else:
        tables = (("raycast", "table"),) + ((("raycast", "gradients"),) if shaded else ())
    blocks = (("raycast", "blocks", block, _reach(spacing, step_mm, preintegrate))
              if skip_empty else None)
    return tables, blocks


# ---------------------------------------------------------------------------- casting
def _preintegration_range(vevm, tf):
    """The densities the pre-integrated table covers, ``(lo, hi)``: the range of the data and
    of the transfer function (a segment's ends must not be clamped)."""
    data_lo, data_hi = vevm.cache.get(("raycast", "range"), lambda: _data_range(vevm))
    lo = min(data_lo, tf.value_range[0])
    hi = max(data_hi, tf.value_range[1])
    return lo, hi if hi > lo else lo + 1.0


def _data_range(vevm):
    """The smallest and largest density of the region, as floats."""
    dens = np.asarray(vevm.table(0), dtype=np.float64)
    return float(dens.min()), float(dens.max())


def _render(vevm, camera, tf, grid_to_world, *, navigate, mode, depth_in, step_mm, skip_empty,
            termination, shading, xray_scale, xray_offset, block, chunk_rays, jitter,
            preintegrate):
    """Both casters: the checks, the kernels' records, and :func:`._ray_march.march_rays` over
    tiles of at most ``chunk_rays`` pixels on all threads. Returns ``(rgba, depth, samples)``,
    ``samples`` the points the rays sampled (their work)."""
    g, depth_in, compositing = checked_view(vevm, camera, tf, grid_to_world, mode, depth_in,
                                            termination, xray_scale, xray_offset)
    shading = checked_shading(shading)
    jitter = flag("jitter", jitter)
    skip_empty = flag("skip_empty", skip_empty)
    preintegrate = flag("preintegrate", preintegrate) and mode in ("over", "under")
    if mode not in ("over", "under"):
        shading = None
    spacing = np.asarray(vevm.spacing, dtype=np.float64)
    step_mm = checked_step_mm(step_mm, spacing, RAY_STEPS_PER_VOXEL)
    block = positive_integer("block", leap_block(block, vevm.shape))
    chunk_rays = positive_integer("chunk_rays", chunk_rays)
    h, w = camera.shape
    rgba = np.zeros((h * w, 4), np.float32)
    depth = np.full(h * w, BACKGROUND_DEPTH, np.float32)
    if vevm.evm.is_empty():
        return rgba.reshape(h, w, 4), depth.reshape(h, w), 0

    optical = optics(tf, compositing, shading, step_mm=step_mm,
                     pre_range=_preintegration_range(vevm, tf) if preintegrate else None)
    tables_keys, blocks_key = _cache_keys(spacing, navigate, shading is not None, skip_empty,
                                          block, step_mm, preintegrate)
    lattice = Lattice(step_mm, jitter, False, np.zeros(0, np.int8), (0, 0, 0), block,
                      (0.0,) * 3, (0.0,) * 3)
    if skip_empty:
        blocks = vevm.cache.get(blocks_key, lambda: _Blocks(vevm, block, blocks_key[3]))
        margin = 0.0 if mode == "xray" else max(1.0 / scale for scale in (
            optical.lut_scale, optical.pre_scale) if scale > 0)  # a table step
        lattice = blocks.leaping(lattice, mode, tf, margin, compositing)
    records = (_view(camera, g, vevm.shape, spacing, depth_in), lattice,
               _volume(vevm, tables_keys), optical)
    vmax = np.full(h * w if mode == "mip" else 0, -np.inf, np.float32)
    side = max(1, math.isqrt(chunk_rays))  # square tiles of at most chunk_rays pixels
    samples = sum(parallel_map(march_rays, [
        ((r, min(h, r + side)), (c, min(w, c + side)), *records, rgba, depth, vmax)
        for r in range(0, h, side) for c in range(0, w, side)]))
    visible = finish_mode(rgba, vmax, mode, tf)
    if visible is not None:
        depth[~visible] = BACKGROUND_DEPTH
    return rgba.reshape(h, w, 4), depth.reshape(h, w), samples


def _view(camera, grid_to_world, shape, spacing, depth_in):
    """The :data:`._ray_march.View` record of a camera looking at a grid of ``shape``."""
    matrix = np.asarray(camera.matrix_world, dtype=np.float64)
    return View(_floats(matrix), _floats(np.linalg.inv(matrix[:3, :3])),
                _floats(np.linalg.inv(grid_to_world)), _floats(camera.viewplane),
                int(camera.shape[1]), int(camera.shape[0]), bool(camera.is_ortho),
                _floats((camera.clip_start, camera.clip_end)),
                np.zeros(0) if depth_in is None else np.ascontiguousarray(depth_in.ravel()),
                _floats(shape), _floats(spacing))


def _volume(vevm, keys):
    """The :data:`._ray_march.Volume` record of a render, from the tables of ``keys``
    (:func:`_cache_keys`) in the cache: the block-sparse sampling table (and gradients), or for
    the navigation variant the densities table and the relation v."""
    n = tuple(int(s) for s in vevm.shape)
    nothing = np.zeros(0, np.float32)
    if keys[0] == ("raycast", "navigation"):
        tables = vevm.cache.get(keys[0], lambda: _NavigationTables(vevm))
        return Volume(n, (0, 0, 0), np.zeros(0, np.int32), (nothing, np.float32(np.nan)),
                      nothing, True,
                      tables.densities, tables.relation, tables.relation_at)
    table = vevm.cache.get(keys[0], lambda: _SamplingTable(vevm))
    grad = vevm.cache.get(keys[1], table.gradients) if len(keys) > 1 else nothing
    return Volume(n, table.strides, table.index, (table.table, table.hole), grad, False, nothing,
                  np.zeros(0, np.int64), (0,) * (len(RELATION_FIELDS) + 1))


def _floats(values):
    """An array (or sequence) of numbers as (nested) tuples of floats, as the kernels' records
    take small vectors and matrices."""
    values = np.asarray(values, dtype=np.float64)
    return tuple(map(tuple, values.tolist())) if values.ndim == 2 else tuple(values.tolist())


def render_raycast(vevm, camera, tf, grid_to_world, *, mode="over", depth_in=None, step_mm=None,
                   skip_empty=True, termination=0.99, shading=None, xray_scale=1.0,
                   xray_offset=0.0, block=None, chunk_rays=1024, jitter=False,
                   preintegrate=False):
    """Ray cast a VolumeEVM with the EVM as space-leaping structure.

    Parameters
    ----------
    vevm : VolumeEVM
    camera : Camera
    tf : TransferFunction
        Post-interpolation classification (unused, may be None, for ``mode="xray"``).
    grid_to_world : (4, 4) ndarray
        Voxel-centre index space to Blender world (:func:`volumeevm_addon.grid_to_world`).
    mode : {"over", "under", "xray", "mip"}
        As in :func:`._reference.render_reference`.
    depth_in : (H, W) ndarray, optional
        Axial depth (Blender units) of scene geometry: rays stop there (exactly: the last
        segment is cut). NaN raises :class:`VolumeEVMError`.
    step_mm : float, optional
        Sample spacing along rays in mm (default: half the smallest voxel size).
    skip_empty : bool
        True: leap over blocks the EVM shows empty or invisible. False: every sample in the
        volume's box, from the sampling table alone. Same image (module docstring).
    termination : float
        ``"over"``: a ray stops once its opacity reaches this value (1 = never); the error
        this makes is at most ``1 - termination`` per channel.
    shading : None, True, dict or Shading
        Gradient shading (Blinn–Phong headlight, :class:`._shading.Shading`) for over/under.
    xray_scale, xray_offset : float
        X-ray attenuation per mm per data unit and the density of zero attenuation.
    block : int, optional
        Edge (voxels) of the space-leaping blocks; by default :data:`BLOCK`, larger for grids
        of more than :data:`MAX_BLOCKS` such blocks (:func:`leap_block`).
    chunk_rays : int
        Pixels per task of the threads (square tiles of at most this many pixels): each ray is
        cast on its own, so the image does not depend on it; it only balances the work between
        threads.
    jitter : bool
        Offset each ray's sample lattice by its pixel's fraction of a step (a fixed hash: the
        same image every run): banding at coarse steps becomes noise. Entry and exit stay exact.
    preintegrate : bool
        ``"over"``/``"under"``: classify each segment by its two ends' densities through the
        pre-integrated table (:meth:`TransferFunction.preintegrated_table`) instead of its
        middle's, for transfer functions narrower than the density change per step. Ignored by
        ``"mip"`` and ``"xray"`` (they classify no segments).

    Returns
    -------
    rgba : (H, W, 4) ndarray of np.float32
        Premultiplied RGBA, row 0 at the top.
    depth : (H, W) ndarray of np.float32
        Axial depth (Blender units) of the first visible segment's front; 1e10 where none.
    """
    return _render(vevm, camera, tf, grid_to_world, navigate=False, mode=mode, depth_in=depth_in,
                   step_mm=step_mm, skip_empty=skip_empty, termination=termination,
                   shading=shading, xray_scale=xray_scale, xray_offset=xray_offset, block=block,
                   chunk_rays=chunk_rays, jitter=jitter, preintegrate=preintegrate)[:2]


def render_raycast_navigate(vevm, camera, tf, grid_to_world, *, mode="over", depth_in=None,
                            step_mm=None, skip_empty=True, termination=0.99, shading=None,
                            xray_scale=1.0, xray_offset=0.0, block=None, chunk_rays=1024,
                            jitter=False, preintegrate=False):
    """Ray cast a VolumeEVM locating every density through the EVM (the report's baseline).

    The same caster as :func:`render_raycast` (same parameters, same image within float
    rounding), but each sample's 8 trilinear neighbours (64 with ``shading``) are found through
    the relation v (:meth:`VolumeEVM.index`) in the densities table; no sampling table exists.
    ``skip_empty=False`` marches every lattice sample in the volume's box.
    """
    return _render(vevm, camera, tf, grid_to_world, navigate=True, mode=mode, depth_in=depth_in,
                   step_mm=step_mm, skip_empty=skip_empty, termination=termination,
                   shading=shading, xray_scale=xray_scale, xray_offset=xray_offset, block=block,
                   chunk_rays=chunk_rays, jitter=jitter, preintegrate=preintegrate)[:2]


# ---------------------------------------------------------------------------- the records
_BLOCK_VIEW_BYTES = 48
"""Space leaping, per block of the (padded) block grid: which blocks the transfer function
leaves visible (the density ranges widened, compared and combined) and their leap levels, made
when the transfer function or mode differs from the last view's (counted for every view).
Measured: 80 MiB for the 2.2 million blocks of a 512³ grid."""


def _block_view_bytes(vevm, options):
    """The space-leaping blocks' per-view working set (none with ``skip_empty=False``; a
    block of 0 is the renderer's to refuse: counted as 1 here)."""
    if not options["skip_empty"]:
        return 0
    block = max(1, int(leap_block(options["block"], vevm.shape)))
    return math.prod(-(-int(n) // block) + 2 for n in vevm.shape) * _BLOCK_VIEW_BYTES


def _tables(vevm, camera, tf, grid_to_world, options):
    """The record's ``tables_to_build`` (:func:`tables_to_build`)."""
    return tables_to_build(vevm, options, navigate=False)


def _navigate_tables(vevm, camera, tf, grid_to_world, options):
    """The navigation record's ``tables_to_build`` (:func:`tables_to_build`)."""
    return tables_to_build(vevm, options, navigate=True)


RAYCAST_METHOD = Method(
    name="raycast", label="Ray Casting",
    description="Trilinear ray casting with the EVM as space-leaping structure",
    render=render_raycast, options=keyword_options(render_raycast),
    # The tables follow the region, not the grid (:func:`table_bytes`: the block-sparse
    # sampling table, its gradients with shading, the space-leaping blocks); per pixel, the ray
    # set-up and per-ray state.
    memory=MemoryModel(pixel=32, per_set=functools.partial(table_bytes, navigate=False),
                       per_view=_block_view_bytes),
    tables_to_build=_tables, check_samples=step_samples(RAY_STEPS_PER_VOXEL),
    quality=step_quality(RAY_STEPS_PER_VOXEL), categorical=True)
"""Ray casting with the EVM as space-leaping structure."""

NAVIGATE_METHOD = Method(
    name="raycast_navigate", label="Ray Casting (Navigation)",
    description="Ray casting that finds every density through the EVM (the report's slow "
                "baseline)",
    render=render_raycast_navigate, options=keyword_options(render_raycast_navigate),
    # No sampling table: float32 densities, the relation v and the blocks (:func:`table_bytes`).
    memory=MemoryModel(pixel=32, per_set=functools.partial(table_bytes, navigate=True),
                       per_view=_block_view_bytes),
    tables_to_build=_navigate_tables, check_samples=step_samples(RAY_STEPS_PER_VOXEL),
    quality=step_quality(RAY_STEPS_PER_VOXEL), categorical=True)
"""Ray casting that finds every density through the EVM (no dense array)."""
