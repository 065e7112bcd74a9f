"""Sheet-buffer splatting of a VolumeEVM (Westover), post-classified.

Object order: the region's voxels are visited sheet by sheet along the principal axis ``A``
(the grid axis most parallel to the view, measured in physical space), front to back (``"under"``:
back to front). A sheet's voxels and densities come straight from the VolumeEVM: the densities
of slice ``a`` are one contiguous run of the slice-major table for ``A`` (:meth:`VolumeEVM.table`),
read forwards or backwards, and their positions are the voxels of the EVM's section valid at
``a`` (:meth:`EVM.sections`, decoded once per slab by a 2-D prefix XOR). Nothing outside the
region is visited.

Footprints
----------
Each voxel carries a 3-D Gaussian kernel, isotropic in index space (``σ = kernel_sigma``
voxels, truncated at ``kernel_radius`` voxels from the line through its centre). Its footprint
is the kernel integrated along the ray (Westover's footprint), evaluated where each pixel's
ray crosses the centre plane of a sub-slab (below), moved along ``A`` into the sheet's plane:
for an in-plane offset ``q`` from the voxel and the ray's unit index-space direction ``u``,
``w = exp(-|q_⊥|² / 2σ²)`` with ``|q_⊥|² = |q|² - (q·u)²`` — a circle for a view along ``A``,
an ellipse stretched along the projected ray otherwise, scaled by the projection
(perspective: per voxel). Weights come from a precomputed footprint table indexed by
``|q_⊥|²``. Each voxel is scattered to the pixels its projected footprint can reach (a window
of offsets around its projected centre, found per sheet from the kernel's ellipse, the
sub-slabs' drift and the local projection; half-width at most ``max_footprint_px``) by a
compiled loop (:mod:`._splat_kernels`), which splats bands of the window's rows on all threads
(:func:`.._jit.parallel_map`): a band writes only its rows and adds a pixel's contributions in
voxel order, so the image does not depend on the bands nor on the number of threads.
Orthographic cameras project affinely, so
every voxel has the same footprint: its window is found once, and a pixel's offset ``q`` from
a voxel is a per-voxel term (its sub-pixel position) plus a per-offset term, with no per-pixel
lookup (a sheet is the 2-D convolution of the slice with the footprint, on the image grid).

Sheet buffer and classification
-------------------------------
The slab ``a ± 0.5`` is cut along ``A`` into ``substeps`` equal sub-slabs. Per sub-slab the
buffer accumulates, per pixel, ``Σ w``, ``Σ w·density`` (footprints at the sub-slab's centre
plane; the density there linear along ``A`` between the voxel and its neighbour in the adjacent
slice on the sub-slab's side, the voxel's own where that neighbour is outside the region: the
reference's trilinear along ``A``, renormalised over region voxels) and the length of the ray's
path through the sub-slab that lies in the sheet's cells (each voxel clips the path's in-plane
segment to its cell; the cells are disjoint, so the sum is exact), with the path cut by the
volume's box, the clip range and ``depth_in``; sub-slabs are composited in view order.
Following the reference's boundary policy ("clamp") the sub-slab's density at a pixel is the
normalised ``Σ w·d / Σ w`` over region voxels, classified (post-classification, "splatting
without the blur") with the opacity corrected for that physical length: coverage is exact, so a
homogeneous region gives the closed form ``1 - (1 - α)^(L/Δ0)`` for its exact chord ``L`` in
any view, and ``depth_in`` cuts exactly. Sheets are composited into the image in view order;
voxels whose whole window is already opaque (``termination``) are not splatted and the loop
stops once every pixel is. Voxels whose in-sheet neighbourhood (every density a pixel they
reach can mix; with sub-slabs also their neighbours' in the adjacent slices) is transparent for
the transfer function (X-ray: does not attenuate) are not splatted either: the image is the
same. Which voxels those are is per-transfer-function work, kept in the VolumeEVM's cache per
axis for the last transfer function (frames of an animation share it). Shading (optional) splats
per-voxel gradients (the 3x3x3 Sobel over region voxels of :mod:`._gradients`, from the
neighbouring sheets) with the densities and lights the sheet's samples like the reference does.

Sub-slabs: with one sample per slab a ray samples each sheet at the same sub-voxel position
(phase) for every pixel when the pixel spacing in the plane is a whole number of voxels, and the
footprints' blur at that phase shows as a change of mean luminance while the view turns (popping).
Along the slab the ray drifts by ``|u_B| / |u_A|`` voxels in the plane, so ``substeps`` sub-slabs
sample spread phases and classify each, linear along ``A`` like the reference. Not the default:
on a thin shell one sample per slab is closer in total (docs/measurements.md has the figures).

Modes follow the reference: over, under, xray (``exp(-Σ μ·length)``), mip (maximum sheet
density). Depth out: axial depth where the ray enters the region's cells in the first visible
sub-slab (:mod:`._depth`: opacity per unit length at least ``VISIBLE_ALPHA``; X-ray:
attenuation; MIP: the sheet holding the maximum, if its class is visible), exact at the
region's surface.

Sheets are taken outward from the camera, the side the view faces first, then the other side
(perspective cameras inside the volume: rays running against the principal direction see
those, front to back as well). Limits: footprints of voxels right at the camera are cut at
``max_footprint_px``.

Sheet families
--------------
A sheet holds one slice's voxels, so its reconstruction is a box along ``A`` (with sub-slabs:
linear) and a Gaussian across it, and the image depends on which axis is principal: a hard
switch where two axes are equally parallel to the view makes the image jump (popping at 45°; on
Marschner–Lobb rotated about x, a step of 1.5 % in mean luminance). Near the switch every axis
within ``blend`` of the principal one renders its own sheets and the images are cross-faded
with weights that are continuous in the view direction (:func:`_family_weights`), so the image
changes smoothly. This removes the jump, not the box reconstruction's own error (Mueller &
Crawfis's image-aligned sheets would; they cost a kernel slice per sheet and voxel).

References
----------
L. Westover, "Footprint evaluation for volume rendering", SIGGRAPH 1990.
K. Mueller, R. Crawfis, "Eliminating popping artifacts in sheet buffer-based splatting",
IEEE Visualization 1998.
K. Mueller, T. Möller, R. Crawfis, "Splatting without the blur", IEEE Visualization 1999.
"""

