"""Ray casting's per-ray loops, compiled (:mod:`.._jit`): each ray from its pixel to its end.

:func:`march_rays` casts the rays of a tile of pixels and writes their results into the image;
:mod:`._raycast` checks the input, builds the tables, runs it over the image's tiles on all
threads and describes the optical model. Each ray, one at a time:

1. is made from its pixel (the ray of :meth:`Camera.rays`), taken into index space and clipped
   to the grid's box, the camera's clip range and ``depth_in`` as :func:`._rays.camera_rays`
   clips it (float64);
2. lays its sample lattice from the entry point (the step in mm, jitter) and, with space
   leaping, narrows it to the region's bounding box;
3. marches its samples (float32 positions) front to back (back to front for ``"under"``):
   a sample in an invisible block leaps past it (past the largest aligned cube of invisible
   blocks holding it); the others are reconstructed (trilinear over the region's voxels, the
   coverage of their segment by region cells), classified, shaded and composited, until the
   ray ends or, ``"over"``, its opacity reaches the termination threshold.

The arithmetic is that of the vectorized NumPy caster these loops replaced, operation for
operation and in the same precision (float32 where it was, float64 where NumPy's type
promotion made it so): on every image compared (the CT head, all modes and options, both
cameras, 48² to 512², and the navigation variant) the two were identical, bit for bit. Only
which blocks are looked at changed (cubes of blocks at once), never which samples are taken.
No ray depends on another, so the image does not depend on the tiles nor on the number of
threads.

The kernels take their inputs as four records (named tuples) of arrays and numbers, with fixed
types so that one compiled kernel serves every render (a feature a render does not use gets an
empty array): :data:`View` (camera and grid), :data:`Lattice` (steps and space leaping),
:data:`Volume` (where densities are read: the block-sparse sampling tables, or the EVM's boxes
for the navigation variant) and :data:`._optics.Optics` (mode, classification, shading; the
helpers of :mod:`._optics` read it, as every renderer's kernels do). Small vectors and
matrices are tuples, and the helpers of the per-sample loop take tuples and numbers (and the
arrays they read): a call passing many arrays costs more than its work.
"""

import math
from collections import namedtuple

import numpy as np

from .._jit import kernel
from ..model import _sweep
from ._gradients import voxel_gradient
from ._modes import MODE_CODES, MODES
from ._optics import (
    attenuation_threshold,
    classify,
    classify_preintegrated,
    corrected,
    visible,
    visible_threshold,
)
from ._shading import headlight

__all__ = ["View", "Lattice", "Volume", "RELATION_FIELDS", "TABLE_BLOCK", "BLOCK_VOXELS",
           "march_rays"]

_OVER, _UNDER, _XRAY, _MIP = (MODE_CODES[mode] for mode in MODES)

View = namedtuple("View", "matrix to_camera to_index plane width height ortho clip depth_in box "
                          "spacing")
View.__doc__ = """The camera and the grid, for making each pixel's ray (matrices as tuples of rows).

``matrix`` (4x4): the camera's matrix_world; ``to_camera`` (3x3): the inverse of its 3x3 part
(:meth:`Camera.world_to_camera`); ``to_index`` (4x4): world to voxel-centre index space;
``plane``: the view plane ``(xmin, xmax, ymin, ymax)`` (:attr:`Camera.viewplane`); ``width``,
``height``: pixels; ``ortho``: orthographic; ``clip``: clip start and end; ``depth_in``
(H·W,) float64: where rays stop (empty: nowhere); ``box``: the grid's voxels per axis (as
floats); ``spacing``: mm per voxel."""

Lattice = namedtuple("Lattice", "step_mm jitter leap levels block_strides block bbox_lo "
                                "bbox_hi")
Lattice.__doc__ = """The samples along rays, and space leaping.

``step_mm``: the step; ``jitter``: offset each ray's lattice by its pixel's fraction of a step
(:func:`_jitter`); ``leap``: space leaping on; ``levels`` (flat int8): per block of
``block``³ cells, over the block grid padded by one block each side (strides
``block_strides``), the largest aligned cube of blocks holding it that rays need not sample
(``L + 1`` for a cube of ``2**L`` blocks) or need not look at block by block (``-(L + 1)``)
(:func:`._raycast.leap_levels`);
``bbox_lo``, ``bbox_hi``: the region's bounding box (first voxel, last + 1), where rays start
and stop when leaping."""

Volume = namedtuple("Volume", "n strides index table grad navigate densities relation "
                               "relation_at")
