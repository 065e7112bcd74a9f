"""Shear-warp rendering of a VolumeEVM (Lacroute & Levoy), parallel and perspective.

The view is factored into a shear (perspective: a shear and a per-slice scale) that makes every
ray perpendicular to the slices of the **principal axis**, and one 2-D warp from the
intermediate image (one pixel per voxel of a slice, or ``intermediate_scale`` pixels per voxel
along each in-slice axis) to the final image.

Pipeline
--------
1. **Principal axis** ``c``: the grid axis whose world direction is most parallel to the view
   (orthographic: the camera's forward vector; perspective with the eye outside the region's
   bounding box: the eye-to-region-centre vector, among the axes along which the eye is outside
   the box, so that every ray crosses the slices the same way), ties to x, then y, then z
   (VolPack ``vp_view.c``). A perspective eye inside the box is rendered in up to six passes,
   the rays grouped by the axis and sign most parallel to each, each pass compositing the
   slices beyond the eye (Lacroute's split of the view into pyramids). The slices ``c = s`` (voxel-centre
   planes) are read front to back (``"over"``, ``"xray"``, ``"mip"``) or back to front
   (``"under"``): the densities table ``vevm.table(c)`` read forwards or backwards.
2. **Intermediate image.** Its pixel ``(p, q)`` is the ray through the point ``(p, q)`` (plus an
   integer origin) of a reference plane ``c = c_ref`` in index space; its two axes are the
   in-slice axes of the table order (:data:`volumeevm_addon.model._densities.TABLE_ORDERS`). The
   ray meets slice ``s`` at in-slice index coordinates ``x = α_s p + β_s`` (and likewise ``y``).
   Orthographic: ``α_s = 1`` and ``β_s = (s - c_ref) d_a / d_c`` (the shear): the slice is
   *translated*, so the four bilinear weights ``(1-f)(1-g), (1-f)g, f(1-g), fg`` with
   ``f = frac(β_s)`` are the same for the whole slice (VolPack ``vp_renderA.c``) and resampling
   is four shifted views of the slice's box (the default, unshaded pre-classification with one
   sample per slice: two 1-D interpolations of shifted views, columns then rows,
   ``a + f·(b - a)``). Perspective: ``α_s = (s - E_c)/(c_ref - E_c)`` with the eye ``E``, a
   per-slice uniform scale about the eye (Lacroute & Levoy 1994, §4; Schulze et al. 2001);
   the reference plane is the region's far end, so ``α_s <= 1`` (slices are magnified, never
   minified) and the bilinear weights are separable: one 2-tap weight vector per row and one
   per column of the slice. ``intermediate_scale = k`` divides ``α_s`` by ``k`` (the separable
   path, orthographic too).
3. **Slices are moved, voxels are not.** What depends only on the principal axis is computed
   once and kept in the VolumeEVM's cache, ``vevm.cache``: per slice, the bounding box of the
   EVM section valid at it (:meth:`EVM.sections`) and, over that box, the position in
   ``vevm.table(c)`` of each voxel (0 outside the region). A view only shifts (scales) these boxes: per slice, the
   work is a few vectorised operations on the box, cut to the part of the intermediate image
   that is still needed (early ray termination) and, for ``"over"``/``"under"``, to the part
   holding voxels that the transfer function does not make transparent (cached per transfer
   function). Slices whose density range is transparent are skipped. Unshaded
   pre-classification also keeps, per transfer function, each voxel's table row per slice, so
   that a view gathers colours with one lookup per voxel.
4. **Samples along the rays** (``slices_per_voxel = k``, Shear-Warp Deluxe's intermediate
   slices): each voxel slice ``s`` owns the slab of its cells, ``c`` in ``[s - 1/2, s + 1/2)``,
   and takes ``k`` samples at the centres of ``k`` equal parts of it; a sample between the
   slice planes is the linear blend of the bilinear samples of ``s`` and its neighbour (so
   trilinear, with the clamp policy of the sample's nearest voxel, which is in ``s``). ``k = 1``
   is VolPack's one sample per slice, on the plane. The opacity is corrected for ``Δ / k``.
   **Classification** ``"pre"`` (VolPack): each voxel's density is quantized once per transfer
   function (:meth:`TransferFunction.quantize`) and looked up in the premultiplied table
   :meth:`TransferFunction.table` computed once per view with the opacity corrected for the
   physical distance between consecutive samples along the ray, ``Δ = |diag(spacing) · d / d_c|``
   mm (``sqrt(1 + s_a² + s_b²)`` slices in VolPack's isotropic case). Perspective rays have
   their own ``Δ``; the table is made for the central ray and each sample is corrected to its
   ray's ``Δ`` by ``α' = 1 - (1 - α)^(Δ/Δ_table)`` (colour scaled by ``α'/α``).
   With ``shading``, each voxel's colour is lit once per view before interpolation (the
   reference's Blinn–Phong headlight on per-voxel central-difference gradients, which are
   computed once per principal axis and cached; the light is the view direction, for
   perspective the eye-to-region-centre direction).
   ``"mip"`` and ``"xray"`` interpolate densities instead (post-classification, as the
   reference does): MIP classifies the maximum with the transfer function's opacity as given,
   X-ray accumulates ``μ·Δ`` with ``μ = xray_scale · max(d - xray_offset, 0)`` per mm and gives
   ``1 - exp(-Σ μΔ)`` as grey premultiplied RGBA. ``"post"`` does the same for ``"over"`` and
   ``"under"``: densities (and, with shading, the per-voxel gradients) are interpolated, then
   classified through the table and lit per sample, the reference's order; slabs whose two
   slices' density range is transparent are skipped.
5. **Boundary policy "clamp"** (:mod:`._reference`), in the slice: a sample is transparent if the
   voxel nearest to it (its cell) is outside the region; otherwise the bilinear weights of
   outside voxels are dropped and the others renormalised. Outside voxels are never read: their
   code is 0 and the table row 0 is ``(0, 0, 0, 0, weight 0)``.
6. **Compositing** into one float32 intermediate image: ``"over"`` front to back,
   ``C += (1 - A)·c``, with early ray termination: a pixel whose opacity reached
   ``termination`` takes nothing more (so its error is at most ``1 - termination``), and
   every few slices the bounding box of the pixels below it is recomputed; slices are cut to it
   and the loop stops when it is empty. (The box only shrinks where whole bands of the
   intermediate image are opaque, e.g. a close-up; around a head seen whole the transparent
   background keeps it wide.) ``"under"`` back to front,
   ``C = c + (1 - a)·C``; ``"xray"`` sums ``μΔ``; ``"mip"`` keeps the maximum and its slice.
7. **Warp**: every final pixel's ray (from :meth:`Camera.rays`) meets the reference plane at
   ``(p, q)``; the colour is the bilinear interpolation of the intermediate image there (an
   affine map for orthographic cameras, a homography for perspective ones).

Depth
-----
- ``depth_in`` (and the camera's clip range): a sample is dropped when its axial depth is not in
  ``[clip_start, min(clip_end, depth_in))``. ``depth_in`` is brought into the intermediate image
  once per view (each intermediate pixel takes the value of the final pixel its ray passes
  through, nearest); per slice the sample depth is affine in ``(p, q)`` and is only evaluated
  on slices whose depth range crosses a limit.
- Depth out: axial depth of the front end (half a slice before the sample, along the ray) of the
  first visible sample (:mod:`._depth`: opacity per unit length at least ``VISIBLE_ALPHA``;
  ``"xray"``: attenuation; ``"mip"``: the frontmost sample holding the maximum, if its class is
  visible), taken from the **nearest** intermediate pixel (halves rounded up; depths are not
  blended); ``1e10`` where there is none.
- Neither depends on where the intermediate image starts (:meth:`_View.extent`): its origin is
  an integer that moves array indices only; fractions, taps and depths are computed in
  absolute intermediate coordinates. (Rounding ``β + origin`` instead gave a fraction of 1e-15
  on the region's path and 0 on the dense path, whose images start elsewhere.)

Known limits: by default one sample per slice (inter-slice aliasing unless
``slices_per_voxel`` > 1), one intermediate pixel per voxel (zooming in blurs unless
``intermediate_scale`` > 1), pre-classification smooths boundaries, and in perspective
rays far from the principal axis are sampled more sparsely (the seams between the passes of an
eye inside the region show as changes of sampling). The principal axis switches at 45°:
on brainsmall at half resolution (MRI preset, orthographic, 64x48, azimuth 40°..50°) the mean
absolute error to the reference stays 0.006 on both sides, and the frame-to-frame change across
the switch (44.9° -> 45.1°: 0.0030) is no larger than between neighbouring angles
(0.003-0.005, against the reference's 0.0003-0.003): resampling noise, not popping, with this
transfer function (``tests/test_shear_warp.py`` keeps the measurement).

References
----------
P. Lacroute, M. Levoy, "Fast volume rendering using a shear-warp factorization of the viewing
transformation", SIGGRAPH 1994, https://doi.org/10.1145/192161.192283.
J. P. Schulze, R. Niemeier, U. Lang, "The perspective shear-warp algorithm in a virtual
environment", IEEE Visualization 2001, https://doi.org/10.1109/VISUAL.2001.964517.
VolPack 1.0b3 (``vp_view.c``, ``vp_renderA.c``, ``vp_warp.c``), Stanford University.
"""