from dataclasses import dataclass

import numpy as np

from .._errors import VolumeEVMError
from .._jit import parallel_map
from ..model._densities import TABLE_ORDERS
from ..model._volume import transform
from ._camera import BACKGROUND_DEPTH
from ._checks import checked_view, positive_integer
from ._gradients import region_gradients
from ._method import MAX_SAMPLES, MemoryModel, Method, keyword_options
from ._modes import finish_mode
from ._optics import Optics, optics
from ._rays import Rays, camera_rays
from ._shading import Lighting, checked_shading
from ._splat_kernels import Crossings, Footprint, Image, Slab, Voxels, splat_rows

__all__ = ["render_splat", "SPLAT_METHOD"]

_FOOTPRINT_SIZE = 1024
_CULL_INVISIBLE = True
"""Drop voxels whose whole neighbourhood is transparent (they cannot change the image)."""
_BAND_ROWS = 64
"""Window rows a kernel call splats (the calls run on all threads)."""
_NONE2 = np.zeros((0, 2))
_NONE3 = np.zeros((0, 3))
"""What the kernel gets for unused per-voxel terms (perspective; unshaded)."""


def _section_voxels(section):
    """The cells ``(m, 2)`` (B, C) of a 2-D EVM given by its points, in C order."""
    if len(section) == 0:
        return np.zeros((0, 2), np.int64)
    pts = np.asarray(section, dtype=np.int64)
    lo = pts.min(axis=0)
    hi = pts.max(axis=0)
    grid = np.zeros(tuple(hi - lo + 1), np.uint8)
    grid[pts[:, 0] - lo[0], pts[:, 1] - lo[1]] = 1
    np.bitwise_xor.accumulate(grid, axis=0, out=grid)
    np.bitwise_xor.accumulate(grid, axis=1, out=grid)
    return np.argwhere(grid) + lo


def _slabs(vevm, axis):
    """Per slab of the sweep along ``axis``: ``(lo, hi, cells (m, 2) B, C, table offset)``,
    kept in ``vevm.cache`` (:func:`_slabs_key`)."""

    def make():
        out = []
        base = 0
        for slab in vevm.evm.sections(TABLE_ORDERS[axis]):
            cells = _section_voxels(slab.section)
            out.append((slab.lo, slab.hi, cells, base))
            base += len(cells) * (slab.hi - slab.lo)
        return out

    return vevm.cache.get(_slabs_key(axis), make)


def _slabs_key(axis):
    """The ``vevm.cache`` key of the sections of ``axis``: one function for the render and
    :func:`tables_to_build`, so that the memory check sees the same cache the render uses."""
    return ("splat", "slabs", axis)


def _kept_voxels(vevm, axis, rule):
    """The dict ``a -> indices of slice a's voxels that can change the image`` for the
    culling ``rule`` (mode, transfer function's opacity, reach), kept in ``vevm.cache`` for
    the last rule per axis: per-transfer-function work, like a classified volume, that frames
    with the same transfer function share. The render fills it a slice at a time."""
    key = ("splat", "kept", axis)
    kept_rule, kept = vevm.cache.get(key, lambda: (rule, {}))
    if kept_rule != rule:
        vevm.cache.discard(key)
        _, kept = vevm.cache.get(key, lambda: (rule, {}))
    return kept


def _slices_evm(vevm, axis):
    """A function ``a -> (cells (m, 2) B, C, densities (m,))`` (None for an empty slice) reading
    the sections and the densities table of ``axis``."""
    table = vevm.table(axis)
    slabs = _slabs(vevm, axis)
    starts = np.array([s[0] for s in slabs])

    def get(a):
        i = np.searchsorted(starts, a, side="right") - 1
        if i < 0 or a >= slabs[i][1] or len(slabs[i][2]) == 0:
            return None
        lo, _, cells, base = slabs[i]
        n = len(cells)
        off = base + (a - lo) * n
        return cells, table[off:off + n]

    return get


def _slices_dense(vevm, axis):
    """Same as :func:`_slices_evm`, from the dense grid and the region mask (no EVM)."""
    axes = ["xyz".index(c) for c in TABLE_ORDERS[axis]]
    mask = np.transpose(vevm.evm.to_mask(vevm.shape), axes)
    dens = np.transpose(vevm.to_dense(), axes)

    def get(a):
        if not (0 <= a < mask.shape[0] and mask[a].any()):
            return None
        return np.argwhere(mask[a]), dens[a][mask[a]]

    return get


def _sheets(get, order):
    """Yield ``(a, cells (m, 2), densities (m,))`` for the non-empty slices of ``order``
    (slice coordinates), read with ``get`` (:func:`_slices_evm` or :func:`_slices_dense`)."""
    for a in order:
        got = get(a)
        if got is not None:
            yield (a,) + got


