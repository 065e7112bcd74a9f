"""Shear-warp rendering of a VolumeEVM (Lacroute & Levoy), parallel and perspective.

The view is factored into a shear (perspective: a shear and a per-slice scale) that makes every
ray perpendicular to the slices of the **principal axis**, and one 2-D warp from the
intermediate image (one pixel per voxel of a slice, or ``intermediate_scale`` pixels per voxel
along each in-slice axis) to the final image. The loops are compiled kernels
(:mod:`._kernels`); this module factors the view and builds their tables.

Pipeline
--------
1. **Principal axis** ``c``: the grid axis whose world direction is most parallel to the view
   (orthographic: the camera's forward vector; perspective with the eye outside the region's
   bounding box: the eye-to-region-centre vector, among the axes along which the eye is outside
   the box, so that every ray crosses the slices the same way), ties to x, then y, then z
   (VolPack ``vp_view.c``). A perspective eye inside the box is rendered in up to six passes,
   the rays grouped by the axis and sign most parallel to each, each pass compositing the
   slices beyond the eye (Lacroute's split of the view into pyramids). The slices ``c = s``
   (voxel-centre planes) are read front to back (``"over"``, ``"xray"``, ``"mip"``) or back to
   front (``"under"``).
2. **Intermediate image.** Its pixel ``(p, q)`` is the ray through the point ``(p, q)`` (plus an
   integer origin) of a reference plane ``c = c_ref`` in index space; its two axes are the
   in-slice axes of the table order (:data:`volumeevm_addon.model._densities.TABLE_ORDERS`):
   rows are the slices' scanlines, columns run along them. The ray meets slice ``s`` at
   in-slice index coordinates ``x = α_s p + β_s`` (and likewise ``y``). Orthographic:
   ``α_s = 1`` and ``β_s = (s - c_ref) d_a / d_c`` (the shear): the slice is *translated*, so
   the bilinear weights are the same for the whole slice (VolPack ``vp_renderA.c``).
   Perspective: ``α_s = (s - E_c)/(c_ref - E_c)`` with the eye ``E``, a per-slice uniform scale
   about the eye (Lacroute & Levoy 1994, §4; Schulze et al. 2001); the reference plane is the
   region's far end, so ``α_s <= 1`` (slices are magnified, never minified).
   ``intermediate_scale = k`` divides ``α_s`` by ``k``.
3. **Runs, not boxes** (the report's Figure 4). The EVM is the run-length encoding: the 1-D
   sections of the section valid at slice ``s`` are the runs of region voxels along its
   scanlines, and the densities table ``vevm.table(c)`` lists them in that order. What depends
   only on the principal axis is computed once and kept in the VolumeEVM's cache,
   ``vevm.cache``: the runs of every scanline with the table position of their first voxel
   (:func:`._kernels.box_runs`). Per transfer function (also kept) the runs of the
   voxels worth compositing: pre-classification, the voxels the function does not make
   transparent; post-classification, the voxels where a sample may be visible
   (:func:`._kernels.mixed_codes`); X-ray and MIP, every region voxel. The kernel
   (:func:`._kernels.composite`) samples, per slice and intermediate scanline, only
   the pixels whose bilinear taps touch such a run, reads the taps through the region's runs,
   and skips the pixels that are opaque already ("over", early ray termination) by pointers
   to the next pixel that is not (VolPack). Bands of intermediate scanlines are composited in
   parallel (:func:`.._jit.parallel_map`), each through every slice: the image does not depend
   on the number of threads.
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
   With ``shading``, each visible voxel's colour is lit once per view before interpolation
   (the reference's Blinn–Phong headlight on per-voxel 3x3x3 Sobel gradients, which are
   computed once per principal axis and cached; the light is the view direction, for
   perspective the eye-to-region-centre direction).
   ``"mip"`` and ``"xray"`` interpolate densities instead (post-classification, as the
   reference does): MIP classifies the maximum with the transfer function's opacity as given,
   X-ray accumulates ``μ·Δ`` with ``μ = xray_scale · max(d - xray_offset, 0)`` per mm and gives
   ``1 - exp(-Σ μΔ)`` as grey premultiplied RGBA. ``"post"`` does the same for ``"over"`` and
   ``"under"``: densities (and, with shading, the per-voxel gradients) are interpolated, then
   classified through the table and lit per sample, the reference's order.
   A **categorical** transfer function (label maps) puts all of a sample's bilinear weight on
   the slice's voxel nearest to it (one sample per slice), and its table has a row per label.
5. **Boundary policy "clamp"** (:mod:`._reference`), in the slice: a sample is transparent if the
   voxel nearest to it (its cell) is outside the region; otherwise the bilinear weights of
   outside voxels are dropped and the others renormalised. Outside voxels are never read: they
   have no code in the runs.
6. **Compositing** into one float32 intermediate image: ``"over"`` front to back,
   ``C += (1 - A)·c``, with early ray termination: a pixel whose opacity reached
   ``termination`` takes nothing more (so its error is at most ``1 - termination``) and is
   skipped from then on. ``"under"`` back to front, ``C = c + (1 - a)·C``; ``"xray"`` sums
   ``μΔ``; ``"mip"`` keeps the maximum and its slice.
7. **Warp**: every final pixel's ray (from :meth:`Camera.rays`) meets the reference plane at
   ``(p, q)``; the colour is the bilinear interpolation of the intermediate image there (an
   affine map for orthographic cameras, a homography for perspective ones).

Depth
-----
- ``depth_in`` (and the camera's clip range): a sample is dropped when its axial depth is not in
  ``[clip_start, min(clip_end, depth_in))``. ``depth_in`` is brought into the intermediate image
  once per view (each intermediate pixel takes the value of the final pixel its ray passes
  through, nearest); per slice the sample depth is affine in ``(p, q)`` and is only evaluated
  per pixel on slices whose depth range crosses a limit.
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

from ..._errors import VolumeEVMError
from ..._jit import parallel_map
from ...model._densities import TABLE_ORDERS
from ...model._volume import transform
from .. import _depth
from .._camera import BACKGROUND_DEPTH
from .._checks import categorical, checked_view, flag, positive_integer
from .._gradients import region_gradients
from .._modes import MODE_CODES, finish_mode
from .._shading import Shading, checked_shading, fade_magnitudes
from ._kernels import (NEVER, Frame, Light, Optics, Plan, Runs, Voxels, box_runs, composite,
                       flagged_runs, lit_colours, mask_runs, mixed_codes, ray_points, warp)

__all__ = ["render_shear_warp", "SLICES_PER_VOXEL", "CLASSIFICATIONS"]

SLICES_PER_VOXEL = (1, 2, 3, 4, 8)
"""Allowed samples per voxel slice along the rays (Shear-Warp Deluxe's intermediate slices)."""
CLASSIFICATIONS = ("pre", "post")
"""Classify voxels, then interpolate colours ("pre"), or interpolate densities, then classify."""

_MAX_INTERMEDIATE = 1 << 26
"""Largest intermediate image (pixels); only extreme perspective close-ups come near it."""
_BAND = 4
"""Intermediate scanlines per band of the compositing (a band goes through every slice)."""
_TASKS = 16
"""Tasks the bands are dealt to, in turn (task ``k`` takes bands ``k, k + 16, ...``): the
image's middle, where the volume is, is shared out evenly whatever the number of threads."""
_WARP_CHUNK = 1 << 14
"""Final pixels per task of the warp (and, in whole rows, of the perspective rays' points)."""
_UNSEEN = -np.finfo(np.float32).max
"""MIP maximum before any sample (finite, so that the tie margin stays a number)."""
_EMPTY = np.zeros((0, 0), np.float32)


@dataclass(frozen=True, slots=True, eq=False)
class _Layout:
    """The slices of one principal axis as runs.

    Attributes
    ----------
    axis, axes : int, list of int
        The principal axis; the table order as grid axes (slice, scanline, column).
    shape : tuple of int
        Slices, scanlines per slice and columns per scanline.
    runs : Runs
        The region's runs per scanline (:data:`._kernels.Runs`), each voxel's code
        its position in ``values`` (``values[0]``: outside).
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


def _key(axis, part, tf=None, lut_size=None):
    """The ``vevm.cache`` key of ``part`` of the slices of principal axis ``axis``: "layout"
    (:func:`_region_layout`), "gradients", "post" or "post_shaded" (:func:`_post_table`), and
    per transfer function and table size "classes" and "mixed" (:func:`_classes`,
    :func:`_mixed`). The function enters the key by its control points, all these depend on:
    equal functions share them, and the cache keeps no function (nor its own tables) alive.
    One function for the render and :func:`tables_to_build`, so that the memory check sees the
    same cache the render uses."""
    if part in ("classes", "mixed"):
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
    """The runs of the EVM's ordered boxes in the table order of ``axis`` (slabs, sub-slabs,
    runs: :meth:`EVM.boxes`), numbered as ``vevm.table(axis)`` lists their voxels."""
    order = TABLE_ORDERS[axis]
    axes = ["xyz".index(ch) for ch in order]
    shape = tuple(int(vevm.shape[a]) for a in axes)
    lo, hi = (np.ascontiguousarray(corner[:, axes], dtype=np.int64)
              for corner in vevm.evm.boxes(order))
    runs = Runs(shape[1], shape[2], *box_runs(lo, hi, shape[0], shape[1]))
    table = vevm.table(axis)
    return _Layout(axis, axes, shape, runs, np.concatenate([np.zeros(1, table.dtype), table]),
                   True)


def _dense_layout(vevm, axis):
    """The same slices over the whole dense grid, runs read from the region's mask and codes
    numbering every voxel of the grid: the dense side of the exactness contract (no EVM, no
    table, no skipping)."""
    order = TABLE_ORDERS[axis]
    axes = ["xyz".index(ch) for ch in order]
    dense = np.transpose(vevm.to_dense(), axes)
    mask = np.ascontiguousarray(np.transpose(vevm.evm.to_mask(vevm.shape), axes))
    runs = Runs(dense.shape[1], dense.shape[2], *mask_runs(mask))
    values = np.concatenate([np.zeros(1, dense.dtype), dense.ravel()])
    return _Layout(axis, axes, dense.shape, runs, values, False)


def _gradients(layout, vevm):
    """Per code, the voxel's index-space gradient (:func:`_make_gradients`), kept
    (:func:`_kept`)."""
    return _kept(vevm, layout, "gradients", lambda: _make_gradients(layout, vevm))


def _make_gradients(layout, vevm):
    """Per voxel, in code order, ``(codes, 3)`` float32: index-space gradients over region
    voxels, the reference's rule (:func:`._gradients.region_gradients`)."""
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


