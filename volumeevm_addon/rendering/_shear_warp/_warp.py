"""Shear-warp's warp: the intermediate image resampled into the final image, with the depth of
each pixel's first visible sample; its driver and its compiled loop.

This is the stage VolPack keeps in ``vp_warp.c``. Every final pixel's ray (from
:meth:`Camera.rays`) meets the reference plane at ``(p, q)`` (the map :mod:`._view` made: an
affine map for orthographic cameras, a homography for perspective ones); the colour is the
bilinear interpolation of the intermediate image (:mod:`._composite`) there. The output depth is
the axial depth of the front end (half a slice before the sample, along the ray) of the depth
sample of the **nearest** intermediate pixel (halves rounded up; depths are not blended);
``1e10`` where there is none. Chunks of final pixels are warped in parallel; each writes only
its own pixels.
"""

import math

import numpy as np

from ..._jit import kernel, parallel_map
from ._composite import NEVER

__all__ = ["warp_frame", "warp"]

_WARP_CHUNK = 1 << 14
"""Final pixels per task of the warp."""
_ZERO = np.float32(0.0)


def warp_frame(view, camera, frame, front, rgba_out, depth_out):
    """Final image: bilinear interpolation of the intermediate colour at each pixel's ray, and
    the depth of the nearest intermediate pixel's depth sample (:func:`warp`),
    :data:`_WARP_CHUNK` pixels per task."""
    h, w = camera.shape
    k0, kp, kq = view.depth_coefficients(front)
    none = np.zeros((0, 2))  # (unused: orthographic rows and columns, or perspective points)
    if view.ortho:
        rows, cols, reach = view.rows, view.cols, _reach(view, w)
        pq, rays = none, np.zeros(0, bool)
    else:
        rows = cols = none
        reach = np.zeros((0, 2), np.int64)
        pq, rays = view.pq, view.rays_ok
    parallel_map(lambda start: warp(start, min(start + _WARP_CHUNK, h * w), w, rows, cols, reach,
                                    pq, rays, frame, k0, kp, kq, rgba_out, depth_out),
                 [(start,) for start in range(0, h * w, _WARP_CHUNK)])


def _reach(view, width):
    """Orthographic: per final row ``y``, the columns ``[x0, x1)`` whose intermediate point
    ``rows[y] + cols[x]`` may fall within a pixel of the intermediate image (its taps then
    touch it), one column wider at each end than exact (the warp tests every pixel it does)."""
    reach = np.zeros((len(view.rows), 2), np.int64)
    reach[:, 1] = width
    for k in range(2):
        # The point's tap floor(v) - origin must lie in [-1, size): v in
        # [origin - 1, origin + size).
        lo = view.origin[k] - 1 - view.rows[:, k]
        hi = view.origin[k] + view.size[k] - view.rows[:, k]
        column = view.cols[:, k]
        if column[-1] < column[0]:
            lo, hi, column = -hi, -lo, -column
        x0 = np.searchsorted(column, lo, side="left") - 1
        x1 = np.searchsorted(column, hi, side="right") + 1
        if column[-1] == column[0]:  # the same point all along the row
            inside = (lo <= column[0]) & (column[0] < hi)
            x0, x1 = np.where(inside, 0, width), np.where(inside, width, 0)
        reach[:, 0] = np.maximum(reach[:, 0], x0)
        reach[:, 1] = np.minimum(reach[:, 1], x1)
    np.clip(reach, 0, width, out=reach)
    return reach


# ------------------------------------------------------------------------------------- kernels
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
