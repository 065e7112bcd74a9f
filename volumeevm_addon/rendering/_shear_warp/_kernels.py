"""Shear-warp's loops, compiled (:mod:`.._jit`): the EVM's runs per scanline, the runs worth
compositing for a transfer function, the slices composited into bands of intermediate
scanlines, and the warp to the final image.

:mod:`._shear_warp` factors the view, builds the tables and describes the optical model; here
is the report's loop (Lacroute & Levoy, Figure 4): per band of intermediate scanlines, per
sample slice front to back, per intermediate scanline, per run of the two (four, between two
slices) voxel scanlines its bilinear taps read:

- **transparent voxels are skipped with the runs**: the region's runs are the 1-D sections of
  the EVM's sections, in the densities table's order (:func:`box_runs`); a transfer function
  keeps the runs of the voxels worth compositing (:func:`flagged_runs`), and only intermediate
  pixels whose taps touch one of them are sampled;
- **opaque intermediate pixels are skipped with pointers** to the next pixel that is not
  opaque (VolPack's trick): a pixel whose opacity reaches the termination threshold points
  past itself, and a search follows and shortens the chain;
- the pixels left form stretches; the voxel columns a stretch reads are decoded from the
  region's runs (each voxel's channels and region weight, zeros outside the region: the
  boundary policy needs both) into a buffer of 8 lanes per column, so that the stretch's
  bilinear samples are one loop the compiler vectorizes (a translated slice: the same four
  weights at every pixel, VolPack), or, on a scaled slice, one such loop blending the two
  rows and then two taps per pixel along the row (the columns' taps are computed once per
  slice); then the samples are composited pixel by pixel.

The arithmetic is the vectorized compositing's it replaced, in float32 where that was (the
largest difference in the images was of the order of 1e-7). A band writes only its own
intermediate scanlines and reads nothing another band writes, so the image does not depend on
how the bands are spread over threads. (The loops are written out in :func:`composite`: a
compiled helper that takes arrays costs their reference counting on every call, more than the
work of a pixel; the helpers take numbers.)

The kernels take their inputs as records of arrays and numbers with fixed types, so that one
compiled kernel serves every render (what a render does not use is an empty array):
:data:`Runs`, :data:`Plan`, :data:`Voxels`, :data:`Light`, :data:`Optics` and :data:`Frame`.
"""

import math
from collections import namedtuple

import numpy as np

from ..._jit import kernel
from .._modes import MODE_CODES, MODES
from .._shading import fade

__all__ = ["Runs", "Plan", "Voxels", "Light", "Optics", "Frame", "NEVER",
           "box_runs", "mask_runs", "flagged_runs", "mixed_codes", "lit_colours", "tap", "span",
           "composite", "ray_points", "warp"]

_OVER, _UNDER, _XRAY, _MIP = (MODE_CODES[mode] for mode in MODES)
NEVER = np.iinfo(np.int32).max
"""Rank of an intermediate pixel without a depth sample."""
_TIE = np.float32(1e-6)
"""Relative margin a MIP sample must exceed the maximum by to replace it (float32 ties)."""
_TINY = np.float32(1e-30)
"""Smallest region weight a sample is divided by."""
_ONE = np.float32(1.0)
_ZERO = np.float32(0.0)
_HALF = np.float32(0.5)
_EIGHT = np.uint64(8)

Runs = namedtuple("Runs", "lines columns starts lo hi pos box")
Runs.__doc__ = """Runs of voxels along the scanlines of the slices of one principal axis.

Scanline ``a`` of slice ``s`` (``lines`` scanlines of ``columns`` voxels per slice) is line
``s·lines + a``; its runs are ``starts[line] .. starts[line + 1] - 1``, sorted; run ``r``
covers the columns ``lo[r] .. hi[r] - 1``. ``pos`` (region runs): the position in the
densities table of each run's first voxel (a voxel's *code* is its position + 1; 0 is outside
the region); empty for the runs a transfer function keeps. ``box`` (slices, 4): per slice the
rows ``[a0, a1)`` and columns ``[b0, b1)`` its runs span (``a1 <= a0`` when it has none)."""