import math
from dataclasses import dataclass

import numpy as np

from .._errors import VolumeEVMError
from ..model._densities import TABLE_ORDERS
from . import _depth
from ._camera import BACKGROUND_DEPTH
from ._checks import checked_view
from ._gradients import region_gradients
from ._modes import finish_mode
from ._shading import Shading, blinn_phong, checked_shading

__all__ = ["render_shear_warp", "SLICES_PER_VOXEL", "CLASSIFICATIONS"]

SLICES_PER_VOXEL = (1, 2, 3, 4, 8)
"""Allowed samples per voxel slice along the rays (Shear-Warp Deluxe's intermediate slices)."""
CLASSIFICATIONS = ("pre", "post")
"""Classify voxels, then interpolate colours ("pre"), or interpolate densities, then classify."""

_ERT_EVERY = 8
"""Slices between two updates of the early-ray-termination bounding box."""
_MAX_INTERMEDIATE = 1 << 26
"""Largest intermediate image (pixels); only extreme perspective close-ups come near it."""
_WARP_CHUNK = 1 << 14
"""Final pixels the warp computes per NumPy call: its temporaries stay small enough for the
allocator to reuse them (whole-image ones went back to the system and were page-faulted in
again on every frame, which cost the 512² warp more than its arithmetic)."""
_NEVER = np.iinfo(np.int32).max
_TIE = 1e-6
"""Relative margin a MIP sample must exceed the maximum by to replace it (float32 ties)."""
_UNSEEN = -np.finfo(np.float32).max
"""MIP maximum before any sample (finite, so that the tie margin stays a number)."""


class _Layout:
    """The slices of one principal axis.

    Attributes
    ----------
    boxes : (n, 4) ndarray of np.int64
        Per slice ``(a0, a1, b0, b1)``: the bounding box of its region voxels in the two in-slice
        axes (table order), empty (``a1 <= a0``) for a slice without voxels.
    codes : list of ndarray of np.int32
        Per slice, over its box: ``1 +`` the position of each voxel in ``values[1:]``, 0 outside.
    values : (N + 1,) ndarray
        ``values[0] = 0``, then the densities the codes point at.
    ranges : (n, 2) ndarray or None
        Per slice, min and max density of its voxels (``None``: no slice may be skipped).
    axis, axes, region_only
        The principal axis; the table order as grid axes; whether codes number the region's
        voxels (True: the layout is kept in ``vevm.cache``, and so is what is derived from it,
        :func:`_kept`) or every voxel of the dense grid (False: made for one render).
    """

    def __init__(self, boxes, codes, values, ranges, axes, region_only):
        self.axis = axes[0]
        self.axes = axes
        self.region_only = region_only
        self.boxes = boxes
        self.codes = codes
        self.values = values
        self.values32 = values.astype(np.float32)
        self.ranges = ranges


def _key(axis, part, tf=None, lut_size=None):
    """The ``vevm.cache`` key of ``part`` of the slices of principal axis ``axis``: "layout"
    (:func:`_region_layout`), "gradients", "post" or "post_shaded" (:func:`_post_table`), and
    per transfer function and table size "classes" and "slice_rows" (:func:`_classes`,
    :func:`_slice_rows`). The function enters the key by its control points, all these depend
    on: equal functions share them, and the cache keeps no function (nor its own tables) alive.
    One function for the render and :func:`tables_to_build`, so that the memory check sees the
    same cache the render uses."""
    if part in ("classes", "slice_rows"):
        return ("shear_warp", part, axis, tf.points.tobytes(), lut_size)
    return ("shear_warp", part, axis)


def _kept(vevm, layout, part, make, tf=None, lut_size=None):
    """``make()``, kept in ``vevm.cache`` under :func:`_key` for the region's layouts; for the
    dense layout (made anew for every render: the dense side of the exactness contract)
    nothing is kept."""
    if not layout.region_only:
        return make()
    return vevm.cache.get(_key(layout.axis, part, tf, lut_size), make)


def _region_layout(vevm, axis):
    """The region's slices along ``axis`` (:func:`_make_region_layout`), kept in
    ``vevm.cache``."""
    return vevm.cache.get(_key(axis, "layout"), lambda: _make_region_layout(vevm, axis))


def _make_region_layout(vevm, axis):
    """Slice boxes from the EVM's sections and table positions, for ``vevm.table(axis)``."""
    order = TABLE_ORDERS[axis]
    axes = ["xyz".index(ch) for ch in order]
    shape = tuple(vevm.shape[a] for a in axes)
    boxes = np.zeros((shape[0], 4), np.int64)
    for slab in vevm.evm.sections(order):
        lo, hi = max(slab.lo, 0), min(slab.hi, shape[0])
        if len(slab.section) and lo < hi:
            pts = slab.section.astype(np.int64)
            bmin, bmax = np.maximum(pts.min(axis=0), 0), np.minimum(pts.max(axis=0), shape[1:])
            boxes[lo:hi] = (bmin[0], bmax[0], bmin[1], bmax[1])
    # Table position of every voxel: the table lists the region's voxels in C order of the grid
    # transposed to the table order (VolumeEVM.table), so a running count numbers them.
    mask = np.transpose(vevm.evm.to_mask(vevm.shape), axes)
    position = np.cumsum(mask, dtype=np.int32).reshape(shape)
    position *= mask
    codes = [position[s, a0:a1, b0:b1].copy() for s, (a0, a1, b0, b1) in enumerate(boxes)]
    table = vevm.table(axis)
    counts = mask.sum(axis=(1, 2))
    ranges = np.zeros((shape[0], 2))
    full = counts > 0
    if table.size:
        starts = (np.cumsum(counts) - counts)[full]
        ranges[full, 0] = np.minimum.reduceat(table, starts)
        ranges[full, 1] = np.maximum.reduceat(table, starts)
    values = np.concatenate([np.zeros(1, table.dtype), table])
    return _Layout(boxes, codes, values, ranges, axes, True)


def _dense_layout(vevm, axis):
    """The same slices over the whole dense grid, outside voxels coded 0: the dense side of the
    exactness contract (no section, no table, no skipping)."""
    order = TABLE_ORDERS[axis]
    axes = ["xyz".index(ch) for ch in order]
    dense = np.transpose(vevm.to_dense(), axes)
    mask = np.transpose(vevm.evm.to_mask(vevm.shape), axes)
    n = dense.shape
    flat = np.arange(1, dense.size + 1, dtype=np.int64).reshape(n) * mask
    boxes = np.tile(np.array([0, n[1], 0, n[2]], np.int64), (n[0], 1))
    codes = [flat[s] for s in range(n[0])]
    values = np.concatenate([np.zeros(1, dense.dtype), dense.ravel()])
    return _Layout(boxes, codes, values, None, axes, False)


def _transform(points, matrix, offset=None):
    """``points @ matrix (+ offset)`` for ``(..., 3)`` points and a 3x3 matrix, as three scaled
    sums: BLAS would treat these tall, thin products as matrix products and, on a loaded
    machine, its threads spin for tens of milliseconds."""
    m = np.asarray(matrix, dtype=points.dtype)  # float32 points stay float32
    out = points[..., 0:1] * m[0] + points[..., 1:2] * m[1]
    out += points[..., 2:3] * m[2]
    if offset is not None:
        out += offset
    return out


def _gradients(layout, vevm):
    """Per code, the voxel's index-space gradient (:func:`_make_gradients`), kept
    (:func:`_kept`)."""
    return _kept(vevm, layout, "gradients", lambda: _make_gradients(layout, vevm))


def _make_gradients(layout, vevm):
    """Per voxel, in code order: index-space gradients over region voxels, the reference's
    rule (:func:`._gradients.region_gradients`)."""
    mask = vevm.evm.to_mask(vevm.shape)
    pad = tuple(int(n) + 2 for n in vevm.shape)
    dense = np.zeros(pad, np.float32)
    dense[1:-1, 1:-1, 1:-1] = vevm.to_dense()
    region = np.zeros(pad, bool)
    region[1:-1, 1:-1, 1:-1] = mask
    grads = np.empty((3,) + tuple(int(n) for n in vevm.shape), np.float32)
    region_gradients(dense, region, grads)
    chosen = np.transpose(mask, layout.axes) if layout.region_only else None
    out = np.zeros((len(layout.values), 3), np.float32)
    for k in range(3):
        grad = np.transpose(grads[k], layout.axes)
        out[1:, k] = grad[chosen] if layout.region_only else grad.ravel()
    return out


def _light(grads, view, shading):
    """Blinn–Phong headlight along the view direction for index-space gradients ``(..., 3)``:
    the factor on the straight colour and the specular term added to it
    (:func:`._shading.blinn_phong`), both ``(...)`` float32."""
    normals = _transform(grads, view.inv[:3, :3])  # to world: the inverse transpose
    norm = np.sqrt(np.einsum("...i,...i->...", normals, normals))
    has = norm > 0
    cos = np.abs(_transform(normals, view.light[:, None])[..., 0]) / np.where(has, norm, 1.0)
    cos[~has] = 1.0
    return blinn_phong(cos, has, shading)


