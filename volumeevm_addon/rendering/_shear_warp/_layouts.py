"""Shear-warp's run layouts: the slices of a principal axis as runs of voxels along their
scanlines, and what is derived from them per transfer function, kept in ``vevm.cache``.

This is the stage VolPack keeps in ``vp_rle.c`` (the run-length encoded volume) and
``vp_octree.c`` (the classified runs worth compositing): the data the compositing
(:mod:`._composite`) reads, built once per principal axis (the layout, the gradients) or per
transfer function and table size (the classes, the post-classification runs), not per view.

**Runs, not boxes** (Lacroute & Levoy, Figure 4). The EVM is the run-length encoding: the 1-D
sections of the section valid at slice ``s`` are the runs of region voxels along its scanlines,
and the densities table ``vevm.table(c)`` lists them in that order. What depends only on the
principal axis is computed once and kept in the VolumeEVM's cache, ``vevm.cache``: the runs of
every scanline with the table position of their first voxel (:func:`box_runs`), and, with
shading, the per-voxel gradients. Per transfer function (also kept) the runs of the voxels worth
compositing: pre-classification, the voxels the function does not make transparent
(:class:`Classes`); post-classification, the voxels where a sample may be visible
(:func:`mixed_codes`, :func:`mixed_runs`); X-ray and MIP, every region voxel. The dense layout
(:func:`dense_layout`, ``skip_empty=False``) numbers every voxel of the grid instead and is made
for one render: the dense side of the exactness contract.

The loops over runs are compiled kernels (:mod:`..._jit`); :data:`Runs` is the record they take.
"""

from collections import namedtuple
from dataclasses import dataclass

import numpy as np

from ..._jit import kernel
from ...model._densities import TABLE_ORDERS, reordered_table, scanline_runs
from .._gradients import region_gradients, table_gradients

__all__ = ["Runs", "Layout", "Classes", "cache_key", "region_layout", "dense_layout",
           "voxel_gradients", "post_table", "voxel_classes", "table_rows", "lit_codes",
           "mixed_runs", "box_runs", "mask_runs", "flagged_runs", "mixed_codes"]

Runs = namedtuple("Runs", "lines columns starts lo hi pos box")
Runs.__doc__ = """Runs of voxels along the scanlines of the slices of one principal axis.

Scanline ``a`` of slice ``s`` (``lines`` scanlines of ``columns`` voxels per slice) is line
``s·lines + a``; its runs are ``starts[line] .. starts[line + 1] - 1``, sorted; run ``r``
covers the columns ``lo[r] .. hi[r] - 1``. ``pos`` (region runs): the position in the
densities table of each run's first voxel (a voxel's *code* is its position + 1; 0 is outside
the region); empty for the runs a transfer function keeps. ``box`` (slices, 4): per slice the
rows ``[a0, a1)`` and columns ``[b0, b1)`` its runs span (``a1 <= a0`` when it has none)."""


@dataclass(frozen=True, slots=True, eq=False)
class Layout:
    """The slices of one principal axis as runs.

    Attributes
    ----------
    axis, axes : int, list of int
        The principal axis; the table order as grid axes (slice, scanline, column).
    shape : tuple of int
        Slices, scanlines per slice and columns per scanline.
    runs : Runs
        The region's runs per scanline, each voxel's code its position in ``values``
        (``values[0]``: outside).
    values : (N + 1,) ndarray
        ``values[0] = 0``, then the densities the codes point at: the densities table of the
        axis, or the whole dense grid.
    region_only : bool
        Whether codes number the region's voxels (True: the layout is kept in ``vevm.cache``,
        and so is what is derived from it, :func:`_kept`) or every voxel of the dense grid
        (False: made for one render, and every region voxel is composited).
    """

    axis: int
    axes: list
    shape: tuple
    runs: Runs
    values: np.ndarray
    region_only: bool

    @property
    def nbytes(self):
        """Bytes of its arrays: what ``vevm.cache`` counts (at once, on every use)."""
        return self.values.nbytes + _runs_bytes(self.runs)


