"""Splatting's loops, compiled (:mod:`.._jit`): one sub-slab of a sheet scattered into the
sheet buffer and composited into the image.

:mod:`._splat` orders the sheets, culls and places their voxels and finds the footprint's window
of pixel offsets; :func:`splat_rows` splats and composites a band of the sheet's window rows.
First, per pixel of the band, the part of the sub-slab its ray travels (box, clip range,
``depth_in``: ``[s0, s1]`` as A-offsets from the sheet's plane, empty for pixels that take no
more contributions) and, perspective, where the ray crosses the plane and its drift.
Then per voxel, per offset of its window, per pixel the offset lands on in the band: the
footprint weight from the footprint table (indexed by ``|q_⊥|²`` where the ray is ``at`` from
the plane), added to ``Σ w``, ``Σ w·density`` (and ``Σ w·gradient``), and the length of the
ray's path in the voxel's cell, added to the pixel's path length (the earliest A-offset where
it enters one kept where the depth is still wanted). Last, per pixel of the band whose ray
runs through the sheet's cells and meets a footprint: the sample (density ``Σ w·d / Σ w`` over
that length) classified (:mod:`._optics`), shaded (:func:`._shading.headlight`) and composited
into the image; the helpers take numbers, not arrays: a compiled call passing arrays costs their
reference counting, more than the work of a pixel.

The arithmetic is that of the vectorized NumPy splatting it replaced, in the same precision
(float32 footprint and path arithmetic, float64 sums, classification and shading as NumPy's
type promotion made them); only the order in which a pixel's sums are added changed (voxel by
voxel instead of offset by offset), which moves them by float64 rounding: the images compared
(CT head and brainsmall, all modes, shading, sub-slabs, both cameras) were identical, bit for
bit. A band writes only its own rows of the image, and adds a pixel's contributions in voxel
order whatever the bands, so the image does not depend on how the window is cut into bands
nor on the number of threads.

The kernel takes its inputs as records of arrays and numbers with fixed types, so that one
compiled kernel serves every render (what a render does not use is an empty array):
:data:`Crossings`, :data:`Voxels`, :data:`Footprint`, :data:`Slab`, :data:`._optics.Optics`
(opacity per unit length), the sheets' normal matrix and :data:`Image`.
"""

from collections import namedtuple

import numpy as np

from .._jit import kernel
from ._camera import BACKGROUND_DEPTH
from ._modes import MODE_CODES, MODES
from ._optics import (
    attenuation_threshold,
    classify,
    corrected,
    visible,
    visible_threshold,
)
from ._shading import headlight

__all__ = ["Crossings", "Voxels", "Footprint", "Slab", "Image", "splat_rows"]

_OVER, _UNDER, _XRAY, _MIP = (MODE_CODES[mode] for mode in MODES)

_HALF = np.float32(0.5)
_ZERO = np.float32(0.0)
_TINY = np.float32(1e-12)
"""Smallest drift a path is divided by (a ray along the cell's face)."""
_BACKGROUND = np.float32(BACKGROUND_DEPTH)

Crossings = namedtuple("Crossings", "ta ia span t0 t1 b0 b1 c0 c1 db dc mm a0 kz dirs")
Crossings.__doc__ = """Per image pixel ((H, W) float64 each), where its ray meets the sheets of
one principal axis A: the ray parameter at the plane ``A = a`` is ``ta + a·ia``, ``span`` the
parameter per unit of A, ``[t0, t1]`` the clipped ray range (box, clip range, ``depth_in``);
perspective, the crossing point ``(b0 + a·b1, c0 + a·c1)`` in the plane and the drift ``(db,
dc)`` per unit of A along the ray (orthographic: unused); ``mm`` per unit of A, the axial depth
``a0 + kz·t`` at parameter ``t``, and ``dirs`` ((H, W, 3)) the world ray direction."""

Voxels = namedtuple("Voxels", "col row b c dens grads ub uc centre")
Voxels.__doc__ = """The voxels of a sheet to splat, one entry each: ``col``, ``row`` (int64) the
pixel of their projected centre in window coordinates; ``b``, ``c`` (float32) their cell;
``dens`` (float32) the sub-slab's density; ``grads`` ((m, 3) float64, empty unshaded) the
gradient; ``ub``, ``uc`` (float32) the in-plane components of the unit view direction (index
space); ``centre`` ((m, 2) float64, orthographic; empty perspective): the voxel's term of the
in-plane offset from it to a pixel's crossing point."""