def _shaded_voxels(layout, vevm, classes, tf, lut, lut_size, view, shading):
    """Premultiplied, step-corrected RGBA (and region weight 1) of every voxel, lit by a
    Blinn–Phong headlight along the view direction: the per-view table of shaded
    pre-classification, ``(5, codes)``, indexed by code (column 0: outside)."""
    lit, glint = _light(_gradients(layout, vevm), view, shading)
    rows = classes.rows
    out = np.take(lut, rows, axis=1)
    rgb = np.take(_straight_rgb(tf, lut_size), rows, axis=1) * lit + glint
    np.minimum(rgb, 1.0, out=rgb)
    out[:3] = rgb * out[3]
    return out


def _straight_rgb(tf, lut_size):
    """Straight colours of the table rows, ``(3, lut_size + 1)``, column 0 (outside) black."""
    straight = np.zeros((3, lut_size + 1), np.float32)
    straight[:, 1:] = tf.straight_table(n=lut_size)[:, :3].T
    return straight


def _post_table(layout, vevm, with_gradients):
    """Per code, what post-classification interpolates, channels first: the density, the
    index-space gradient (``with_gradients``) and the region weight (0 for code 0). Kept
    (:func:`_kept`)."""

    def make():
        rows = [layout.values32[None]]
        if with_gradients:
            rows.append(_gradients(layout, vevm).T)
        weight = np.ones((1, len(layout.values)), np.float32)
        weight[0, 0] = 0.0
        return np.ascontiguousarray(np.concatenate(rows + [weight]), dtype=np.float32)

    return _kept(vevm, layout, "post_shaded" if with_gradients else "post", make)


class _Classes:
    """Per transfer function and table size: the table row of every voxel (0 outside) and per
    slice the box of voxels the function does not make transparent."""

    def __init__(self, layout, tf, lut_size):
        q = tf.quantize(layout.values[1:], n=lut_size)
        self.rows = np.zeros(len(layout.values), np.int32)
        self.rows[1:] = q + 1
        visible = np.zeros(len(layout.values), bool)
        visible[1:] = tf.straight_table(n=lut_size)[q, 3] > 0
        self.tight = layout.boxes.copy()
        if layout.ranges is None:  # dense: every voxel is worked on
            return
        clear = tf.transparent_between(layout.ranges[:, 0], layout.ranges[:, 1])
        for s, (a0, a1, b0, b1) in enumerate(layout.boxes):
            if a1 <= a0 or b1 <= b0 or clear[s]:
                self.tight[s] = (0, 0, 0, 0)
                continue
            seen = visible[layout.codes[s]]
            rows = np.flatnonzero(seen.any(axis=1))
            cols = np.flatnonzero(seen.any(axis=0))
            if rows.size == 0:
                self.tight[s] = (0, 0, 0, 0)
            else:
                self.tight[s] = (a0 + rows[0], a0 + rows[-1] + 1, b0 + cols[0], b0 + cols[-1] + 1)


def _classes(vevm, layout, tf, lut_size):
    """The :class:`_Classes` of ``tf`` and ``lut_size`` for ``layout``, kept (:func:`_kept`)."""
    return _kept(vevm, layout, "classes", lambda: _Classes(layout, tf, lut_size), tf, lut_size)


def _slice_rows(vevm, layout, classes, tf, lut_size):
    """Per slice, over its box (as :attr:`_Layout.codes`), the table row of each voxel
    (int16: ``lut_size < 32767``) for ``classes`` (of ``tf`` and ``lut_size``): unshaded
    pre-classification gathers colours with one lookup per voxel instead of two. Kept
    (:func:`_kept`)."""
    return _kept(vevm, layout, "slice_rows",
                 lambda: [classes.rows[codes].astype(np.int16) for codes in layout.codes],
                 tf, lut_size)


def _reads_slice_rows(constant, per_voxel, shaded, post):
    """Whether a view reads :func:`_slice_rows`: the default path, slices only translated
    (``constant``: orthographic, ``intermediate_scale`` 1), one sample per slice, unshaded
    pre-classification. One rule for the render and :func:`tables_to_build`."""
    return constant and per_voxel == 1 and not shaded and not post


def _window(codes, box, a0, a1, b0, b1):
    """Codes over ``[a0, a1) x [b0, b1)`` (slice coordinates), 0 outside the slice's box."""
    out = np.zeros((a1 - a0, b1 - b0), codes.dtype)
    ia0, ia1 = max(a0, box[0]), min(a1, box[1])
    ib0, ib1 = max(b0, box[2]), min(b1, box[3])
    if ia0 < ia1 and ib0 < ib1:
        out[ia0 - a0:ia1 - a0, ib0 - b0:ib1 - b0] = codes[ia0 - box[0]:ia1 - box[0],
                                                          ib0 - box[2]:ib1 - box[2]]
    return out


