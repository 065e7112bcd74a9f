"""Shear-warp rendering of a VolumeEVM (Lacroute & Levoy), parallel and perspective.

The view is factored into a shear (perspective: a shear and a per-slice scale) that makes every
ray perpendicular to the slices of the **principal axis**, and one 2-D warp from the
intermediate image (one pixel per voxel of a slice, or ``intermediate_scale`` pixels per voxel
along each in-slice axis) to the final image. The stages live in modules of their own, as
VolPack keeps them in files of their own; each module's docstring describes its stage:

- :mod:`._view` (VolPack ``vp_view.c``): the factorization of a view: principal axis, passes,
  per-slice maps, the warp's map, the sample spacing along the rays;
- :mod:`._layouts` (``vp_rle.c``, ``vp_octree.c``): the slices of a principal axis as runs of
  voxels (the EVM's runs) and, per transfer function, the runs worth compositing, kept in
  ``vevm.cache``;
- :mod:`._composite` (``vp_compA*.c``): the samples classified, lit and composited slice by
  slice into the intermediate image, with the runs skipping transparent voxels and pointers
  skipping opaque pixels;
- :mod:`._warp` (``vp_warp.c``): the intermediate image resampled into the final image, and the
  output depth.

This module checks the options, says which tables a render would build
(:func:`tables_to_build`, for the memory check) and runs the stages per pass
(:func:`render_shear_warp`). Each stage's loops are compiled kernels in its own module.

Known limits: by default one sample per slice (inter-slice aliasing unless
``slices_per_voxel`` > 1), one intermediate pixel per voxel (zooming in blurs unless
``intermediate_scale`` > 1), pre-classification smooths boundaries, and in perspective
rays far from the principal axis are sampled more sparsely (the seams between the passes of an
eye inside the region show as changes of sampling). The principal axis switches at 45°; the
change across the switch is resampling noise, not popping (docs/measurements.md).

References
----------
P. Lacroute, M. Levoy, "Fast volume rendering using a shear-warp factorization of the viewing
transformation", SIGGRAPH 1994, https://doi.org/10.1145/192161.192283.
J. P. Schulze, R. Niemeier, U. Lang, "The perspective shear-warp algorithm in a virtual
environment", IEEE Visualization 2001, https://doi.org/10.1109/VISUAL.2001.964517.
VolPack 1.0b3 (``vp_view.c``, ``vp_renderA.c``, ``vp_warp.c``), Stanford University.
"""

import numpy as np

from ..._errors import VolumeEVMError
from ...model._densities import TABLE_ORDERS, run_count
from .._camera import BACKGROUND_DEPTH
from .._checks import categorical, checked_view, flag, positive_integer
from .._method import MemoryModel, Method, keyword_options
from .._shading import checked_shading
from ._composite import Clip, Sampling, intermediate_image
from ._layouts import CHUNK, cache_key, dense_layout, region_layout
from ._view import View, passes
from ._warp import warp_frame

__all__ = ["render_shear_warp", "tables_to_build", "SLICES_PER_VOXEL", "CLASSIFICATIONS",
           "SHEAR_WARP_METHOD"]

SLICES_PER_VOXEL = (1, 2, 3, 4, 8)
"""Allowed samples per voxel slice along the rays (Shear-Warp Deluxe's intermediate slices)."""
CLASSIFICATIONS = ("pre", "post")
"""Classify voxels, then interpolate colours ("pre"), or interpolate densities, then classify."""


