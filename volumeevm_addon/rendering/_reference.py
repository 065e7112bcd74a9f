"""The dense float64 reference ray caster: the accuracy oracle of every VolumeEVM renderer.

It renders a dense grid of densities with a region-of-interest mask through a :class:`Camera`
and a :class:`TransferFunction`, as exactly as a sampled method can: float64 throughout, exact
ray–box clipping, rays split exactly where the reconstruction changes, a tiny step, trilinear
reconstruction, post-classification, no early termination. Speed is not its job; NumPy
vectorises over rays, Python loops over ray steps and chunks of rays.

Boundary policy (the region of interest, VoI)
---------------------------------------------
The VoI is the union of its voxels' **cells** (voxel ``(i, j, k)`` is the cell of half-width 0.5
around the index point ``(i, j, k)``; the volume's box spans ``-0.5 .. n - 0.5`` per axis), the
same solid the EVM describes.

- A sample at index-space point ``p`` lies in the cell ``floor(p + 0.5)``. If that voxel is
  outside the VoI (or the grid) the sample is **transparent**: no opacity, no colour, no X-ray
  attenuation, ignored by MIP. The VoI's surface is where the EVM's mesh is.
- Inside, the density is trilinearly interpolated from the voxels the policy may read, with the
  weights of the others dropped and the rest renormalised (the sample's own voxel always keeps
  at least 1/8 of the weight). At a flat boundary, e.g. the grid's own faces, this is exactly
  clamp-to-edge interpolation.

  * ``boundary="clamp"`` (default): only the VoI's voxels are read. This is what a VolumeEVM
    storing only the VoI's densities renders, so the exactness contract (VolumeEVM render ==
    dense render with the outside transparent) needs nothing more; masking a volume gives
    exactly the image of the volume cropped to the mask; a homogeneous region is homogeneous up
    to its cell boundary, so closed forms hold with the exact chord. The price: isolated bright
    voxels and thin structures next to outside voxels keep their full density and show as
    opaque cells. Measured on the CT head (256x256x108, ct_bone, front view 64^2, premultiplied
    RGBA, mean absolute difference to the full dense render): VoI = voxels above -300 HU:
    0.006 (max 0.22); VoI above 150 HU (the VoI's surface where the TF turns opaque): 0.019.
    With 2x or 8x downsampled data (larger voxels) it grows to 0.04-0.08.
  * ``boundary="shell"``: also the one-voxel shell around the VoI (its 26-neighbourhood) is
    read, with its true densities, as a VolumeEVM that stores that shell (a second EVM with its
    own densities table: 9 % of the VoI's voxels for the head above -300 HU, 66 % for bone
    above 150 HU) could. Interpolation in the VoI then equals the full dense render's. Same
    measurements: 0.0000 (above -300 HU) and 0.004 (above 150 HU).
- A categorical transfer function (label maps) reads no neighbours: a sample takes the label
  of its own voxel (its cell), so the image is the exact integral of the labels' cells.
- Gradients (shading) are per voxel the 3x3x3 Sobel over readable voxels (:mod:`._gradients`:
  each of the 9 lines' central difference, one-sided where one end is not readable, lines
  without one left out, zero where none has one); they are interpolated like the densities.
  Shading fades out where they are small (:func:`._shading.fade`).

Sampling
--------
Each ray is clipped to the volume's box, to the camera's clip range (axial depths ``clip_start ..
clip_end``) and to ``depth_in``. The remaining segment is split at every crossing of a cell
boundary (index ``m + 0.5``: where the VoI can start or stop) and of a voxel-centre plane (index
``m``: where the trilinear weights change cell), so each piece lies in one cell and sees one
smooth polynomial. Each piece of ``L`` mm (physical: ``|diag(spacing) · δ|`` for an index-space
step ``δ``) is cut into ``ceil(L / step_mm)`` equal parts of ``Δ <= step_mm`` sampled at their
midpoints, with the opacity corrected for ``Δ``. Hence a homogeneous VoI gets exactly
``1 - (1 - a)^(L/Δ0)`` for its exact chord ``L`` (any mask, any view), and masks and ``depth_in``
cut rays exactly. MIP also evaluates both ends of each part (nudged into it): along an axis-
parallel ray the field is linear between breakpoints, so the maximum is found exactly. Pieces
that cannot contribute are not sampled (cell outside the VoI; over/under: the transfer
function's opacity is 0 on the range of the 8 neighbours' densities; X-ray: no density above
``xray_offset``): their samples would add exact zeros, so the image is bit-identical.

Depth out
---------
Axial depth (Blender units, float32) of the **front end of the first visible part**: its
opacity per unit length is at least :data:`._depth.VISIBLE_ALPHA` (over, under; X-ray: its
attenuation per mm, :data:`._depth.VISIBLE_OPTICAL_DEPTH`); for MIP, of the frontmost point
holding the maximum, if its classified opacity is at least ``VISIBLE_ALPHA``. ``1e10`` where
there is none (Blender's background). The threshold is per unit length, so a part's length does
not matter: at the VoI's surface, the volume's box, the near clip and ``depth_in`` the depth is
exact.
"""