def _sheet_gradients(get, a, cells):
    """Index-space gradients ``(m, 3)`` (A, B, C) at the cells of slice ``a``, the
    reference's rule (:func:`._gradients.region_gradients`), from slices ``a - 1 .. a + 1``."""
    lo = cells.min(axis=0) - 1
    shape = tuple(cells.max(axis=0) - lo + 2)
    dens = np.zeros((3,) + shape)
    mask = np.zeros((3,) + shape, bool)
    for j, k in enumerate((a - 1, a, a + 1)):
        got = get(k)
        if got is not None:
            c, d = got
            c = c - lo
            fits = np.all((c >= 0) & (c < shape), axis=1)
            dens[j, c[fits, 0], c[fits, 1]] = d[fits]
            mask[j, c[fits, 0], c[fits, 1]] = True
    grads = np.empty((3, 1, shape[0] - 2, shape[1] - 2))
    region_gradients(dens, mask, grads)
    return grads[:, 0, cells[:, 0] - lo[0] - 1, cells[:, 1] - lo[1] - 1].T


def _sheet_neighbours(get, a, cells, dens):
    """Densities ``(2, m)`` at the cells of slice ``a`` in slices ``a - 1`` and ``a + 1``, the
    cell's own density where that neighbour is outside the region (the reference's clamp
    policy: interpolation renormalised over region voxels)."""
    lo = cells.min(axis=0)
    shape = tuple(cells.max(axis=0) - lo + 1)
    at = (cells[:, 0] - lo[0], cells[:, 1] - lo[1])
    out = np.empty((2, len(cells)), np.float32)
    for j, k in enumerate((a - 1, a + 1)):
        out[j] = dens
        got = get(k)
        if got is None:
            continue
        grid = np.full(shape, -1, np.int64)  # index into slice k's voxels, -1: none
        c, d = got
        c = c - lo
        fits = np.flatnonzero(np.all((c >= 0) & (c < shape), axis=1))
        grid[c[fits, 0], c[fits, 1]] = fits
        idx = grid[at]
        has = idx >= 0
        out[j, has] = d[idx[has]]
    return out


def _neighbourhood(cells, dens, radius, op, fill):
    """``op`` (np.minimum / np.maximum) of the densities of the sheet's voxels within
    ``radius`` voxels (square window) of each voxel; ``(m,)`` float64."""
    lo = cells.min(axis=0)
    size = cells.max(axis=0) - lo + 1 + 2 * radius
    grid = np.full(tuple(size), fill)
    at = (cells[:, 0] - lo[0] + radius, cells[:, 1] - lo[1] + radius)
    grid[at] = dens
    # Windows of 2·radius + 1 per axis by doubling: after the loop ``src[i]`` covers
    # ``i .. i + width - 1`` (cut at the end, which is padding), and two such windows with
    # ``width > radius`` cover ``i - radius .. i + radius``.
    for ax in (0, 1):
        src = np.moveaxis(grid, ax, 0)
        width = 1
        while 2 * width <= 2 * radius + 1:
            op(src[:-width], src[width:], out=src[:-width])
            width *= 2
        out = np.full_like(grid, fill)
        m = src.shape[0] - 2 * radius
        shift = 2 * radius + 1 - width
        op(src[:m], src[shift:shift + m], out=np.moveaxis(out, ax, 0)[radius:radius + m])
        grid = out
    return grid[at]


def _footprint_table(sigma, radius):
    """``exp(-r² / 2σ²)`` at ``_FOOTPRINT_SIZE`` values of ``r²`` over ``[0, radius²]`` and a
    final 0 (beyond the radius); returns ``(table, scale)`` with row ``= floor(r²·scale)``."""
    r2 = (np.arange(_FOOTPRINT_SIZE) + 0.5) * (radius ** 2 / _FOOTPRINT_SIZE)
    tab = np.append(np.exp(-r2 / (2 * sigma ** 2)), 0.0).astype(np.float32)
    return tab, _FOOTPRINT_SIZE / radius ** 2