Plan = namedtuple("Plan", "slice other keep blend alpha beta_a beta_b k0 kp kq rank test")
Plan.__doc__ = """The samples of a view, in compositing order (front to back; back to front for
``"under"``).

Sample ``n`` lies at ``c = slice[n] + offset`` between voxel slices ``slice[n]`` (its nearest)
and ``other[n]`` (-1: on the slice plane), blended with weights ``keep[n]`` on the nearest and
``blend[n]`` on the other (float32); it meets intermediate point ``(P, Q)`` (absolute
coordinates) at slice coordinates ``(alpha P + beta_a, alpha Q + beta_b)`` (float64), where
its axial depth is ``k0 + kp P + kq Q``; ``rank[n]``: its front-to-back index (the depth
samples); ``test[n]``: whether the clip range or ``depth_in`` may cut it (then each pixel is
tested)."""

Voxels = namedtuple("Voxels", "index values channels")
Voxels.__doc__ = """What a tap reads from a voxel of code ``c`` (weight 1; code 0: all 0).

``values[index[c]]`` (``index`` empty: ``values[c]``), float32 rows of which the first
``channels`` are read: pre-classification's premultiplied RGBA (the classification table
indexed by each voxel's row, or the view's lit colours of the visible voxels), or
post-classification's density (and index-space gradient)."""

Light = namedtuple("Light", "normal towards ambient diffuse specular shininess fade_lo fade_hi")
Light.__doc__ = """A view's headlight, numbers only (float32): ``normal`` (9,), the matrix taking
an index-space gradient to a world normal, row by row (``n = g @ normal``); ``towards`` (3,),
the unit world direction of the light; the Blinn–Phong weights (:class:`._shading.Shading`);
the fade's gradient magnitudes (float64, :attr:`._shading.Lighting.fade`)."""

Optics = namedtuple("Optics", "mode post nearest shaded termination visible lut straight lut_lo "
                              "lut_scale lut_rows light xray_offset xray_factor xray_visible")
Optics.__doc__ = """How samples become colour.

``mode``: :data:`._modes.MODE_CODES`; ``post``: classify interpolated densities through ``lut``
((rows + 1, 4) float32, premultiplied for the view's step, row 0 transparent), the row
``clip(rint((d - lut_lo)·lut_scale), 0, lut_rows - 1) + 1``; ``shaded`` (post): light each
sample with ``light`` (:data:`Light`) on the straight colours ``straight`` (rows + 1, 3);
``termination`` (float32): "over" stops a pixel at this opacity (1: never); ``visible``
(float32): the opacity from which a sample is visible (:mod:`._depth`); ``xray_offset``,
``xray_factor`` (float32): X-ray's ``μ·Δ = max(d - offset, 0)·factor`` and ``xray_visible``
its visibility threshold; ``nearest``: samples take the nearest voxel of the slice (all the
bilinear weight on it: categorical transfer functions, one sample per slice)."""

Frame = namedtuple("Frame", "origin_p origin_q ratio near far limit image rank next")
Frame.__doc__ = """The intermediate image a view composites into.

``origin_p``, ``origin_q``: the absolute point of array index ``(0, 0)``; ``ratio`` (hi, wi)
float32: perspective, each pixel's step over the table's (empty: orthographic); ``near``,
``far`` (float32): the clip range; ``limit`` (hi, wi) float32: ``min(clip_end, depth_in)``
per pixel (empty: none); ``image`` (hi, wi, 4) float32: premultiplied RGBA ("xray" and "mip"
accumulate in channel 0); ``rank`` (hi, wi) int32: the depth sample's rank (:data:`NEVER`:
none); ``next`` (hi, wi + 1) int32: per pixel itself, or, once opaque, a later pixel with no
pixel between that is not opaque (column ``wi``: the end)."""