import numpy as np

from .._errors import VolumeEVMError
from . import _depth
from ._camera import BACKGROUND_DEPTH, Camera  # noqa: F401  (Camera: doctest)
from ._checks import (
    REFERENCE_STEPS_PER_VOXEL,
    categorical,
    check_camera,
    check_mode,
    check_transfer_function,
    checked_affine,
    checked_step_mm,
    checked_xray,
    positive_integer,
)
from ._gradients import region_gradients
from ._method import MemoryModel, Method, keyword_options, one_set, step_quality, step_samples
from ._modes import Compositing, finish_mode
from ._rays import camera_rays
from ._shading import Lighting, checked_shading
from ._transfer import TransferFunction  # noqa: F401  (doctest)

__all__ = ["render_reference", "render_reference_vevm", "BOUNDARIES", "REFERENCE_METHOD"]

BOUNDARIES = ("clamp", "shell")


def _check_inputs(densities, mask, grid_to_world, spacing, camera, tf, mode, step_mm, depth_in,
                  shading):
    d = np.asarray(densities)
    if d.ndim != 3 or min(d.shape) < 1:
        raise VolumeEVMError(f"densities: expected an (X, Y, Z) array, got shape {d.shape}")
    if not (np.issubdtype(d.dtype, np.number) or d.dtype == bool):
        raise VolumeEVMError(f"densities: expected numbers, got dtype {d.dtype}")
    d = d.astype(np.float64)
    if not np.all(np.isfinite(d)):
        raise VolumeEVMError("densities: NaN or infinite values")
    if mask is None:
        m = np.ones(d.shape, dtype=bool)
    else:
        m = np.asarray(mask)
        if m.dtype != bool:
            raise VolumeEVMError(f"mask: expected a bool array, got dtype {m.dtype}")
        if m.shape != d.shape:
            raise VolumeEVMError(f"mask: shape {m.shape} differs from densities' {d.shape}")
    g = checked_affine("grid_to_world", grid_to_world, invertible=True)
    sp = np.asarray(spacing, dtype=np.float64)
    if sp.shape != (3,) or not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise VolumeEVMError(f"spacing: expected 3 positive mm values, got {spacing!r}")
    check_camera(camera)
    check_mode(mode)
    check_transfer_function(tf, mode)
    step = checked_step_mm(step_mm, sp, REFERENCE_STEPS_PER_VOXEL)
    depth_in = _depth.checked_depth_in(depth_in, camera.shape)
    return d, m, g, sp, step, depth_in, checked_shading(shading)


def _dilate(mask):
    """The mask grown by one voxel in all 26 directions (within the grid)."""
    pad = np.pad(mask, 1)
    out = np.zeros_like(mask)
    nx, ny, nz = mask.shape
    for dx in (0, 1, 2):
        for dy in (0, 1, 2):
            for dz in (0, 1, 2):
                out |= pad[dx:dx + nx, dy:dy + ny, dz:dz + nz]
    return out