Footprint = namedtuple("Footprint", "table scale offsets per_offset drift")
Footprint.__doc__ = """Footprints: ``table`` (float32) the weights by ``floor(|q_⊥|²·scale)``
(last entry 0, beyond the radius); ``offsets`` ((k, 2) int64) the window, pixel offsets
(column, row) from a voxel's pixel; orthographic: ``per_offset`` ((k, 2) float64) the offset's
term of the in-plane offset and ``drift`` ((2,) float32) the rays' drift per unit of A
(perspective: ``per_offset`` empty, the drift per pixel from :data:`Crossings`)."""

Slab = namedtuple("Slab", "a lo hi at r0 c0 live")
Slab.__doc__ = """The sub-slab: sheet ``a`` (float), the sub-slab ``[lo, hi]`` as A-offsets from
its plane and ``at`` (float32) the offset of its centre plane, where footprints are evaluated;
the window's top left image pixel ``(r0, c0)`` and its pixels that take contributions, ``live``
((rows, cols) bool)."""

Image = namedtuple("Image", "acc depth done vmax")
Image.__doc__ = """What a sheet family composites into, flat per pixel: premultiplied RGBA
``acc`` ((H·W, 4) float32; X-ray: optical depth in channel 0), the axial ``depth`` (float32),
``done`` (bool: pixels that take no more contributions) and MIP's maxima ``vmax`` (float32;
empty for the other modes)."""