# ---------------------------------------------------------------------------- runs
@kernel
def box_runs(lo, hi, slices, lines):
    """The region's runs per scanline from the EVM's ordered boxes, in the table's order.

    ``lo``, ``hi`` (m, 3): the boxes of :meth:`EVM.boxes` in the table order, columns
    permuted to (slice, scanline, column): slabs of boxes sharing a slice range, split in
    sub-slabs sharing a scanline range, split in runs. The table lists each slice's voxels
    scanline by scanline, each scanline run by run, so a running count gives every run's
    position. Returns ``(starts, run_lo, run_hi, pos, box)`` of :data:`Runs`.
    """
    m = lo.shape[0]
    starts = np.zeros(slices * lines + 1, np.int64)
    for k in range(m):
        for s in range(lo[k, 0], hi[k, 0]):
            for a in range(lo[k, 1], hi[k, 1]):
                starts[s * lines + a + 1] += 1
    for line in range(slices * lines):
        starts[line + 1] += starts[line]
    total = starts[slices * lines]
    run_lo = np.empty(total, np.int32)
    run_hi = np.empty(total, np.int32)
    pos = np.empty(total, np.int64)
    fill = starts[:-1].copy()
    at = 0
    k = 0
    while k < m:
        slab = k
        while slab < m and lo[slab, 0] == lo[k, 0] and hi[slab, 0] == hi[k, 0]:
            slab += 1
        for s in range(lo[k, 0], hi[k, 0]):
            u = k
            while u < slab:
                v = u
                while v < slab and lo[v, 1] == lo[u, 1] and hi[v, 1] == hi[u, 1]:
                    v += 1
                for a in range(lo[u, 1], hi[u, 1]):
                    w = fill[s * lines + a]
                    for r in range(u, v):
                        run_lo[w] = lo[r, 2]
                        run_hi[w] = hi[r, 2]
                        pos[w] = at
                        at += hi[r, 2] - lo[r, 2]
                        w += 1
                    fill[s * lines + a] = w
                u = v
        k = slab
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
    transparent rows its row is in. A sample's density lies between its taps' densities, so
    its row between theirs: when all its taps are in one run of transparent rows, it is
    transparent. A voxel is flagged when it is visible or a region voxel next to it (the 26
    around it: every tap of a sample is next to the others) is in another run or visible;
    a sample without a flagged tap is transparent.
    """
    lines = region.lines
    run_starts, run_lo, run_hi, run_pos = region.starts, region.lo, region.hi, region.pos
    grid = np.full((slices, lines, columns), -2, np.int32)  # -2: outside the region
    for s in range(slices):
        for a in range(lines):
            for r in range(run_starts[s * lines + a], run_starts[s * lines + a + 1]):
                code = run_pos[r] + 1 - run_lo[r]
                for b in range(run_lo[r], run_hi[r]):
                    grid[s, a, b] = ids[code + b]
    out = np.zeros(ids.size, np.bool_)
    for s in range(slices):
        for a in range(lines):
            for r in range(run_starts[s * lines + a], run_starts[s * lines + a + 1]):
                code = run_pos[r] + 1 - run_lo[r]
                for b in range(run_lo[r], run_hi[r]):
                    own = grid[s, a, b]
                    mixed = own < 0
                    for ds in range(max(s - 1, 0), min(s + 2, slices)):
                        for da in range(max(a - 1, 0), min(a + 2, lines)):
                            for db in range(max(b - 1, 0), min(b + 2, columns)):
                                other = grid[ds, da, db]
                                mixed |= other != own and other != -2
                    out[code + b] = mixed
    return out


# ---------------------------------------------------------------------------- shading
@kernel
def _headlight(gx, gy, gz, light):
    """The Blinn–Phong headlight (:mod:`._shading`) for an index-space gradient: the factor on
    the straight colour and the highlight added to it, float32 (as ``_shading.blinn_phong``
    on ``cos = |N·L|`` and the fade ``t`` of :func:`._shading.fade`)."""
    m = light.normal
    nx = gx * m[0] + gy * m[3] + gz * m[6]
    ny = gx * m[1] + gy * m[4] + gz * m[7]
    nz = gx * m[2] + gy * m[5] + gz * m[8]
    norm = np.float32(math.sqrt(nx * nx + ny * ny + nz * nz))
    cos = _ZERO
    if norm > 0:
        towards = light.towards
        cos = abs(nx * towards[0] + ny * towards[1] + nz * towards[2]) / norm
    t = np.float32(fade(math.sqrt(np.float64(gx) ** 2 + np.float64(gy) ** 2
                                  + np.float64(gz) ** 2), light.fade_lo, light.fade_hi))
    glint = t * (light.specular * np.float32(cos ** light.shininess))
    return light.ambient + light.diffuse * (_ONE - t + t * cos), glint


@kernel
def lit_colours(codes, rows, gradients, lut, straight, light, out):
    """Shaded pre-classification: the premultiplied, step-corrected RGBA of the voxels
    ``codes`` (their table ``rows`` and index-space ``gradients``, by code) through the
    view's table ``lut`` (and its ``straight`` colours), lit by the view's headlight, into
    ``out[1:]`` (``out[0]`` stays transparent)."""
    for k in range(codes.size):
        code = codes[k]
        row = rows[code]
        lit, glint = _headlight(gradients[code, 0], gradients[code, 1], gradients[code, 2],
                                light)
        a = lut[row, 3]
        for ch in range(3):
            out[k + 1, ch] = min(straight[row, ch] * lit + glint, _ONE) * a
        out[k + 1, 3] = a


# ---------------------------------------------------------------------------- compositing
@kernel
def tap(point, alpha, beta, nearest):
    """First tap ``i`` and fraction ``f`` (float32) of the sample at absolute intermediate
    coordinate ``point``: ``x = alpha·point + beta = i + f``. A translated slice (``alpha``
    1) takes its fraction from ``beta`` alone, so that it does not depend on the point (nor
    on where the intermediate image starts). ``nearest``: ``f`` rounded to 0 or 1, all the
    weight on the nearest voxel (categorical transfer functions)."""
    if alpha == 1.0:
        base = math.floor(beta)
        i, f = point + base, np.float32(beta - base)
    else:
        x = alpha * point + beta
        i = math.floor(x)
        f = np.float32(x - i)
    if nearest:
        f = np.float32(1) if f >= _HALF else np.float32(0)
    return i, f


@kernel
def span(t0, t1, alpha, beta, origin, lo, hi):
    """Array indices ``[p0, p1)`` within ``[lo, hi)`` of the samples whose taps ``i`` or
    ``i + 1`` may reach columns ``t0 .. t1 - 1`` of a slice (exact for a translated slice,
    one more at each end otherwise, for rounding); sample ``p`` is at the absolute point
    ``p + origin`` (:func:`tap`), so the span moves with the origin and nothing else does."""
    if alpha == 1.0:
        base = math.floor(beta)
        first, stop = t0 - 1 - base, t1 - base
    else:
        first = math.ceil((t0 - 1 - beta) / alpha) - 1
        stop = math.ceil((t1 - beta) / alpha) + 1
    return max(first - origin, lo), min(stop - origin, hi)


@kernel
def _table_row(d, lo, scale, rows):
    """Row of the view's classification table (:meth:`TransferFunction.quantize` plus 1, row
    0 being transparent) of density ``d``."""
    row = np.rint((np.float64(d) - lo) * scale)
    return int(min(max(row, 0.0), rows - 1.0)) + 1


@kernel
def _step_factor(a, ratio):
    """The factor on a premultiplied sample of opacity ``a`` made for the table's step that
    corrects it to a step ``ratio`` times longer: ``α' = 1 - (1 - α)^ratio``, colour and
    opacity times ``α'/α`` (1 for a transparent sample)."""
    if a <= 0:
        return _ONE
    left = max(_ONE - a, _ZERO)
    return (_ONE - left ** ratio) / a