def _post_table(layout, vevm, with_gradients):
    """Per code, what post-classification interpolates: the density and, ``with_gradients``,
    the index-space gradient, ``(codes, 1 or 4)`` float32 (row 0: outside). Kept
    (:func:`_kept`)."""

    def make():
        columns = [layout.values.astype(np.float32)[:, None]]
        if with_gradients:
            columns.append(_gradients(layout, vevm))
        return np.ascontiguousarray(np.concatenate(columns, axis=1))

    return _kept(vevm, layout, "post_shaded" if with_gradients else "post", make)


@dataclass(frozen=True, slots=True, eq=False)
class _Classes:
    """Pre-classification by one transfer function and table size.

    ``rows``: per code, the voxel's row of the classification table (0: outside);
    ``codes``: the codes of the voxels the function does not make transparent (all, on the
    dense layout) and ``index``: per code, 1 + its place among them (0: the others), where
    shading lights them; ``work``: the runs of those voxels (:data:`Runs`).
    """

    rows: np.ndarray
    codes: np.ndarray
    index: np.ndarray
    work: Runs

    @property
    def nbytes(self):
        """Bytes of its arrays: what ``vevm.cache`` counts (at once, on every use)."""
        return self.rows.nbytes + self.codes.nbytes + self.index.nbytes + _runs_bytes(self.work)

    @classmethod
    def of(cls, layout, tf, lut_size):
        """The classes of the voxels of ``layout``."""
        q = tf.quantize(layout.values[1:], n=lut_size)
        rows = np.zeros(len(layout.values), np.int32)
        rows[1:] = q + 1
        if layout.region_only:
            visible = np.zeros(len(layout.values), bool)
            visible[1:] = tf.straight_table(n=lut_size)[q, 3] > 0
            starts, lo, hi, box = flagged_runs(layout.runs, visible, layout.shape[0])
            work = layout.runs._replace(starts=starts, lo=lo, hi=hi, pos=np.zeros(0, np.int64),
                                        box=box)
            codes = np.flatnonzero(visible)
        else:  # dense: every voxel is worked on
            work = layout.runs
            codes = np.arange(1, len(layout.values))
        index = np.zeros(len(layout.values), np.int32)
        index[codes] = np.arange(1, len(codes) + 1, dtype=np.int32)
        return cls(rows, codes, index, work)