def _runs_bytes(runs):
    """Bytes of the arrays of a :data:`Runs`."""
    return sum(field.nbytes for field in runs if isinstance(field, np.ndarray))


def cache_key(axis, part, tf=None, lut_size=None):
    """The ``vevm.cache`` key of ``part`` of the slices of principal axis ``axis``: "layout"
    (:func:`region_layout`), "gradients", "post" or "post_shaded" (:func:`post_table`), and
    per transfer function and table size "classes" and "mixed" (:func:`voxel_classes`,
    :func:`mixed_runs`). The function enters the key by its control points, all these depend
    on: equal functions share them, and the cache keeps no function (nor its own tables) alive.
    One function for the render and the package's ``tables_to_build``, so that the memory check
    sees the same cache the render uses."""
    if part in ("classes", "lit", "mixed"):
        return ("shear_warp", part, axis, tf.points.tobytes(), lut_size)
    return ("shear_warp", part, axis)


def _kept(vevm, layout, part, make, tf=None, lut_size=None):
    """``make()``, kept in ``vevm.cache`` under :func:`cache_key` for the region's layouts; for
    the dense layout (made anew for every render: the dense side of the exactness contract)
    nothing is kept."""
    if not layout.region_only:
        return make()
    return vevm.cache.get(cache_key(layout.axis, part, tf, lut_size), make)


def region_layout(vevm, axis):
    """The region's slices along ``axis`` (:func:`_make_region_layout`), kept in
    ``vevm.cache``."""
    return vevm.cache.get(cache_key(axis, "layout"), lambda: _make_region_layout(vevm, axis))


def _make_region_layout(vevm, axis):
    """The runs of the EVM's ordered boxes in the table order of ``axis`` (slabs, sub-slabs,
    runs: :meth:`EVM.boxes`), numbered as ``vevm.table(axis)`` lists their voxels. The values
    are that table behind a 0, listed straight into place (the VolumeEVM does not keep a
    second copy)."""
    order = TABLE_ORDERS[axis]
    axes = ["xyz".index(ch) for ch in order]
    shape = tuple(int(vevm.shape[a]) for a in axes)
    lo, hi = (np.ascontiguousarray(corner[:, axes], dtype=np.int64)
              for corner in vevm.evm.boxes(order))
    runs = Runs(shape[1], shape[2], *box_runs(lo, hi, shape[0], shape[1]))
    stored = vevm.table(0)
    values = np.zeros(len(stored) + 1, stored.dtype)
    if axis == 0:
        values[1:] = stored
    else:
        reordered_table(vevm.evm, stored, vevm.shape, axis, out=values[1:])
    return Layout(axis, axes, shape, runs, values, True)


def dense_layout(vevm, axis):
    """The same slices over the whole dense grid, runs read from the region's mask and codes
    numbering every voxel of the grid: the dense side of the exactness contract (no EVM, no
    table, no skipping)."""
    order = TABLE_ORDERS[axis]
    axes = ["xyz".index(ch) for ch in order]
    dense = np.transpose(vevm.to_dense(), axes)
    mask = np.ascontiguousarray(np.transpose(vevm.evm.to_mask(vevm.shape), axes))
    runs = Runs(dense.shape[1], dense.shape[2], *mask_runs(mask))
    values = np.concatenate([np.zeros(1, dense.dtype), dense.ravel()])
    return Layout(axis, axes, dense.shape, runs, values, False)


def voxel_gradients(layout, vevm):
    """Per code, the voxel's index-space gradient (:func:`_make_gradients`), kept
    (:func:`_kept`)."""
    return _kept(vevm, layout, "gradients", lambda: _make_gradients(layout, vevm))