class _View:
    """The factorization of one view: principal axis, slice order, per-slice maps from the
    intermediate image to slice coordinates, the warp and the per-ray sample spacing."""

    def __init__(self, vevm, camera, g, layout, scale, axis, step, rays):
        self.scale = scale  # intermediate pixels per voxel along each in-slice axis
        self.inv = np.linalg.inv(g)
        rot = self.inv[:3, :3].T
        if not camera.is_ortho:
            # Index space; perspective rays share one origin.
            origins, dirs = camera.rays()
            d = _transform(dirs.reshape(-1, 3), rot)
            o = np.broadcast_to(_transform(origins.reshape(-1, 3)[:1], rot, self.inv[:3, 3]),
                                d.shape)
        self.axis = axis
        self.light = self.view_direction(vevm, camera, g)
        a, b = ("xyz".index(ch) for ch in TABLE_ORDERS[axis][1:])
        self.abc = (a, b, axis)
        self.ortho = camera.is_ortho
        self.constant = self.ortho and scale == 1.0  # slices are only translated
        nc = vevm.shape[axis]
        if self.ortho:
            forward = -camera.matrix_world[:3, 2] @ rot  # the rays' index-space direction
            self.step = 1 if forward[axis] > 0 else -1
            self.c_ref = 0.0
            self.slope = forward / forward[axis]  # index-space ray per unit step along c
            self.pq, seen = self.ortho_plane(camera, rot)
            ok = np.ones(len(self.pq), bool)
        else:
            self.eye = self.inv[:3, :3] @ camera.position + self.inv[:3, 3]
            self.step = step
            self.c_ref = nc - 0.5 if self.step > 0 else -0.5
            ok = d[:, axis] * self.step > 1e-12
            if rays is not None:
                ok &= rays
            # Rays that never cross the slices (parallel, or going away) get t = 0, so that no
            # inf or NaN is made for them; they are masked out below.
            t = np.where(ok, (self.c_ref - o[:, axis]) / np.where(ok, d[:, axis], 1.0), 0.0)
            pq = np.stack([o[:, a] + t * d[:, a], o[:, b] + t * d[:, b]], axis=1) * scale
            pq[~ok] = 0.0
            self.pq = pq  # (H*W, 2) intermediate coordinates before the origin shift
            if ok.any():
                seen = pq[ok]
                seen = (seen[:, 0].min(), seen[:, 0].max(), seen[:, 1].min(), seen[:, 1].max())
        self.rays_ok = ok
        lo_box = layout.boxes
        used = np.flatnonzero((lo_box[:, 1] > lo_box[:, 0]) & (lo_box[:, 3] > lo_box[:, 2]))
        if not self.ortho:
            lam = (used - self.eye[axis]) / (self.c_ref - self.eye[axis])
            used = used[lam > 0]
        # Slices front to back.
        self.slices = used if self.step > 0 else used[::-1]
        self.empty = self.slices.size == 0 or not ok.any()
        if self.empty:
            return
        # Extent: the region's footprint over all slices, within the image's footprint.
        alpha, beta_a, beta_b = self.slice_maps(self.slices.astype(np.float64))
        bx = lo_box[self.slices]
        foot = [((bx[:, 0] - 1 - beta_a) / alpha).min(), ((bx[:, 1] - beta_a) / alpha).max(),
                ((bx[:, 2] - 1 - beta_b) / alpha).min(), ((bx[:, 3] - beta_b) / alpha).max()]
        img = [seen[0] - 1, seen[1] + 2, seen[2] - 1, seen[3] + 2]
        self.origin, self.size = self.extent(foot, img)
        if self.size[0] * self.size[1] == 0:
            self.empty = True
            return
        if self.size[0] * self.size[1] > _MAX_INTERMEDIATE:
            raise VolumeEVMError(
                f"camera: the intermediate image would have {self.size[0]}x{self.size[1]} "
                "pixels (a perspective camera too close to the volume for shear-warp)")
        # Axial depth as an affine function of index-space points.
        basis = np.vstack([np.zeros(3), np.eye(3)])
        dep = camera.axial_depth(basis @ g[:3, :3].T + g[:3, 3])
        self.depth0, self.depth_grad = dep[0], dep[1:] - dep[0]
        # Physical length (mm) per step of one slice along each intermediate pixel's ray.
        sp = np.asarray(vevm.spacing, dtype=np.float64)
        if self.ortho:
            self.delta = float(np.linalg.norm(sp * self.slope))
            self.ratio = None
        else:
            p = self.origin[0] + np.arange(self.size[0])
            q = self.origin[1] + np.arange(self.size[1])
            delta = self.ray_step(p[:, None], q[None, :], sp)
            # The table's step: the central ray's nearest intermediate pixel (the centre of the
            # rays' footprint if the central ray is not in this pass).
            centre = np.array(camera.shape) // 2
            k = centre[0] * camera.shape[1] + centre[1]
            pc = self.pq[k] if ok[k] else np.array([seen[0] + seen[1], seen[2] + seen[3]]) / 2
            pc = np.floor(pc + 0.5)
            self.delta = float(self.ray_step(pc[0], pc[1], sp))
            self.ratio = (delta / self.delta).astype(np.float32)

    def ray_step(self, p, q, spacing):
        """Perspective: mm between consecutive slices along the ray through the absolute
        intermediate point ``(p, q)`` (arrays broadcast), for voxel ``spacing``."""
        a, b, c = self.abc
        span = self.c_ref - self.eye[c]
        va = ((p / self.scale - self.eye[a]) / span * spacing[a]) ** 2
        vb = ((q / self.scale - self.eye[b]) / span * spacing[b]) ** 2
        return np.sqrt(va + vb + spacing[c] ** 2)

    @staticmethod
    def extent(foot, img):
        """The intermediate image over the region's footprint ``foot`` within the image's
        footprint ``img`` (both ``(p min, p max, q min, q max)``, absolute intermediate
        coordinates): its origin, the absolute point of array index ``(0, 0)``, and its size.

        The origin is an integer applied to indices only: the samples' fractions, the warp's
        taps and the depths are computed in absolute coordinates, so that they do not depend
        on where the image starts (the region's path and the dense path start it differently).
        """
        p_lo, p_hi = math.floor(max(foot[0], img[0])), math.ceil(min(foot[1], img[1]))
        q_lo, q_hi = math.floor(max(foot[2], img[2])), math.ceil(min(foot[3], img[3]))
        return (np.array([p_lo, q_lo], np.int64),
                (max(p_hi - p_lo + 1, 0), max(q_hi - q_lo + 1, 0)))

    def ortho_plane(self, camera, rot):
        """Orthographic: the intermediate coordinates of every pixel's ray, ``(H*W, 2)``, and
        their ``(p min, p max, q min, q max)``.

        The rays of :meth:`Camera.rays` start at ``m + x_j r + y_i u`` (pixel column ``j``,
        row ``i``) and share one direction, so each coordinate is a sum of a per-row and a
        per-column term: two outer sums instead of transforming every ray (same values up to
        rounding).
        """
        a, b, c = self.abc
        h, w = camera.shape
        xmin, xmax, ymin, ymax = camera.viewplane
        x = xmin + (np.arange(w) + 0.5) * ((xmax - xmin) / w)
        y = ymax - (np.arange(h) + 0.5) * ((ymax - ymin) / h)
        m = camera.matrix_world
        origin = m[:3, 3] @ rot + self.inv[:3, 3]
        right, up = m[:3, 0] @ rot, m[:3, 1] @ rot
        pq = np.empty((h, w, 2))
        extent = []
        for k, e in enumerate((a, b)):
            # Along the ray to c = c_ref: coordinate e moves by slope[e] per unit of c.
            along = np.eye(3)[e] - self.slope[e] * np.eye(3)[c]
            base = (origin @ along + self.slope[e] * self.c_ref) * self.scale
            rows = base + y * ((up @ along) * self.scale)
            cols = x * ((right @ along) * self.scale)
            np.add(rows[:, None], cols[None, :], out=pq[..., k])
            extent += [rows.min() + cols.min(), rows.max() + cols.max()]
        return pq.reshape(-1, 2), extent

    @staticmethod
    def principal_axis(vevm, camera, g):
        """The grid axis most parallel (in world space) to the viewing direction.

        Orthographic: to the camera's forward vector. Perspective, eye outside the region's
        bounding box: to the eye-to-centre vector, among the axes along which the eye is
        outside the box (so that every ray crosses the slices in one direction); eye inside
        the box: to the forward vector (:func:`_passes` then splits the rays instead).
        """
        cols = g[:3, :3]
        forward = np.asarray(camera.forward, dtype=np.float64)
        allowed = np.ones(3, bool)
        view = forward
        if not camera.is_ortho:
            lo, hi = (np.array(b, dtype=np.float64) - 0.5 for b in vevm.evm.bounds())
            eye = np.linalg.solve(cols, camera.position - g[:3, 3])
            outside = (eye < lo) | (eye > hi)
            if outside.any():
                allowed = outside
                view = cols @ ((lo + hi) / 2.0) + g[:3, 3] - camera.position
        cos = np.abs(view @ cols) / np.linalg.norm(cols, axis=0)
        return int(np.argmax(np.where(allowed, cos, -1.0)))

    @staticmethod
    def view_direction(vevm, camera, g):
        """Unit world direction of the headlight: the forward vector (orthographic) or from the
        eye to the region's centre (perspective)."""
        view = np.asarray(camera.forward, dtype=np.float64)
        if not camera.is_ortho:
            lo, hi = (np.array(b, dtype=np.float64) - 0.5 for b in vevm.evm.bounds())
            toward = g[:3, :3] @ ((lo + hi) / 2.0) + g[:3, 3] - camera.position
            if np.any(toward):
                view = toward
        return view / np.linalg.norm(view)

    def slice_maps(self, s):
        """``(α, β_a, β_b)``: slice coordinates ``x = α p + β_a``, ``y = α q + β_b`` of the ray
        through intermediate point ``(p, q)`` (before the origin shift) at ``c = s``; the
        intermediate point is ``scale`` times the reference plane's index coordinates."""
        a, b, c = self.abc
        s = np.asarray(s, dtype=np.float64)
        if self.ortho:
            run = s - self.c_ref
            return np.full_like(s, 1.0 / self.scale), run * self.slope[a], run * self.slope[b]
        lam = (s - self.eye[c]) / (self.c_ref - self.eye[c])
        return lam / self.scale, self.eye[a] * (1 - lam), self.eye[b] * (1 - lam)

    def depth_coefficients(self, s):
        """Axial depth ``k0 + kp·p + kq·q`` of the sample of slice ``s`` at the absolute
        intermediate point ``(p, q)`` (array index plus origin), as ``(k0, kp, kq)``."""
        a, b, c = self.abc
        alpha, beta_a, beta_b = self.slice_maps(s)
        ga, gb, gc = self.depth_grad[a], self.depth_grad[b], self.depth_grad[c]
        k0 = self.depth0 + ga * beta_a + gb * beta_b + gc * np.asarray(s, dtype=np.float64)
        return k0, ga * alpha, gb * alpha

    def depth_limit(self, camera, g, depth_in):
        """``min(clip_end, depth_in)`` at every intermediate pixel (nearest final pixel)."""
        a, b, c = self.abc
        h, w = camera.shape
        p = (self.origin[0] + np.arange(self.size[0])) / self.scale
        q = (self.origin[1] + np.arange(self.size[1])) / self.scale
        pts = np.empty(self.size + (3,))
        pts[..., a] = p[:, None]
        pts[..., b] = q[None, :]
        pts[..., c] = self.c_ref
        uv, _ = camera.project(_transform(pts, g[:3, :3].T, g[:3, 3]))
        with np.errstate(invalid="ignore"):
            col = np.floor(uv[..., 0])
            row = np.floor(uv[..., 1])
            inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        limit = np.full(self.size, camera.clip_end)
        hit = depth_in[row[inside].astype(np.int64), col[inside].astype(np.int64)]
        limit[inside] = np.minimum(hit, camera.clip_end)
        return limit.astype(np.float32)


