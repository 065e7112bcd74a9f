"""Shear-warp's compositing: the samples of one view classified (and lit) and composited, slice
by slice, into the intermediate image; its driver and its compiled loops.

This is the stage VolPack keeps in ``vp_compA*.c`` (and ``vp_shade.c``): per band of
intermediate scanlines, per sample slice, it reads the runs of :mod:`._layouts` through the
maps of :mod:`._view` and leaves an intermediate image (:data:`Frame`) for :mod:`._warp`.

1. **Samples along the rays** (``slices_per_voxel = k``, Shear-Warp Deluxe's intermediate
   slices): each voxel slice ``s`` owns the slab of its cells, ``c`` in ``[s - 1/2, s + 1/2)``,
   and takes ``k`` samples at the centres of ``k`` equal parts of it; a sample between the
   slice planes is the linear blend of the bilinear samples of ``s`` and its neighbour (so
   trilinear, with the clamp policy of the sample's nearest voxel, which is in ``s``). ``k = 1``
   is VolPack's one sample per slice, on the plane. The opacity is corrected for ``Δ / k``
   (``Δ``: the view's slice spacing along the ray, :class:`._view.View`).
2. **Classification** ``"pre"`` (VolPack): each voxel's density is quantized once per transfer
   function (:meth:`TransferFunction.quantize`) and looked up in the premultiplied table
   :meth:`TransferFunction.table` computed once per view with the opacity corrected for the
   physical distance between consecutive samples along the ray. Perspective rays have
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
3. **Boundary policy "clamp"** (:mod:`.._reference`), in the slice: a sample is transparent if
   the voxel nearest to it (its cell) is outside the region; otherwise the bilinear weights of
   outside voxels are dropped and the others renormalised. Outside voxels are never read: they
   have no code in the runs.
4. **Compositing** into one float32 intermediate image: ``"over"`` front to back,
   ``C += (1 - A)·c``, with early ray termination: a pixel whose opacity reached
   ``termination`` takes nothing more (so its error is at most ``1 - termination``) and is
   skipped from then on. ``"under"`` back to front, ``C = c + (1 - a)·C``; ``"xray"`` sums
   ``μΔ``; ``"mip"`` keeps the maximum and its slice.
5. **Depth**: ``depth_in`` (and the camera's clip range): a sample is dropped when its axial
   depth is not in ``[clip_start, min(clip_end, depth_in))``. ``depth_in`` is brought into the
   intermediate image once per view (each intermediate pixel takes the value of the final pixel
   its ray passes through, nearest); per slice the sample depth is affine in ``(p, q)`` and is
   only evaluated per pixel on slices whose depth range crosses a limit. Each intermediate pixel
   keeps the rank of its first visible sample (:mod:`.._depth`: opacity per unit length at least
   ``VISIBLE_ALPHA``; ``"xray"``: attenuation; ``"mip"``: the frontmost sample holding the
   maximum, if its class is visible), from which the warp takes the output depth.

The loop (Lacroute & Levoy, Figure 4; :func:`composite`): per band of intermediate scanlines,
per sample slice front to back, per intermediate scanline, per run of the two (four, between two
slices) voxel scanlines its bilinear taps read:

- **transparent voxels are skipped with the runs**: only intermediate pixels whose taps touch a
  run worth compositing (:mod:`._layouts`) are sampled;
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
largest difference in the images was of the order of 1e-7). Bands of intermediate scanlines are
composited in parallel (:func:`..._jit.parallel_map`), each through every slice; a band writes
only its own intermediate scanlines and reads nothing another band writes, so the image does not
depend on how the bands are spread over threads. (The loops are written out in
:func:`composite`: a compiled helper that takes arrays costs their reference counting on every
call, more than the work of a pixel; the helpers take numbers.)

The kernels take their inputs as records of arrays and numbers with fixed types, so that one
compiled kernel serves every render (what a render does not use is an empty array):
:data:`._layouts.Runs`, :data:`Plan`, :data:`Voxels`, :data:`.._optics.Optics` (what every
renderer shares: mode, termination, visibility; its helpers decide visibility) with
:data:`Tables` (shear-warp's own classification tables and :data:`Light`) and :data:`Frame`.
"""

import math
from collections import namedtuple
from dataclasses import dataclass

import numpy as np

from ..._jit import kernel, parallel_map
from .._modes import MODE_CODES, MODES, finish_mode
from .._optics import attenuation_threshold, optics, visible
from .._shading import Shading, fade
from ._layouts import lit_codes, mixed_runs, post_table, voxel_classes, voxel_gradients