class _Sampler:
    """Trilinear reconstruction at index-space points: samples in ``visible`` cells interpolate
    the densities of ``readable`` voxels (renormalised weights), others are transparent.
    ``nearest`` (categorical transfer functions): a sample takes its own voxel's density."""

    def __init__(self, densities, visible, readable, with_gradient, nearest=False):
        self.nearest = nearest
        self.n = np.array(densities.shape)
        pshape = tuple(self.n + 2)
        vpad = np.zeros(pshape, dtype=bool)
        vpad[1:-1, 1:-1, 1:-1] = visible
        rpad = np.zeros(pshape, dtype=bool)
        rpad[1:-1, 1:-1, 1:-1] = readable
        dpad = np.zeros(pshape)
        dpad[1:-1, 1:-1, 1:-1] = np.where(readable, densities, 0.0)
        cols = [dpad, rpad.astype(np.float64)]
        if with_gradient:
            grads = np.zeros((3,) + pshape)
            region_gradients(dpad, rpad, grads[:, 1:-1, 1:-1, 1:-1])
            cols.extend(grads)
        self.table = np.stack([c.ravel() for c in cols], axis=1)  # (P, 2 or 5)
        self.inside = vpad.ravel()
        self.strides = np.array([pshape[1] * pshape[2], pshape[2], 1], dtype=np.int64)
        corners = np.array([(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)])
        self.corners = corners  # (8, 3)
        self.offsets = corners @ self.strides  # (8,)

    def _block_ranges(self):
        """Per trilinear block (the 8 voxels from base index b to b + 1, padded indexing):
        min and max of the readable densities; +inf / -inf where none is readable."""
        pshape = tuple(self.n + 2)
        dens = self.table[:, 0].reshape(pshape)
        readable = self.table[:, 1].reshape(pshape) > 0
        lo_src = np.where(readable, dens, np.inf)
        hi_src = np.where(readable, dens, -np.inf)
        lo = np.full(pshape, np.inf)
        hi = np.full(pshape, -np.inf)
        nx, ny, nz = (int(v) + 1 for v in self.n)
        core = (slice(0, nx), slice(0, ny), slice(0, nz))
        for a, b, c in self.corners:
            np.minimum(lo[core], lo_src[a:a + nx, b:b + ny, c:c + nz], out=lo[core])
            np.maximum(hi[core], hi_src[a:a + nx, b:b + ny, c:c + nz], out=hi[core])
        self.block_lo, self.block_hi = lo.ravel(), hi.ravel()

    def corner_range(self, p):
        """For points ``p`` (m, 3): is the cell visible, and the min and max of the readable
        densities among the 8 trilinear neighbours (every interpolated value lies between)."""
        if not hasattr(self, "block_lo"):
            self._block_ranges()
        cell = np.floor(p + 0.5)
        np.clip(cell, -1, self.n, out=cell)
        inside = self.inside[(cell.astype(np.int64) + 1) @ self.strides]
        i0 = np.floor(p)
        np.clip(i0, -1, self.n - 1, out=i0)
        base = (i0.astype(np.int64) + 1) @ self.strides
        return inside, self.block_lo[base], self.block_hi[base]

    def __call__(self, p):
        """``p`` (m, 3) index-space points -> (inside (m,), value (m,), grad (m, 3) or None)."""
        cell = np.floor(p + 0.5)
        np.clip(cell, -1, self.n, out=cell)
        cidx = (cell.astype(np.int64) + 1) @ self.strides
        inside = self.inside[cidx]
        i0 = np.floor(p)
        np.clip(i0, -1, self.n - 1, out=i0)
        f = np.clip(p - i0, 0.0, 1.0)
        if self.nearest:  # all the weight on the corner whose cell holds p
            f = (f >= 0.5).astype(np.float64)
        base = (i0.astype(np.int64) + 1) @ self.strides
        vals = self.table[base[:, None] + self.offsets[None, :]]  # (m, 8, C)
        # weights: prod over axes of (f if corner==1 else 1-f)
        w = np.where(self.corners[None, :, :] == 1, f[:, None, :], 1.0 - f[:, None, :]).prod(axis=2)
        acc = np.einsum("mc,mck->mk", w, vals)  # (m, C)
        wsum = np.where(inside, acc[:, 1], 1.0)
        value = np.where(inside, acc[:, 0] / wsum, 0.0)
        grad = None
        if acc.shape[1] > 2:
            grad = np.where(inside[:, None], acc[:, 2:5] / wsum[:, None], 0.0)
        return inside, value, grad