def _classes(vevm, layout, tf, lut_size):
    """The :class:`_Classes` of ``tf`` and ``lut_size`` for ``layout``, kept (:func:`_kept`)."""
    return _kept(vevm, layout, "classes", lambda: _Classes.of(layout, tf, lut_size), tf,
                 lut_size)


def _mixed(vevm, layout, tf, lut_size):
    """Post-classification: the runs of the voxels where a sample may be visible
    (:func:`._kernels.mixed_codes`) for ``tf`` and ``lut_size``, kept
    (:func:`_kept`); every region voxel on the dense layout."""

    def make():
        visible = tf.straight_table(n=lut_size)[:, 3] > 0
        # Per table row: -1 where visible, else the index of its run of transparent rows.
        ids = np.where(visible, -1, np.cumsum(np.r_[True, visible[1:] != visible[:-1]]) - 1)
        codes = np.zeros(len(layout.values), np.int32)
        codes[1:] = ids[tf.quantize(layout.values[1:], n=lut_size)]
        flags = mixed_codes(layout.runs, codes, layout.shape[0], layout.shape[2])
        starts, lo, hi, box = flagged_runs(layout.runs, flags, layout.shape[0])
        return layout.runs._replace(starts=starts, lo=lo, hi=hi, pos=np.zeros(0, np.int64),
                                    box=box)

    if not layout.region_only:
        return layout.runs
    return _kept(vevm, layout, "mixed", make, tf, lut_size)