def _make_gradients(layout, vevm):
    """Per voxel, in code order, ``(codes, 3)`` float32: index-space gradients over region
    voxels, the reference's rule (:func:`.._gradients.region_gradients`). The region's are made
    slab by slab in the stored table's order (:func:`.._gradients.table_gradients`) and listed
    in the layout's (:func:`...model._densities.reordered_table`); the dense layout's on the
    dense grid (no EVM)."""
    out = np.zeros((len(layout.values), 3), np.float32)
    if layout.region_only:
        if layout.axis == 0:
            table_gradients(vevm, out=out[1:].T)
        else:
            stored = table_gradients(vevm)
            for k in range(3):
                reordered_table(vevm.evm, stored[k], vevm.shape, layout.axis, out=out[1:, k])
        return out
    pad = tuple(int(n) + 2 for n in vevm.shape)
    dense = np.zeros(pad, np.float32)
    dense[1:-1, 1:-1, 1:-1] = vevm.to_dense()
    region = np.zeros(pad, bool)
    region[1:-1, 1:-1, 1:-1] = vevm.evm.to_mask(vevm.shape)
    grads = np.empty((3,) + tuple(int(n) for n in vevm.shape), np.float32)
    region_gradients(dense, region, grads)
    for k in range(3):
        out[1:, k] = np.transpose(grads[k], layout.axes).ravel()
    return out


def post_table(layout, vevm, with_gradients):
    """Per code, what post-classification interpolates: the density and, ``with_gradients``,
    the index-space gradient, ``(codes, 1 or 4)`` float32 (row 0: outside). Kept
    (:func:`_kept`)."""

    def make():
        table = np.empty((len(layout.values), 4 if with_gradients else 1), np.float32)
        table[:, 0] = layout.values
        if with_gradients:
            table[:, 1:] = voxel_gradients(layout, vevm)
        return table

    return _kept(vevm, layout, "post_shaded" if with_gradients else "post", make)


@dataclass(frozen=True, slots=True, eq=False)
class Classes:
    """Pre-classification by one transfer function and table size.

    ``rows``: per code, the voxel's row of the classification table (0: outside), int16
    (``lut_size`` < 32767); ``work``: the runs of the voxels the function does not make
    transparent (:data:`Runs`; every voxel's, on the dense layout).
    """

    rows: np.ndarray
    work: Runs

    @property
    def nbytes(self):
        """Bytes of its arrays: what ``vevm.cache`` counts (at once, on every use)."""
        return self.rows.nbytes + _runs_bytes(self.work)

    @classmethod
    def of(cls, layout, tf, lut_size):
        """The classes of the voxels of ``layout``."""
        rows = table_rows(layout.values, tf, lut_size)
        if not layout.region_only:  # dense: every voxel is worked on
            return cls(rows, layout.runs)
        visible = _visible(rows, tf, lut_size)
        starts, lo, hi, box = flagged_runs(layout.runs, visible, layout.shape[0])
        return cls(rows, layout.runs._replace(starts=starts, lo=lo, hi=hi,
                                              pos=np.zeros(0, np.int64), box=box))


CHUNK = 1 << 18
"""Voxels per chunk of :func:`table_rows` (its temporaries: about 32 B each)."""


def table_rows(values, tf, lut_size):
    """Per code, 1 + the classification table's row of ``values[code]`` (``values[0]``, outside:
    0), int16; quantized a chunk at a time, so that no float64 copy of the table is made."""
    rows = np.zeros(len(values), np.int16)
    for start in range(1, len(values), CHUNK):
        stop = min(start + CHUNK, len(values))
        rows[start:stop] = tf.quantize(values[start:stop], n=lut_size) + 1
    return rows


def _visible(rows, tf, lut_size):
    """Per code, whether ``tf`` leaves its voxel (table row ``rows[code] - 1``) any opacity."""
    return np.r_[False, tf.straight_table(n=lut_size)[:, 3] > 0][rows]


def voxel_classes(vevm, layout, tf, lut_size):
    """The :class:`Classes` of ``tf`` and ``lut_size`` for ``layout``, kept (:func:`_kept`)."""
    return _kept(vevm, layout, "classes", lambda: Classes.of(layout, tf, lut_size), tf,
                 lut_size)