def render_shear_warp(vevm, camera, tf, grid_to_world, *, mode="over", depth_in=None,
                      skip_empty=True, termination=0.99, shading=None, intermediate_scale=1.0,
                      slices_per_voxel=1, classification="pre", lut_size=4096, xray_scale=1.0,
                      xray_offset=0.0):
    """Render a VolumeEVM by shear-warp (module docstring: factorization, policy, depth).

    Parameters
    ----------
    vevm : VolumeEVM
    camera : Camera
        Orthographic or perspective (Blender's conventions, :mod:`._camera`).
    tf : TransferFunction
        Classification; unused (may be None) for ``mode="xray"``.
    grid_to_world : (4, 4) ndarray
        Voxel-centre index space to world (Blender units), :func:`volumeevm_addon.grid_to_world`.
    mode : {"over", "under", "xray", "mip"}
        As in :func:`._reference.render_reference`.
    depth_in : (H, W) ndarray, optional
        Axial depth (Blender units) of scene geometry; samples at or beyond it are dropped.
        ``1e10`` or ``inf`` = nothing; NaN raises.
    skip_empty : bool
        True (default): work only on each slice's section box (and, for ``"over"``/``"under"``,
        the box of its voxels the transfer function does not make transparent) from the EVM
        and the densities table. False: the same algorithm over every voxel of the dense grid,
        with the region as a mask (the dense side of the exactness contract; slower).
    termination : float
        Early ray termination for ``"over"``: pixels whose opacity reached it stop receiving
        slices (error at most ``1 - termination`` per pixel); 1.0 composites every slice.
    shading : None, True, dict or Shading
        Gradient shading for ``"over"`` and ``"under"`` (:class:`._shading.Shading`:
        Blinn–Phong headlight; ignored by ``"xray"`` and ``"mip"``), applied per voxel before
        interpolation (pre-classification): per-voxel gradients (reference's central
        differences) are computed once per principal axis and cached; each view lights them
        along one direction (perspective: eye to the region's centre).
    slices_per_voxel : {1, 2, 3, 4, 8}
        Samples along each ray per voxel slice (module docstring, 4): 1 is VolPack's one sample
        per slice; more interpolate between slices (trilinear): each voxel slice is classified
        once and every sample blends two of them, then resamples once (CT head 512²: 2 slices
        cost 1.6 times one).
    classification : {"pre", "post"}
        ``"pre"``: classify (and light) voxels, then interpolate colours (VolPack); ``"post"``:
        interpolate densities (and gradients), then classify and light each sample, as the
        reference does (sharper boundaries, narrow transfer-function features kept). Only
        ``"over"`` and ``"under"``; ``"xray"`` and ``"mip"`` always interpolate densities.
    intermediate_scale : float
        Intermediate pixels per voxel along each in-slice axis (VolPack: 1). Above 1 the slices
        are resampled more finely (bilinear, per-row and per-column weights), which keeps
        detail when the camera zooms in beyond one image pixel per voxel; below 1 gives a
        coarse preview. Cost grows with its square; one sample per slice along every ray
        either way.
    lut_size : int
        Rows of the classification table over the transfer function's control-point range.
    xray_scale, xray_offset : float
        X-ray attenuation per mm per data unit, and the density of zero attenuation.

    Returns
    -------
    rgba : (H, W, 4) ndarray of np.float32
        Premultiplied RGBA, row 0 at the top of the image.
    depth : (H, W) ndarray of np.float32
        Axial depth in Blender units of the first visible sample, ``1e10`` where none.

    Raises
    ------
    VolumeEVMError
        For a bad mode, camera, transfer function, matrix, ``depth_in`` or option, and for a
        perspective camera so close that the intermediate image would be unreasonably large.

    See Also
    --------
    volumeevm_addon.rendering._reference.render_reference : the accuracy oracle (same conventions).

    Examples
    --------
    A 2x2x2 mm block of 1 mm voxels seen from above; opacity 0.5 per mm over a 2 mm chord:

    >>> from volumeevm_addon import Camera, TransferFunction, VolumeEVM
    >>> BU = 0.001  # Blender units per mm
    >>> cam_matrix = np.eye(4)
    >>> cam_matrix[:3, 3] = (0.5 * BU, 0.5 * BU, 1.0)
    >>> cam = Camera.orthographic(cam_matrix, 2 * BU, resolution_x=2, resolution_y=2)
    >>> tf = TransferFunction([(0, 1, 1, 1, 0.5), (1, 1, 1, 1, 0.5)])
    >>> vevm = VolumeEVM.from_array(np.zeros((2, 2, 2)), 0.0)
    >>> rgba, depth = render_shear_warp(vevm, cam, tf, np.diag([BU, BU, BU, 1.0]))
    >>> rgba[..., 3].astype(float).round(6).tolist(), depth.astype(float).round(6).tolist()
    ([[0.75, 0.75], [0.75, 0.75]], [[0.9985, 0.9985], [0.9985, 0.9985]])
    """
    g, depth_in, compositing = checked_view(vevm, camera, tf, grid_to_world, mode, depth_in,
                                            termination, xray_scale, xray_offset)
    if int(lut_size) != lut_size or not 2 <= lut_size < 32767:
        raise VolumeEVMError(f"lut_size: an integer in [2, 32767), got {lut_size!r}")
    try:
        intermediate_scale = float(intermediate_scale)
    except (TypeError, ValueError):
        intermediate_scale = np.nan
    if not 0.1 <= intermediate_scale <= 8.0:
        raise VolumeEVMError(
            f"intermediate_scale: a number in [0.1, 8], got {intermediate_scale!r}")
    if slices_per_voxel not in SLICES_PER_VOXEL:
        raise VolumeEVMError(
            f"slices_per_voxel: one of {SLICES_PER_VOXEL}, got {slices_per_voxel!r}")
    if classification not in CLASSIFICATIONS:
        raise VolumeEVMError(
            f"classification: one of {CLASSIFICATIONS}, got {classification!r}")
    shading = checked_shading(shading) if mode in ("over", "under") else None
    sampling = _Sampling(int(slices_per_voxel), classification, int(lut_size), shading)
    h, w = camera.shape
    rgba_out = np.zeros((h, w, 4), np.float32)
    depth_out = np.full((h, w), BACKGROUND_DEPTH, np.float32)
    if vevm.evm.is_empty():
        return rgba_out, depth_out
    for axis, step, rays in _passes(vevm, camera, g):
        layout = _region_layout(vevm, axis) if skip_empty else _dense_layout(vevm, axis)
        view = _View(vevm, camera, g, layout, intermediate_scale, axis, step, rays)
        if view.empty:
            continue
        image, rank, front = _composite(vevm, view, layout, tf, compositing, sampling,
                                        _Clip.of_view(view, camera, g, depth_in))
        _warp(view, camera, image, rank, front, rgba_out, depth_out)
    return rgba_out, depth_out


def tables_to_build(vevm, camera, tf, grid_to_world, options):
    """How many principal axes the render would build slice tables for: the axes of its passes
    (:func:`_passes`) whose layout, or what this render reads beside it (the transfer
    function's classes and, on the default path, its rows per slice; or the
    post-classification table; the gradients with shading), is not in ``vevm.cache``
    (:func:`_key`); every one with ``skip_empty=False`` (the dense layout is made per render).
    Changes nothing: it only looks at the cache.

    ``options`` are the renderer's keywords (``mode`` included).
    """
    if vevm.evm.is_empty():
        return 0
    axes = {axis for axis, _, _ in _passes(vevm, camera, np.asarray(grid_to_world, float))}
    if not options.get("skip_empty", True):
        return len(axes)
    mode = options.get("mode", "over")
    shaded = mode in ("over", "under") and options.get("shading") not in (None, False)
    post = mode in ("xray", "mip") or options.get("classification", "pre") == "post"
    lut_size = options.get("lut_size", 4096)
    constant = camera.is_ortho and float(options.get("intermediate_scale", 1.0)) == 1.0
    if post:
        parts = ("layout", "post_shaded" if shaded else "post")
    else:
        parts = ("layout", "classes") + (("gradients",) if shaded else ()) + (
            ("slice_rows",) if _reads_slice_rows(constant, options.get("slices_per_voxel", 1),
                                                 shaded, post) else ())
    return sum(not all(_key(axis, part, tf, lut_size) in vevm.cache for part in parts)
               for axis in axes)