class _View:
    """The factorization of one view: principal axis, slice order, per-slice maps from the
    intermediate image to slice coordinates, the warp and the per-ray sample spacing."""

    def __init__(self, vevm, camera, g, layout, scale, axis, step, rays):
        self.scale = scale  # intermediate pixels per voxel along each in-slice axis
        self.inv = np.linalg.inv(g)
        rot = self.inv[:3, :3].T
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
            self.rows, self.cols, seen = self.ortho_plane(camera, rot)
            ok = True
        else:
            self.eye = self.inv[:3, :3] @ camera.position + self.inv[:3, 3]
            self.step = step
            self.c_ref = nc - 0.5 if self.step > 0 else -0.5
            self.pq, ok, seen = self.persp_plane(camera, rot, rays)
        self.rays_ok = ok
        lo_box = layout.runs.box
        used = np.flatnonzero(lo_box[:, 1] > lo_box[:, 0])
        if not self.ortho:
            lam = (used - self.eye[axis]) / (self.c_ref - self.eye[axis])
            used = used[lam > 0]
        # Slices front to back.
        self.slices = used if self.step > 0 else used[::-1]
        self.empty = self.slices.size == 0 or not np.any(ok)
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
            pc = self.pq[:, k] if ok[k] else np.array([seen[0] + seen[1], seen[2] + seen[3]]) / 2
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
        """Orthographic: the intermediate coordinates of every pixel's ray as the sum of a
        per-row term ``(H, 2)`` and a per-column term ``(W, 2)``, and their ``(p min, p max,
        q min, q max)``.

        The rays of :meth:`Camera.rays` start at ``m + x_j r + y_i u`` (pixel column ``j``,
        row ``i``) and share one direction, so each coordinate is a sum of a per-row and a
        per-column term (same values as transforming every ray, up to rounding).
        """
        a, b, c = self.abc
        h, w = camera.shape
        x, y = camera.pixel_centres()
        m = camera.matrix_world
        origin = m[:3, 3] @ rot + self.inv[:3, 3]
        right, up = m[:3, 0] @ rot, m[:3, 1] @ rot
        rows_pq, cols_pq = np.empty((h, 2)), np.empty((w, 2))
        extent = []
        for k, e in enumerate((a, b)):
            # Along the ray to c = c_ref: coordinate e moves by slope[e] per unit of c.
            along = np.eye(3)[e] - self.slope[e] * np.eye(3)[c]
            base = (origin @ along + self.slope[e] * self.c_ref) * self.scale
            rows = rows_pq[:, k] = base + y * ((up @ along) * self.scale)
            cols = cols_pq[:, k] = x * ((right @ along) * self.scale)
            extent += [rows.min() + cols.min(), rows.max() + cols.max()]
        return rows_pq, cols_pq, extent

    def persp_plane(self, camera, rot, rays):
        """Perspective: the intermediate coordinates of every pixel's ray, ``(2, H*W)`` before
        the origin shift (0 for rays that do not cross the slices towards the reference plane),
        which rays do (those of ``rays``, a flat mask or None for all) and their ``(p min,
        p max, q min, q max)`` (:func:`._kernels.ray_points`)."""
        h, w = camera.shape
        x, y = camera.pixel_centres()
        m = camera.matrix_world
        right, up, back = m[:3, 0], m[:3, 1], m[:3, 2]
        axes = list(self.abc)
        terms = np.stack([right @ rot, up @ rot, -(back @ rot)], axis=1)[axes]
        gram = np.array([right @ right, up @ up, back @ back, right @ up, right @ back,
                         up @ back])
        eye = (m[:3, 3] @ rot + self.inv[:3, 3])[axes]
        pq, ok = np.empty((2, h * w)), np.empty(h * w, bool)
        rows = max(1, _WARP_CHUNK // w)
        only = np.zeros(0, bool) if rays is None else rays
        parts = parallel_map(
            lambda first: ray_points(first, min(first + rows, h), x, y, terms, gram, eye,
                                     self.c_ref, float(self.step), self.scale, only, pq, ok),
            [(first,) for first in range(0, h, rows)])
        parts = np.array(parts)
        seen = np.array([parts[:, 0].min(), parts[:, 1].max(), parts[:, 2].min(),
                         parts[:, 3].max()])
        return pq, ok, seen

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
        uv, _ = camera.project(transform(pts, g[:3, :3].T, g[:3, 3]))
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
        True (default): sample only around the runs of voxels worth compositing (the EVM's
        runs, less those the transfer function makes transparent), reading the densities
        table. False: the same algorithm over the runs of the region's mask in the dense grid,
        every region voxel composited (the dense side of the exactness contract; slower).
    termination : float
        Early ray termination for ``"over"``: pixels whose opacity reached it stop receiving
        slices (error at most ``1 - termination`` per pixel); 1.0 composites every slice.
    shading : None, True, dict or Shading
        Gradient shading for ``"over"`` and ``"under"`` (:class:`._shading.Shading`:
        Blinn–Phong headlight; ignored by ``"xray"`` and ``"mip"``), applied per voxel before
        interpolation (pre-classification): per-voxel gradients (the reference's 3x3x3
        Sobel, :mod:`._gradients`) are computed once per principal axis and cached; each
        view lights them along one direction (perspective: eye to the region's centre).
    slices_per_voxel : {1, 2, 3, 4, 8}
        Samples along each ray per voxel slice (module docstring, 4): 1 is VolPack's one sample
        per slice; more interpolate between slices (trilinear): each voxel slice is classified
        once and every sample blends two of them, then resamples once (CT head 512²: 2 slices
        cost twice one).
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
    lut_size = positive_integer("lut_size", lut_size)
    skip_empty = flag("skip_empty", skip_empty)
    if not 2 <= lut_size < 32767:
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
    if categorical(tf, mode):  # one table row per label
        lut_size = tf.lut_size(lut_size)
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
        frame, front = _composite(vevm, view, layout, tf, compositing, sampling,
                                  _Clip.of_view(view, camera, g, depth_in))
        _warp(view, camera, frame, front, rgba_out, depth_out)
    return rgba_out, depth_out


def tables_to_build(vevm, camera, tf, grid_to_world, options):
    """How many principal axes the render would build slice tables for: the axes of its passes
    (:func:`_passes`) whose layout, or what this render reads beside it (the transfer
    function's classes, or the post-classification table and the function's runs; the
    gradients with shading), is not in ``vevm.cache`` (:func:`_key`); every one with
    ``skip_empty=False`` (the dense layout is made per render). Changes nothing: it only
    looks at the cache.

    ``options`` are the renderer's keywords (``mode`` included).
    """
    if vevm.evm.is_empty():
        return 0
    axes = {axis for axis, _, _ in _passes(vevm, camera, np.asarray(grid_to_world, float))}
    if not options.get("skip_empty", True):
        return len(axes)
    mode = options.get("mode", "over")
    shaded = mode in ("over", "under") and options.get("shading") not in (None, False)
    lut_size = options.get("lut_size", 4096)
    if categorical(tf, mode):
        lut_size = tf.lut_size(lut_size)
    if mode in ("xray", "mip"):
        parts = ("layout", "post")
    elif options.get("classification", "pre") == "post":
        parts = ("layout", "post_shaded" if shaded else "post", "mixed")
    else:
        parts = ("layout", "classes") + (("gradients",) if shaded else ())
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
    cos = np.abs(transform(dirs, cols)) / np.linalg.norm(cols, axis=0)
    dominant = np.argmax(cos, axis=1)
    index_dirs = transform(dirs, np.linalg.inv(cols).T)
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

    def cuts(self, view, k0, kp, kq):
        """Per sample of axial depth ``k0 + kp p + kq q``, whether its depth over the
        intermediate image crosses a limit (then each pixel is tested)."""
        hi, wi = view.size
        p0, q0 = view.origin
        corners = [k0 + kp * p + kq * q for p in (p0, p0 + hi - 1) for q in (q0, q0 + wi - 1)]
        low, high = np.minimum.reduce(corners), np.maximum.reduce(corners)
        return (low < self.near) | (high >= self.far_min)


def _optics(vevm, view, layout, tf, compositing, sampling, delta):
    """What the samples of a view read and how they become colour: the runs worth compositing
    (:data:`Runs`), the voxels' channels (:data:`Voxels`) and the :data:`Optics`, for samples
    ``delta`` mm apart."""
    mode, shading, lut_size = compositing.mode, sampling.shading, sampling.lut_size
    post = mode in ("xray", "mip") or sampling.classification == "post"
    units = None if tf is None else delta / tf.unit_length_mm  # in the function's unit lengths
    lut = np.zeros((lut_size + 1, 4), np.float32)
    straight = np.zeros((lut_size + 1, 3), np.float32)
    lut_lo = lut_scale = 0.0
    if mode in ("over", "under"):
        lut[1:] = tf.table(n=lut_size, step_mm=delta)
        straight[1:] = tf.straight_table(n=lut_size)[:, :3]
        lo, hi, _ = tf._range(None, None, lut_size)  # the rows of quantize
        lut_lo, lut_scale = lo, (lut_size - 1) / (hi - lo)
    optics = Optics(MODE_CODES[mode], post, categorical(tf, mode), shading is not None,
                    np.float32(compositing.termination),
                    _depth.visible_threshold(1.0 if units is None else units, np.float32),
                    lut, straight, lut_lo, lut_scale, float(lut_size), _light(view, shading, tf),
                    np.float32(compositing.xray_offset),
                    np.float32(compositing.xray_scale * delta),
                    _depth.attenuation_threshold(delta, np.float32))
    if post:
        table = _post_table(layout, vevm, shading is not None)
        work = layout.runs if mode in ("xray", "mip") else _mixed(vevm, layout, tf, lut_size)
        return work, Voxels(np.zeros(0, np.int32), table, table.shape[1]), optics
    classes = _classes(vevm, layout, tf, lut_size)
    if shading is None:
        return classes.work, Voxels(classes.rows, lut, 4), optics
    return classes.work, Voxels(classes.index, _lit_voxels(classes, _gradients(layout, vevm),
                                                           optics), 4), optics


def _light(view, shading, tf):
    """The view's headlight with the transfer function ``tf`` as the kernels take it
    (:data:`Light`; zeros without shading)."""
    if shading is None:
        return Light((np.float32(0.0),) * 9, (np.float32(0.0),) * 3, *(np.float32(0.0),) * 4,
                     0.0, 0.0)
    return Light(tuple(view.inv[:3, :3].astype(np.float32).ravel()),
                 tuple(view.light.astype(np.float32)),
                 *(np.float32(w) for w in (shading.ambient, shading.diffuse, shading.specular,
                                           shading.shininess)),
                 *fade_magnitudes(shading, tf))


def _lit_voxels(classes, gradients, optics):
    """Shaded pre-classification: the lit colours of the visible voxels, ``(1 + visible, 4)``
    (row 0 transparent, then by :attr:`_Classes.index`), in parallel over chunks of them
    (:func:`._kernels.lit_colours`)."""
    codes = classes.codes
    out = np.zeros((len(codes) + 1, 4), np.float32)
    chunk = 1 << 16
    parallel_map(lambda start: lit_colours(codes[start:start + chunk], classes.rows, gradients,
                                           optics.lut, optics.straight, optics.light,
                                           out[start:start + chunk + 1]),
                 [(start,) for start in range(0, len(codes), chunk)])
    return out


def _plan(view, layout, work, clip, owner, offset, ranks):
    """The :data:`Plan` of the samples ``owner + offset`` (compositing order, front-to-back
    ``ranks``) that may touch a run of ``work``."""
    other = np.where(offset > 0, owner + 1, owner - 1)
    other[(offset == 0) | (other < 0) | (other >= layout.shape[0])] = -1
    box = work.box
    has = box[:, 1] > box[:, 0]
    keep = has[owner] | ((other >= 0) & has[np.maximum(other, 0)])
    owner, offset, ranks, other = owner[keep], offset[keep], ranks[keep], other[keep]
    centre = owner + offset
    alpha, beta_a, beta_b = view.slice_maps(centre)
    k0, kp, kq = view.depth_coefficients(centre)
    return Plan(owner.astype(np.int64), other.astype(np.int64),
                (1.0 - np.abs(offset)).astype(np.float32), np.abs(offset).astype(np.float32),
                alpha, beta_a, beta_b, k0, kp, kq,
                ranks.astype(np.int32), clip.cuts(view, k0, kp, kq))


def _composite(vevm, view, layout, tf, compositing, sampling, clip):
    """The slice loop: returns the intermediate image as a :data:`Frame` (premultiplied RGBA,
    the front-to-back rank of each pixel's depth sample, :data:`NEVER` where none) and, per
    rank, the slice coordinate of the front end of its samples."""
    mode = compositing.mode
    per_voxel = sampling.per_voxel
    owner, offset = _samples(view.slices, view.step, per_voxel)
    front = owner + offset - 0.5 * view.step / per_voxel
    ranks = np.arange(len(owner))
    if mode == "under":
        owner, offset, ranks = owner[::-1], offset[::-1], ranks[::-1]
    work, voxels, optics = _optics(vevm, view, layout, tf, compositing, sampling,
                                   view.delta / per_voxel)
    plan = _plan(view, layout, work, clip, owner, offset, ranks)
    hi, wi = view.size
    image = np.zeros((hi, wi, 4), np.float32)
    if mode == "mip":
        image[..., 0] = _UNSEEN
    following = _EMPTY.astype(np.int32)
    if mode == "over" and compositing.termination < 1.0:
        following = np.empty((hi, wi + 1), np.int32)
        following[:] = np.arange(wi + 1, dtype=np.int32)
    frame = Frame(int(view.origin[0]), int(view.origin[1]),
                  _EMPTY if view.ratio is None else view.ratio,
                  np.float32(clip.near), np.float32(clip.far),
                  _EMPTY if clip.limit is None else clip.limit, image,
                  np.full((hi, wi), NEVER, np.int32), following)
    tasks = min(_TASKS, -(-hi // _BAND))
    parallel_map(lambda first: composite(first, tasks, _BAND, plan, layout.runs, work, voxels,
                                         optics, frame),
                 [(first,) for first in range(tasks)])
    if mode in ("xray", "mip"):
        _finish(frame, mode, tf)
    return frame, front


def _finish(frame, mode, tf):
    """X-ray's optical depths or MIP's maxima (channel 0 of the image) as premultiplied RGBA
    (:func:`._modes.finish_mode`), in place; pixels whose maximum is not visible lose their
    depth sample."""
    acc = frame.image.reshape(-1, 4)
    vmax = None if mode == "xray" else np.where(acc[:, 0] > _UNSEEN, acc[:, 0], -np.inf)
    visible = finish_mode(acc, vmax, mode, tf)
    if visible is not None:
        frame.rank[~visible.reshape(frame.rank.shape)] = NEVER


def _warp(view, camera, frame, front, rgba_out, depth_out):
    """Final image: bilinear interpolation of the intermediate colour at each pixel's ray, and
    the depth of the nearest intermediate pixel's depth sample
    (:func:`._kernels.warp`), :data:`_WARP_CHUNK` pixels per task."""
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