def lit_codes(vevm, layout, tf, lut_size):
    """Shaded pre-classification: ``(codes, index)``, the codes of the voxels ``tf`` does not
    make transparent (all, on the dense layout) and per code 1 + its place among them (0: the
    others): the voxels each view lights, and where their colours go. Kept (:func:`_kept`)."""

    def make():
        rows = voxel_classes(vevm, layout, tf, lut_size).rows
        if layout.region_only:
            codes = np.flatnonzero(_visible(rows, tf, lut_size))
        else:
            codes = np.arange(1, len(rows))
        kind = np.int32 if len(rows) < 2 ** 31 else np.int64
        index = np.zeros(len(rows), kind)
        index[codes] = np.arange(1, len(codes) + 1, dtype=kind)
        return codes.astype(kind), index

    return _kept(vevm, layout, "lit", make, tf, lut_size)


def mixed_runs(vevm, layout, tf, lut_size):
    """Post-classification: the runs of the voxels where a sample may be visible
    (:func:`mixed_codes`) for ``tf`` and ``lut_size``, kept (:func:`_kept`); every region voxel
    on the dense layout."""

    def make():
        visible = tf.straight_table(n=lut_size)[:, 3] > 0
        # Per table row: -1 where visible, else the index of its run of transparent rows; read
        # by a voxel's row + 1 (:func:`table_rows`; 0, outside, reads -2).
        ids = np.where(visible, -1, np.cumsum(np.r_[True, visible[1:] != visible[:-1]]) - 1)
        codes = np.r_[-2, ids].astype(np.int32)[table_rows(layout.values, tf, lut_size)]
        flags = mixed_codes(layout.runs, codes, layout.shape[0], layout.shape[2])
        starts, lo, hi, box = flagged_runs(layout.runs, flags, layout.shape[0])
        return layout.runs._replace(starts=starts, lo=lo, hi=hi, pos=np.zeros(0, np.int64),
                                    box=box)

    if not layout.region_only:
        return layout.runs
    return _kept(vevm, layout, "mixed", make, tf, lut_size)


# ------------------------------------------------------------------------------------- kernels
@kernel
def box_runs(lo, hi, slices, lines):
    """The region's runs per scanline from the EVM's ordered boxes, in the table's order
    (:func:`...model._densities.scanline_runs`), and the slices' spans. Returns ``(starts,
    run_lo, run_hi, pos, box)`` of :data:`Runs`.
    """
    starts, run_lo, run_hi, pos = scanline_runs(lo, hi, slices, lines)
    return starts, run_lo, run_hi, pos, _boxes(starts, run_lo, run_hi, slices, lines)


@kernel
def mask_runs(mask):
    """The runs of a dense mask ``(slices, lines, columns)`` (the dense side of the exactness
    contract): each run's position is the flat index of its first voxel in the grid. Returns
    ``(starts, run_lo, run_hi, pos, box)`` of :data:`Runs`."""
    slices, lines, columns = mask.shape
    starts = np.zeros(slices * lines + 1, np.int64)
    for s in range(slices):
        for a in range(lines):
            count = 0
            inside = False
            for b in range(columns):
                if mask[s, a, b] and not inside:
                    count += 1
                inside = mask[s, a, b]
            starts[s * lines + a + 1] = starts[s * lines + a] + count
    total = starts[slices * lines]
    run_lo = np.empty(total, np.int32)
    run_hi = np.empty(total, np.int32)
    pos = np.empty(total, np.int64)
    w = 0
    for s in range(slices):
        for a in range(lines):
            b = 0
            while b < columns:
                if mask[s, a, b]:
                    first = b
                    while b < columns and mask[s, a, b]:
                        b += 1
                    run_lo[w] = first
                    run_hi[w] = b
                    pos[w] = (s * lines + a) * columns + first
                    w += 1
                else:
                    b += 1
    return starts, run_lo, run_hi, pos, _boxes(starts, run_lo, run_hi, slices, lines)