def render_splat(vevm, camera, tf, grid_to_world, *, mode="over", depth_in=None, skip_empty=True,
                 termination=0.99, shading=None, kernel_sigma=0.4, kernel_radius=1.0,
                 max_footprint_px=32, blend=0.2, substeps=1, xray_scale=1.0, xray_offset=0.0):
    """Render a VolumeEVM by sheet-buffer splatting (module docstring).

    Parameters
    ----------
    vevm : VolumeEVM
    camera : Camera
    tf : TransferFunction
        Post-classification (unused, may be None, for ``mode="xray"``).
    grid_to_world : (4, 4) ndarray
        Voxel-centre index space to Blender world.
    mode : {"over", "under", "xray", "mip"}
    depth_in : (H, W) ndarray, optional
        Axial depth of scene geometry (Blender units): each sheet counts only the part of its
        slab in front of it; NaN raises :class:`VolumeEVMError`.
    skip_empty : bool
        True: sheets from the EVM's sections and the densities table (the region only).
        False: the same algorithm scanning the dense grid with the region mask. Same image.
    termination : float
        ``"over"``: pixels whose opacity reaches it take no more splats, and voxels whose
        window is all such pixels are skipped (error at most ``1 - termination``); 1 = off.
    shading : None, True, dict or Shading
        Gradient shading for over/under (:class:`._shading.Shading`, the reference's
        Blinn–Phong headlight): per-voxel 3x3x3 Sobel gradients over region voxels (from the
        neighbouring sheets, :mod:`._gradients`), splatted with the densities and normalised
        the same way.
    kernel_sigma, kernel_radius : float
        Gaussian kernel's standard deviation and truncation radius, in voxels (defaults 0.4
        and 1.0: weights are normalised per pixel, so the cut costs little; the radius must
        exceed √3/2 so that every cell a ray crosses reaches the pixel).
    max_footprint_px : int
        Largest half-width (pixels) of a footprint window; larger footprints (extreme
        close-ups) are cut.
    blend : float in [0, 1)
        Cross-fade between sheet families: every axis whose physical ``|view|`` component is
        within this fraction of the largest one renders its own sheets, and the images are
        blended with smooth weights (:func:`_family_weights`), so the image changes smoothly
        where the principal axis switches (about one axis: from 38.7° to 51.3° for the
        default 0.2; costs up to 2×, 3× near a diagonal, there). Depth comes from the family
        with the largest weight. 0 = hard switch (pops).
    substeps : int >= 1
        Sub-slabs per sheet, the density linear along ``A`` and each classified apart
        (module docstring: one sample per slab makes the image depend on the sub-voxel phase
        of the rays). 1 (default) = Westover's one sample per sheet, box along ``A``; 3
        removes the phase pop and halves the error on smooth data, at 2.2× the frame time
        (CT head, 512²), but is not the default yet (module docstring: thin shells). MIP always
        takes one: the density, linear along ``A`` between the sheets, peaks on their planes.
    xray_scale, xray_offset : float
        X-ray attenuation per mm per data unit and the density of zero attenuation.

    Returns
    -------
    rgba : (H, W, 4) ndarray of np.float32
        Premultiplied RGBA, row 0 at the top.
    depth : (H, W) ndarray of np.float32
        Axial depth (Blender units) of the first visible sheet; 1e10 where none.
    """
    g, depth_in, compositing = checked_view(vevm, camera, tf, grid_to_world, mode, depth_in,
                                            termination, xray_scale, xray_offset)
    shading = checked_shading(shading) if mode in ("over", "under") else None
    try:
        sigma, radius = float(kernel_sigma), float(kernel_radius)
    except (TypeError, ValueError):
        sigma = radius = np.nan
    if not (np.isfinite(sigma) and np.isfinite(radius) and sigma > 0 and radius >= 0.9):
        raise VolumeEVMError(f"kernel_sigma/kernel_radius: need sigma > 0 and radius >= 0.9 "
                             f"voxels, got {kernel_sigma!r}, {kernel_radius!r}")
    max_px = positive_integer("max_footprint_px", max_footprint_px)
    try:
        blend = float(blend)
    except (TypeError, ValueError):
        blend = np.nan
    if not 0 <= blend < 1:
        raise VolumeEVMError(f"blend: must be in [0, 1), got {blend!r}")
    substeps = positive_integer("substeps", substeps)
    h, w = camera.shape
    depth = np.full(h * w, BACKGROUND_DEPTH, np.float32)
    if vevm.evm.is_empty():
        return np.zeros((h, w, 4), np.float32), depth.reshape(h, w)

    inv = np.linalg.inv(g)
    view, cam_i = _view(vevm, camera, inv)
    splat_view = _SplatView(camera, g, inv, camera_rays(camera, g, vevm.shape, depth_in), view,
                            cam_i, Lighting.of_view(shading, g, tf),
                            optics(tf, compositing, shading))
    kernel = _Kernel(sigma, radius, max_px, 1 if mode == "mip" else substeps)
    weights = _family_weights(view * np.asarray(vevm.spacing, dtype=np.float64), blend)
    out = None
    for axis in np.argsort(-weights, kind="stable"):  # ties: the lower axis first
        if weights[axis] == 0:
            break
        acc, dep = _render_axis(vevm, int(axis), splat_view, kernel, compositing, tf,
                                skip_empty)
        if out is None:  # the dominant family gives the depth
            out, depth = acc * np.float32(weights[axis]), dep
        else:
            out += acc * np.float32(weights[axis])
    return out, depth


def tables_to_build(vevm, camera, tf, grid_to_world, options):
    """How many sheet families (principal axes) the render would build tables for: the axes
    the view blends (:func:`_family_weights`) whose sections (:func:`_slabs`, made with the
    axis's densities table) are not in ``vevm.cache`` yet; every one with ``skip_empty=False``
    (the dense slices are made per render). Changes nothing: it only looks at the caches.

    ``options`` are the renderer's keywords (``mode`` included); ``tf`` is unused (the culled
    voxels per transfer function are made a slice at a time, small beside the sections).
    """
    if vevm.evm.is_empty():
        return 0
    view, _ = _view(vevm, camera, np.linalg.inv(grid_to_world))
    weights = _family_weights(view * np.asarray(vevm.spacing, dtype=np.float64),
                              float(options.get("blend", 0.2)))
    axes = np.flatnonzero(weights > 0)
    if not options.get("skip_empty", True):
        return len(axes)
    return sum(_slabs_key(int(axis)) not in vevm.cache for axis in axes)


def _view(vevm, camera, inv):
    """The view direction in index space (perspective: from the camera to the volume's
    centre) and the camera's position in index space (None when orthographic); ``inv``:
    world to index space."""
    if camera.is_ortho:
        return camera.forward @ inv[:3, :3].T, None
    cam_i = camera.position @ inv[:3, :3].T + inv[:3, 3]
    view = (np.asarray(vevm.shape) - 1) / 2.0 - cam_i
    if not np.any(view):
        view = camera.forward @ inv[:3, :3].T
    return view, cam_i


def _family_weights(view, blend):
    """Weights ``(3,)`` of the three sheet families (principal axes) for a physical-space view
    direction: 1 for the axis most parallel to the view alone, a smooth cross-fade between
    the axes whose ``|view|`` lies within ``blend`` (relative) of the largest one. The
    weights are continuous in the view direction, so the image is too (no popping where
    the principal axis switches); ``blend = 0`` is the classic hard switch."""
    ratio = np.abs(view) / np.abs(view).max()
    if blend == 0:
        weights = (np.arange(3) == np.argmax(ratio)).astype(np.float64)
    else:
        x = np.clip((ratio - (1 - blend)) / blend, 0, 1)
        weights = x * x * (3 - 2 * x)  # smoothstep: no kink where a family fades in
    return weights / weights.sum()