Volume.__doc__ = """Where samples read densities.

``n``: voxels per axis. Block-sparse tables (``navigate`` False): the grid padded by one voxel
each side is cut into blocks of :data:`TABLE_BLOCK`³ voxels; ``index`` (int32, flat, strides
``strides``) gives each block's place in the pool of stored blocks, -1 for a block none of
whose voxels, nor those of its apron (the next voxel along each axis), is in the region. A
stored block holds its :data:`TABLE_BLOCK` + 1 voxels per axis (C order, :data:`BLOCK_VOXELS`
in all), so that the 8 corners of every cell whose first corner lies in the block are in it.
``table``: ``(pool, hole)``, the pool (BLOCK_VOXELS per block) holding each voxel's density
and ``hole`` where the voxel is outside the region — float32 and NaN, or for densities of 8 or
16 bits their own type and its smallest value when no region voxel holds it — read as the
density (as float32) and region weight 1, or 0 and 0; ``grad``
(3·BLOCK_VOXELS per block)
float32, each voxel's gradient (empty without shading). Navigation: ``densities``, the
densities table of order "xyz" as float32, and ``relation`` (int64), the arrays
:data:`RELATION_FIELDS` of :class:`..model._densities.TableIndex` one after another, array
``i`` at ``relation_at[i] .. relation_at[i + 1]``."""

TABLE_BLOCK = 8
"""Edge (voxels) of the blocks of the sampling tables (:data:`Volume`). Measured on the CT head
at 300 HU resampled to 1024³: 8 stores 1.7 times the region's voxels, 16 twice as many."""
_EDGE = TABLE_BLOCK + 1
BLOCK_VOXELS = _EDGE ** 3
"""Voxels stored per block of the sampling tables: the block and its apron."""

RELATION_FIELDS = ("slab_lo", "slab_hi", "slab_base", "slab_area", "sub_keys", "sub_slab",
                   "sub_lo", "sub_hi", "sub_base", "line_length", "run_keys", "run_sub",
                   "run_lo", "run_hi", "run_before")
"""The arrays of :class:`..model._densities.TableIndex` in ``Volume.relation``, in order."""
(_SLAB_LO, _SLAB_HI, _SLAB_BASE, _SLAB_AREA, _SUB_KEYS, _SUB_SLAB, _SUB_LO, _SUB_HI, _SUB_BASE,
 _LINE_LENGTH, _RUN_KEYS, _RUN_SUB, _RUN_LO, _RUN_HI, _RUN_BEFORE) = range(15)

_ZEROS8 = (np.float32(0),) * 8

_EPS = 2e-3
"""Index-space tolerance of a leap: samples this close to a block's exit are never skipped (in
samples: ``_EPS`` over the ray's largest step along an axis)."""
_END = 1 - 1e-3
"""Where MIP evaluates a segment's ends, as a fraction of its half-length."""
_KEEP = 1 - 1e-12
"""A ray takes ``ceil(segments · _KEEP)`` samples: a last segment of rounding dust is dropped."""


# ---------------------------------------------------------------------------- rays
@kernel
def _jitter(pixel):
    """The pixel's fraction of a step in ``[0, 1)``: a hash (Wellons' lowbias32) of its flat
    index, the same on every run and white noise (banding becomes noise without a pattern)."""
    x = np.uint64(pixel)
    x ^= x >> np.uint64(16)
    x = (x * np.uint64(0x7FEB352D)) & np.uint64(0xFFFFFFFF)
    x ^= x >> np.uint64(15)
    x = (x * np.uint64(0x846CA68B)) & np.uint64(0xFFFFFFFF)
    x ^= x >> np.uint64(16)
    return x / 2.0 ** 32


