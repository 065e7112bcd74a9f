"""Splatting's footprint loop, compiled (:mod:`.._jit`): one sub-slab of a sheet scattered into
the sheet buffer.

:mod:`._splat` orders the sheets, culls and places their voxels, finds the footprint's window of
pixel offsets and composites the buffer; :func:`splat_rows` fills the buffer for a band of the
sheet's window rows. First, per pixel of the band, the part of the sub-slab its ray travels (box,
clip range, ``depth_in``: ``[s0, s1]`` as A-offsets from the sheet's plane, empty for pixels
that take no more contributions) and, perspective, where the ray crosses the plane and its drift.
Then per voxel, per offset of its window, per pixel the offset lands on in the band: the
footprint weight from the footprint table (indexed by ``|q_⊥|²`` where the ray is ``at`` from
the plane), added to ``Σ w``, ``Σ w·density`` (and ``Σ w·gradient``), and the length of the
ray's path in the voxel's cell, added to the pixel's path length (the earliest A-offset where
it enters one kept where the depth is still wanted).

The arithmetic is that of the vectorized NumPy scatter it replaced, in the same precision
(float32 footprint and path arithmetic, float64 sums); only the order in which a pixel's sums
are added changed (voxel by voxel instead of offset by offset), which moves them by float64
rounding. A band writes only its own rows of the buffer, and adds a pixel's contributions in
voxel order whatever the bands, so the buffer does not depend on how the window is cut into
bands nor on the number of threads.

The kernel takes its inputs as records of arrays and numbers with fixed types, so that one
compiled kernel serves every render (what a render does not use is an empty array):
:data:`Crossings`, :data:`Voxels`, :data:`Footprint`, :data:`Slab` and :data:`Buffer`.
"""

from collections import namedtuple

import numpy as np

from .._jit import kernel
from ._camera import BACKGROUND_DEPTH

__all__ = ["Crossings", "Voxels", "Footprint", "Slab", "Buffer", "splat_rows"]

_HALF = np.float32(0.5)
_ZERO = np.float32(0.0)
_TINY = np.float32(1e-12)
"""Smallest drift a path is divided by (a ray along the cell's face)."""
_BACKGROUND = np.float32(BACKGROUND_DEPTH)

Crossings = namedtuple("Crossings", "ta ia span t0 t1 b0 b1 c0 c1 db dc")
Crossings.__doc__ = """Per image pixel ((H, W) float64 each), where its ray meets the sheets of
one principal axis A: the ray parameter at the plane ``A = a`` is ``ta + a·ia``, ``span`` the
parameter per unit of A, ``[t0, t1]`` the clipped ray range (box, clip range, ``depth_in``);
perspective, the crossing point ``(b0 + a·b1, c0 + a·c1)`` in the plane and the drift ``(db,
dc)`` per unit of A along the ray (orthographic: unused)."""

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

Slab = namedtuple("Slab", "a lo hi at r0 c0 live depth first_only")
Slab.__doc__ = """The sub-slab: sheet ``a`` (float), the sub-slab ``[lo, hi]`` as A-offsets from
its plane and ``at`` (float32) the offset of its centre plane, where footprints are evaluated;
the window's top left image pixel ``(r0, c0)`` and its pixels that take contributions, ``live``
((rows, cols) bool); the image's ``depth`` ((H, W) float32): with ``first_only`` the path's start
is kept only where it is still the background."""

Buffer = namedtuple("Buffer", "w wd length start grad")
Buffer.__doc__ = """The sheet buffer, flat over the window's pixels (float64): ``Σ w``,
``Σ w·density``, the path ``length`` (units of A) in the sheet's cells, its ``start`` (inf: none
or not wanted) and ``Σ w·gradient`` ((n, 3); empty unshaded). Zeros (``start``: inf) on entry."""


@kernel
def splat_rows(top, bottom, voxels, footprint, slab, crossings, buffer):
    """Splat the voxels into the window rows ``top .. bottom - 1`` of ``buffer`` (module
    docstring)."""
    rows, cols = slab.live.shape
    ortho = footprint.per_offset.shape[0] > 0
    shaded = buffer.grad.shape[0] > 0
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
            p = r * cols + col
            buffer.w[p] += wt
            buffer.wd[p] += wt * dens
            if shaded:
                for j in range(3):
                    buffer.grad[p, j] += wt * voxels.grads[v, j]
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
            buffer.length[p] += length
            if length > 0 and lo < buffer.start[p] and not (
                    slab.first_only
                    and slab.depth[slab.r0 + r, slab.c0 + col] != _BACKGROUND):
                buffer.start[p] = lo