@dataclass(frozen=True, slots=True, eq=False)
class _Kernel:
    """The voxels' footprints: a Gaussian of ``sigma`` voxels truncated at ``radius`` voxels,
    windows of at most ``max_px`` pixels half-width, ``substeps`` sub-slabs per sheet."""

    sigma: float
    radius: float
    max_px: int
    substeps: int


@dataclass(frozen=True, slots=True, eq=False)
class _SplatView:
    """What the sheet families of a view share: the ``camera``, ``g`` (grid to world) and its
    inverse ``inv``, the pixel ``rays`` (:func:`._rays.camera_rays`), the index-space
    ``view`` direction and camera position ``cam_i`` (None when orthographic, :func:`_view`),
    the ``lighting`` (None: unshaded) and the ``optics`` (opacity per unit length: each sample
    is corrected for its own path)."""

    camera: object
    g: np.ndarray
    inv: np.ndarray
    rays: Rays
    view: np.ndarray
    cam_i: np.ndarray
    lighting: Lighting
    optics: Optics


@dataclass(frozen=True, slots=True, eq=False)
class _Sheet:
    """The voxels of a sheet to splat, one row each: ``cells`` (B, C), densities ``dens``,
    the densities at the same cells in the neighbouring slices ``nb`` ((2, m); None without
    sub-slabs), pixel positions ``uv`` and those of the neighbours one voxel along B and C
    (``uvb``, ``uvc``), the unit view direction ``u`` (index space) and the half-widths of
    each footprint's window in pixels, ``hwid`` (m, 2)."""

    cells: np.ndarray
    dens: np.ndarray
    nb: np.ndarray
    uv: np.ndarray
    uvb: np.ndarray
    uvc: np.ndarray
    u: np.ndarray
    hwid: np.ndarray

    def take(self, keep):
        """The voxels ``keep`` (a mask or indices)."""
        return _Sheet(self.cells[keep], self.dens[keep],
                      None if self.nb is None else self.nb[:, keep], self.uv[keep],
                      self.uvb[keep], self.uvc[keep], self.u[keep], self.hwid[keep])


@dataclass(frozen=True, slots=True, eq=False)
class _Projection:
    """How the voxels of the sheets along ``axes[0]`` reach the image: ``axes`` (A, B, C as
    grid axes), the ``view``, ``fwd_i`` (the camera's forward direction in index space) and,
    orthographic, ``ortho``: the projection, affine in index space (rows: pixel u, v and depth
    of the index origin, then per unit of x, y, z; None for perspective)."""

    view: _SplatView
    axes: tuple
    fwd_i: np.ndarray
    ortho: np.ndarray

    @classmethod
    def of_view(cls, view, axes):
        """The projection of ``view`` for the sheet family of ``axes``."""
        camera, g = view.camera, view.g
        ortho = None
        if camera.is_ortho:
            corners = np.vstack([g[:3, 3], g[:3, 3] + g[:3, :3].T])
            uv0, depth0 = camera.project(corners)
            ortho = np.column_stack([uv0, depth0])
            ortho[1:] -= ortho[0]
        return cls(view, axes, camera.forward @ view.inv[:3, :3].T, ortho)

    def project(self, a, cells):
        """The voxels ``cells`` of sheet ``a`` in the image: pixel positions ``uv``, depths,
        the positions of their neighbours one voxel along B and C (``uvb``, ``uvc``), the
        image motion per unit of B and C (``jb``, ``jc``) and the view direction (index
        space); orthographic: one row of motion and direction for all voxels."""
        axis, b_ax, c_ax = self.axes
        vox = np.empty((len(cells), 3), np.float64)
        vox[:, axis] = a
        vox[:, b_ax] = cells[:, 0]
        vox[:, c_ax] = cells[:, 1]
        if self.ortho is not None:
            uvd = transform(vox, self.ortho[1:], self.ortho[0])
            uv, vdepth = uvd[:, :2], uvd[:, 2]
            jb, jc = self.ortho[1 + b_ax, None, :2], self.ortho[1 + c_ax, None, :2]
            return uv, vdepth, uv + jb, uv + jc, jb, jc, self.fwd_i[None, :]
        g, camera = self.view.g, self.view.camera
        world = transform(vox, g[:3, :3].T, g[:3, 3])
        uv, vdepth = camera.project(world)
        uvb, _ = camera.project(world + g[:3, b_ax])
        uvc, _ = camera.project(world + g[:3, c_ax])
        return uv, vdepth, uvb, uvc, uvb - uv, uvc - uv, vox - self.view.cam_i

    def place(self, a, cells, dens, nb, kernel):
        """The :class:`_Sheet` of the voxels of sheet ``a`` in front of the camera whose
        footprints the image can show, and ``reach``: offsets reach a sub-sample's footprint
        if they lie within this of the crossing point; None if there are none."""
        axis, b_ax, c_ax = self.axes
        n = len(cells)
        uv, vdepth, uvb, uvc, jb, jc, dirs = self.project(a, cells)
        u = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        uA = np.abs(u[:, axis])
        # Footprint window: the kernel's in-plane ellipse mapped by the local projection, moved
        # along the ray's drift by up to ``shift`` (the slab's outermost sub-sample).
        shift = (1 - 1 / kernel.substeps) / 2
        with np.errstate(invalid="ignore", divide="ignore"):
            slope_b = np.abs(u[:, b_ax]) / uA
            slope_c = np.abs(u[:, c_ax]) / uA
            ext_b = kernel.radius * np.sqrt(1 + slope_b ** 2) + shift * slope_b
            ext_c = kernel.radius * np.sqrt(1 + slope_c ** 2) + shift * slope_c
            hwid = np.abs(jb) * ext_b[:, None] + np.abs(jc) * ext_c[:, None]
        ok = (np.isfinite(uv).all(axis=1) & (vdepth > 0) & (uA > 1e-6)
              & np.isfinite(hwid).all(axis=1))
        sheet = _Sheet(cells, dens, nb, uv, uvb, uvc, np.broadcast_to(u, (n, 3)),
                       np.broadcast_to(hwid, (n, 2)))
        if not ok.all():
            sheet = sheet.take(ok)
        if len(sheet.cells) == 0:
            return None
        u = sheet.u
        reach = kernel.radius + shift * float(np.max(np.hypot(u[:, b_ax], u[:, c_ax])
                                                     / np.abs(u[:, axis])))
        return sheet, reach