__all__ = ["Plan", "Voxels", "Light", "Tables", "Frame", "NEVER", "Sampling", "Clip",
           "intermediate_image", "lit_colours", "tap", "span", "composite"]

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
_BAND = 4
"""Intermediate scanlines per band of the compositing (a band goes through every slice)."""
_TASKS = 16
"""Tasks the bands are dealt to, in turn (task ``k`` takes bands ``k, k + 16, ...``): the
image's middle, where the volume is, is shared out evenly whatever the number of threads."""
_UNSEEN = -np.finfo(np.float32).max
"""MIP maximum before any sample (finite, so that the tie margin stays a number)."""
_EMPTY = np.zeros((0, 0), np.float32)

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
the unit world direction of the light; the Blinn–Phong weights (:class:`.._shading.Shading`);
the fade's gradient magnitudes (float64, :attr:`.._shading.Lighting.fade`)."""

Tables = namedtuple("Tables", "post lut straight lut_lo lut_scale lut_rows light xray_factor")
Tables.__doc__ = """Shear-warp's classification (its :data:`.._optics.Optics` holds the rest).

``post``: classify interpolated densities through ``lut`` ((rows + 1, 4) float32,
premultiplied for the view's step, row 0 transparent), the row ``clip(rint((d -
lut_lo)·lut_scale), 0, lut_rows - 1) + 1`` (:meth:`TransferFunction.quantize`); shaded (post):
light each sample with ``light`` (:data:`Light`) on the straight colours ``straight``
(rows + 1, 3); ``xray_factor`` (float32): X-ray's ``μ·Δ = max(d - xray_offset, 0)·factor``."""

Frame = namedtuple("Frame", "origin_p origin_q ratio near far limit image rank next")
Frame.__doc__ = """The intermediate image a view composites into.

``origin_p``, ``origin_q``: the absolute point of array index ``(0, 0)``; ``ratio`` (hi, wi)
float32: perspective, each pixel's step over the table's (empty: orthographic); ``near``,
``far`` (float32): the clip range; ``limit`` (hi, wi) float32: ``min(clip_end, depth_in)``
per pixel (empty: none); ``image`` (hi, wi, 4) float32: premultiplied RGBA ("xray" and "mip"
accumulate in channel 0); ``rank`` (hi, wi) int32: the depth sample's rank (:data:`NEVER`:
none); ``next`` (hi, wi + 1) int32: per pixel itself, or, once opaque, a later pixel with no
pixel between that is not opaque (column ``wi``: the end)."""


def intermediate_image(vevm, view, layout, tf, compositing, sampling, clip):
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
    work, voxels, optical, tables = _classification(vevm, view, layout, tf, compositing,
                                                    sampling, view.delta / per_voxel)
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
                                         optical, tables, frame),
                 [(first,) for first in range(tasks)])
    if mode in ("xray", "mip"):
        _finish(frame, mode, tf)
    return frame, front


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
class Sampling:
    """How a render samples and classifies (checked): ``per_voxel`` samples per voxel slice,
    ``classification`` (the package's ``CLASSIFICATIONS``), ``lut_size`` rows of the
    classification table, ``shading`` (None: unshaded)."""

    per_voxel: int
    classification: str
    lut_size: int
    shading: Shading


@dataclass(frozen=True, slots=True, eq=False)
class Clip:
    """The depth test of a view: a sample counts where its axial depth is in ``[near,
    min(far, limit))``; ``limit``: ``depth_in`` per intermediate pixel
    (:meth:`._view.View.depth_limit`) or None; ``far_min``: the smallest of the far limits."""

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