@kernel
def composite(first, step, band, plan, region, work, voxels, optics, frame):
    """Composite the samples of ``plan`` into the intermediate scanlines of bands ``first``,
    ``first + step``, ... (``band`` scanlines each) of ``frame``.

    Per band, per sample, per scanline: the runs of ``work`` on the voxel scanlines the
    scanline's taps read give the pixels to sample (merged in column order, as spans); less
    the opaque ones ("over": following and shortening the chains of ``frame.next``), they
    form stretches; per stretch, the columns it reads are decoded through the runs of
    ``region`` (a pointer per voxel scanline moving along with the stretches), sampled and
    composited (module docstring).
    """
    image, ranks, following, ratio = frame.image, frame.rank, frame.next, frame.ratio
    limit, origin_p, origin_q = frame.limit, frame.origin_p, frame.origin_q
    hi, wi = ranks.shape
    lines = region.lines
    run_starts, run_lo, run_hi, run_pos = region.starts, region.lo, region.hi, region.pos
    work_starts, work_lo, work_hi, work_box = work.starts, work.lo, work.hi, work.box
    index, values, channels = voxels.index, voxels.values, voxels.channels
    direct = index.size == 0
    lut, straight, light = optics.lut, optics.straight, optics.light
    mode, post, snap = optics.mode, optics.post, optics.nearest
    skip = mode == _OVER and optics.termination < 1.0
    slices, others, keeps, blends = plan.slice, plan.other, plan.keep, plan.blend
    alphas, betas_a, betas_b = plan.alpha, plan.beta_a, plan.beta_b
    k0s, kps, kqs, sample_ranks, tests = plan.k0, plan.kp, plan.kq, plan.rank, plan.test
    # Per slot (voxel scanline i, i + 1; the other slice's i, i + 1), a stretch's decoded
    # columns, 8 lanes each: the voxel's channels, its region weight (lane 4), its region
    # weight again in the nearest slice's slots (lane 5, unblended: is the sample's nearest
    # voxel in the region?) and padding; flat, so that the samples are one loop.
    scan = np.zeros((4, 8 * (region.columns + 3)), np.float32)
    scan0, scan1 = scan[0], scan[1]
    samples = np.zeros(8 * wi, np.float32)
    mixed = np.zeros(8 * (region.columns + 3), np.float32)
    column_tap = np.empty(wi, np.int64)
    column_fraction = np.empty(wi, np.float32)
    c = np.zeros(4, np.float32)
    run = np.empty(4, np.int64)  # per slot: the first region run that may hold the next tap
    run_end = np.empty(4, np.int64)
    kept = np.empty(4, np.int64)  # per slot: the next kept run
    kept_end = np.empty(4, np.int64)
    spans = np.empty((wi + 2, 2), np.int64)
    bands = (hi + band - 1) // band
    for b in range(first, bands, step):
        r0, r1 = b * band, min(b * band + band, hi)
        for n in range(slices.size):
            s, s2 = slices[n], others[n]
            a0, a1 = work_box[s, 0], work_box[s, 1]
            if s2 >= 0 and work_box[s2, 1] > work_box[s2, 0]:
                if a1 > a0:
                    a0, a1 = min(a0, work_box[s2, 0]), max(a1, work_box[s2, 1])
                else:
                    a0, a1 = work_box[s2, 0], work_box[s2, 1]
            if a1 <= a0:
                continue
            alpha, beta_a, beta_b = alphas[n], betas_a[n], betas_b[n]
            translated = alpha == 1.0
            keep, blend, test, rank = keeps[n], blends[n], tests[n], sample_ranks[n]
            slots = 2 if s2 < 0 else 4
            g = tap(0, alpha, beta_b, snap)[1]  # (a translated slice's fraction, every pixel)
            for x in range(wi):  # the columns' taps, the same on every scanline
                column_tap[x], column_fraction[x] = tap(x + origin_q, alpha, beta_b, snap)
            p0, p1 = span(a0, a1, alpha, beta_a, origin_p, r0, r1)
            for p in range(p0, p1):
                i, f = tap(p + origin_p, alpha, beta_a, snap)
                busy = False
                for k in range(slots):
                    row = i + (k & 1)
                    run[k] = run_end[k] = kept[k] = kept_end[k] = 0
                    if 0 <= row < lines:
                        line = (s if k < 2 else s2) * lines + row
                        kept[k], kept_end[k] = work_starts[line], work_starts[line + 1]
                        run[k], run_end[k] = run_starts[line], run_starts[line + 1]
                        busy = busy or kept_end[k] > kept[k]
                if not busy:
                    continue
                # The pixels whose taps touch a kept run, as merged spans in column order.
                count = 0
                while True:
                    best = -1
                    for k in range(slots):
                        if kept[k] < kept_end[k] and (best < 0 or
                                                      work_lo[kept[k]] < work_lo[kept[best]]):
                            best = k
                    if best < 0:
                        break
                    q0, q1 = span(work_lo[kept[best]], work_hi[kept[best]], alpha, beta_b,
                                  origin_q, 0, wi)
                    kept[best] += 1
                    if q1 <= q0:
                        continue
                    if count and q0 <= spans[count - 1, 1]:
                        spans[count - 1, 1] = max(spans[count - 1, 1], q1)
                    else:
                        spans[count, 0], spans[count, 1] = q0, q1
                        count += 1
                nearest = 1 if f >= _HALF else 0
                for u in range(count):
                    q, q_stop = spans[u, 0], spans[u, 1]
                    while q < q_stop:
                        if skip and following[p, q] != q:
                            # An opaque pixel: to the first one after it that is not, along
                            # the chain of pointers, which is shortened on the way back.
                            r = q
                            while following[p, r] != r:
                                r = following[p, r]
                            while q != r:
                                q_next = following[p, q]
                                following[p, q] = r
                                q = q_next
                            if q >= q_stop:
                                break
                        # A stretch of pixels that are not opaque, and the columns they read
                        # (beyond -1 .. columns there is no voxel: pixels reading only those
                        # are outside the region).
                        stop = q + 1
                        while stop < q_stop and (not skip or following[p, stop] == stop):
                            stop += 1
                        first_col = max(column_tap[q], -1)
                        last_col = min(column_tap[stop - 1] + 1, region.columns)
                        for k in range(slots):
                            # Decode the columns: the run pointer moves along the scanline
                            # with the pixels.
                            own = _ONE if k < 2 else _ZERO
                            lanes = scan[k]
                            r, end = run[k], run_end[k]
                            while r < end and run_hi[r] <= first_col:
                                r += 1
                            run[k] = r
                            col = first_col
                            while col <= last_col:
                                if r < end and run_lo[r] <= col:
                                    col_stop = min(run_hi[r], last_col + 1)
                                    code = run_pos[r] + 1 - run_lo[r]
                                    for x in range(col, col_stop):
                                        at = code + x if direct else index[code + x]
                                        lane = np.uint64(8 * (x - first_col))
                                        if channels == 4:
                                            for ch in range(4):
                                                lanes[lane + np.uint64(ch)] = values[at, ch]
                                        else:
                                            for ch in range(channels):
                                                lanes[lane + np.uint64(ch)] = values[at, ch]
                                        lanes[lane + np.uint64(4)] = _ONE
                                        lanes[lane + np.uint64(5)] = own
                                    col = col_stop
                                    r += 1
                                else:  # outside the region
                                    col_stop = last_col + 1 if r >= end else \
                                        min(run_lo[r], last_col + 1)
                                    for lane in range(np.uint64(8 * (col - first_col)),
                                                      np.uint64(8 * (col_stop - first_col))):
                                        lanes[lane] = _ZERO
                                    col = col_stop
                        width = 8 * (last_col - first_col + 1)
                        if s2 >= 0:  # blend the two slices voxel by voxel (then trilinear)
                            for k in range(2):
                                lanes, others_lanes = scan[k], scan[k + 2]
                                for lane in range(np.uint64(width)):
                                    lanes[lane] = lanes[lane] * keep + others_lanes[lane] * blend
                        # The stretch's samples: channels, region weight and (lane 5) whether
                        # the nearest voxel is in the region.
                        if translated:  # the same four weights at every pixel
                            w00, w01 = (_ONE - f) * (_ONE - g), (_ONE - f) * g
                            w10, w11 = f * (_ONE - g), f * g
                            offset = 8 * (column_tap[q] - first_col)
                            # (Unsigned indices: no negative-index wrap-around, so the loop
                            # is vectorized with contiguous loads.)
                            top, under = scan0[offset:], scan1[offset:]
                            for lane in range(np.uint64(8 * (stop - q))):
                                samples[lane] = (top[lane] * w00 + top[lane + _EIGHT] * w01
                                                 + under[lane] * w10
                                                 + under[lane + _EIGHT] * w11)
                            near = offset + (8 if g >= _HALF else 0) + 5
                            for x in range(stop - q):
                                samples[8 * x + 5] = scan[nearest, near + 8 * x]
                        else:  # rows first (one pass over the columns), then columns
                            for lane in range(np.uint64(width)):
                                mixed[lane] = scan0[lane] * (_ONE - f) + scan1[lane] * f
                            for x in range(stop - q):
                                j, g = column_tap[x + q], column_fraction[x + q]
                                if j < first_col or j >= last_col:  # no voxel: outside
                                    samples[8 * x + 5] = _ZERO
                                    continue
                                at, out = np.uint64(8 * (j - first_col)), np.uint64(8 * x)
                                for ch in range(np.uint64(5)):
                                    samples[out + ch] = (mixed[at + ch] * (_ONE - g)
                                                         + mixed[at + _EIGHT + ch] * g)
                                samples[out + np.uint64(5)] = scan[
                                    nearest, at + np.uint64(13 if g >= _HALF else 5)]
                        for x in range(q, stop):
                            u8 = 8 * (x - q)
                            if samples[u8 + 5] == 0:
                                continue  # the sample's nearest voxel is outside the region
                            if test:
                                depth = np.float32(k0s[n] + kps[n] * (p + origin_p)
                                                   + kqs[n] * (x + origin_q))
                                far = frame.far if limit.size == 0 else limit[p, x]
                                if not (depth >= frame.near and depth < far):
                                    continue
                            # The clamp policy: renormalise over region voxels.
                            factor = _ONE / max(samples[u8 + 4], _TINY)
                            if mode == _XRAY:
                                tau = max(samples[u8] * factor - optics.xray_offset, _ZERO) * \
                                    optics.xray_factor
                                # (The ray's own step is ratio times the table's: so are μΔ
                                # and the threshold.)
                                if tau > 0 and tau >= optics.xray_visible and \
                                        ranks[p, x] == NEVER:
                                    ranks[p, x] = rank
                                if ratio.size:
                                    tau *= ratio[p, x]
                                image[p, x, 0] += tau
                                continue
                            if mode == _MIP:
                                # Ties (within float32 rounding of the renormalised weights)
                                # keep the first, frontmost sample, as the reference does.
                                value = samples[u8] * factor
                                current = image[p, x, 0]
                                if value > current + _TIE * max(abs(current), _ONE):
                                    image[p, x, 0] = value
                                    ranks[p, x] = rank
                                continue
                            if post:  # classify (and light) the interpolated density
                                row = _table_row(samples[u8] * factor, optics.lut_lo,
                                                 optics.lut_scale, optics.lut_rows)
                                for ch in range(4):
                                    c[ch] = lut[row, ch]
                                if optics.shaded:
                                    lit, glint = _headlight(
                                        samples[u8 + 1] * factor, samples[u8 + 2] * factor,
                                        samples[u8 + 3] * factor, light)
                                    for ch in range(3):
                                        c[ch] = min(straight[row, ch] * lit + glint, _ONE) * c[3]
                            else:
                                for ch in range(4):
                                    c[ch] = samples[u8 + ch] * factor
                            # Before the correction to each ray's step: the threshold scales
                            # with the step too.
                            hit = c[3] > 0 and c[3] >= optics.visible
                            if ratio.size:
                                correction = _step_factor(c[3], ratio[p, x])
                                for ch in range(4):
                                    c[ch] *= correction
                            if mode == _OVER:
                                trans = _ONE - image[p, x, 3]
                                for ch in range(4):
                                    image[p, x, ch] += c[ch] * trans
                                if hit and ranks[p, x] == NEVER:
                                    ranks[p, x] = rank
                                if skip and image[p, x, 3] >= optics.termination:
                                    following[p, x] = x + 1
                            else:
                                left = _ONE - c[3]
                                for ch in range(4):
                                    image[p, x, ch] = image[p, x, ch] * left + c[ch]
                                if hit:
                                    ranks[p, x] = rank
                        q = stop