def _passes(vevm, camera, g):
    """``(principal axis, step, rays)`` of each shear-warp pass; ``step`` (perspective) is the
    front-to-back direction along the axis, ``rays`` (flat bool mask or None: all) the pixels
    the pass renders.

    One pass, except for a perspective eye inside the region's bounding box: there no axis has
    the whole region on one side of the eye, so the rays are split by the grid axis and sign
    most parallel to each (up to six pyramids around the eye, as Lacroute suggests); each pass
    composites the slices beyond the eye for its rays. The rays are disjoint, so the passes
    fill disjoint pixels.
    """
    axis = _View.principal_axis(vevm, camera, g)
    if camera.is_ortho:
        return [(axis, None, None)]
    cols = g[:3, :3]
    lo, hi = (np.array(b, dtype=np.float64) - 0.5 for b in vevm.evm.bounds())
    eye = np.linalg.solve(cols, camera.position - g[:3, 3])
    if eye[axis] < lo[axis] or eye[axis] > hi[axis]:
        return [(axis, 1 if eye[axis] < lo[axis] else -1, None)]
    _, dirs = camera.rays()
    dirs = dirs.reshape(-1, 3)
    cos = np.abs(_transform(dirs, cols)) / np.linalg.norm(cols, axis=0)
    dominant = np.argmax(cos, axis=1)
    index_dirs = _transform(dirs, np.linalg.inv(cols).T)
    ahead = index_dirs[np.arange(len(dirs)), dominant] > 0
    key = 2 * dominant + ahead
    return [(int(k // 2), 1 if k % 2 else -1, key == k) for k in np.unique(key)]


def _samples(slices, step, per_voxel):
    """Front-to-back samples of the slice loop: ``(slice, offset)`` per sample, the sample at
    ``c = slice + offset``. Each voxel slice owns the slab ``[s - 1/2, s + 1/2)`` (its cells)
    and takes ``per_voxel`` samples at the centres of equal parts of it; one sample per slice
    is the slice plane itself."""
    offsets = (np.arange(per_voxel) + 0.5) / per_voxel - 0.5
    if step < 0:
        offsets = offsets[::-1]
    owner = np.repeat(slices, per_voxel)
    return owner, np.tile(offsets, len(slices))


def _slab_box(boxes, full, s, s2):
    """Box of slice ``s`` a sample between slices ``s`` and ``s2`` (None: none) may take
    something from: the union of their ``boxes`` (what may be visible) within slice ``s``'s
    region box ``full`` (a sample whose nearest voxel is outside is transparent)."""
    t = boxes[s]
    if s2 is None or boxes[s2, 1] <= boxes[s2, 0] or boxes[s2, 3] <= boxes[s2, 2]:
        return t
    u = boxes[s2]
    if t[1] > t[0] and t[3] > t[2]:
        u = (min(t[0], u[0]), max(t[1], u[1]), min(t[2], u[2]), max(t[3], u[3]))
    f = full[s]
    return (max(u[0], f[0]), min(u[1], f[1]), max(u[2], f[2]), min(u[3], f[3]))


@dataclass(frozen=True, slots=True, eq=False)
class _Sampling:
    """How a render samples and classifies (checked): ``per_voxel`` samples per voxel slice,
    ``classification`` (:data:`CLASSIFICATIONS`), ``lut_size`` rows of the classification
    table, ``shading`` (None: unshaded)."""

    per_voxel: int
    classification: str
    lut_size: int
    shading: Shading


@dataclass(frozen=True, slots=True, eq=False)
class _Tables:
    """What the samples of a view read (:func:`_tables`).

    ``post``: densities are interpolated, then classified (post-classification, X-ray, MIP);
    ``boxes``: per slice, the box of its voxels worth sampling; ``ranges``: per slice, the
    density range, where transparent slabs may be skipped (post-classified over/under), else
    None; ``lut``: over/under, the classification table, channels first (R, G, B, A, region
    weight; row 0 for outside voxels: every plane of a slice's samples is contiguous), else
    None; ``straight``: shaded post-classification, the table's straight colours
    (:func:`_straight_rgb`); ``gathered``: the slices a sample interpolates
    (:class:`_Gathered`); ``slice_rows`` and ``pixels``: the default path (orthographic, one
    sample per translated slice, unshaded pre-classification: colours gathered as 16-byte RGBA
    pixels of the table, by each voxel's row), else None.
    """

    post: bool
    boxes: np.ndarray
    ranges: np.ndarray
    lut: np.ndarray
    straight: np.ndarray
    gathered: object
    slice_rows: list
    pixels: np.ndarray


def _tables(vevm, view, layout, tf, mode, sampling, delta):
    """The :class:`_Tables` of a view whose samples are ``delta`` mm apart."""
    shading, lut_size = sampling.shading, sampling.lut_size
    post = mode in ("xray", "mip") or sampling.classification == "post"
    table = voxels = classes = lut = straight = ranges = slice_rows = pixels = None
    if post:
        table = _post_table(layout, vevm, shading is not None)
        boxes = layout.boxes
        ranges = layout.ranges if mode in ("over", "under") else None
    else:
        classes = _classes(vevm, layout, tf, lut_size)
        boxes = classes.tight
    if mode in ("over", "under"):
        lut = np.zeros((5, lut_size + 1), np.float32)
        lut[:4, 1:] = tf.table(n=lut_size, step_mm=delta).T
        lut[4, 1:] = 1.0
        if shading is not None and post:
            straight = _straight_rgb(tf, lut_size)
        elif shading is not None:
            voxels = _shaded_voxels(layout, vevm, classes, tf, lut, lut_size, view, shading)
    if _reads_slice_rows(view.constant, sampling.per_voxel, shading is not None, post):
        slice_rows = _slice_rows(vevm, layout, classes, tf, lut_size)
        pixels = np.ascontiguousarray(lut[:4].T).view(np.complex128).ravel()
    return _Tables(post, boxes, ranges, lut, straight,
                   _Gathered(layout, classes, table, voxels, lut, boxes), slice_rows, pixels)


def _composite(vevm, view, layout, tf, compositing, sampling, clip):
    """The slice loop: returns the intermediate premultiplied RGBA, the front-to-back rank of
    the depth sample per pixel (``_NEVER`` where none) and, per rank, the slice coordinate of
    the front end of its samples."""
    mode = compositing.mode
    hi, wi = view.size
    per_voxel = sampling.per_voxel
    owner, offset = _samples(view.slices, view.step, per_voxel)
    centre = owner + offset
    ranks = np.arange(len(owner))
    if mode == "under":
        owner, offset, ranks = owner[::-1], offset[::-1], ranks[::-1]
    # Per-sample scalars as Python floats: the loop reads them one at a time.
    alpha_s, beta_a, beta_b = (v.tolist() for v in view.slice_maps(owner + offset))
    k0, kp, kq = (v.tolist() for v in view.depth_coefficients(owner + offset))
    delta = view.delta / per_voxel
    units = None if tf is None else delta / tf.unit_length_mm  # in the function's unit lengths
    tables = _tables(vevm, view, layout, tf, mode, sampling, delta)
    n_slices = len(layout.boxes)
    rank_map = np.full((hi, wi), _NEVER, np.int32)
    if mode in ("over", "under"):
        image = np.zeros((4, hi, wi), np.float32)
    else:
        image = np.zeros((hi, wi), np.float32)
        if mode == "mip":
            image.fill(_UNSEEN)
    active = [0, hi, 0, wi]
    for n, s in enumerate(owner):
        t = offset[n]
        s2 = s + (1 if t > 0 else -1) if t != 0 else None
        if s2 is not None and not 0 <= s2 < n_slices:
            s2 = None
        if tables.ranges is not None:
            pair = [s] if s2 is None else [s, s2]
            if tf.transparent_between(tables.ranges[pair, 0].min(),
                                      tables.ranges[pair, 1].max()):
                continue
        box = _slab_box(tables.boxes, layout.boxes, s, s2)
        if box[1] <= box[0] or box[3] <= box[2]:
            continue
        if tables.pixels is not None:
            got = _shifted(tables, layout, view, s, box, active, beta_a[n], beta_b[n])
            if got is None:
                continue
            out, inside, area = got
            clip.apply(inside, k0[n], kp[n], kq[n], area, view.origin)
            # One per-pixel factor: the clamp policy's renormalisation, the depth limits and,
            # front to back, the transparency left in front (zero where terminated).
            factor = _renormaliser(out, inside)
            c = out[:4]
            hit = _depth.visible(out[3] * factor, units)  # the sample's own opacity
        else:
            got = _resampled(tables.gathered, view, s, s2, t, box, active,
                             (alpha_s[n], beta_a[n], beta_b[n]))
            if got is None:
                continue
            sample, inside, area = got
            clipped = clip.apply(inside, k0[n], kp[n], kq[n], area, view.origin)
            if mode in ("xray", "mip"):
                _accumulate(image, rank_map, sample[0], inside, area, ranks[n], view,
                            compositing, delta)
                continue
            c = _post_classify(sample, inside, tables, tf, sampling, view) if tables.post \
                else sample
            if clipped or tables.post:  # (pre: _normalise already made outside samples zero)
                c *= inside
            # Before the correction to each ray's step: the threshold scales with the step too.
            hit = _depth.visible(c[3], units)
            if view.ratio is not None:
                _correct(c, view.ratio[area])
            factor = None
        _blend(image, rank_map, c, factor, hit, area, ranks[n], compositing)
        if mode == "over" and (n + 1) % _ERT_EVERY == 0:
            active = _active_box(image, compositing.termination, active)
            if active is None:
                break
    if mode in ("xray", "mip"):
        image = _finished(image, rank_map, mode, tf)
    return image, rank_map, centre - 0.5 * view.step / per_voxel


def _shifted(tables, layout, view, s, box, active, beta_a, beta_b):
    """The default path's sample of slice ``s``, translated by ``(beta_a, beta_b)``, over
    ``box`` within the ``active`` part of the intermediate image: ``(interpolated RGBA and
    region weight, inside, area)``, or None where it misses."""
    rows = _shift(box[0], box[1], beta_a, int(view.origin[0]), active[0], active[1])
    cols = _shift(box[2], box[3], beta_b, int(view.origin[1]), active[2], active[3])
    if rows is None or cols is None:
        return None
    (p0, p1, i0, f), (q0, q1, j0, g) = rows, cols
    out, inside = _translated(tables.pixels, tables.slice_rows[s], layout.boxes[s],
                              (i0, i0 + p1 - p0 + 1, j0, j0 + q1 - q0 + 1), f, g)
    return out, inside, (slice(p0, p1), slice(q0, q1))


def _resampled(gathered, view, s, s2, t, box, active, maps):
    """The sample at ``c = s + t`` (``s2``: the other slice it blends, or None) over ``box``
    within the ``active`` part of the intermediate image, with the slice map ``maps = (α,
    β_a, β_b)``: ``(normalised channels, inside, area)``, or None where it misses."""
    alpha, beta_a, beta_b = maps
    rows = _span(box[0], box[1], alpha, beta_a, int(view.origin[0]), active[0], active[1])
    cols = _span(box[2], box[3], alpha, beta_b, int(view.origin[1]), active[2], active[3])
    if rows is None or cols is None:
        return None
    p0, p1, ia, fa = rows
    q0, q1, ib, fb = cols
    window = (ia[0], ia[-1] + 2, ib[0], ib[-1] + 2)
    if s2 is None:
        src = _classified(*gathered.args, s, window)
        region = src[-1] > 0
    else:
        # Bilinear resampling is linear: blend the two slices voxel by voxel, then resample
        # once (trilinear). Each voxel slice feeds up to 2k samples: gathered once.
        mine, other = gathered.get(s, window), gathered.get(s2, window)
        region = mine[-1] > 0
        src = mine * np.float32(1.0 - abs(t))
        src += other * np.float32(abs(t))
    # (The clamp policy looks at the sample's nearest voxel, which is in slice s.)
    out, inside = _bilinear(src, region, ia - ia[0], fa, ib - ib[0], fb, view.constant)
    return _normalise(out, inside), inside, (slice(p0, p1), slice(q0, q1))


def _accumulate(image, rank_map, value, inside, area, rank, view, compositing, delta):
    """X-ray: add the optical depth of samples of density ``value`` (``delta`` mm apart) to
    ``image`` over ``area``; MIP: keep the maximum. The pixels whose depth sample this is take
    ``rank``."""
    if compositing.mode == "xray":
        np.subtract(value, np.float32(compositing.xray_offset), out=value)
        np.maximum(value, 0, out=value)
        value *= np.float32(compositing.xray_scale * delta)
        value *= inside
        # (The ray's own step is ratio times the table's: so are μΔ and the threshold.)
        hit = _depth.attenuates(value, delta)
        hit &= rank_map[area] == _NEVER
        if view.ratio is not None:
            value *= view.ratio[area]
        image[area] += value
    else:
        # Ties (within float32 rounding of the renormalised weights) keep the first,
        # frontmost sample, as the reference does.
        current = image[area]
        bar = current + np.float32(_TIE) * np.maximum(np.abs(current), 1)
        hit = inside & (value > bar)
        np.copyto(image[area], value, where=hit)
    np.copyto(rank_map[area], rank, where=hit)


def _blend(image, rank_map, c, factor, hit, area, rank, compositing):
    """Over or under: composite premultiplied samples ``c`` (4, ...), times ``factor`` if
    given, into ``image`` over ``area``; visible samples (``hit``) give their pixels ``rank``
    (over: the first, under: the last met, which is the frontmost)."""
    target = image[(slice(None),) + area]
    ranks = rank_map[area]
    if compositing.mode == "over":
        trans = 1.0 - target[3]
        if compositing.termination < 1.0:  # terminated rays take nothing more
            np.putmask(trans, target[3] >= compositing.termination, 0.0)
        if factor is not None:
            factor *= trans
            trans = factor
        c *= trans
        target += c
        np.copyto(ranks, rank, where=hit & (ranks == _NEVER))
    else:
        if factor is not None:
            c *= factor
        target *= 1.0 - c[3]
        target += c
        np.copyto(ranks, rank, where=hit)


def _finished(image, rank_map, mode, tf):
    """X-ray's optical depths or MIP's maxima ``(hi, wi)`` as premultiplied RGBA
    ``(4, hi, wi)`` (:func:`._modes.finish_mode`); pixels whose maximum is not visible lose
    their depth sample."""
    hi, wi = image.shape
    acc = np.zeros((hi * wi, 4), np.float32)
    vmax = None
    if mode == "xray":
        acc[:, 0] = image.ravel()
    else:
        vmax = np.where(image > _UNSEEN, image, -np.inf).ravel()
    visible = finish_mode(acc, vmax, mode, tf)
    if visible is not None:
        rank_map[~visible.reshape(hi, wi)] = _NEVER
    return acc.reshape(hi, wi, 4).transpose(2, 0, 1)


def _post_classify(sample, inside, tables, tf, sampling, view):
    """Premultiplied, step-corrected RGBA (4, ...) of interpolated densities ``sample[0]``
    (and, with shading, gradients ``sample[1:4]``) through the table ``tables.lut``."""
    rows = tf.quantize(sample[0], n=sampling.lut_size)
    rows += 1
    rows *= inside  # row 0: transparent
    c = np.take(tables.lut[:4], rows, axis=1)
    if sampling.shading is not None:
        grads = np.moveaxis(sample[1:4], 0, -1)
        lit, glint = _light(grads, view, sampling.shading)
        rgb = np.take(tables.straight, rows, axis=1)
        rgb *= lit
        rgb += glint
        np.minimum(rgb, 1.0, out=rgb)
        rgb *= c[3]
        c[:3] = rgb
    return c


def _span(t0, t1, alpha, beta, origin, lo, hi):
    """Intermediate indices ``[p0, p1)`` whose samples touch voxels ``[t0, t1)`` of a slice,
    within ``[lo, hi)``, with each sample's first tap ``i`` and fraction ``f`` (``x = i + f``).

    Sample ``p`` (array index) is at ``x = α (p + origin) + β``: the integer ``origin`` is
    applied to indices only, so ``i - origin`` and ``f`` do not depend on it.
    """
    if alpha == 1.0:
        span = _shift(t0, t1, beta, origin, lo, hi)
        if span is None:
            return None
        p0, p1, i0, f = span
        return p0, p1, np.arange(i0, i0 + p1 - p0, dtype=np.int64), np.full(p1 - p0, f)
    p0 = max(int(np.ceil((t0 - 1 - beta) / alpha)), lo + origin)
    p1 = min(int(np.ceil((t1 - beta) / alpha)), hi + origin)
    if p1 <= p0:
        return None
    x = alpha * np.arange(p0, p1, dtype=np.float64) + beta
    i = np.floor(x).astype(np.int64)
    return p0 - origin, p1 - origin, i, (x - i).astype(np.float32)


def _shift(t0, t1, beta, origin, lo, hi):
    """:func:`_span` of a translated slice (``α = 1``): ``(p0, p1, i0, f)``, sample ``p`` at
    ``x = (p - p0 + i0) + f``, the one fraction ``f = β - floor(β)`` as float32 (the integer
    ``origin`` goes to the indices only); None if empty."""
    base = math.floor(beta)
    p0, p1 = max(t0 - 1 - base, lo + origin), min(t1 - base, hi + origin)
    if p1 <= p0:
        return None
    return p0 - origin, p1 - origin, p0 + base, np.float32(beta - base)


@dataclass(frozen=True, slots=True, eq=False)
class _Clip:
    """The depth test of a view: a sample counts where its axial depth is in ``[near,
    min(far, limit))``; ``limit``: ``depth_in`` per intermediate pixel
    (:meth:`_View.depth_limit`) or None; ``far_min``: the smallest of the far limits."""

    near: float
    far: float
    far_min: float
    limit: np.ndarray

    @classmethod
    def of_view(cls, view, camera, g, depth_in):
        """The camera's clip range and ``depth_in`` (None: no geometry) for ``view``."""
        limit = None if depth_in is None else view.depth_limit(camera, g, depth_in)
        far_min = camera.clip_end if limit is None else float(limit.min())
        return cls(camera.clip_start, camera.clip_end, far_min, limit)

    def apply(self, inside, k0, kp, kq, area, origin):
        """Clear the samples ``inside`` over ``area`` of the intermediate image (array
        indices; ``origin`` added gives the absolute point), whose axial depth is
        ``k0 + kp p + kq q``, that fail the test. Only evaluated per pixel where the area's
        depth range crosses a limit; returns whether it was."""
        p0, p1 = area[0].start + origin[0], area[0].stop + origin[0]
        q0, q1 = area[1].start + origin[1], area[1].stop + origin[1]
        corners = [k0 + kp * pp + kq * qq for pp in (p0, p1 - 1) for qq in (q0, q1 - 1)]
        if min(corners) >= self.near and max(corners) < self.far_min:
            return False
        dep = (k0 + kp * np.arange(p0, p1, dtype=np.float64)[:, None]
               + kq * np.arange(q0, q1, dtype=np.float64)[None, :]).astype(np.float32)
        inside &= dep >= self.near
        inside &= dep < (self.far if self.limit is None else self.limit[area])
        return True


def _classified(layout, classes, table, voxels, lut, s, window):
    """What a sample interpolates from slice ``s`` over ``window`` (slice coordinates), channels
    first, the last the region weight: post-classification's per-code ``table``, shaded
    pre-classification's per-code ``voxels``, or the rows of the classification table
    ``lut``."""
    codes = _window(layout.codes[s], layout.boxes[s], *window)
    if table is not None:
        return np.take(table, codes, axis=1)
    if voxels is not None:
        return np.take(voxels, codes, axis=1)
    return np.take(lut, np.take(classes.rows, codes), axis=1)


class _Gathered:
    """:func:`_classified` slices kept while consecutive samples blend them (``slices_per_voxel``
    > 1): each slice is gathered once, over every window a sample may ask of it.

    A sample between slices ``s`` and ``s ± 1`` reads ``[t0 - 1, t1 + 1)`` of the union of
    their boxes (:func:`_span`), so slice ``s``'s cover is the union of the boxes of ``s - 1``,
    ``s`` and ``s + 1``, widened by one voxel. The three slices last asked for are kept.
    """

    def __init__(self, layout, classes, table, voxels, lut, boxes):
        self.args = (layout, classes, table, voxels, lut)
        self.boxes = boxes
        self.kept = {}

    def get(self, s, window):
        """Slice ``s`` over ``window`` (slice coordinates), channels first: a read-only view."""
        if s not in self.kept:
            near = self.boxes[max(s - 1, 0):s + 2]
            near = near[(near[:, 1] > near[:, 0]) & (near[:, 3] > near[:, 2])]
            cover = (near[:, 0].min() - 1, near[:, 1].max() + 1, near[:, 2].min() - 1,
                     near[:, 3].max() + 1)
            if len(self.kept) == 3:
                del self.kept[next(iter(self.kept))]
            self.kept[s] = cover, _classified(*self.args, s, cover)
        (a0, _, b0, _), values = self.kept[s]
        return values[:, window[0] - a0:window[1] - a0, window[2] - b0:window[3] - b0]


def _bilinear(src, region, ia, fa, ib, fb, constant):
    """Bilinear samples of a slice window ``src`` (channels first; the last channel is the
    region weight) at ``x = ia + fa`` (rows) and ``y = ib + fb`` (columns), window
    coordinates, not yet renormalised; and ``inside``: whether each sample's nearest voxel is
    in the region (``region``: the window's voxels that are).

    ``constant``: the fractions are the same for all rows and all columns (a translated slice,
    ``ia``/``ib`` consecutive): four shifted views instead of gathers.
    """
    if constant:
        f, g = fa[0], fb[0]
        n, m = len(ia), len(ib)
        out = src[:, :n, :m] * ((1 - f) * (1 - g))
        out += src[:, :n, 1:m + 1] * ((1 - f) * g)
        out += src[:, 1:n + 1, :m] * (f * (1 - g))
        out += src[:, 1:n + 1, 1:m + 1] * (f * g)
        ra, rb = int(f >= 0.5), int(g >= 0.5)
        inside = region[ra:ra + n, rb:rb + m]
    else:
        cols = np.take(src, ib, axis=2)
        cols *= 1 - fb
        cols += np.take(src, ib + 1, axis=2) * fb
        near_b = np.take(region, ib + (fb >= 0.5), axis=1)
        fa2 = fa[:, None]
        out = np.take(cols, ia, axis=1)
        out *= 1 - fa2
        out += np.take(cols, ia + 1, axis=1) * fa2
        inside = np.take(near_b, ia + (fa >= 0.5), axis=0)
    return out, inside


def _translated(pixels, rows, box, window, f, g):
    """:func:`_bilinear` of pre-classified colours on a translated slice (one fraction ``f``
    for all rows, ``g`` for all columns): ``window`` (slice coordinates) of the slice whose
    table ``rows`` cover ``box``, its RGBA gathered from ``pixels`` (the table's rows as
    complex128) and the region weight from ``rows > 0``; resampled separably, columns then
    rows, as ``a + f·(b - a)``. Returns the 5 channels (RGBA, weight) and ``inside``."""
    idx = _window(rows, box, *window)
    n, m = idx.shape[0] - 1, idx.shape[1] - 1
    rgba = np.take(pixels, idx).view(np.float32).reshape(n + 1, m + 1, 4)
    region = idx > 0
    cols = np.empty((5, n + 1, m), np.float32)
    src = np.ascontiguousarray(rgba.transpose(2, 0, 1))  # (strided ufunc passes are slower)
    np.subtract(src[:, :, 1:], src[:, :, :m], out=cols[:4])
    weight = region.astype(np.float32)
    np.subtract(weight[:, 1:], weight[:, :m], out=cols[4])
    cols *= np.float32(g)
    cols[:4] += src[:, :, :m]
    cols[4] += weight[:, :m]
    out = np.subtract(cols[:, 1:], cols[:, :n])
    out *= np.float32(f)
    out += cols[:, :n]
    ra, rb = int(f >= 0.5), int(g >= 0.5)
    return out, region[ra:ra + n, rb:rb + m]


def _normalise(out, inside):
    """The clamp policy on interpolated channels ``out`` (last: the summed weight of region
    voxels): the others divided by that weight, zero where the nearest voxel is outside."""
    result = out[:-1]
    result *= _renormaliser(out, inside)
    return result


def _renormaliser(out, inside):
    """The factor of the clamp policy on interpolated channels ``out`` (last: the summed weight
    of region voxels): ``inside / weight``, float32."""
    weight = out[-1]
    np.maximum(weight, np.float32(1e-30), out=weight)
    return inside / weight


def _correct(c, ratio):
    """Opacity of premultiplied samples ``c`` (4, ...) made for the table's step, corrected to
    each ray's step ``ratio`` times longer: ``α' = 1 - (1 - α)^ratio``, colour times ``α'/α``."""
    a = c[3]
    factor = np.subtract(np.float32(1.0), a)
    np.maximum(factor, 0, out=factor)
    with np.errstate(divide="ignore", invalid="ignore"):
        # log/exp rather than log1p/expm1: NumPy vectorises them (5x faster); the absolute
        # error stays at float32 rounding.
        np.log(factor, out=factor)
        factor *= ratio
        np.exp(factor, out=factor)
        np.subtract(np.float32(1.0), factor, out=factor)  # α', 0 where α is 0
        np.divide(factor, a, out=factor, where=a > 0)
    c *= factor


def _active_box(image, threshold, box):
    """Bounding box of the pixels of ``box`` whose opacity is below ``threshold``; None if none."""
    a0, a1, b0, b1 = box
    open_ = image[3, a0:a1, b0:b1] < threshold
    rows = np.flatnonzero(open_.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(open_[rows[0]:rows[-1] + 1].any(axis=0))
    return [a0 + rows[0], a0 + rows[-1] + 1, b0 + cols[0], b0 + cols[-1] + 1]


def _warp(view, camera, image, rank_map, front, rgba_out, depth_out):
    """Final image: bilinear interpolation of the intermediate colour at each pixel's ray, and
    the depth of the nearest intermediate pixel's depth sample.

    Only the pixels whose taps touch the intermediate image are computed (the others stay
    transparent), :data:`_WARP_CHUNK` at a time. The intermediate RGBA is gathered channels
    last, one 16-byte pixel per index (viewed as complex128), which is what the final image's
    layout wants.
    """
    hi, wi = view.size
    # The image with a border of zeros: taps outside it read zeros, with no masking.
    padded = np.zeros((hi + 2, wi + 2, 4), np.float32)
    padded[1:-1, 1:-1] = image.transpose(1, 2, 0)
    pixels = padded.reshape(-1).view(np.complex128)
    rgba_flat = rgba_out.reshape(-1).view(np.complex128)
    depth_flat = depth_out.reshape(-1)
    for start in range(0, len(view.pq), _WARP_CHUNK):
        part = slice(start, start + _WARP_CHUNK)
        # Taps, fractions and nearest pixels from the absolute intermediate point: the origin
        # (an integer) only moves the indices, so none of them depends on it.
        p, q = view.pq[part, 0], view.pq[part, 1]
        ok = view.rays_ok[part]
        fp, fq = np.floor(p), np.floor(q)
        fa, fb = p - fp, q - fq
        ia = fp.astype(np.int64) - view.origin[0]
        ib = fq.astype(np.int64) - view.origin[1]
        idx = np.flatnonzero(ok & (ia >= -1) & (ia < hi) & (ib >= -1) & (ib < wi))
        # Each pixel's fractions repeated for its 4 channels: NumPy's broadcasting of an
        # (n, 1) factor over (n, 4) is several times slower than flat arrays.
        fa4 = np.repeat(fa[idx].astype(np.float32), 4)
        fb4 = np.repeat(fb[idx].astype(np.float32), 4)
        base = (ia[idx] + 1) * (wi + 2) + ib[idx] + 1
        top = _texels(pixels, base)
        top += fb4 * (_texels(pixels, base + 1) - top)
        base += wi + 2
        bottom = _texels(pixels, base)
        bottom += fb4 * (_texels(pixels, base + 1) - bottom)
        bottom -= top
        bottom *= fa4
        top += bottom
        rgba_flat[start + idx] = top.view(np.complex128)
        # The nearest intermediate pixel, halves rounded up (as the clamp policy's nearest
        # voxel): np.rint's half to even would depend on the origin's parity.
        near_p, near_q = ia + (fa >= 0.5), ib + (fb >= 0.5)
        idx = np.flatnonzero(ok & (near_p >= 0) & (near_p < hi) & (near_q >= 0) & (near_q < wi))
        pp, qq = near_p[idx], near_q[idx]
        r = rank_map[pp, qq]
        hit = r != _NEVER
        idx, r, pp, qq = idx[hit], r[hit], pp[hit], qq[hit]
        k0, kp, kq = view.depth_coefficients(front[r])
        depth_flat[start + idx] = k0 + kp * (pp + view.origin[0]) + kq * (qq + view.origin[1])


def _texels(pixels, index):
    """The RGBA of a channels-last image ``pixels`` (viewed as complex128) at ``index``, flat
    float32 ``(4 n,)``."""
    return np.take(pixels, index).view(np.float32)
