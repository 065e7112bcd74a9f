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
  others dropped and the rest renormalised. Gradients (for shading) are per-voxel central
  differences over region voxels (one-sided at the surface), interpolated the same way, as in
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
  keeps its ratio to the opacity). Measured on a linear ramp with jitter (every first segment
  partial): within 2.5e-3 of the reference, the table's resolution (7e-5 with 1024²). Segments
  the region's surface cuts keep the point-sampled middle with the coverage correction.
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
first lattice sample past the block's exit. Skipped samples would add exact zeros, so the
image equals ``skip_empty=False`` (every lattice sample in the volume's box, the dense grid
with the region mask, no EVM) up to float rounding, which is the exactness contract.

Navigation (``render_raycast_navigate``)
----------------------------------------
The report's baseline: the same caster, but every density is located through the EVM: the 8
neighbours of each sample go through the relation v (:meth:`VolumeEVM.index`, from the EVM's
boxes by binary search) into the densities table, ``-1`` meaning "outside, not readable". No
dense array is sampled (the space-leaping block grid, shared with :func:`render_raycast`, is
made once through a temporary grid). Slow by design; same image as :func:`render_raycast`.

Python loops over ray steps (and chunks of rays); all rays of a chunk advance together and the
active set is compacted as rays finish. The padded sampling tables (complex64 density and
weight, float32 gradients when shading) and the block grid are built on first use, in place
(no grid-sized temporaries beside the region mask), and kept in the VolumeEVM's cache,
``vevm.cache`` (about 8 bytes per grid voxel, 20 with gradients); :func:`tables_to_build` tells
whether a render would build them.