# ---------------------------------------------------------------------------- warp
@kernel
def ray_points(first_row, stop_row, x, y, terms, gram, eye, c_ref, step, scale, rays, pq, ok):
    """Perspective: where the ray of each pixel of rows ``first_row .. stop_row - 1`` meets
    the reference plane
    ``c = c_ref`` of index space, as intermediate coordinates ``pq[:, pixel]`` (times
    ``scale``), and whether it does, going the slices' way (``ok``; also only pixels of
    ``rays``, empty: all). Returns ``(p min, p max, q min, q max)`` over those rays.

    The ray of pixel ``(i, j)`` leaves the ``eye`` (index space) along ``x_j r + y_i u - f``
    (:meth:`Camera.rays`): index-space component ``k`` (of ``a, b, c``) is ``terms[k, 0] x_j +
    terms[k, 1] y_i + terms[k, 2]``; ``gram``: the world dot products ``r·r, u·u, f·f, r·u,
    r·f, u·f``, for the length of the direction (the test is on the unit direction, as the
    rays have it). Where the ray meets the plane does not depend on that length.
    """
    extent = np.array([np.inf, -np.inf, np.inf, -np.inf])
    width = x.size
    for i in range(first_row, stop_row):
        for j in range(width):
            k = i * width + j
            xj, yi = x[j], y[i]
            dc = terms[2, 0] * xj + terms[2, 1] * yi + terms[2, 2]
            length = math.sqrt(xj * xj * gram[0] + yi * yi * gram[1] + gram[2]
                               + 2 * xj * yi * gram[3] - 2 * xj * gram[4] - 2 * yi * gram[5])
            ok[k] = dc / length * step > 1e-12 and (rays.size == 0 or rays[k])
            if not ok[k]:
                pq[0, k] = pq[1, k] = 0.0
                continue
            t = (c_ref - eye[2]) / dc
            pq[0, k] = (eye[0] + t * (terms[0, 0] * xj + terms[0, 1] * yi + terms[0, 2])) * scale
            pq[1, k] = (eye[1] + t * (terms[1, 0] * xj + terms[1, 1] * yi + terms[1, 2])) * scale
            extent[0] = min(extent[0], pq[0, k])
            extent[1] = max(extent[1], pq[0, k])
            extent[2] = min(extent[2], pq[1, k])
            extent[3] = max(extent[3], pq[1, k])
    return extent