@kernel
def flagged_runs(region, flags, slices):
    """The runs of the region's voxels whose ``flags[code]`` is set, per scanline: the voxels a
    transfer function makes worth compositing. Returns ``(starts, run_lo, run_hi, box)``."""
    lines = region.lines
    run_starts, run_lo, run_hi, run_pos = region.starts, region.lo, region.hi, region.pos
    starts = np.zeros(slices * lines + 1, np.int64)
    for line in range(slices * lines):
        count = 0
        for r in range(run_starts[line], run_starts[line + 1]):
            inside = False
            for b in range(run_lo[r], run_hi[r]):
                flag = flags[run_pos[r] + b - run_lo[r] + 1]
                if flag and not inside:
                    count += 1
                inside = flag
        starts[line + 1] = starts[line] + count
    total = starts[slices * lines]
    lo = np.empty(total, np.int32)
    hi = np.empty(total, np.int32)
    w = 0
    for line in range(slices * lines):
        for r in range(run_starts[line], run_starts[line + 1]):
            code = run_pos[r] + 1 - run_lo[r]
            b = run_lo[r]
            while b < run_hi[r]:
                if flags[code + b]:
                    lo[w] = b
                    while b < run_hi[r] and flags[code + b]:
                        b += 1
                    hi[w] = b
                    w += 1
                else:
                    b += 1
    return starts, lo, hi, _boxes(starts, lo, hi, slices, lines)


@kernel
def _boxes(starts, run_lo, run_hi, slices, lines):
    """Per slice, the rows and columns ``(a0, a1, b0, b1)`` its runs span (empty: ``a1 <= a0``)."""
    box = np.zeros((slices, 4), np.int64)
    for s in range(slices):
        a0, a1, b0, b1 = lines, 0, np.iinfo(np.int32).max, 0
        for a in range(lines):
            first, stop = starts[s * lines + a], starts[s * lines + a + 1]
            if stop > first:
                a0 = min(a0, a)
                a1 = a + 1
                b0 = min(b0, run_lo[first])
                b1 = max(b1, run_hi[stop - 1])
        if a1 > a0:
            box[s, 0], box[s, 1], box[s, 2], box[s, 3] = a0, a1, b0, b1
    return box


@kernel
def mixed_codes(region, ids, slices, columns):
    """Post-classification: per code, whether a sample with a tap on this voxel may be visible.

    ``ids[code]``: -1 where the voxel's table row is visible, else the index of the run of
    transparent rows its row is in (-2 at code 0). A sample's density lies between its taps'
    densities, so its row between theirs: when all its taps are in one run of transparent rows,
    it is transparent. A voxel is flagged when it is visible or a region voxel next to it (the
    26 around it: every tap of a sample is next to the others) is in another run or visible;
    a sample without a flagged tap is transparent. Three slices of codes are kept at a time.
    """
    lines = region.lines
    run_starts, run_lo, run_hi, run_pos = region.starts, region.lo, region.hi, region.pos
    window = np.full((3, lines, columns), -2, np.int32)  # slice s in window[s % 3]; -2: outside
    out = np.zeros(ids.size, np.bool_)
    for s in range(-1, slices):
        if s + 1 < slices:  # the next slice replaces slice s - 2
            grid = window[(s + 1) % 3]
            grid[:] = -2
            for line in range((s + 1) * lines, (s + 2) * lines):
                a = line - (s + 1) * lines
                for r in range(run_starts[line], run_starts[line + 1]):
                    code = run_pos[r] + 1 - run_lo[r]
                    for b in range(run_lo[r], run_hi[r]):
                        grid[a, b] = ids[code + b]
        if s < 0:
            continue
        for a in range(lines):
            for r in range(run_starts[s * lines + a], run_starts[s * lines + a + 1]):
                code = run_pos[r] + 1 - run_lo[r]
                for b in range(run_lo[r], run_hi[r]):
                    own = window[s % 3, a, b]
                    mixed = own < 0
                    for ds in range(max(s - 1, 0), min(s + 2, slices)):
                        for da in range(max(a - 1, 0), min(a + 2, lines)):
                            for db in range(max(b - 1, 0), min(b + 2, columns)):
                                other = window[ds % 3, da, db]
                                mixed |= other != own and other != -2
                    out[code + b] = mixed
    return out