References
----------
M. Levoy, "Efficient ray tracing of volume data", ACM TOG 9(3), 1990 (front-to-back
compositing, early ray termination, hierarchical space leaping).
J. Rodríguez, D. Ayala, "VolumeEVM: a new surface/volume integrated model", UPC technical
report (density location through the EVM).
"""

from dataclasses import dataclass

import numpy as np

from . import _depth
from ._camera import BACKGROUND_DEPTH
from ._checks import (RAY_STEPS_PER_VOXEL, checked_step_mm, checked_view, flag,
                      positive_integer)
from ._gradients import region_gradients
from ._modes import finish_mode
from ._rays import box_entry_exit, camera_rays
from ._shading import Lighting, checked_shading

__all__ = ["render_raycast", "render_raycast_navigate"]

_LUT_SIZE = 4096
_PREINT_SIZE = 256
"""Rows and columns of the pre-integrated table (over the data's and the function's range)."""


# ---------------------------------------------------------------------------- samplers
def _lerp8(v, f):
    """Trilinear blend of the 8 corner arrays ``v[(a, b, c)]`` with fractions ``f`` (m, 3)."""
    fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
    if v[0].dtype.kind == "c":
        fx, fy, fz = (x.astype(np.complex64) for x in (fx, fy, fz))
    c00 = v[0] + fz * (v[1] - v[0])
    c01 = v[2] + fz * (v[3] - v[2])
    c10 = v[4] + fz * (v[5] - v[4])
    c11 = v[6] + fz * (v[7] - v[6])
    c0 = c00 + fy * (c01 - c00)
    c1 = c10 + fy * (c11 - c10)
    return c0 + fx * (c1 - c0)


class _Grid:
    """Index arithmetic on the grid padded by one voxel on each side."""

    def __init__(self, shape):
        self.n = np.array(shape, dtype=np.int64)
        p = self.n + 2
        self.strides = np.array([p[1] * p[2], p[2], 1], dtype=np.int64)
        self.corner_offsets = [int(a * self.strides[0] + b * self.strides[1] + c)
                               for a in (0, 1) for b in (0, 1) for c in (0, 1)]

    def locate(self, p):
        """``p`` (m, 3) float32 -> (base voxel (m, 3) int64 in ``-1 .. n-1``, fractions (m, 3)
        float32, nearest voxel (m, 3) int64 in ``-1 .. n``)."""
        fl = np.floor(p)
        f = p - fl
        base = fl.astype(np.int64)
        np.maximum(base, -1, out=base)
        np.minimum(base, self.n - 1, out=base)
        np.maximum(f, 0, out=f)
        np.minimum(f, 1, out=f)
        nearest = base + (f >= 0.5)
        return base, f, nearest

    def flat(self, voxels):
        """Flat index into the padded grid of voxels ``(m, 3)`` (``-1 .. n``)."""
        sx, sy, _ = self.strides
        return (voxels[:, 0] + 1) * sx + (voxels[:, 1] + 1) * sy + (voxels[:, 2] + 1)


class _DenseSampler:
    """Trilinear reconstruction from padded dense tables made from the VolumeEVM: complex64
    ``density·r + i·r`` (``r`` = in the region) and the gradients."""

    def __init__(self, vevm, with_gradient):
        self.grid = _Grid(vevm.shape)
        mask = vevm.evm.to_mask(vevm.shape)
        pad = tuple(int(s) + 2 for s in vevm.shape)
        # Written in place into the real and imaginary parts: no grid-sized temporaries.
        tab = np.zeros(pad, np.complex64)
        inner = tab[1:-1, 1:-1, 1:-1]
        inner.real[mask] = vevm.table(0)
        inner.imag[...] = mask
        self.table = tab.ravel()
        self.grad = None
        if with_gradient:
            gpad = np.zeros((3,) + pad, np.float32)
            region_gradients(tab.real, tab.imag, gpad[:, 1:-1, 1:-1, 1:-1])
            self.grad = gpad.reshape(3, -1)

    def __call__(self, p):
        """``p`` (m, 3) float32 -> (base voxel (m, 3), fractions (m, 3), readable corners
        (m, 8) bool, density (m,) float32, gradient (m, 3) float32 or None); the density and
        gradient are 0 where no corner is readable."""
        base, f, _ = self.grid.locate(p)
        b = self.grid.flat(base)
        vals = [self.table[b + o] for o in self.grid.corner_offsets]
        readable = np.stack([v.imag > 0 for v in vals], axis=1)
        return (base, f, readable) + _renormalised(
            _lerp8(vals, f), None if self.grad is None else [
                _lerp8([g[b + o] for o in self.grid.corner_offsets], f) for g in self.grad])


class _NavigationSampler:
    """Trilinear reconstruction with every density located through the EVM (relation v): no
    dense array."""

    def __init__(self, vevm, with_gradient):
        self.vevm = vevm
        self.table = np.asarray(vevm.table(0))
        self.grid = _Grid(vevm.shape)
        self.with_gradient = with_gradient
        corners = np.array([(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)])
        self.corners = corners
        # The 4x4x4 neighbourhood base-1 .. base+2 (central differences at the 8 corners).
        self.hood = np.array([(a, b, c) for a in range(4) for b in range(4) for c in range(4)])

    def _lookup(self, voxels):
        """Densities (float32) and readability of voxels ``(..., 3)`` through the EVM."""
        idx = self.vevm.index(voxels.reshape(-1, 3)).reshape(voxels.shape[:-1])
        ok = idx >= 0
        dens = np.where(ok, self.table[np.maximum(idx, 0)], 0).astype(np.float32)
        return dens, ok

    def __call__(self, p):
        base, f, nearest = self.grid.locate(p)
        if not self.with_gradient:
            dens, ok = self._lookup(base[:, None, :] + self.corners[None])  # (m, 8)
            grad = None
        else:
            hd, hok = self._lookup(base[:, None, :] - 1 + self.hood[None])  # (m, 64)
            hd, hok = hd.reshape(-1, 4, 4, 4), hok.reshape(-1, 4, 4, 4)
            dens = hd[:, 1:3, 1:3, 1:3].reshape(-1, 8)
            ok = hok[:, 1:3, 1:3, 1:3].reshape(-1, 8)
            gcols = np.empty((3, len(hd), 2, 2, 2), np.float32)  # at the 8 corners
            region_gradients(hd, hok, gcols)
            gcols = gcols.reshape(3, -1, 8)
        cvals = (dens + 1j * ok.astype(np.float32)).astype(np.complex64)
        grads = None
        if self.with_gradient:
            grads = [_lerp8([g[:, i] for i in range(8)], f) for g in gcols]
        return (base, f, ok) + _renormalised(_lerp8([cvals[:, i] for i in range(8)], f), grads)


def _renormalised(acc, grads):
    """Density (and gradient) from the interpolated ``density·r + i·r`` (and ``gradient·r``)
    divided by the interpolated weight of readable corners; 0 where there is none."""
    wsum = acc.imag
    has = wsum > 0
    wsum = np.where(has, wsum, np.float32(1))
    value = acc.real / wsum
    grad = None
    if grads is not None:
        grad = np.stack(grads, axis=1) / wsum[:, None]
    return value, grad


def _coverage(pf, pb, base, readable):
    """Fraction of each segment ``pf -> pb`` (index space) lying in readable cells, and where
    (as a fraction) its first readable piece starts (NaN for none).

    The segment is cut where it crosses a cell boundary (index ``m + 0.5``; at most one per
    axis when the step is at most a voxel); each piece's cell is one of the 8 trilinear
    corners of the segment's midpoint (``base``), whose readability is known. Segments whose
    8 corners are all readable (or none) need no cutting.
    """
    every = readable.all(axis=1)
    frac = every.astype(np.float32)
    first = np.where(every, np.float32(0), np.float32(np.nan))
    mixed = np.flatnonzero(readable.any(axis=1) & ~every)
    if len(mixed) == 0:
        return frac, first
    pf, pb, base, readable = pf[mixed], pb[mixed], base[mixed], readable[mixed]
    m = len(mixed)
    span = pb - pf
    cf = np.floor(pf + np.float32(0.5))
    cb = np.floor(pb + np.float32(0.5))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (np.maximum(cf, cb) - np.float32(0.5) - pf) / span
    t = np.where(cf != cb, np.clip(t, 0, 1), np.float32(1))
    t.sort(axis=1)
    edges = [np.zeros(m, np.float32), t[:, 0], t[:, 1], t[:, 2], np.ones(m, np.float32)]
    part = np.zeros(m, np.float32)
    start = np.full(m, np.nan, np.float32)
    rows = np.arange(m)
    for e0, e1 in zip(edges[:-1], edges[1:]):
        length = e1 - e0
        q = pf + (np.float32(0.5) * (e0 + e1))[:, None] * span
        rel = np.floor(q + np.float32(0.5)).astype(np.int64) - base
        np.clip(rel, 0, 1, out=rel)
        ins = readable[rows, rel[:, 0] * 4 + rel[:, 1] * 2 + rel[:, 2]] & (length > 0)
        part += length * ins
        start = np.where(np.isnan(start) & ins, e0, start)
    frac[mixed] = part
    first[mixed] = start
    return frac, first


# ---------------------------------------------------------------------------- blocks
class _Blocks:
    """Coarse occupancy of the region (from the EVM's boxes) with per-block density ranges.

    Block ``b`` holds the cells ``b·B .. (b + 1)·B - 1``; it is occupied when a region voxel
    lies within one voxel of them, and its range covers the densities of the region voxels
    within ``reach`` voxels of them (1: what trilinear interpolation at a sample in the block
    can read; more for pre-integration, whose segment ends lie up to half a step away).
    """

    def __init__(self, vevm, size, reach=1):
        self.size = size
        shape = np.array(vevm.shape, dtype=np.int64)
        self.nb = -(-shape // size)
        lo, hi = vevm.evm.boxes()
        lo = lo.astype(np.int64)
        hi = hi.astype(np.int64)
        # Rasterise the boxes, grown by one voxel (a sample's segment may reach a neighbouring
        # cell), into blocks: +-1 at the corners of each box's block range, then prefix sums
        # (a 3-D difference array).
        diff = np.zeros(tuple(self.nb + 1), np.int64)
        blo = np.maximum(lo - 1, 0) // size
        bhi = np.minimum(hi, shape - 1) // size + 1
        for cx in (0, 1):
            for cy in (0, 1):
                for cz in (0, 1):
                    sign = (-1) ** (cx + cy + cz)
                    pts = np.where([cx, cy, cz], bhi, blo)
                    np.add.at(diff, (pts[:, 0], pts[:, 1], pts[:, 2]), sign)
        occ = diff.cumsum(0).cumsum(1).cumsum(2)[:-1, :-1, :-1] > 0
        self.occupied = occ
        self.bbox = np.stack([lo.min(axis=0), hi.max(axis=0)]) if len(lo) else None
        # Density ranges per block: every region voxel within `reach` voxels of the block's
        # cells, from a temporary grid of the table's densities grown by `reach` voxels (min
        # and max filters), then reduced block by block.
        mask = vevm.evm.to_mask(vevm.shape)
        dens = np.asarray(vevm.table(0), dtype=np.float32)
        self.range_lo = self._ranges(mask, dens, reach, np.minimum, np.inf)
        self.range_hi = self._ranges(mask, dens, reach, np.maximum, -np.inf)

    def _ranges(self, mask, dens, reach, op, fill):
        """Per block, ``op`` (``np.minimum`` or ``np.maximum``) of the densities ``dens`` of the
        region ``mask`` within ``reach`` voxels of the block's cells (``fill`` for none)."""
        size = self.size
        grid = np.full(tuple(int(b) * size for b in self.nb), fill, np.float32)
        grid[tuple(slice(0, n) for n in mask.shape)][mask] = dens
        _grow(grid, op, reach)
        nx, ny, nz = (int(b) for b in self.nb)
        return op.reduce(grid.reshape(nx, size, ny, size, nz, size), axis=(1, 3, 5))

    def visible(self, mode, tf, lut_step, xray_scale, xray_offset):
        """Flat bool array over the blocks padded by one invisible block on each side."""
        vis = self.occupied.copy()
        if mode in ("over", "under"):
            has = vis & np.isfinite(self.range_lo)
            lo = np.where(has, self.range_lo - lut_step, 0.0)
            hi = np.where(has, self.range_hi + lut_step, 0.0)
            vis &= ~tf.transparent_between(lo, hi)
        elif mode == "xray":
            vis &= (self.range_hi > xray_offset) & (xray_scale > 0)
        return np.pad(vis, 1).ravel()


def _grow(grid, op, reach):
    """Replace, in place, every value of ``grid`` by ``op`` (``np.minimum`` or ``np.maximum``)
    of the values within ``reach`` voxels along each axis (a min or max filter over a cube).

    One axis at a time, one plane across another axis at a time: the copy each step needs is
    a plane, not the grid (min and max are exact, so the order does not change the result).
    """
    for _ in range(reach):
        for ax in range(3):
            across = 1 if ax == 0 else 0
            k = ax - (ax > across)  # `ax` among the plane's two axes
            lo, hi = [slice(None)] * 2, [slice(None)] * 2
            lo[k], hi[k] = slice(0, -1), slice(1, None)
            lo, hi = tuple(lo), tuple(hi)
            for i in range(grid.shape[across]):
                plane = grid[(slice(None),) * across + (i,)]
                src = plane.copy()
                op(plane[lo], src[hi], out=plane[lo])
                op(plane[hi], src[lo], out=plane[hi])


def _reach(spacing, step_mm, preintegrate):
    """Voxels from a sample's cell whose densities the sample may read: 1 (trilinear
    interpolation), more with pre-integration, whose segment ends lie half a step away."""
    if not preintegrate:
        return 1
    return int(np.floor(1.5 + 0.5 * step_mm / float(np.min(spacing))))


def tables_to_build(vevm, options, *, navigate):
    """1 when the render would build grid tables (the dense sampling tables, unless
    ``navigate``; the space-leaping blocks with ``skip_empty``) that are not cached for
    ``vevm`` yet, else 0. Changes nothing: it only looks at the cache.

    ``options`` are the renderer's keywords (``mode`` included).
    """
    if vevm.evm.is_empty():
        return 0
    mode = options.get("mode", "over")
    shaded = mode in ("over", "under") and options.get("shading") not in (None, False)
    spacing = np.asarray(vevm.spacing, dtype=np.float64)
    step_mm = options.get("step_mm")
    step_mm = float(spacing.min()) / 2 if step_mm is None else float(step_mm)
    preintegrate = bool(options.get("preintegrate", False)) and mode in ("over", "under")
    keys = _cache_keys(spacing, navigate, shaded, options.get("skip_empty", True),
                       options.get("block", 8), step_mm, preintegrate)
    return int(not all(key in vevm.cache for key in keys if key is not None))


def _cache_keys(spacing, navigate, shaded, skip_empty, block, step_mm, preintegrate):
    """The ``vevm.cache`` keys of the tables a render reads, ``(sampler, blocks)``: the dense
    sampling tables (None when ``navigate``) and the space-leaping blocks (None without
    ``skip_empty``). One function for the render and :func:`tables_to_build`, so that the
    memory check sees the same cache the render uses."""
    sampler = None if navigate else ("raycast", "sampler", shaded)
    blocks = (("raycast", "blocks", block, _reach(spacing, step_mm, preintegrate))
              if skip_empty else None)
    return sampler, blocks


# ---------------------------------------------------------------------------- casting
def _lut(tf, step_mm):
    """Straight colour and step-corrected opacity at ``_LUT_SIZE`` values over the transfer
    function's control range; returns ``(table (n, 4) float32, lo, scale, step)``."""
    lo, hi = tf.value_range
    if hi <= lo:
        hi = lo + 1.0
    tab = np.array(tf.straight_table(lo=lo, hi=hi, n=_LUT_SIZE), dtype=np.float64)
    tab[:, 3] = 1.0 - np.power(1.0 - tab[:, 3], step_mm / tf.unit_length_mm)
    step = (hi - lo) / (_LUT_SIZE - 1)
    return tab.astype(np.float32), lo, 1.0 / step, step


def _preintegration(vevm, tf, step_mm):
    """The pre-integrated table for segments of ``step_mm`` over the range of the data and the
    transfer function (a segment's ends must not be clamped); returns ``(table (n·n, 4)
    float32, lo, scale, step, n)``."""
    data_lo, data_hi = vevm.cache.get(("raycast", "range"), lambda: _data_range(vevm))
    lo = min(data_lo, tf.value_range[0])
    hi = max(data_hi, tf.value_range[1])
    if hi <= lo:
        hi = lo + 1.0
    n = _PREINT_SIZE
    tab = tf.preintegrated_table(lo=lo, hi=hi, n=n, step_mm=step_mm)
    step = (hi - lo) / (n - 1)
    return tab.reshape(-1, 4), lo, 1.0 / step, step, n


def _data_range(vevm):
    """The smallest and largest density of the region, as floats."""
    dens = np.asarray(vevm.table(0), dtype=np.float64)
    return float(dens.min()), float(dens.max())


def _classify_preintegrated(pre, front, back, ratio):
    """Straight RGB (m, 3) and opacity (m,) of segments whose density runs linearly from
    ``front`` to ``back``, of ``ratio`` (m,) steps: bilinear in the pre-integrated table, the
    opacity corrected for segments shorter than a step as if their density were constant
    (their colour keeps its ratio to the opacity)."""
    tab, lo, scale, _, n = pre
    idx, frac = [], []
    for s in (front, back):
        x = (s - np.float32(lo)) * np.float32(scale)
        np.clip(x, 0, n - 1, out=x)
        i = np.minimum(x.astype(np.int64), n - 2)
        idx.append(i)
        frac.append((x - i)[:, None])
    (i, j), (fi, fj) = idx, frac
    flat = i * n + j
    top = tab[flat] + fj * (tab[flat + 1] - tab[flat])
    bottom = tab[flat + n] + fj * (tab[flat + n + 1] - tab[flat + n])
    rgba = top + fi * (bottom - top)
    alpha = rgba[:, 3]
    has = alpha > 0
    rgb = rgba[:, :3] / np.where(has, alpha, np.float32(1))[:, None]
    short = np.flatnonzero(ratio != 1)
    if len(short):
        alpha[short] = 1 - np.power(1 - alpha[short], ratio[short])
    return rgb, alpha


def _jitter(count):
    """Fraction of a step in ``[0, 1)`` per pixel: a hash (Wellons' lowbias32) of the flat pixel
    index, so the same pixel gets the same offset on every run and chunking does not matter;
    white noise, so banding turns into noise without a pattern of its own."""
    x = np.arange(count, dtype=np.uint64)
    for shift, mult in ((16, 0x7FEB352D), (15, 0x846CA68B)):
        x ^= x >> np.uint64(shift)
        x = (x * np.uint64(mult)) & np.uint64(0xFFFFFFFF)
    x ^= x >> np.uint64(16)
    return x / 2.0 ** 32


def _classify(lut, value, ratio):
    """Straight RGB (m, 3) and opacity (m,) of densities for segments of ``ratio`` (m,) steps
    (in the region)."""
    tab, lo, scale, _ = lut
    x = (value - np.float32(lo)) * np.float32(scale)
    np.maximum(x, 0, out=x)
    np.minimum(x, len(tab) - 1, out=x)
    i = np.minimum(x.astype(np.int64), len(tab) - 2)
    f = (x - i)[:, None]
    t0 = tab[i]
    rgba = t0 + f * (tab[i + 1] - t0)
    alpha = rgba[:, 3]
    short = np.flatnonzero(ratio != 1)
    if len(short):
        alpha[short] = 1 - np.power(1 - alpha[short], ratio[short])
    return rgba[:, :3], alpha


@dataclass(frozen=True, slots=True, eq=False)
class _Sampling:
    """A view's samples: their length and how they are classified.

    ``step_mm``: the lattice step in mm; ``tf``: the transfer function (None for X-ray);
    ``lut``: :func:`_lut` (None for X-ray); ``pre``: :func:`_preintegration` (None without
    pre-integration).
    """

    step_mm: float
    tf: object
    lut: tuple
    pre: tuple


@dataclass(frozen=True, slots=True, eq=False)
class _Leaping:
    """Space leaping: ``visible``, per block of ``size``³ voxels (flat, the grid of ``nb``
    blocks padded by one invisible block on each side), whether a ray must sample it."""

    visible: np.ndarray
    nb: np.ndarray
    size: int


@dataclass(frozen=True, slots=True, eq=False)
class _Lattice:
    """The sample lattices of rays, one row per ray: sample ``k`` at ``p0 + k·sv`` (index
    space) stands for the segment ``[k - 0.5, k + 0.5]`` of ``K`` (the first starts at
    ``0.5 - head``, the last ends at ``K - 1.5 + last``); ``first .. stop - 1`` are the
    samples to march; ``dirs``: the world directions (for shading, else None)."""

    p0: np.ndarray
    sv: np.ndarray
    first: np.ndarray
    stop: np.ndarray
    K: np.ndarray
    head: np.ndarray
    last: np.ndarray
    dirs: np.ndarray

    def chunk(self, rows):
        """The lattices of ``rows`` (a slice), positions in float32 as the caster marches."""
        return _Lattice(self.p0[rows].astype(np.float32), self.sv[rows].astype(np.float32),
                        self.first[rows], self.stop[rows], self.K[rows], self.head[rows],
                        self.last[rows], None if self.dirs is None else self.dirs[rows])


def _render(vevm, camera, tf, grid_to_world, *, navigate, mode, depth_in, step_mm, skip_empty,
            termination, shading, xray_scale, xray_offset, block, chunk_rays, jitter,
            preintegrate):
    g, depth_in, compositing = checked_view(vevm, camera, tf, grid_to_world, mode, depth_in,
                                            termination, xray_scale, xray_offset)
    shading = checked_shading(shading)
    jitter = flag("jitter", jitter)
    preintegrate = flag("preintegrate", preintegrate) and mode in ("over", "under")
    if mode not in ("over", "under"):
        shading = None
    spacing = np.asarray(vevm.spacing, dtype=np.float64)
    step_mm = checked_step_mm(step_mm, spacing, RAY_STEPS_PER_VOXEL)
    block = positive_integer("block", block)
    chunk_rays = positive_integer("chunk_rays", chunk_rays)
    h, w = camera.shape
    rgba = np.zeros((h * w, 4), np.float32)
    depth = np.full(h * w, BACKGROUND_DEPTH, np.float32)
    if vevm.evm.is_empty():
        return rgba.reshape(h, w, 4), depth.reshape(h, w)

    r = camera_rays(camera, g, vevm.shape, depth_in)
    mm_per_t = r.mm_per_t(spacing)
    with np.errstate(divide="ignore", invalid="ignore"):
        dt = step_mm / mm_per_t
        nseg = (r.t1 - r.t0) / dt
    rays = np.flatnonzero(nseg > 0)
    if len(rays) == 0:
        return rgba.reshape(h, w, 4), depth.reshape(h, w)
    dt = dt[rays]
    # Jitter moves the lattice back by a fraction of a step: the first segment, from the entry
    # point, is then shorter (`head` steps).
    shift = _jitter(h * w)[rays] if jitter else np.zeros(len(rays))
    t0 = r.t0[rays] - shift * dt
    nseg = nseg[rays] + shift
    K = np.maximum(np.ceil(nseg * (1 - 1e-12)), 1).astype(np.int64)
    last = (nseg - (K - 1)).astype(np.float32)  # length of the last segment, in steps
    head = (1 - shift).astype(np.float32)  # length of the first segment, in steps
    o, d = r.o[rays], r.d[rays]
    p0 = o + (t0 + 0.5 * dt)[:, None] * d  # sample k is at p0 + k sv
    sv = dt[:, None] * d
    first = np.zeros(len(rays), np.int64)
    stop = K.copy()
    leaping = None
    lut = None if mode == "xray" else _lut(tf, step_mm)
    pre = _preintegration(vevm, tf, step_mm) if preintegrate else None
    sampler_key, blocks_key = _cache_keys(spacing, navigate, shading is not None, skip_empty,
                                          block, step_mm, pre is not None)
    if skip_empty:
        blocks = vevm.cache.get(blocks_key, lambda: _Blocks(vevm, block, blocks_key[3]))
        margin = 0.0 if lut is None else lut[3] if pre is None else max(lut[3], pre[3])
        leaping = _Leaping(blocks.visible(mode, tf, margin, compositing.xray_scale,
                                          compositing.xray_offset), blocks.nb, block)
        # Start and stop at the region's bounding box (cells lo .. hi - 1) grown by one voxel,
        # with one sample to spare at each end (the last sample sits before its lattice
        # position).
        bmin, bmax = box_entry_exit(p0, sv, blocks.bbox[0] - 1.5, blocks.bbox[1] + 0.5)
        with np.errstate(invalid="ignore"):
            first = np.maximum(np.ceil(bmin) - 1, 0)
            stop = np.minimum(np.floor(bmax) + 2, K)
        first = np.where(np.isfinite(first), first, K).astype(np.int64)
        stop = np.where(np.isfinite(stop), stop, 0).astype(np.int64)
    if navigate:
        sampler = _NavigationSampler(vevm, shading is not None)
    else:
        sampler = vevm.cache.get(sampler_key,
                                 lambda: _DenseSampler(vevm, shading is not None))
    lighting = Lighting.of_view(shading, g)
    sampling = _Sampling(step_mm, tf, lut, pre)
    lattice = _Lattice(p0, sv, first, stop, K, head, last,
                       None if lighting is None else r.dirs[rays])

    out_acc = np.zeros((len(rays), 4), np.float32)
    out_k = np.full(len(rays), np.nan)  # depth event, in sample units along the lattice
    for c0 in range(0, len(rays), chunk_rays):
        sl = slice(c0, min(len(rays), c0 + chunk_rays))
        acc, kev = _march(sampler, leaping, compositing, sampling, lighting, lattice.chunk(sl))
        out_acc[sl] = acc
        out_k[sl] = kev
    found = np.isfinite(out_k)
    t_ev = t0 + (out_k + 0.5) * dt
    rgba[rays] = out_acc
    dep = r.a0[rays] + r.kz[rays] * t_ev
    depth[rays[found]] = dep[found]
    return rgba.reshape(h, w, 4), depth.reshape(h, w)


_END = 1 - 1e-3
"""Where MIP evaluates a segment's ends, as a fraction of its half-length."""
_LEAPS = 3
"""Blocks a ray may leap over per step (more would cost Python iterations on few rays)."""
_EPS = 2e-3
"""Index-space tolerance of a leap: samples this close to a block's exit are never skipped."""


def _march(sampler, leaping, compositing, sampling, lighting, lattice):
    """March one chunk of rays (``lattice``: :meth:`_Lattice.chunk`; ``leaping`` None: no
    space leaping; ``lighting`` None: no shading); returns (accumulated (m, 4) float32, depth
    event (m,) float64: lattice position ``k'`` of the event, the ray point ``p0 + k'·sv``; NaN
    for none).

    The state of the rays still marching is kept compact (finished rays are frozen, then
    dropped once they are a tenth of the set). Each step first leaps every ray whose current
    sample lies in an invisible block (repeatedly, only those rays), then samples all rays.
    With pre-integration the density at the segment boundary shared with the previous step's
    segment is kept, so a marching ray samples one segment end per step.
    """
    march = _Marching(sampler, leaping, compositing, sampling, lighting, lattice)
    while march.live.any():
        hold = None if leaping is None else march.leap()
        march.sample(hold)
        march.advance(hold)
    return march.result()


class _Marching:
    """The state of a chunk of rays on their lattices (:func:`_march`).

    ``st`` holds, per ray still marching (``live``: not finished yet), one array per quantity:
    its lattice, its current sample ``k``, its accumulators (``acc``, the depth event ``kev``,
    MIP's ``vmax``) and, with pre-integration, the density at the segment boundary it last
    sampled (``edge_b``, ``edge_v``); finished rays are copied to the ``out_*`` arrays.
    """

    def __init__(self, sampler, leaping, compositing, sampling, lighting, lattice):
        self.sampler = sampler
        self.leaping = leaping
        self.compositing = compositing
        self.sampling = sampling
        self.lighting = lighting
        self.backward = compositing.mode == "under"
        self.step = -1 if self.backward else 1
        m = len(lattice.p0)
        self.out_acc = np.zeros((m, 4), np.float32)
        self.out_kev = np.full(m, np.nan)
        self.out_vmax = np.full(m, -np.inf, np.float32)
        first, stop = lattice.first, lattice.stop
        k = (stop - 1) if self.backward else first.copy()
        keep = (k >= first) & (k < stop)
        st = {"idx": np.flatnonzero(keep), "k": k[keep]}
        st.update({name: getattr(lattice, name)[keep]
                   for name in ("p0", "sv", "first", "stop", "K", "head", "last")})
        if lighting is not None:
            st["dirs"] = lattice.dirs[keep]
        n = len(st["idx"])
        st["acc"] = np.zeros((n, 4), np.float32)
        st["kev"] = np.full(n, np.nan)
        st["vmax"] = np.full(n, -np.inf, np.float32)
        if sampling.pre is not None:
            st["edge_b"] = np.full(n, -1, np.int64)  # lattice boundary b is at b - 0.5
            st["edge_v"] = np.zeros(n, np.float32)
        self.live = np.ones(n, bool)
        if leaping is not None:
            nb = leaping.nb
            self.pstrides = np.array([(nb[1] + 2) * (nb[2] + 2), nb[2] + 2, 1], dtype=np.int64)
            st["eps"] = _EPS / np.abs(st["sv"].astype(np.float64)).max(axis=1)
        self.st = st

    def position(self, rows, kk):
        """Lattice ends (float32) of the segments of samples ``kk`` of ``rows`` and the
        index-space points of their middles."""
        st = self.st
        kf = kk.astype(np.float32)
        lo, hi = kf - np.float32(0.5), kf + np.float32(0.5)
        cut = kk == 0
        if cut.any():
            lo[cut] = np.float32(0.5) - st["head"][rows][cut]
        cut = kk == st["K"][rows] - 1
        if cut.any():
            hi[cut] = kf[cut] - np.float32(0.5) + st["last"][rows][cut]
        mid = np.float32(0.5) * (lo + hi)
        return lo, hi, st["p0"][rows] + mid[:, None] * st["sv"][rows]

    def ends(self, rows, lo, hi):
        """Densities at the front and back ends of the segments of ``rows`` (lattice ends
        ``lo``, ``hi``), reusing the boundary the ray's previous segment shared."""
        st, backward = self.st, self.backward
        kk = st["k"][rows]
        near, far = (kk + 1, kk) if backward else (kk, kk + 1)
        p_near, p_far = (hi, lo) if backward else (lo, hi)
        fresh = np.flatnonzero(st["edge_b"][rows] != near)
        which = np.concatenate([fresh, np.arange(len(rows))])
        lattice = np.concatenate([p_near[fresh], p_far])
        value = self.sampler(st["p0"][rows][which] + lattice[:, None] * st["sv"][rows][which])[3]
        v_near = st["edge_v"][rows]
        v_near[fresh] = value[:len(fresh)]
        v_far = value[len(fresh):]
        st["edge_b"][rows] = far
        st["edge_v"][rows] = v_far
        return (v_far, v_near) if backward else (v_near, v_far)

    def finish(self, rows):
        """Copy the results of ``rows`` to the outputs."""
        st = self.st
        ids = st["idx"][rows]
        self.out_acc[ids] = st["acc"][rows]
        self.out_kev[ids] = st["kev"][rows]
        self.out_vmax[ids] = st["vmax"][rows]

    def leap(self):
        """Rays whose current sample is in an invisible block jump past the block (up to
        :data:`_LEAPS` blocks per step); returns the rays still in one, which wait for the
        next step (bool per ray), or None."""
        st, live, size = self.st, self.live, self.leaping.size
        visible, pstrides = self.leaping.visible, self.pstrides
        rows = np.flatnonzero(live)
        for _ in range(_LEAPS):
            _, _, pos = self.position(rows, st["k"][rows])
            _, _, nearest = self.sampler.grid.locate(pos)
            bcell = (nearest + size) // size  # padded block coordinates
            out = ~visible[bcell[:, 0] * pstrides[0] + bcell[:, 1] * pstrides[1] + bcell[:, 2]]
            rows, bcell = rows[out], bcell[out]
            if not len(rows):
                break
            blo = (bcell - 1) * size - 0.5
            kk = _leap(st["p0"][rows].astype(np.float64), st["sv"][rows].astype(np.float64),
                       blo, blo + size, st["eps"][rows], self.backward)
            kold = st["k"][rows]
            knew = np.minimum(kold - 1, kk) if self.backward else np.maximum(kold + 1, kk)
            st["k"][rows] = knew
            gone = (knew < st["first"][rows]) | (knew >= st["stop"][rows])
            live[rows[gone]] = False
            rows = rows[~gone]
        if not len(rows):
            return None
        hold = np.zeros(len(live), bool)
        hold[rows] = True
        return hold

    def sample(self, hold):
        """Sample the current segment of every ray not on ``hold`` and accumulate it."""
        st = self.st
        lo, hi, pos = self.position(slice(None), st["k"])
        base, f, readable, value, grad = self.sampler(pos)
        active = self.live if hold is None else self.live & ~hold
        # The sample's segment: half a step each side (the first and last may be shorter).
        kf = np.float32(0.5) * (lo + hi)
        half = np.float32(0.5) * (hi - lo)
        hsv = st["sv"] * half[:, None]
        if self.compositing.mode == "mip":
            self.maximum(pos, hsv, f, readable, value, kf, half, active)
            return
        frac, start = _coverage(pos - hsv, pos + hsv, base, readable)
        frac *= active
        length = frac * (2 * half)  # in steps: the part of the segment in the region
        front = kf - half + start * (2 * half)  # lattice position where it starts
        if self.compositing.mode == "xray":
            self.attenuate(value, length, front)
        else:
            self.composite(lo, hi, value, grad, frac, length, front)

    def maximum(self, pos, hsv, f, readable, value, kf, half, active):
        """MIP: the segment's two ends (nudged into it) and its middle, in ray order (linear
        stretches of the field peak at their ends, as the reference's MIP knows)."""
        vmax, kev = self.st["vmax"], self.st["kev"]
        for e in (-_END, None, _END):
            if e is None:
                f_, readable_, value_, kpos = f, readable, value, kf
            else:
                _, f_, readable_, value_, _ = self.sampler(pos + np.float32(e) * hsv)
                kpos = kf + np.float32(e) * half
            corner = (f_[:, 0] >= 0.5) * 4 + (f_[:, 1] >= 0.5) * 2 + (f_[:, 2] >= 0.5)
            inside = readable_[np.arange(len(f_)), corner] & active
            better = inside & (value_ > vmax)  # ties keep the frontmost
            vmax[better] = value_[better]
            kev[better] = kpos[better]

    def attenuate(self, value, length, front):
        """X-ray: add the optical depth of segments of ``length`` steps in the region."""
        acc, kev = self.st["acc"], self.st["kev"]
        step_mm = np.float32(self.sampling.step_mm)
        c = self.compositing
        mu = np.float32(c.xray_scale) * np.maximum(value - np.float32(c.xray_offset), 0)
        tau = mu * length * step_mm
        acc[:, 0] += tau
        hit = _depth.attenuates(tau, length * step_mm) & np.isnan(kev)
        kev[hit] = front[hit]

    def composite(self, lo, hi, value, grad, frac, length, front):
        """Over and under: classify segments of ``length`` steps in the region (``frac`` of
        each), light them, and composite them."""
        st, sampling = self.st, self.sampling
        acc, kev = st["acc"], st["kev"]
        rgb, alpha = _classify(sampling.lut, value, length)
        if sampling.pre is not None:
            # Segments wholly in the region are pre-integrated from their ends' densities;
            # those the region's surface cuts keep the point-sampled middle.
            whole = np.flatnonzero(frac == 1)
            if len(whole):
                front_s, back_s = self.ends(whole, lo[whole], hi[whole])
                rgb[whole], alpha[whole] = _classify_preintegrated(
                    sampling.pre, front_s, back_s, length[whole])
        if grad is not None:
            rgb = self.lighting.shade(rgb, grad, st["dirs"]).astype(np.float32)
        c = rgb * alpha[:, None]
        hit = _depth.visible(alpha, length * np.float32(sampling.step_mm
                                                        / sampling.tf.unit_length_mm))
        if self.backward:
            keep = 1 - alpha
            acc[:, :3] *= keep[:, None]
            acc[:, :3] += c
            acc[:, 3] *= keep
            acc[:, 3] += alpha
            kev[hit] = front[hit]  # the last met is the frontmost
        else:
            trans = 1 - acc[:, 3]
            acc[:, :3] += trans[:, None] * c
            acc[:, 3] += trans * alpha
            hit &= np.isnan(kev)
            kev[hit] = front[hit]

    def advance(self, hold):
        """Move every ray not on ``hold`` to its next sample; retire finished rays (and, over,
        terminated ones), compacting the state once they are a tenth of it."""
        st, live = self.st, self.live
        st["k"] += self.step if hold is None else np.where(hold, 0, self.step)
        kk = st["k"]
        ended = live & ((kk < st["first"]) | (kk >= st["stop"]))
        termination = self.compositing.termination
        if self.compositing.mode == "over" and termination < 1:
            ended |= live & (st["acc"][:, 3] >= termination)
        live &= ~ended
        dead = ~live
        if dead.sum() * 10 >= len(live):
            self.finish(np.flatnonzero(dead))
            self.st = {name: arr[live] for name, arr in st.items()}
            self.live = live[live]

    def result(self):
        """The outputs of :func:`_march`, once every ray finished."""
        self.finish(slice(None))
        acc, kev = self.out_acc, self.out_kev
        visible = finish_mode(acc, self.out_vmax, self.compositing.mode, self.sampling.tf)
        if visible is not None:
            kev = np.where(visible, kev, np.nan)
        return acc, kev


def _leap(p0, sv, blo, bhi, eps, backward):
    """Lattice index of the first sample past the block ``[blo, bhi)`` (index space) in the
    marching direction, minus the tolerance ``eps`` (in samples)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (blo - p0) / sv
        tb = (bhi - p0) / sv
    tlo = np.where(sv == 0, -np.inf, np.minimum(ta, tb)).max(axis=1)
    thi = np.where(sv == 0, np.inf, np.maximum(ta, tb)).min(axis=1)
    if backward:
        return np.floor(tlo + eps).astype(np.int64)
    return np.ceil(thi - eps).astype(np.int64)


def render_raycast(vevm, camera, tf, grid_to_world, *, mode="over", depth_in=None, step_mm=None,
                   skip_empty=True, termination=0.99, shading=None, xray_scale=1.0,
                   xray_offset=0.0, block=8, chunk_rays=262144, jitter=False,
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
        volume's box, from the dense grid with the region mask. Same image (module docstring).
    termination : float
        ``"over"``: a ray stops once its opacity reaches this value (1 = never); the error
        this makes is at most ``1 - termination`` per channel.
    shading : None, True, dict or Shading
        Gradient shading (Blinn–Phong headlight, :class:`._shading.Shading`) for over/under.
    xray_scale, xray_offset : float
        X-ray attenuation per mm per data unit and the density of zero attenuation.
    block : int
        Edge (voxels) of the space-leaping blocks.
    chunk_rays : int
        Rays marched together (bounds memory: the default, a 512² image at once, peaks near
        170 MB for the CT head beside the cached tables; fewer Python steps than smaller
        chunks).
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
                   chunk_rays=chunk_rays, jitter=jitter, preintegrate=preintegrate)


def render_raycast_navigate(vevm, camera, tf, grid_to_world, *, mode="over", depth_in=None,
                            step_mm=None, skip_empty=True, termination=0.99, shading=None,
                            xray_scale=1.0, xray_offset=0.0, block=8, chunk_rays=16384,
                            jitter=False, preintegrate=False):
    """Ray cast a VolumeEVM locating every density through the EVM (the report's baseline).

    The same caster as :func:`render_raycast` (same parameters, same image within float
    rounding), but each sample's 8 trilinear neighbours (64 with ``shading``) are found through
    the relation v (:meth:`VolumeEVM.index`) in the densities table; no dense array exists.
    ``skip_empty=False`` marches every lattice sample in the volume's box.
    """
    return _render(vevm, camera, tf, grid_to_world, navigate=True, mode=mode, depth_in=depth_in,
                   step_mm=step_mm, skip_empty=skip_empty, termination=termination,
                   shading=shading, xray_scale=xray_scale, xray_offset=xray_offset, block=block,
                   chunk_rays=chunk_rays, jitter=jitter, preintegrate=preintegrate)