@kernel
def warp(start, stop, width, rows, cols, reach, pq, rays, frame, k0, kp, kq, rgba, depth):
    """Final pixels ``start .. stop - 1`` (row by row, ``width`` per row): the bilinear
    interpolation of the intermediate image at each pixel's ray, and the depth of the nearest
    intermediate pixel's depth sample (axial depth ``k0 + kp P + kq Q`` of rank ``r``).

    A pixel's intermediate point is ``rows[y] + cols[x]`` (orthographic: an affine map; only
    the columns ``reach[y, 0] .. reach[y, 1] - 1`` of row ``y`` may reach the intermediate
    image) or ``pq[:, pixel]`` (perspective), and only pixels of ``rays`` are written (empty:
    all). Taps outside the intermediate image read zeros; a fraction ``>= 0.5`` rounds up (as
    the clamp policy's nearest voxel: half to even would depend on the origin's parity).
    """
    image, ranks, origin_p, origin_q = frame.image, frame.rank, frame.origin_p, frame.origin_q
    hi, wi = ranks.shape
    for y in range(start // width, (stop - 1) // width + 1):
        x_lo, x_hi = max(start - y * width, 0), min(stop - y * width, width)
        if not pq.size:  # only the columns that may reach the intermediate image
            x_lo, x_hi = max(x_lo, reach[y, 0]), min(x_hi, reach[y, 1])
        for x in range(x_lo, x_hi):
            k = y * width + x
            if rays.size and not rays[k]:
                continue
            if pq.size:
                p, q = pq[0, k], pq[1, k]
            else:
                p, q = rows[y, 0] + cols[x, 0], rows[y, 1] + cols[x, 1]
            fp, fq = math.floor(p), math.floor(q)
            ia, ib = fp - origin_p, fq - origin_q
            if ia < -1 or ia >= hi or ib < -1 or ib >= wi:
                continue
            fa, fb = p - fp, q - fq
            f, g = np.float32(fa), np.float32(fb)
            if 0 <= ia < hi - 1 and 0 <= ib < wi - 1:
                for ch in range(4):
                    t00, t01 = image[ia, ib, ch], image[ia, ib + 1, ch]
                    t10, t11 = image[ia + 1, ib, ch], image[ia + 1, ib + 1, ch]
                    top = t00 + g * (t01 - t00)
                    bottom = t10 + g * (t11 - t10)
                    rgba[y, x, ch] = top + (bottom - top) * f
            else:  # on the border: taps outside the image read zeros
                for ch in range(4):
                    t00 = image[ia, ib, ch] if ia >= 0 and ib >= 0 else _ZERO
                    t01 = image[ia, ib + 1, ch] if ia >= 0 and ib + 1 < wi else _ZERO
                    t10 = image[ia + 1, ib, ch] if ia + 1 < hi and ib >= 0 else _ZERO
                    t11 = image[ia + 1, ib + 1, ch] if ia + 1 < hi and ib + 1 < wi else _ZERO
                    top = t00 + g * (t01 - t00)
                    bottom = t10 + g * (t11 - t10)
                    rgba[y, x, ch] = top + (bottom - top) * f
            near_p = ia + (1 if fa >= 0.5 else 0)
            near_q = ib + (1 if fb >= 0.5 else 0)
            if 0 <= near_p < hi and 0 <= near_q < wi:
                r = ranks[near_p, near_q]
                if r != NEVER:
                    depth[y, x] = k0[r] + kp[r] * (near_p + origin_p) + kq[r] * (near_q + origin_q)