def _render_axis(vevm, axis, view, kernel, compositing, tf, skip_empty):
    """Composite the sheets along ``axis`` (checked arguments as :func:`render_splat` gives
    them). Returns ``(rgba (H, W, 4), depth (H, W))``."""
    camera = view.camera
    mode, termination = compositing.mode, compositing.termination
    substeps = kernel.substeps
    h, w = camera.shape
    b_ax, c_ax = ["xyz".index(ch) for ch in TABLE_ORDERS[axis][1:]]
    img, entered = _crossings(view.rays, axis, b_ax, c_ax, vevm.spacing)
    img = {k: v.reshape(h, w) for k, v in img.items()}
    crossings = Crossings(*(np.ascontiguousarray(img[key], dtype=np.float64) for key in (
        "tA", "iA", "span", "t0", "t1", "B0", "B1", "C0", "C1", "dB", "dC", "mm", "a0", "kz")),
        np.ascontiguousarray(view.rays.dirs, dtype=np.float64).reshape(h, w, 3))
    get = (_slices_evm if skip_empty else _slices_dense)(vevm, axis)
    sheets = _sheets(get, _sheet_order(vevm.shape[axis], axis, view, mode))

    ftab, fscale = _footprint_table(kernel.sigma, kernel.radius)
    fscale = np.float32(fscale)
    normal = np.zeros(0)  # the sheets' (A, B, C) gradient to a world normal, row by row
    if view.lighting is not None:
        normal = np.ascontiguousarray(view.lighting.inv_t[:, [axis, b_ax, c_ax]],
                                      dtype=np.float64).ravel()
    acc = np.zeros((h, w, 4), np.float32)
    depth = np.full((h, w), BACKGROUND_DEPTH, np.float32)
    done = ~entered.reshape(h, w)  # pixels that take no more contributions
    # Flat views of the images for the kernel.
    out = Image(acc.reshape(-1, 4), depth.reshape(-1), done.reshape(-1),
                np.full(h * w if mode == "mip" else 0, -np.inf, np.float32))
    cull = None
    if _CULL_INVISIBLE and mode != "mip":
        rule, visible = _cull_rule(kernel, compositing, tf, view.optics.lut_scale)
        cull = _culler(get, _kept_voxels(vevm, axis, rule) if skip_empty else {}, visible,
                       substeps)
    projection = _Projection.of_view(view, (axis, b_ax, c_ax))
    drift = np.zeros(2, np.float32)  # perspective: per pixel, from the crossings
    if camera.is_ortho:
        ortho_offsets = {}  # the same footprint for every voxel and sheet
        fwd_i = projection.fwd_i
        drift = (fwd_i[[b_ax, c_ax]] / abs(fwd_i[axis])).astype(np.float32)  # dB/dA, dC/dA
    for a, cells, dens in sheets:
        live_rows = np.flatnonzero(~done.all(axis=1))
        if len(live_rows) == 0:
            break
        live_cols = np.flatnonzero(~done.all(axis=0))
        if cull is not None:
            keep = cull(a, cells, dens)
            cells, dens = cells[keep], dens[keep]
            if len(cells) == 0:
                continue
        # Off the sheet's plane the density is linear along A towards the neighbouring slice.
        nb = _sheet_neighbours(get, a, cells, dens) if substeps > 1 else None
        placed = projection.place(a, cells, dens, nb, kernel)
        if placed is None:
            continue
        sheet, reach = placed
        hu = int(min(np.ceil(sheet.hwid[:, 0].max()) + 1, kernel.max_px + 1))
        hv = int(min(np.ceil(sheet.hwid[:, 1].max()) + 1, kernel.max_px + 1))
        col = np.floor(sheet.uv[:, 0]).astype(np.int64)
        row = np.floor(sheet.uv[:, 1]).astype(np.int64)
        # The sheet's window in the image, cut to the pixels still taking contributions.
        c0 = max(int(col.min()) - hu, int(live_cols[0]))
        c1 = min(int(col.max()) + hu + 1, int(live_cols[-1]) + 1)
        r0 = max(int(row.min()) - hv, int(live_rows[0]))
        r1 = min(int(row.max()) + hv + 1, int(live_rows[-1]) + 1)
        if c0 >= c1 or r0 >= r1:
            continue
        win = np.s_[r0:r1, c0:c1]
        live = ~done[win]
        if not live.any():
            continue
        bh, bw = live.shape
        if mode == "over" and termination < 1:
            # Skip voxels whose whole window is finished (summed-area table of live pixels).
            sat = np.zeros((bh + 1, bw + 1), np.int32)
            np.cumsum(np.cumsum(live, axis=0, dtype=np.int32), axis=1, out=sat[1:, 1:])
            ra = np.clip(row - hv - r0, 0, bh)
            rb = np.clip(row + hv + 1 - r0, 0, bh)
            ca = np.clip(col - hu - c0, 0, bw)
            cb = np.clip(col + hu + 1 - c0, 0, bw)
            keep = (sat[rb, cb] - sat[ra, cb] - sat[rb, ca] + sat[ra, ca]) > 0
            if not keep.all():
                sheet, col, row = sheet.take(keep), col[keep], row[keep]
            if len(sheet.cells) == 0:
                continue
        cells, dens, nb, uv, u = sheet.cells, sheet.dens, sheet.nb, sheet.uv, sheet.u
        if camera.is_ortho:
            if (hu, hv) not in ortho_offsets:
                ortho_offsets[hu, hv] = _window_offsets(uv, sheet.uvb, sheet.uvc, u[:, b_ax],
                                                        u[:, c_ax], hu, hv, reach, False)
            offsets = ortho_offsets[hu, hv]
        else:
            offsets = _window_offsets(uv, sheet.uvb, sheet.uvc, u[:, b_ax], u[:, c_ax], hu, hv,
                                      reach, True)
        # Orthographic: the crossing point relative to a voxel is J⁻¹ (pixel centre - the
        # voxel's projection), per voxel plus per offset, and the drift is constant.
        # Perspective: the kernel reads the crossing point and drift per pixel.
        centre = per_offset = _NONE2
        if camera.is_ortho:
            ortho = projection.ortho
            kinv = np.linalg.inv(np.column_stack([ortho[1 + b_ax, :2], ortho[1 + c_ax, :2]]))
            centre = transform(np.column_stack([col + 0.5 - uv[:, 0], row + 0.5 - uv[:, 1]]),
                               kinv.T)
            per_offset = offsets @ kinv.T
        footprint = Footprint(ftab, fscale, offsets, per_offset, drift)
        grads = _NONE3 if view.lighting is None else np.ascontiguousarray(
            _sheet_gradients(get, a, cells))
        fb = cells[:, 0].astype(np.float32)
        fc = cells[:, 1].astype(np.float32)
        ub = u[:, b_ax].astype(np.float32)
        uc = u[:, c_ax].astype(np.float32)
        bounds = np.linspace(-0.5, 0.5, substeps + 1)
        bands = [(top, min(top + _BAND_ROWS, bh)) for top in range(0, bh, _BAND_ROWS)]
        # Every ray crossing the sheet runs along +A (or every one along -A): the sheet lies on
        # one side of the camera.
        ahead = u[0, axis] > 0
        for k in (range(substeps)[::-1] if mode == "under" else range(substeps)):
            at = 0.5 * (bounds[k] + bounds[k + 1])  # the sub-slab's centre, along the ray
            sub = dens
            if nb is not None and abs(at) > 1e-9:
                # Linear interpolation (the reference's trilinear along A) with the slice on
                # the sub-slab's side, |at| slices away.
                side = nb[1] if (at > 0) == ahead else nb[0]
                sub = dens + np.float32(abs(at)) * (side - dens)
            voxels = Voxels(col - c0, row - r0, fb, fc, np.asarray(sub, dtype=np.float32), grads,
                            ub, uc, centre)
            slab = Slab(float(a), float(bounds[k]), float(bounds[k + 1]), np.float32(at), r0, c0,
                        live)
            parallel_map(splat_rows, [(top, bottom, voxels, footprint, slab, crossings,
                                       view.optics, normal, out) for top, bottom in bands])
    visible = finish_mode(out.acc, out.vmax, mode, tf)
    if visible is not None:
        out.depth[~visible] = BACKGROUND_DEPTH
    return acc, depth