@kernel
def splat_rows(top, bottom, voxels, footprint, slab, crossings, optics, normal, image):
    """Splat the voxels into the window rows ``top .. bottom - 1`` and composite them into
    ``image`` (module docstring); ``normal`` ((9,) float64, empty unshaded): the matrix taking
    the sheets' (A, B, C) gradient to a world normal, row by row."""
    rows, cols = slab.live.shape
    width = crossings.ta.shape[1]
    ortho = footprint.per_offset.shape[0] > 0
    shaded = voxels.grads.shape[0] > 0
    first_only = optics.mode == _OVER or optics.mode == _XRAY
    offsets = footprint.offsets
    k = offsets.shape[0]
    last = footprint.table.shape[0] - 1
    # Per pixel of the band: [s0, s1], and (perspective) the crossing point and the drift.
    n = (bottom - top) * cols
    s0 = np.zeros(n, np.float32)
    s1 = np.zeros(n, np.float32)
    pb = np.zeros(0 if ortho else n, np.float32)
    pc = np.zeros(0 if ortho else n, np.float32)
    drb = np.zeros(0 if ortho else n, np.float32)
    drc = np.zeros(0 if ortho else n, np.float32)
    a = slab.a
    for r in range(top, bottom):
        y = slab.r0 + r
        for col in range(cols):
            x = slab.c0 + col
            i = (r - top) * cols + col
            if slab.live[r, col]:
                ta = crossings.ta[y, x] + a * crossings.ia[y, x]
                span = crossings.span[y, x]
                lo = np.float32(min(max((crossings.t0[y, x] - ta) / span, -0.5), 0.5))
                hi = np.float32(min(max((crossings.t1[y, x] - ta) / span, -0.5), 0.5))
                s0[i] = np.float32(min(max(lo, slab.lo), slab.hi))
                s1[i] = np.float32(min(max(hi, slab.lo), slab.hi))
            if not ortho:
                pb[i] = np.float32(crossings.b0[y, x] + a * crossings.b1[y, x])
                pc[i] = np.float32(crossings.c0[y, x] + a * crossings.c1[y, x])
                drb[i] = np.float32(crossings.db[y, x])
                drc[i] = np.float32(crossings.dc[y, x])
    # The band's sheet buffer: Σ w, Σ w·density, the path's length (units of A) in the sheet's
    # cells, its start (inf: none or not wanted), Σ w·gradient.
    w_sum = np.zeros(n)
    wd_sum = np.zeros(n)
    path = np.zeros(n)
    start = np.full(n, np.inf)
    grad = np.zeros((n if shaded else 0, 3))
    low = 0
    high = 0
    for o in range(k):
        low = min(low, offsets[o, 1])
        high = max(high, offsets[o, 1])
    at = slab.at
    scale = footprint.scale
    drift_b = footprint.drift[0] if ortho else _ZERO
    drift_c = footprint.drift[1] if ortho else _ZERO
    for v in range(voxels.col.shape[0]):
        row = voxels.row[v]
        if row + high < top or row + low >= bottom:
            continue
        ub = voxels.ub[v]
        uc = voxels.uc[v]
        dens = voxels.dens[v]
        for o in range(k):
            r = row + offsets[o, 1]
            col = voxels.col[v] + offsets[o, 0]
            if r < top or r >= bottom or col < 0 or col >= cols:
                continue
            i = (r - top) * cols + col
            if ortho:
                db = np.float32(footprint.per_offset[o, 0] + voxels.centre[v, 0])
                dc = np.float32(footprint.per_offset[o, 1] + voxels.centre[v, 1])
            else:
                db = pb[i] - voxels.b[v]
                dc = pc[i] - voxels.c[v]
                drift_b = drb[i]
                drift_c = drc[i]
            # Footprint: the kernel integrated along the ray, where the ray is ``at`` from the
            # plane.
            qb = db + at * drift_b
            qc = dc + at * drift_c
            proj = qb * ub + qc * uc
            r2 = max(qb * qb + qc * qc - proj * proj, _ZERO)
            wt = footprint.table[min(np.int64(r2 * scale), last)]
            w_sum[i] += wt
            wd_sum[i] += wt * dens
            if shaded:
                for j in range(3):
                    grad[i, j] += wt * voxels.grads[v, j]
            # The ray's path in the slab, (db, dc) + s (drift_b, drift_c) for s in [s0, s1],
            # clipped to the voxel's cell |.| <= 0.5 in both in-plane axes; only where the
            # path can reach the cell, its boundary included (rays along a face).
            if (abs(db) - _HALF * abs(drift_b) > _HALF
                    or abs(dc) - _HALF * abs(drift_c) > _HALF):
                continue
            lo = s0[i]
            hi = s1[i]
            for delta, drift in ((db, drift_b), (dc, drift_c)):
                if abs(drift) < _TINY:
                    drift = _TINY
                e0 = (-_HALF - delta) / drift
                e1 = (_HALF - delta) / drift
                lo = max(lo, min(e0, e1))
                hi = min(hi, max(e0, e1))
            length = max(hi - lo, _ZERO)
            path[i] += length
            if length > 0 and lo < start[i] and not (
                    first_only and image.depth[(slab.r0 + r) * width + slab.c0 + col]
                    != _BACKGROUND):
                start[i] = lo
    # Composite the band's samples (the NumPy compositing's arithmetic, types and all).
    mode = optics.mode
    lut = optics.lut
    matrix = (0.0,) * 9
    if normal.shape[0] > 0:
        m = normal
        matrix = (m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8])
    weights = optics.phong
    for r in range(top, bottom):
        y = slab.r0 + r
        for col in range(cols):
            i = (r - top) * cols + col
            if not (path[i] > 0 and w_sum[i] > 0):
                continue
            x = slab.c0 + col
            p = y * width + x
            value = np.float32(wd_sum[i] / w_sum[i])
            length = np.float32(path[i] * crossings.mm[y, x])
            ta = crossings.ta[y, x] + a * crossings.ia[y, x]
            first_depth = np.float32(crossings.a0[y, x] + crossings.kz[y, x] * (
                ta + start[i] * crossings.span[y, x]))
            if mode == _XRAY:
                tau = optics.xray_scale * max(value - optics.xray_offset, _ZERO) * length
                image.acc[p, 0] += tau
                if (visible(tau, attenuation_threshold(length))
                        and image.depth[p] == _BACKGROUND):
                    image.depth[p] = first_depth
                continue
            if mode == _MIP:
                if value > image.vmax[p]:
                    image.vmax[p] = value
                    image.depth[p] = first_depth
                continue
            red, green, blue, opacity = classify(lut, optics.lut_lo, optics.lut_scale, value)
            units = np.float64(length / optics.unit_length)
            alpha = corrected(opacity, units)
            if shaded:
                red, green, blue = headlight(
                    (red, green, blue), (grad[i, 0] / w_sum[i], grad[i, 1] / w_sum[i],
                                         grad[i, 2] / w_sum[i]), matrix,
                    (crossings.dirs[y, x, 0], crossings.dirs[y, x, 1], crossings.dirs[y, x, 2]),
                    weights)
            hit = visible(alpha, visible_threshold(units))
            if mode == _OVER:
                trans = np.float32(1.0) - image.acc[p, 3]
                image.acc[p, 0] = np.float32(image.acc[p, 0] + trans * (red * alpha))
                image.acc[p, 1] = np.float32(image.acc[p, 1] + trans * (green * alpha))
                image.acc[p, 2] = np.float32(image.acc[p, 2] + trans * (blue * alpha))
                image.acc[p, 3] = np.float32(image.acc[p, 3] + trans * alpha)
                if hit and image.depth[p] == _BACKGROUND:
                    image.depth[p] = first_depth
                if image.acc[p, 3] >= optics.termination:
                    image.done[p] = True
            else:  # under: back to front
                keep = 1.0 - alpha
                image.acc[p, 0] = np.float32(red * alpha + keep * image.acc[p, 0])
                image.acc[p, 1] = np.float32(green * alpha + keep * image.acc[p, 1])
                image.acc[p, 2] = np.float32(blue * alpha + keep * image.acc[p, 2])
                image.acc[p, 3] = np.float32(alpha + keep * image.acc[p, 3])
                if hit:
                    image.depth[p] = first_depth