def _classification(vevm, view, layout, tf, compositing, sampling, delta):
    """What the samples of a view read and how they become colour: the runs worth compositing
    (:data:`._layouts.Runs`), the voxels' channels (:data:`Voxels`), the
    :data:`.._optics.Optics` and the :data:`Tables`, for samples ``delta`` mm apart."""
    mode, shading, lut_size = compositing.mode, sampling.shading, sampling.lut_size
    post = mode in ("xray", "mip") or sampling.classification == "post"
    optical = optics(tf, compositing, shading, step_mm=delta, lut=False)
    lut = np.zeros((lut_size + 1, 4), np.float32)
    straight = np.zeros((lut_size + 1, 3), np.float32)
    lut_lo = lut_scale = 0.0
    if mode in ("over", "under"):
        lut[1:] = tf.table(n=lut_size, step_mm=delta)
        straight[1:] = tf.straight_table(n=lut_size)[:, :3]
        lo, hi, _ = tf._range(None, None, lut_size)  # the rows of quantize
        lut_lo, lut_scale = lo, (lut_size - 1) / (hi - lo)
    tables = Tables(post, lut, straight, lut_lo, lut_scale, float(lut_size),
                    _light(view, optical), np.float32(compositing.xray_scale * delta))
    if post:
        table = post_table(layout, vevm, shading is not None)
        work = layout.runs if mode in ("xray", "mip") else mixed_runs(vevm, layout, tf, lut_size)
        return work, Voxels(np.zeros(0, np.int32), table, table.shape[1]), optical, tables
    classes = voxel_classes(vevm, layout, tf, lut_size)
    if shading is None:
        return classes.work, Voxels(classes.rows, lut, 4), optical, tables
    codes, index = lit_codes(vevm, layout, tf, lut_size)
    lit = _lit_voxels(codes, classes.rows, voxel_gradients(layout, vevm), tables)
    return classes.work, Voxels(index, lit, 4), optical, tables


def _light(view, optical):
    """The view's headlight with the weights of ``optical`` (:data:`.._optics.Optics`) as the
    kernels take it (:data:`Light`; zeros without shading)."""
    if not optical.shaded:
        return Light((np.float32(0.0),) * 9, (np.float32(0.0),) * 3, *(np.float32(0.0),) * 4,
                     0.0, 0.0)
    return Light(tuple(view.inv[:3, :3].astype(np.float32).ravel()),
                 tuple(view.light.astype(np.float32)),
                 *(np.float32(w) for w in optical.phong[:4]), *optical.phong[4:])


def _lit_voxels(codes, rows, gradients, tables):
    """Shaded pre-classification: the lit colours of the visible voxels ``codes``, ``(1 +
    visible, 4)`` (row 0 transparent, then in the order of ``codes``: :func:`._layouts.lit_codes`),
    in parallel over chunks of them (:func:`lit_colours`)."""
    out = np.zeros((len(codes) + 1, 4), np.float32)
    chunk = 1 << 16
    parallel_map(lambda start: lit_colours(codes[start:start + chunk], rows, gradients,
                                           tables.lut, tables.straight, tables.light,
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


def _finish(frame, mode, tf):
    """X-ray's optical depths or MIP's maxima (channel 0 of the image) as premultiplied RGBA
    (:func:`.._modes.finish_mode`), in place; pixels whose maximum is not visible lose their
    depth sample."""
    acc = frame.image.reshape(-1, 4)
    vmax = None if mode == "xray" else np.where(acc[:, 0] > _UNSEEN, acc[:, 0], -np.inf)
    visible = finish_mode(acc, vmax, mode, tf)
    if visible is not None:
        frame.rank[~visible.reshape(frame.rank.shape)] = NEVER


# ----------------------------------------------------------------------------- shading kernels
@kernel
def _headlight(gx, gy, gz, light):
    """The Blinn–Phong headlight (:mod:`.._shading`) for an index-space gradient: the factor on
    the straight colour and the highlight added to it, float32 (as ``_shading.blinn_phong``
    on ``cos = |N·L|`` and the fade ``t`` of :func:`.._shading.fade`)."""
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


# ------------------------------------------------------------------------- compositing kernels
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
def composite(first, step, band, plan, region, work, voxels, optics, tables, frame):
    """Composite the samples of ``plan`` into the intermediate scanlines of bands ``first``,
    ``first + step``, ... (``band`` scanlines each) of ``frame``, classified by ``optics``
    (:data:`.._optics.Optics`) and ``tables`` (:data:`Tables`).

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
    lut, straight, light = tables.lut, tables.straight, tables.light
    mode, post, snap = optics.mode, tables.post, optics.nearest
    # The visibility thresholds in the samples' float32 (of a whole sample: the threshold of a
    # perspective ray's step is compared before the correction to it).
    threshold = np.float32(optics.visible)
    xray_threshold = attenuation_threshold(optics.step_mm)
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
                                    tables.xray_factor
                                # (The ray's own step is ratio times the table's: so are μΔ
                                # and the threshold.)
                                if visible(tau, xray_threshold) and ranks[p, x] == NEVER:
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
                                row = _table_row(samples[u8] * factor, tables.lut_lo,
                                                 tables.lut_scale, tables.lut_rows)
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
                            hit = visible(c[3], threshold)
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