def _crossings(rays, axis, b_ax, c_ax, spacing):
    """Per pixel: where its ray crosses the plane ``A = a`` (``B = B0 + a·B1``, ``C``
    likewise), its parameter there (``t = tA + a·iA``), the drift per unit of path along the
    ray's own direction (``dB``, ``dC``: offsets count along the ray), the mm per unit of
    ``A``, its axial depth ``a0 + kz·t`` and the clipped ray range ``[t0, t1]``; and which
    rays reach the volume at all."""
    o, d = rays.o, rays.d
    reach = rays.t1 > rays.t0
    with np.errstate(divide="ignore", invalid="ignore"):
        iA = 1.0 / d[:, axis]
    reach &= np.isfinite(iA)
    iA = np.where(reach, iA, 0.0)
    img = {
        "B1": d[:, b_ax] * iA,
        "C1": d[:, c_ax] * iA,
        "tA": -o[:, axis] * iA,
        "iA": iA,
        "span": np.abs(iA),  # ray parameter per unit of A
        "t0": np.where(reach, rays.t0, 0.0),
        "t1": np.where(reach, rays.t1, 0.0),
        "mm": rays.mm_per_t(np.asarray(spacing, dtype=np.float64)) * np.abs(iA),
        "a0": rays.a0,
        "kz": rays.kz,
    }
    img["B0"] = o[:, b_ax] - o[:, axis] * img["B1"]
    img["C0"] = o[:, c_ax] - o[:, axis] * img["C1"]
    img["dB"] = img["B1"] * np.sign(iA)
    img["dC"] = img["C1"] * np.sign(iA)
    return img, reach


def _sheet_order(n_a, axis, view, mode):
    """The slices along ``axis`` in compositing order: outward from the camera, the side the
    view faces first (front to back for every ray that sees a sheet; rays see no sheet behind
    their start); reversed for ``"under"``."""
    ahead = np.arange(n_a) if view.view[axis] > 0 else np.arange(n_a)[::-1]
    if view.cam_i is None:
        order = ahead
    else:
        is_ahead = (ahead - view.cam_i[axis]) * np.sign(view.view[axis]) >= 0
        order = np.concatenate([ahead[is_ahead], ahead[~is_ahead][::-1]])
    return order[::-1] if mode == "under" else order