def render_reference(densities, mask, grid_to_world, spacing, camera, tf, *, mode="over",
                     step_mm=None, depth_in=None, shading=None, boundary="clamp", xray_scale=1.0,
                     xray_offset=0.0, chunk_rays=8192):
    """Render a dense volume with a region-of-interest mask, as exactly as sampling allows.

    Parameters
    ----------
    densities : (X, Y, Z) ndarray
        Densities in data units, indexed ``[x, y, z]``; voxel centres at integer indices.
    mask : (X, Y, Z) ndarray of bool or None
        The region of interest; voxels outside it are transparent (module docstring: boundary
        policy). ``None``: every voxel.
    grid_to_world : (4, 4) ndarray
        Voxel-centre index space to Blender world (compose ``BLENDER_UNITS_PER_MM``,
        ``index_to_physical`` and the object's ``matrix_world``).
    spacing : (3,) array_like
        Voxel size in mm: lengths along rays are measured in physical mm for opacity correction,
        independent of how ``grid_to_world`` scales the volume into the scene.
    camera : Camera
    tf : TransferFunction
        Classification (post-interpolation). Unused (may be None) for ``mode="xray"``.
    mode : {"over", "under", "xray", "mip"}
        ``"over"``: front-to-back emission–absorption compositing; ``"under"``: back to front
        (same image up to rounding); ``"xray"``: attenuation ``T = exp(-Σ μ·Δ)`` with
        ``μ = xray_scale · max(density - xray_offset, 0)`` per mm, output grey premultiplied
        ``(1 - T, 1 - T, 1 - T, 1 - T)`` (white fog that lets ``T`` of the background through);
        ``"mip"``: the maximum density along the ray within the VoI, classified by ``tf`` with
        its opacity as given (no length correction).
    step_mm : float, optional
        Largest sample spacing along rays in mm (default: the smallest voxel size / 16).
    depth_in : (H, W) ndarray, optional
        Axial depth (Blender units) of scene geometry: each ray stops there. ``1e10`` or ``inf``
        = nothing. NaN raises.
    shading : None, True, dict or Shading
        Gradient shading for ``"over"`` and ``"under"`` (ignored by ``"xray"`` and ``"mip"``).
    boundary : {"clamp", "shell"}
        What interpolation reads at the VoI's surface (module docstring). ``"clamp"`` (default):
        only the VoI's voxels. ``"shell"``: also the one-voxel shell of outside voxels around
        the VoI (26-neighbourhood), as a VolumeEVM that stores that shell could.
    xray_scale, xray_offset : float
        Attenuation per mm per data unit, and the density of zero attenuation (e.g. -1000 HU).
    chunk_rays : int
        Rays processed at once (bounds memory).

    Returns
    -------
    rgba : (H, W, 4) ndarray of np.float32
        Premultiplied RGBA, row 0 at the top of the image.
    depth : (H, W) ndarray of np.float32
        Axial depth in Blender units (module docstring), ``1e10`` where nothing is seen.

    Raises
    ------
    VolumeEVMError
        For inputs of the wrong shape or type, NaN densities or NaN in ``depth_in``.

    Examples
    --------
    A 2x2x2 mm block of 1 mm voxels seen from above; opacity 0.5 per mm over a 2 mm chord:

    >>> BU = 0.001  # Blender units per mm
    >>> cam_matrix = np.eye(4)
    >>> cam_matrix[:3, 3] = (0.5 * BU, 0.5 * BU, 1.0)
    >>> cam = Camera.orthographic(cam_matrix, 2 * BU, resolution_x=2, resolution_y=2)
    >>> tf = TransferFunction([(0, 1, 1, 1, 0.5), (1, 1, 1, 1, 0.5)])
    >>> rgba, depth = render_reference(np.zeros((2, 2, 2)), None, np.diag([BU, BU, BU, 1.0]),
    ...                                (1.0, 1.0, 1.0), cam, tf)
    >>> rgba[..., 3].astype(float).round(6).tolist(), depth.astype(float).round(6).tolist()
    ([[0.75, 0.75], [0.75, 0.75]], [[0.9985, 0.9985], [0.9985, 0.9985]])
    """
    d, m, g, sp, step, depth_in, shading = _check_inputs(
        densities, mask, grid_to_world, spacing, camera, tf, mode, step_mm, depth_in, shading)
    compositing = Compositing(mode, 1.0, *checked_xray(xray_scale, xray_offset))
    if boundary not in BOUNDARIES:
        raise VolumeEVMError(f"boundary: one of {BOUNDARIES}, got {boundary!r}")
    chunk_rays = positive_integer("chunk_rays", chunk_rays)
    h, w = camera.shape
    rgba = np.zeros((h * w, 4))
    depth = np.full(h * w, BACKGROUND_DEPTH)
    if not m.any():
        return rgba.reshape(h, w, 4).astype(np.float32), depth.reshape(h, w).astype(np.float32)

    rays = camera_rays(camera, g, d.shape, depth_in)
    mm_per_t = rays.mm_per_t(sp)
    live = np.nonzero(rays.t1 > rays.t0)[0]

    # Chunks bounded in rays x breakpoints and in samples.
    length = rays.t1[live] - rays.t0[live]
    span = np.abs(rays.d[live]) * length[:, None]  # index-space extent per axis
    estimate = np.ceil(length * mm_per_t[live] / step) + 2.0 * span.sum(axis=1) + 8.0
    per_ray_breaks = 2 * int(sum(d.shape)) + 8
    max_rays = max(1, min(chunk_rays, _BREAK_BUDGET // per_ray_breaks))
    readable = m if boundary == "clamp" else _dilate(m)
    lighting = Lighting.of_view(shading if mode in ("over", "under") else None, g, tf)
    sampler = _Sampler(d, m, readable, with_gradient=lighting is not None,
                       nearest=categorical(tf, mode))
    start = 0
    while start < len(live):
        stop = min(len(live), start + max_rays)
        budget = np.searchsorted(np.cumsum(estimate[start:stop]), _SAMPLE_BUDGET, side="right")
        stop = start + max(1, min(stop - start, int(budget)))
        ids = live[start:stop]
        c_rgba, c_depth = _march(sampler, compositing, tf, lighting, step, rays.take(ids),
                                 mm_per_t[ids])
        rgba[ids] = c_rgba
        depth[ids] = c_depth
        start = stop
    return rgba.reshape(h, w, 4).astype(np.float32), depth.reshape(h, w).astype(np.float32)


_BREAK_BUDGET = 4_000_000
_NUDGE = 1e-9
_TIE = 1e-12
_SAMPLE_BUDGET = 2_000_000


def _breakpoints(o, d, t0, t1):
    """Ray parameters where each ray crosses a cell boundary (index = m + 0.5) or a voxel-centre
    plane (index = m), per axis, with t0 and t1: (n, K) sorted, padded with t1."""
    cols = [t0[:, None], t1[:, None]]
    for ax in range(3):
        u0 = 2.0 * (o[:, ax] + t0 * d[:, ax])  # doubled coordinates: both plane families
        u1 = 2.0 * (o[:, ax] + t1 * d[:, ax])  # sit at integers
        lo, hi = np.minimum(u0, u1), np.maximum(u0, u1)
        first = np.floor(lo) + 1.0
        cnt = np.maximum(np.ceil(hi) - first, 0.0).astype(np.int64)
        cmax = int(cnt.max()) if len(cnt) else 0
        if cmax == 0:
            continue
        q = np.arange(cmax)
        planes = (first[:, None] + q[None, :]) * 0.5
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (planes - o[:, ax, None]) / d[:, ax, None]
        cols.append(np.where(q[None, :] < cnt[:, None], t, t1[:, None]))
    bp = np.sort(np.concatenate(cols, axis=1), axis=1)
    np.clip(bp, t0[:, None], t1[:, None], out=bp)
    return bp


def _plan(o, d, t0, t1, mm_per_t, step, may_contribute):
    """Samples of each ray: every piece between breakpoints that may contribute is split into
    equal parts no longer than ``step`` mm. Returns per-ray counts and flat (front t, dt, dmm),
    ray by ray, front to back.

    Pieces that cannot contribute (cell outside the VoI; for over/under, densities where the
    transfer function's opacity is 0 throughout; for X-ray, no attenuation) are skipped: their
    samples would add exactly nothing, so the image is the same, only faster.
    """
    bp = _breakpoints(o, d, t0, t1)
    length = np.diff(bp, axis=1)
    rows, cols = np.nonzero(length > 0)  # row-major: by ray, then front to back
    lt = length[rows, cols]
    start = bp[rows, cols]
    mid = start + 0.5 * lt
    keep = may_contribute(o[rows] + mid[:, None] * d[rows])
    rows, lt, start = rows[keep], lt[keep], start[keep]
    lmm = lt * mm_per_t[rows]
    c = np.maximum(np.ceil(lmm / step * (1.0 - 1e-12)), 1).astype(np.int64)
    piece_dt = lt / c
    piece_dmm = lmm / c
    total = int(c.sum())
    piece = np.repeat(np.arange(len(c)), c)
    first = np.cumsum(c) - c
    q = np.arange(total) - first[piece]
    t_front = start[piece] + q * piece_dt[piece]
    nsamp = np.bincount(rows, weights=c, minlength=len(t0)).astype(np.int64)
    return nsamp, t_front, piece_dt[piece], piece_dmm[piece]


def _may_contribute(sampler, compositing, tf):
    """The test :func:`_plan` skips pieces with: index-space points -> may the piece holding
    each contribute (its cell in the VoI and, over/under, the transfer function not transparent
    on its 8 neighbours' densities; X-ray: some density attenuates)."""
    mode = compositing.mode
    if mode in ("over", "under"):
        def may_contribute(p):
            inside, lo, hi = sampler.corner_range(p)
            return inside & ~tf.transparent_between(lo, hi)
    elif mode == "xray":
        def may_contribute(p):
            inside, lo, hi = sampler.corner_range(p)
            return inside & (compositing.xray_scale > 0) & (hi > compositing.xray_offset)
    else:
        def may_contribute(p):
            return sampler.corner_range(p)[0]
    return may_contribute


def _march(sampler, compositing, tf, lighting, step, rays, mm_per_t):
    """March one chunk of ``rays`` (:class:`._rays.Rays`, ``mm_per_t`` their mm per unit of
    the ray parameter) with samples no longer than ``step`` mm; returns (premultiplied RGBA
    (m, 4), axial depth (m,)), float64."""
    mode = compositing.mode
    nsamp, t_front, dt, dmm = _plan(rays.o, rays.d, rays.t0, rays.t1, mm_per_t, step,
                                    _may_contribute(sampler, compositing, tf))
    offsets = np.cumsum(nsamp) - nsamp
    order = np.argsort(-nsamp, kind="stable")  # longest first: the active rays are a prefix
    nsamp, offsets = nsamp[order], offsets[order]
    o_i, d_i, dirs = rays.o[order], rays.d[order], rays.dirs[order]
    n = len(nsamp)
    acc = np.zeros((n, 4))
    tdepth = np.full(n, np.inf)  # ray parameter of the depth event
    smax = int(nsamp[0]) if n else 0
    count = np.searchsorted(-nsamp, -np.arange(smax), side="left")  # rays with nsamp > s
    vmax = None
    if mode == "mip":
        vmax = np.full(n, -np.inf)
        tmax = np.zeros(n)
    for s in range(smax):
        a = int(count[s])
        if mode == "under":
            rows = offsets[:a] + (nsamp[:a] - 1 - s)  # back to front
        else:
            rows = offsets[:a] + s
        tf_ = t_front[rows]
        tm = tf_ + 0.5 * dt[rows]
        p = o_i[:a] + tm[:, None] * d_i[:a]
        inside, value, grad = sampler(p)
        if mode == "xray":
            mu = (compositing.xray_scale * np.maximum(value - compositing.xray_offset, 0.0)
                  * inside)
            tau = mu * dmm[rows]
            acc[:a, 0] += tau
            first = _depth.attenuates(tau, dmm[rows]) & np.isinf(tdepth[:a])
            tdepth[:a][first] = tf_[first]
            continue
        if mode == "mip":
            # The midpoint and both ends of the segment (nudged into it, so that each point
            # belongs to the segment's cell): along a ray parallel to an axis the trilinear field
            # is linear between breakpoints, so its maximum is found exactly.
            for tt in (tf_ + _NUDGE * dt[rows], tm, tf_ + (1.0 - _NUDGE) * dt[rows]):  # in order
                ins, val, _ = (inside, value, None) if tt is tm else sampler(
                    o_i[:a] + tt[:, None] * d_i[:a])
                # ties (within rounding) keep the first, frontmost occurrence
                cur = vmax[:a]
                with np.errstate(invalid="ignore"):
                    bar = np.where(np.isfinite(cur), cur + _TIE * np.maximum(1.0, np.abs(cur)),
                                   -np.inf)
                better = ins & (val > bar)
                vmax[:a][better] = val[better]
                tmax[:a][better] = tt[better]
            continue
        straight = tf.evaluate(value)
        units = dmm[rows] / tf.unit_length_mm
        alpha = 1.0 - np.power(1.0 - straight[:, 3], units)
        alpha *= inside
        hit = _depth.visible(alpha, units)
        rgb = straight[:, :3]
        if grad is not None:
            rgb = lighting.shade(rgb, grad, dirs[:a])
        c = rgb * alpha[:, None]
        if mode == "over":
            trans = 1.0 - acc[:a, 3]
            acc[:a, :3] += trans[:, None] * c
            acc[:a, 3] += trans * alpha
            first = hit & np.isinf(tdepth[:a])
            tdepth[:a][first] = tf_[first]
        else:  # under: C = c + (1 - alpha) C
            keep = 1.0 - alpha
            acc[:a, :3] = c + keep[:, None] * acc[:a, :3]
            acc[:a, 3] = alpha + keep * acc[:a, 3]
            tdepth[:a][hit] = tf_[hit]  # the last one met (the frontmost) wins
    visible = finish_mode(acc, vmax, mode, tf)
    if visible is not None:
        tdepth = np.where(visible, tmax, np.inf)
    inverse = np.empty_like(order)
    inverse[order] = np.arange(n)
    acc, tdepth = acc[inverse], tdepth[inverse]
    depth = np.full(n, BACKGROUND_DEPTH)
    found = np.isfinite(tdepth)
    depth[found] = rays.a0[found] + rays.kz[found] * tdepth[found]
    return acc, depth


# ---------------------------------------------------------------------------- the record
def render_reference_vevm(vevm, camera, tf, grid_to_world, **options):
    """:func:`render_reference` of a VolumeEVM, with the signature of every method's renderer.

    Parameters
    ----------
    vevm : VolumeEVM
        Rendered as its dense densities (:meth:`VolumeEVM.to_dense`) and region mask.
    camera : Camera
    tf : TransferFunction
    grid_to_world : (4, 4) ndarray
        Voxel-centre index space to Blender world.
    **options
        ``mode``, ``depth_in`` and the options of :func:`render_reference`.

    Returns
    -------
    rgba : (H, W, 4) ndarray of np.float32
    depth : (H, W) ndarray of np.float32
        As :func:`render_reference`.
    """
    return render_reference(vevm.to_dense(), vevm.evm.to_mask(vevm.shape), grid_to_world,
                            vevm.spacing, camera, tf, **options)


REFERENCE_METHOD = Method(
    name="reference", label="Reference",
    description="Dense float64 ray caster with a tiny step (accuracy oracle, slow)",
    render=render_reference_vevm, options=keyword_options(render_reference),
    # Per grid voxel: dense float64 densities, masks, the padded (P, 2) float64 sampling table
    # and the float64 min/max block-range grids of the sampler; fixed: its chunks (bounded by
    # samples and breakpoints per chunk). It caches nothing: one set of tables per render.
    memory=MemoryModel(pixel=360, fixed=40 << 20, grid=64, shading_grid=32),
    tables_to_build=one_set, check_samples=step_samples(REFERENCE_STEPS_PER_VOXEL),
    quality=step_quality(REFERENCE_STEPS_PER_VOXEL), categorical=True, full_level=True)
"""The dense float64 reference ray caster, the accuracy oracle of every method."""