def render_shear_warp(vevm, camera, tf, grid_to_world, *, mode="over", depth_in=None,
                      skip_empty=True, termination=0.99, shading=None, intermediate_scale=1.0,
                      slices_per_voxel=1, classification="pre", lut_size=4096, xray_scale=1.0,
                      xray_offset=0.0):
    """Render a VolumeEVM by shear-warp (the stages' module docstrings: factorization,
    sampling, boundary policy, depth).

    Parameters
    ----------
    vevm : VolumeEVM
    camera : Camera
        Orthographic or perspective (Blender's conventions, :mod:`.._camera`).
    tf : TransferFunction
        Classification; unused (may be None) for ``mode="xray"``.
    grid_to_world : (4, 4) ndarray
        Voxel-centre index space to world (Blender units), :func:`volumeevm_addon.grid_to_world`.
    mode : {"over", "under", "xray", "mip"}
        As in :func:`.._reference.render_reference`.
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
        Gradient shading for ``"over"`` and ``"under"`` (:class:`.._shading.Shading`:
        Blinn–Phong headlight; ignored by ``"xray"`` and ``"mip"``), applied per voxel before
        interpolation (pre-classification): per-voxel gradients (the reference's 3x3x3
        Sobel, :mod:`.._gradients`) are computed once per principal axis and cached; each
        view lights them along one direction (perspective: eye to the region's centre).
    slices_per_voxel : {1, 2, 3, 4, 8}
        Samples along each ray per voxel slice (:mod:`._composite`): 1 is VolPack's one
        sample per slice; more interpolate between slices (trilinear): each voxel slice is
        classified once and every sample blends two of them, then resamples once (CT head
        512²: 2 slices cost twice one).
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
    sampling = Sampling(int(slices_per_voxel), classification, int(lut_size), shading)
    h, w = camera.shape
    rgba_out = np.zeros((h, w, 4), np.float32)
    depth_out = np.full((h, w), BACKGROUND_DEPTH, np.float32)
    if vevm.evm.is_empty():
        return rgba_out, depth_out
    for axis, step, rays in passes(vevm, camera, g):
        layout = region_layout(vevm, axis) if skip_empty else dense_layout(vevm, axis)
        view = View(vevm, camera, g, layout, intermediate_scale, axis, step, rays)
        if view.empty:
            continue
        frame, front = intermediate_image(vevm, view, layout, tf, compositing, sampling,
                                          Clip.of_view(view, camera, g, depth_in))
        warp_frame(view, camera, frame, front, rgba_out, depth_out)
    return rgba_out, depth_out


def tables_to_build(vevm, camera, tf, grid_to_world, options):
    """How many principal axes the render would build slice tables for: the axes of its passes
    (:func:`._view.passes`) whose layout, or what this render reads beside it (the transfer
    function's classes, or the post-classification table and the function's runs; the
    gradients with shading), is not in ``vevm.cache`` (:func:`._layouts.cache_key`); every one with
    ``skip_empty=False`` (the dense layout is made per render). Changes nothing: it only
    looks at the cache.

    ``options`` are the renderer's keywords (``mode`` included).
    """
    if vevm.evm.is_empty():
        return 0
    axes = {axis for axis, _, _ in passes(vevm, camera, np.asarray(grid_to_world, float))}
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
        parts = ("layout", "classes") + (("gradients", "lit") if shaded else ())
    return sum(not all(cache_key(axis, part, tf, lut_size) in vevm.cache for part in parts)
               for axis in axes)


# ---------------------------------------------------------------------------- the record
_INTERMEDIATE_BYTES = 40
"""Per intermediate pixel: the RGBA image, its rank and depth maps, slice buffers."""


def _intermediate_bytes(vevm, options):
    """The intermediate image: one pixel per voxel (times the scale) along the two in-slice
    axes, the slices sheared across up to one voxel per slice: at most (n1 + n2)² for the two
    largest sides."""
    scale = float(options["intermediate_scale"])
    n1, n2 = sorted(vevm.shape)[-2:]
    return int((scale * (n1 + n2)) ** 2) * _INTERMEDIATE_BYTES


def _set_bytes(vevm, options):
    """One principal axis's tables: the layout (the densities in the axis's order, its runs
    with their scanline starts) and, pre-classification, the classes (int16 rows, the visible
    voxels' flags, their runs) or else the post-classification table (float32 densities) and,
    for "over" and "under", the mixed codes (int32 codes, flags, table rows, three slices of
    codes); with ``skip_empty=False``, the dense layout made for the render instead: the
    transposed grid, its copy as the layout's values, its mask, classes and runs per grid
    voxel."""
    itemsize = vevm.table(0).dtype.itemsize
    nx, ny, nz = (int(n) + 2 for n in vevm.shape)
    face = max(nx * ny, ny * nz, nx * nz)
    if not options.get("skip_empty", True):
        return nx * ny * nz * (2 * itemsize + 10) + 48 * face
    mode = options.get("mode", "over")
    if mode in ("xray", "mip"):
        per_voxel = 4
    elif options.get("classification", "pre") == "post":
        per_voxel = 4 + 4 + 1 + 2
    else:
        per_voxel = 2 + 1
    runs = max(run_count(vevm.evm, order) for order in TABLE_ORDERS)
    return (int(vevm.voxel_count) * (itemsize + per_voxel) + 2 * 16 * runs + 48 * face
            + 32 * CHUNK)


def _quality(quality, smallest_mm):
    """Quality is intermediate pixels per voxel."""
    return {"intermediate_scale": quality}


SHEAR_WARP_METHOD = Method(
    name="shear_warp", label="Shear-Warp",
    description="Sheared slices, one intermediate image, one 2D warp (fast)",
    render=render_shear_warp, options=keyword_options(render_shear_warp),
    # Per principal axis (_set_bytes): the layout and what the transfer function derives from
    # it. Shading: the gradients (12 B per region voxel, and as many while they are listed in
    # the axis's order), the lit voxels' codes, index and colours (16 B per view); counted
    # even when cached (every voxel is lit per view). Checked against tracemalloc peaks on the
    # CT head and the same head upsampled (int16, float32, float64; bone, skin; every mode).
    memory=MemoryModel(pixel=24, shading_region=48, per_set=_set_bytes,
                       per_view=_intermediate_bytes),
    tables_to_build=tables_to_build, check_samples=None,  # bounded by its option ranges
    quality=_quality, categorical=True)
"""Shear-warp (Lacroute & Levoy), parallel and perspective."""