def _cull_rule(kernel, compositing, tf, lut_scale):
    """Which voxels cannot change the image: ``(rule, visible)``, the rule's key (what the
    kept voxels depend on) and ``visible(cells, lo, hi)``, whether the voxels of a sheet whose
    samples lie between densities ``lo`` and ``hi`` may be seen; ``lut_scale``: the
    classification table's rows per data unit."""
    # Every pixel a voxel reaches takes its density from voxels at most 2·radius·√3
    # in-plane voxels from it (the footprint's ellipse for the most oblique view).
    reach_vox = int(np.ceil(2 * kernel.radius * np.sqrt(3.0)))
    if compositing.mode == "xray":
        xray_scale, xray_offset = compositing.xray_scale, compositing.xray_offset
        rule = ("xray", reach_vox, kernel.substeps > 1, xray_scale, xray_offset)

        def visible(cells, lo_, hi_):
            hi = _neighbourhood(cells, hi_, reach_vox, np.maximum, -np.inf)
            return (hi > xray_offset) & (xray_scale > 0)
    else:
        margin = 1.0 / lut_scale  # one lookup-table step: the table is interpolated
        rule = ("tf", reach_vox, kernel.substeps > 1, margin, tf.points[:, [0, 4]].tobytes())

        def visible(cells, lo_, hi_):
            lo_ = _neighbourhood(cells, lo_, reach_vox, np.minimum, np.inf)
            hi_ = _neighbourhood(cells, hi_, reach_vox, np.maximum, -np.inf)
            return ~tf.transparent_between(lo_ - margin, hi_ + margin)
    return rule, visible


def _culler(get, kept, visible, substeps):
    """``cull(a, cells, dens)``: the indices of sheet ``a``'s voxels to splat, by
    :func:`_cull_rule`'s ``visible``, remembered in ``kept`` per slice."""

    def cull(a, cells, dens):
        """Sub-slabs interpolate towards the neighbouring slices, so a voxel's samples lie
        between its density and theirs."""
        if a not in kept:
            lo_ = hi_ = dens
            if substeps > 1:
                nb = _sheet_neighbours(get, a, cells, dens)
                lo_ = np.minimum(dens, nb.min(axis=0))
                hi_ = np.maximum(dens, nb.max(axis=0))
            kept[a] = np.flatnonzero(visible(cells, lo_, hi_)).astype(np.int32)
        return kept[a]

    return cull


def _window_offsets(uv, uvb, uvc, ub, uc, hu, hv, radius, perspective):
    """Pixel offsets ``(k, 2)`` (column, row) from a voxel's pixel that its footprint can reach.

    The footprint is the in-plane set ``|q_⊥| <= radius`` (which also holds every cell the
    ray's path in the slab can cross); a pixel offset ``δ`` maps to ``q = J⁻¹ δ`` with ``J``
    the local projection of the plane (columns: image motion per unit B and C). A pixel
    reaches it if its centre, anywhere within half a pixel of ``δ`` (the voxel's sub-pixel
    position), does; the seminorm's triangle inequality bounds that. Perspective: ``J`` and
    ``u`` of the voxel with the largest footprint, one pixel of margin.
    """
    big = np.argmax(np.abs((uvb - uv)[:, 0] * (uvc - uv)[:, 1]
                           - (uvb - uv)[:, 1] * (uvc - uv)[:, 0]))
    jac = np.stack([uvb[big] - uv[big], uvc[big] - uv[big]], axis=1)  # (2, 2)
    inv = np.linalg.pinv(jac)
    ud = np.array([ub[big], uc[big]])

    def perp(q):  # |q_⊥| for in-plane offsets q (..., 2)
        along = q @ ud
        return np.sqrt(np.maximum((q * q).sum(axis=-1) - along * along, 0))

    ou, ov = np.meshgrid(np.arange(-hu, hu + 1), np.arange(-hv, hv + 1))
    cand = np.stack([ou.ravel(), ov.ravel()], axis=1).astype(np.float64)
    # The pixel centre relative to the voxel's projection lies within half a pixel of delta.
    corners = np.array([(-0.5, -0.5), (-0.5, 0.5), (0.5, -0.5), (0.5, 0.5)])
    slack = perp(corners @ inv.T).max() * (3.0 if perspective else 1.0)
    keep = perp(cand @ inv.T) <= radius + slack
    return cand[keep].astype(np.int64)


# ---------------------------------------------------------------------------- the record
def _check_samples(vevm, pixels, options):
    """Refuse more than ``MAX_SAMPLES`` samples: the sheets (the largest side) times
    ``substeps`` per covered pixel."""
    substeps = options["substeps"]
    per_ray = max(vevm.shape) * substeps
    if pixels * per_ray > MAX_SAMPLES:
        most = max(1, MAX_SAMPLES // (pixels * max(vevm.shape)))
        raise VolumeEVMError(
            f"substeps: {substeps} sub-slabs per sheet would take about "
            f"{pixels * per_ray:.2g} samples ({pixels} pixels x {per_ray} per ray), more "
            f"than the {MAX_SAMPLES:.0e} a render may take (hours); use substeps <= {most} "
            f"or a smaller image")


def _quality(quality, smallest_mm):
    """Quality rounded is sub-slabs per sheet."""
    return {"substeps": max(1, int(round(quality)))}


SPLAT_METHOD = Method(
    name="splat", label="Splatting",
    description="Voxel footprints, sheet by sheet along the principal axis",
    render=render_splat, options=keyword_options(render_splat),
    # Per-axis sheets come from the region's voxels beside the axis's densities table: per
    # region voxel and axis, the sections (cells per slab) and culled voxel lists.
    memory=MemoryModel(pixel=340, region=56, axis_table=True),
    tables_to_build=tables_to_build, check_samples=_check_samples, quality=_quality)
"""Sheet-buffer splatting (Westover), post-classified."""