@kernel
def _pixel_ray(ray, view):
    """The ray of pixel ``ray`` (row by row; :meth:`Camera.rays`), clipped as
    :func:`._rays.camera_rays` clips it: its origin and direction in index space, its world
    direction (unit), the axial depth ``a0 + kz·t`` along it and its part ``t0 .. t1`` in the
    grid's box, the clip range and before ``depth_in`` (empty where ``t1 <= t0``)."""
    m, c, g = view.matrix, view.to_camera, view.to_index
    xmin, xmax, ymin, ymax = view.plane
    x = xmin + (ray % view.width + 0.5) * ((xmax - xmin) / view.width)
    y = ymax - (ray // view.width + 0.5) * ((ymax - ymin) / view.height)
    if view.ortho:
        o = (m[0][3] + x * m[0][0] + y * m[0][1], m[1][3] + x * m[1][0] + y * m[1][1],
             m[2][3] + x * m[2][0] + y * m[2][1])
        w = (-m[0][2], -m[1][2], -m[2][2])
    else:
        o = (m[0][3], m[1][3], m[2][3])
        w = (x * m[0][0] + y * m[0][1] - m[0][2], x * m[1][0] + y * m[1][1] - m[1][2],
             x * m[2][0] + y * m[2][1] - m[2][2])
        norm = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
        w = (w[0] / norm, w[1] / norm, w[2] / norm)
    a0 = -((o[0] - m[0][3]) * c[2][0] + (o[1] - m[1][3]) * c[2][1] + (o[2] - m[2][3]) * c[2][2])
    kz = -((o[0] + w[0] - m[0][3]) * c[2][0] + (o[1] + w[1] - m[1][3]) * c[2][1]
           + (o[2] + w[2] - m[2][3]) * c[2][2]) - a0
    far = view.clip[1]
    if len(view.depth_in):
        far = min(far, view.depth_in[ray])
    t_near = (view.clip[0] - a0) / kz
    t_far = (far - a0) / kz
    oi = (o[0] * g[0][0] + o[1] * g[0][1] + o[2] * g[0][2] + g[0][3],
          o[0] * g[1][0] + o[1] * g[1][1] + o[2] * g[1][2] + g[1][3],
          o[0] * g[2][0] + o[1] * g[2][1] + o[2] * g[2][2] + g[2][3])
    di = (w[0] * g[0][0] + w[1] * g[0][1] + w[2] * g[0][2],
          w[0] * g[1][0] + w[1] * g[1][1] + w[2] * g[1][2],
          w[0] * g[2][0] + w[1] * g[2][1] + w[2] * g[2][2])
    box = view.box
    tmin, tmax = _box_span(oi, di, (-0.5, -0.5, -0.5), (box[0] - 0.5, box[1] - 0.5, box[2] - 0.5))
    return oi, di, w, a0, kz, max(tmin, t_near), min(tmax, t_far)


@kernel
def _box_span(o, d, lo, hi):
    """Entry and exit parameters of the line ``o + t·d`` through the box ``[lo, hi]``
    (:func:`._rays.box_entry_exit`: slab clipping; a line parallel to a slab is inside it
    everywhere or nowhere)."""
    t_in, t_out = -np.inf, np.inf
    for a in range(3):
        if d[a] == 0:
            if not lo[a] <= o[a] <= hi[a]:
                t_in, t_out = np.inf, -np.inf
        else:
            ta = (lo[a] - o[a]) / d[a]
            tb = (hi[a] - o[a]) / d[a]
            t_in = max(t_in, min(ta, tb))
            t_out = min(t_out, max(ta, tb))
    return t_in, t_out


@kernel
def _ray_lattice(ray, lattice, o, d, t0, t1, spacing):
    """The sample lattice of ray ``o + t·d`` (index space) over ``t0 .. t1``: sample ``k`` at
    ``p0 + k·sv`` stands for the segment ``[k - 0.5, k + 0.5]`` of ``count`` (the first starts
    ``head`` steps before its end, the last ends ``last`` steps after its start); samples
    ``first .. stop - 1`` are marched. Returns ``(p0, sv)`` as float32, ``count, head, last,
    first, stop``, and the ray parameter ``t0`` of lattice position -0.5 and ``dt`` per step
    (float64); ``count`` 0 for a ray that misses."""
    mx, my, mz = d[0] * spacing[0], d[1] * spacing[1], d[2] * spacing[2]
    dt = lattice.step_mm / math.sqrt(mx * mx + my * my + mz * mz)
    segments = (t1 - t0) / dt
    zero = (np.float32(0), np.float32(0), np.float32(0))
    if not segments > 0:
        return zero, zero, 0, np.float32(1), np.float32(1), 0, 0, t0, dt
    # Jitter moves the lattice back by a fraction of a step: the first segment, from the entry
    # point, is then shorter (``head`` steps).
    shift = _jitter(ray) if lattice.jitter else 0.0
    t0 = t0 - shift * dt
    segments = segments + shift
    count = np.int64(max(math.ceil(segments * _KEEP), 1.0))
    mid = t0 + 0.5 * dt
    p0 = (o[0] + mid * d[0], o[1] + mid * d[1], o[2] + mid * d[2])
    sv = (dt * d[0], dt * d[1], dt * d[2])
    first, stop = 0, count
    if lattice.leap:
        # Start and stop at the region's bounding box grown by one voxel, with one sample to
        # spare at each end (the last sample sits before its lattice position).
        lo, hi = lattice.bbox_lo, lattice.bbox_hi
        k_in, k_out = _box_span(p0, sv, (lo[0] - 1.5, lo[1] - 1.5, lo[2] - 1.5),
                                (hi[0] + 0.5, hi[1] + 0.5, hi[2] + 0.5))
        first = 0 if k_in == -np.inf else (
            np.int64(max(math.ceil(k_in) - 1, 0)) if math.isfinite(k_in) else count)
        stop = count if k_out == np.inf else (
            np.int64(min(math.floor(k_out) + 2, count)) if math.isfinite(k_out) else 0)
    return ((np.float32(p0[0]), np.float32(p0[1]), np.float32(p0[2])),
            (np.float32(sv[0]), np.float32(sv[1]), np.float32(sv[2])), count,
            np.float32(1 - shift), np.float32(segments - (count - 1)), first, stop, t0, dt)


@kernel
def _segment(k, count, head, last):
    """Lattice ends of sample ``k``'s segment ``[k - 0.5, k + 0.5]`` (float32), the first
    starting ``head`` steps before its end, the last (``count - 1``) ending ``last`` steps
    after its start."""
    kf = np.float32(k)
    lo = np.float32(0.5) - head if k == 0 else kf - np.float32(0.5)
    hi = kf - np.float32(0.5) + last if k == count - 1 else kf + np.float32(0.5)
    return lo, hi


@kernel
def _point(p0, sv, s):
    """The index-space point at lattice position ``s`` (float32)."""
    return (p0[0] + s * sv[0], p0[1] + s * sv[1], p0[2] + s * sv[2])


# ---------------------------------------------------------------------------- space leaping
@kernel
def _blocks_of(p, n, size):
    """The space-leaping block (coordinates in the grid of blocks padded by one each side)
    holding the voxel nearest to index-space point ``p``."""
    scale = 1.0 / size
    return (_block_of(p[0], n[0], size, scale), _block_of(p[1], n[1], size, scale),
            _block_of(p[2], n[2], size, scale))


@kernel
def _past_blocks(cell, level, size, p0, sv, k, eps, backward):
    """The first lattice sample (in the marching direction, after ``k``) past the aligned cube
    of ``2**level`` blocks holding block ``cell`` (:func:`_blocks_of`), ``eps`` samples short of
    where the ray leaves it (the slab of each axis the ray leaves last, or enters first
    marching backwards)."""
    t = -np.inf if backward else np.inf
    for a in range(3):
        if sv[a] != 0:
            lo = (((cell[a] >> level) << level) - 1) * size - 0.5
            face = lo if (sv[a] > 0) == backward else lo + (1 << level) * size
            crossing = (face - np.float64(p0[a])) / np.float64(sv[a])
            t = max(t, crossing) if backward else min(t, crossing)
    if backward:
        return min(k - 1, np.int64(math.floor(t + eps)))
    return max(k + 1, np.int64(math.ceil(t - eps)))


@kernel
def _block_of(p, n, size, scale):
    """Along one axis: the space-leaping block (padded by one) of the voxel nearest to
    coordinate ``p``: ``(voxel + size) // size``, as ``(voxel + size + 0.5) · scale`` with
    ``scale = 1 / size`` (exact: the quotient is at least ``0.5 / size`` from the next
    integer; no integer division)."""
    f, base = _cell(p, n)
    return np.int64((base + (1 if f >= 0.5 else 0) + size + 0.5) * scale)


# ---------------------------------------------------------------------------- sampling
@kernel
def _cell(p, n):
    """Along one axis: the fraction of coordinate ``p`` past its trilinear base voxel (in
    ``[0, 1]``) and the base voxel (in ``-1 .. n - 1``)."""
    fl = np.floor(p)
    f = p - fl
    return min(max(f, np.float32(0)), np.float32(1)), min(max(np.int64(fl), -1), n - 1)


@kernel
def _lerp8(v, f):
    """Trilinear blend of 8 corner values ``v`` (corner ``4a + 2b + c``) with fractions ``f``."""
    fx, fy, fz = f
    c00 = v[0] + fz * (v[1] - v[0])
    c01 = v[2] + fz * (v[3] - v[2])
    c10 = v[4] + fz * (v[5] - v[4])
    c11 = v[6] + fz * (v[7] - v[6])
    c0 = c00 + fy * (c01 - c00)
    c1 = c10 + fy * (c11 - c10)
    return c0 + fx * (c1 - c0)


@kernel
def _table_row(index, strides, base):
    """Where the first corner of cell ``base`` (a voxel in ``-1 .. n - 1`` per axis) sits in
    the block-sparse tables (:data:`Volume`), as a voxel of the pool: in the block holding it
    in the padded grid, whose apron holds the other corners; -1 where that block is empty (its
    voxels are all outside the region: zeros)."""
    px, py, pz = base[0] + 1, base[1] + 1, base[2] + 1
    bx, by, bz = px // TABLE_BLOCK, py // TABLE_BLOCK, pz // TABLE_BLOCK
    slot = index[bx * strides[0] + by * strides[1] + bz]
    if slot < 0:
        return np.int64(-1)
    return (np.int64(slot) * BLOCK_VOXELS + ((px - bx * TABLE_BLOCK) * _EDGE
                                             + (py - by * TABLE_BLOCK)) * _EDGE
            + (pz - bz * TABLE_BLOCK))


@kernel
def _table_corners(table, row):
    """The densities and region weights (8 each) of the corners of the cell whose first corner
    is voxel ``row`` of the pool (``table`` = ``(pool, hole)``, :data:`Volume`;
    :func:`_table_row`; -1: all zeros): a voxel outside the region reads density 0 and weight
    0, one inside its density and weight 1."""
    if row < 0:
        return _ZEROS8, _ZEROS8
    pool, hole = table
    i, j, k, m = _corner_rows(row, 1)
    one = np.uint64(1)
    a, b = _voxel(pool[i], hole), _voxel(pool[i + one], hole)
    c, d = _voxel(pool[j], hole), _voxel(pool[j + one], hole)
    e, f = _voxel(pool[k], hole), _voxel(pool[k + one], hole)
    g, h = _voxel(pool[m], hole), _voxel(pool[m + one], hole)
    return ((a[0], b[0], c[0], d[0], e[0], f[0], g[0], h[0]),
            (a[1], b[1], c[1], d[1], e[1], f[1], g[1], h[1]))


@kernel
def _voxel(value, hole):
    """A voxel of the sampling table as (density as float32, region weight): NaN or ``hole``
    (outside the region) is (0, 0); an integer density converts to float32 exactly."""
    if value != value or value == hole:
        return np.float32(0), np.float32(0)
    return np.float32(value), np.float32(1)


@kernel
def _corner_rows(row, width):
    """Where the corners ``(a, b, 0)`` of the cell whose first corner is voxel ``row`` of the
    pool start in a table of ``width`` values per voxel, for ``(a, b)`` = (0, 0), (0, 1),
    (1, 0), (1, 1); corner ``(a, b, 1)`` follows ``width`` values later. Unsigned: no
    wraparound."""
    sx, sy = np.uint64(width * _EDGE * _EDGE), np.uint64(width * _EDGE)
    i = np.uint64(width * row)
    return i, i + sy, i + sx, i + sx + sy


@kernel
def _table_gradients(grad, row, axis):
    """One axis of the gradients at the 8 corners of the cell whose first corner is voxel
    ``row`` of the gradient pool (-1: zeros)."""
    if row < 0:
        return _ZEROS8
    i, j, k, m = _corner_rows(row, 3)
    a, three = np.uint64(axis), np.uint64(axis + 3)
    return (grad[i + a], grad[i + three], grad[j + a], grad[j + three], grad[k + a],
            grad[k + three], grad[m + a], grad[m + three])


@kernel
def _last_at_most(relation, start, stop, key):
    """The last index in ``start .. stop - 1`` whose (sorted) value in ``relation`` is at most
    ``key`` (``np.searchsorted(..., side="right") - 1``), ``start - 1`` for none."""
    lo, hi = start, stop
    while lo < hi:
        mid = (lo + hi) >> 1
        if relation[mid] <= key:
            lo = mid + 1
        else:
            hi = mid
    return lo - 1


@kernel
def _table_index(relation, at, a, b, c):
    """The relation v (:class:`..model._densities.TableIndex`, order "xyz"): where voxel
    ``(a, b, c)`` sits in the densities table, -1 outside the region; three binary searches
    over the EVM's slabs, sub-slabs and runs (``Volume.relation``)."""
    i = _last_at_most(relation, at[_SLAB_LO], at[_SLAB_LO + 1], a) - at[_SLAB_LO]
    if i < 0 or a >= relation[at[_SLAB_HI] + i]:
        return -1
    j = _last_at_most(relation, at[_SUB_KEYS], at[_SUB_KEYS + 1],
                      (i << _sweep.BITS) | (b + _sweep.OFFSET)) - at[_SUB_KEYS]
    if (j < 0 or relation[at[_SUB_SLAB] + j] != i or b < relation[at[_SUB_LO] + j]
            or b >= relation[at[_SUB_HI] + j]):
        return -1
    k = _last_at_most(relation, at[_RUN_KEYS], at[_RUN_KEYS + 1],
                      (j << _sweep.BITS) | (c + _sweep.OFFSET)) - at[_RUN_KEYS]
    if (k < 0 or relation[at[_RUN_SUB] + k] != j or c < relation[at[_RUN_LO] + k]
            or c >= relation[at[_RUN_HI] + k]):
        return -1
    return (relation[at[_SLAB_BASE] + i] + (a - relation[at[_SLAB_LO] + i])
            * relation[at[_SLAB_AREA] + i] + relation[at[_SUB_BASE] + j]
            + (b - relation[at[_SUB_LO] + j]) * relation[at[_LINE_LENGTH] + j]
            + relation[at[_RUN_BEFORE] + k] + (c - relation[at[_RUN_LO] + k]))


@kernel
def _navigated_corners(densities, relation, at, base, shaded, hood, hood_in):
    """The densities and region weights of the corners of ``base`` found through the EVM
    (relation v), and with ``shaded`` their gradients per axis (else zeros): the voxels around
    the cell go in the scratch ``hood`` and ``hood_in`` (4x4x4, from ``base - 1``; only the
    inner 2x2x2 without shading)."""
    for h in range(64):
        a, b, c = h >> 4, (h >> 2) & 3, h & 3
        if shaded or (0 < a < 3 and 0 < b < 3 and 0 < c < 3):
            idx = _table_index(relation, at, base[0] - 1 + a, base[1] - 1 + b, base[2] - 1 + c)
            hood[h] = densities[idx] if idx >= 0 else np.float32(0)
            hood_in[h] = idx >= 0
    gradients = (_ZEROS8, _ZEROS8, _ZEROS8)
    if shaded:
        gradients = (_hood_gradients(hood, hood_in, 16, 4, 1),
                     _hood_gradients(hood, hood_in, 4, 16, 1),
                     _hood_gradients(hood, hood_in, 1, 16, 4))
    return _inner(hood), _inner(hood_in), gradients


@kernel
def _inner(hood):
    """The values at the 8 inner voxels (the cell's corners) of the flat 4x4x4 ``hood``, as
    float32 (region flags as weights 0 and 1)."""
    return (np.float32(hood[21]), np.float32(hood[22]), np.float32(hood[25]),
            np.float32(hood[26]), np.float32(hood[37]), np.float32(hood[38]),
            np.float32(hood[41]), np.float32(hood[42]))


@kernel
def _hood_gradients(hood, hood_in, step, first, second):
    """One axis (``step`` in the flat 4x4x4 ``hood``; ``first`` and ``second``: the steps of
    the other two axes, the lower axis first) of the gradients at its 8 inner voxels."""
    return (voxel_gradient(hood, hood_in, 21, step, first, second),
            voxel_gradient(hood, hood_in, 22, step, first, second),
            voxel_gradient(hood, hood_in, 25, step, first, second),
            voxel_gradient(hood, hood_in, 26, step, first, second),
            voxel_gradient(hood, hood_in, 37, step, first, second),
            voxel_gradient(hood, hood_in, 38, step, first, second),
            voxel_gradient(hood, hood_in, 41, step, first, second),
            voxel_gradient(hood, hood_in, 42, step, first, second))


@kernel
def _region_mask(weights):
    """The bit mask of a cell's corners in the region (corner ``4a + 2b + c``, weight > 0)."""
    mask = 0
    for i in range(8):
        if weights[i] > 0:
            mask |= 1 << i
    return mask


@kernel
def _renormalised(values, weights, f):
    """Trilinear reconstruction over the region's voxels in a cell not wholly in the region
    (fractions ``f``): the weights of corners outside dropped and the rest renormalised, 0
    where none is in. Returns the density and the interpolated weight (1 where none is in).
    (A cell wholly in the region is a plain trilinear blend: its weight is exactly 1.)"""
    weight = _lerp8(weights, f)
    if not weight > 0:
        weight = np.float32(1)
    return _lerp8(values, f) / weight, weight


@kernel
def _gradient(gradients, f, weight):
    """The gradient interpolated as the density is (:func:`_renormalised`)."""
    return (_lerp8(gradients[0], f) / weight, _lerp8(gradients[1], f) / weight,
            _lerp8(gradients[2], f) / weight)


@kernel
def _density(p, n, strides, index, table, navigate, densities, relation, at, hood, hood_in):
    """The reconstructed density at point ``p`` and its fractions and region mask
    (:func:`_renormalised`; the sampling tables or, ``navigate``, the EVM), for the samples beyond a
    segment's middle (MIP's ends, pre-integration's ends)."""
    f, base = _cells(p, n)
    if navigate:
        values, weights, _ = _navigated_corners(densities, relation, at, base, False, hood,
                                                hood_in)
    else:
        values, weights = _table_corners(table, _table_row(index, strides, base))
    mask = _region_mask(weights)
    value = _lerp8(values, f) if mask == 255 else _renormalised(values, weights, f)[0]
    return value, f, mask


@kernel
def _nearest(f):
    """Fractions ``f`` rounded to the nearest corner (0 or 1): trilinear blending then gives
    exactly the nearest voxel's value."""
    one, zero = np.float32(1), np.float32(0)
    return (one if f[0] >= 0.5 else zero, one if f[1] >= 0.5 else zero,
            one if f[2] >= 0.5 else zero)


@kernel
def _corner(f):
    """The corner ``4a + 2b + c`` that rounded fractions ``f`` (:func:`_nearest`) select."""
    return 4 * np.int64(f[0]) + 2 * np.int64(f[1]) + np.int64(f[2])


@kernel
def _cells(p, n):
    """:func:`_cell` along the three axes: the fractions and the base voxel of point ``p``."""
    fx, bx = _cell(p[0], n[0])
    fy, by = _cell(p[1], n[1])
    fz, bz = _cell(p[2], n[2])
    return (fx, fy, fz), (bx, by, bz)


@kernel
def _coverage(pf, pb, base, mask):
    """Fraction of the segment ``pf -> pb`` (index space) lying in region cells, and where (as
    a fraction) its first such piece starts (NaN for none).

    The segment is cut where it crosses a cell boundary (index ``m + 0.5``; at most one per
    axis when the step is at most a voxel); each piece's cell is one of the 8 trilinear corners
    of the segment's midpoint (``base``), in the region when its bit of ``mask`` is set. (With
    all 8 set the whole segment counts, from its start: the caller knows that without a call.)
    """
    if mask == 0:
        return np.float32(0), np.float32(np.nan)
    half = np.float32(0.5)
    t0, t1, t2 = _crossing(pf[0], pb[0]), _crossing(pf[1], pb[1]), _crossing(pf[2], pb[2])
    if t0 > t1:
        t0, t1 = t1, t0
    if t1 > t2:
        t1, t2 = t2, t1
    if t0 > t1:
        t0, t1 = t1, t0
    edges = (np.float32(0), t0, t1, t2, np.float32(1))
    part = np.float32(0)
    start = np.float32(np.nan)
    for e in range(4):
        e0, e1 = edges[e], edges[e + 1]
        length = e1 - e0
        if not length > 0:
            continue
        middle = half * (e0 + e1)
        corner = 0
        for a in range(3):
            q = pf[a] + middle * (pb[a] - pf[a])
            corner = 2 * corner + min(max(np.int64(np.floor(q + half)) - base[a], 0), 1)
        if (mask >> corner) & 1:
            part += length
            if math.isnan(start):
                start = e0
    return part, start


@kernel
def _crossing(pf, pb):
    """Where (as a fraction) the segment ``pf -> pb`` along one axis crosses a cell boundary
    (index ``m + 0.5``); 1 where it crosses none."""
    half = np.float32(0.5)
    cf = np.floor(pf + half)
    cb = np.floor(pb + half)
    if cf == cb:
        return np.float32(1)
    return min(max((max(cf, cb) - half - pf) / (pb - pf), np.float32(0)), np.float32(1))


# ---------------------------------------------------------------------------- visibility
@kernel
def _threshold(length, units, full):
    """The visibility threshold of a sample over ``length`` steps of ``units`` unit lengths:
    ``full``, the threshold of a whole step (the common case), or
    :func:`._optics.visible_threshold`."""
    if length == 1:
        return full
    return visible_threshold(length * units)


# ---------------------------------------------------------------------------- marching
@kernel
def march_rays(rows, columns, view, lattice, volume, optics, rgba, depth, vmax):
    """Cast the rays of the pixels in ``rows`` and ``columns`` (``(first, stop)`` each: a tile,
    whose neighbouring rays read the same voxels while they are in the cache) into ``rgba``
    (H·W, 4) float32 (X-ray: the optical depth in channel 0), ``depth`` (H·W,) float32 (axial
    depth of the depth event; left as it is where there is none) and, for MIP, ``vmax`` (H·W,)
    float32 (the maximum density). Returns the points sampled (densities reconstructed)."""
    table, grad, densities, relation = volume.table, volume.grad, volume.densities, volume.relation
    index = volume.index
    n, strides, at, navigate = volume.n, volume.strides, volume.relation_at, volume.navigate
    leap, levels, block_strides, block = (lattice.leap, lattice.levels, lattice.block_strides,
                                          lattice.block)
    lut, pre = optics.lut, optics.pre
    mode, shaded, preintegrated = optics.mode, optics.shaded, len(optics.pre) > 0
    phong, units, full = optics.phong, optics.units, optics.visible
    m = view.to_index  # its 3x3 part transposed takes index-space gradients to world normals
    normal = (m[0][0], m[1][0], m[2][0], m[0][1], m[1][1], m[2][1], m[0][2], m[1][2], m[2][2])
    backward = mode == _UNDER
    step32 = np.float32(lattice.step_mm)
    hood = np.zeros(64, np.float32)  # navigation with shading: the 4x4x4 voxels around a cell
    hood_in = np.zeros(64, np.bool_)
    row = np.int64(-1)  # the sample's cell in the sampling tables (:func:`_table_row`)
    samples = 0
    for pixel in range((rows[1] - rows[0]) * (columns[1] - columns[0])):
        ray = ((rows[0] + pixel // (columns[1] - columns[0])) * view.width + columns[0]
               + pixel % (columns[1] - columns[0]))
        o, d, view_dir, a0, kz, t0, t1 = _pixel_ray(ray, view)
        p0, sv, count, head, last, first, end, t0, dt = _ray_lattice(ray, lattice, o, d, t0, t1,
                                                                      view.spacing)
        if first >= end:
            continue  # it samples nothing: its pixel keeps the background
        eps = _EPS / max(abs(np.float64(sv[0])), abs(np.float64(sv[1])), abs(np.float64(sv[2])))
        red = green = blue = opacity = np.float32(0)  # X-ray: the optical depth in red
        event = np.nan  # lattice position of the depth event
        peak = np.float32(-np.inf)
        edge_b, edge_v = -1, np.float32(0)  # the segment boundary sampled last (at edge_b - 0.5)
        k = end - 1 if backward else first
        checked = k  # the next sample whose block must be looked at
        while first <= k < end:
            lo, hi = _segment(k, count, head, last)
            kf = np.float32(0.5) * (lo + hi)
            half = np.float32(0.5) * (hi - lo)
            p = _point(p0, sv, kf)
            if leap and (k >= checked if not backward else k <= checked):
                # A sample in an invisible block leaps to the first one past the largest
                # aligned cube of invisible blocks holding it; in a visible block, the samples
                # up to the exit of the largest cube of visible blocks need no look.
                cell = _blocks_of(p, n, block)
                cube = levels[cell[0] * block_strides[0] + cell[1] * block_strides[1] + cell[2]]
                past = _past_blocks(cell, abs(cube) - 1, block, p0, sv, k, eps, backward)
                if cube > 0:
                    k = past
                    continue
                checked = past
            f, base = _cells(p, n)
            if optics.nearest:
                f = _nearest(f)
            if navigate:
                values, weights, gradients = _navigated_corners(densities, relation, at, base,
                                                                shaded, hood, hood_in)
            else:
                row = _table_row(index, strides, base)
                values, weights = _table_corners(table, row)
                gradients = (_ZEROS8, _ZEROS8, _ZEROS8)  # read below, if the sample is seen
            mask = _region_mask(weights)
            if optics.nearest and not (mask >> _corner(f)) & 1:
                k += -1 if backward else 1  # its nearest voxel is outside: transparent
                continue
            value, weight = _lerp8(values, f), np.float32(1)
            if mask != 255:
                value, weight = _renormalised(values, weights, f)
            samples += 1
            hsv = (sv[0] * half, sv[1] * half, sv[2] * half)
            if mode == _MIP:
                # The segment's two ends (nudged into it) and its middle, in ray order: linear
                # stretches of the field peak at their ends. Ties keep the frontmost.
                for e in (np.float32(-_END), np.float32(0), np.float32(_END)):
                    value_e, f_e, mask_e = value, f, mask
                    if e != 0:
                        q = (p[0] + e * hsv[0], p[1] + e * hsv[1], p[2] + e * hsv[2])
                        value_e, f_e, mask_e = _density(q, n, strides, index, table, navigate,
                                                        densities, relation, at, hood, hood_in)
                        samples += 1
                    corner = ((4 if f_e[0] >= 0.5 else 0) + (2 if f_e[1] >= 0.5 else 0)
                              + (1 if f_e[2] >= 0.5 else 0))
                    if (mask_e >> corner) & 1 and value_e > peak:
                        peak = value_e
                        event = kf + e * half
                k += 1
                continue
            frac, start_f = np.float32(1), np.float32(0)
            if mask != 255:
                frac, start_f = _coverage((p[0] - hsv[0], p[1] - hsv[1], p[2] - hsv[2]),
                                          (p[0] + hsv[0], p[1] + hsv[1], p[2] + hsv[2]), base,
                                          mask)
                if not frac > 0:  # no part of the segment in region cells: it adds exactly 0
                    k += -1 if backward else 1
                    continue
            length = frac * (np.float32(2) * half)  # steps of the segment in the region
            front = kf - half + start_f * (np.float32(2) * half)  # where that part starts
            if mode == _XRAY:
                tau = optics.xray_scale * max(value - optics.xray_offset, np.float32(0)) \
                    * length * step32
                red += tau
                if math.isnan(event) and visible(tau, attenuation_threshold(length * step32)):
                    event = front
                k += 1
                continue
            r, g, b, alpha = classify(lut, optics.lut_lo, optics.lut_scale, value)
            if preintegrated and frac == 1:
                # Segments wholly in the region are pre-integrated from their ends' densities
                # (the boundary shared with the segment before is not sampled again); those
                # the region's surface cuts keep the point-sampled middle.
                near, far = (k + 1, k) if backward else (k, k + 1)
                s_near, s_far = (hi, lo) if backward else (lo, hi)
                if edge_b != near:
                    edge_v = _density(_point(p0, sv, s_near), n, strides, index, table,
                                      navigate, densities, relation, at, hood, hood_in)[0]
                    samples += 1
                v_near = edge_v
                v_far = _density(_point(p0, sv, s_far), n, strides, index, table, navigate,
                                 densities, relation, at, hood, hood_in)[0]
                samples += 1
                edge_b, edge_v = far, v_far
                v_front, v_back = (v_far, v_near) if backward else (v_near, v_far)
                r, g, b, alpha = classify_preintegrated(pre, optics.pre_lo, optics.pre_scale,
                                                        optics.pre_n, v_front, v_back)
            # A segment shorter than a step: its opacity corrected for its length (a
            # pre-integrated one's as if its density were constant; its colour keeps its ratio
            # to the opacity).
            alpha = corrected(alpha, length)
            if not alpha > 0:  # transparent: it adds exactly 0 (and is not visible)
                k += -1 if backward else 1
                continue
            if shaded:
                if not navigate:
                    gradients = (_table_gradients(grad, row, 0), _table_gradients(grad, row, 1),
                                 _table_gradients(grad, row, 2))
                r, g, b = headlight((r, g, b), _gradient(gradients, f, weight), normal,
                                    view_dir, phong)
            if backward:
                keep = 1.0 - alpha
                red = np.float32(np.float32(red * keep) + r * alpha)
                green = np.float32(np.float32(green * keep) + g * alpha)
                blue = np.float32(np.float32(blue * keep) + b * alpha)
                opacity = np.float32(np.float32(opacity * keep) + alpha)
                if visible(alpha, _threshold(length, units, full)):
                    event = front  # the last met is the frontmost
                k -= 1
            else:
                trans = np.float64(np.float32(1) - opacity)
                red = np.float32(red + trans * (r * alpha))
                green = np.float32(green + trans * (g * alpha))
                blue = np.float32(blue + trans * (b * alpha))
                opacity = np.float32(opacity + trans * alpha)
                if math.isnan(event) and visible(alpha, _threshold(length, units, full)):
                    event = front
                k += 1
                if opacity >= optics.termination:
                    break
        rgba[ray, 0] = red
        rgba[ray, 1] = green
        rgba[ray, 2] = blue
        rgba[ray, 3] = opacity
        if mode == _MIP:
            vmax[ray] = peak
        if not math.isnan(event):
            depth[ray] = np.float32(a0 + kz * (t0 + (event + 0.5) * dt))
    return samples
