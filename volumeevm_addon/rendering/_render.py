"""One entry point for direct volume rendering of a VolumeEVM, whatever the method.

Every method reads the VolumeEVM (its EVM for empty-space skipping, its densities tables) and
returns the same thing: a premultiplied RGBA image (row 0 at the top) and the axial depth of the
first visible sample in Blender units (1e10 where nothing is visible), for the scene camera.
The dense reference ray caster of :mod:`._reference` is the accuracy oracle of all of them.

Boundary policy ("clamp", :mod:`._reference`): voxels outside the region are transparent and
never read; interpolation at the region's surface uses only the region's voxels (weights
renormalised). Rendering a VolumeEVM therefore equals rendering the dense volume with
everything outside the region transparent, which is the exactness contract every method keeps.

Resolution levels (:mod:`volumeevm_addon.model._levels`): ``level="auto"`` renders a volume much
finer than the image's pixels from a coarser VolumeEVM (kept in its cache); the exactness
contract holds for the level rendered, and the default ``level="full"`` renders the VolumeEVM
itself.

Before anything is allocated, :func:`render` checks its inputs (every error a
:class:`VolumeEVMError` naming the parameter), bounds the work (:data:`MAX_SAMPLES`) and checks
the memory the render needs (:func:`render_memory`) against what is available
(:func:`volumeevm_addon.system.check_memory`).
"""

import numbers

import numpy as np

from .._errors import VolumeEVMError
from .._memory import check_memory
from ..model._volume import grid_to_world
from ._camera import Camera
from ._checks import (
    categorical,
    check_mode,
    check_volumeevm,
    checked_affine,
    checked_categorical_level,
    positive_number,
)
from ._depth import checked_depth_in
from ._levels import level_factor
from ._method import IMAGE_BYTES_PER_PIXEL, check_method_samples
from ._registry import CPU_METHODS, REGISTRY, method_record

METHODS = CPU_METHODS
"""The methods :func:`render` runs, by name (:func:`~volumeevm_addon.rendering.methods` has
their records, the GPU's too)."""


def render(vevm, camera, tf, *, method="shear_warp", mode="over", depth_in=None, matrix_world=None,
           level="full", **options):
    """Render ``vevm`` seen by ``camera`` with transfer function ``tf``.

    Every method gives the same image up to its sampling error (the exactness contract in the
    module docstring); they differ in speed, memory and quality settings. All settings but the
    volume, the camera and the transfer function are keyword-only.

    Parameters
    ----------
    vevm : VolumeEVM
        The region and its densities.
    camera : Camera
        Blender's projection (see :mod:`._camera`): image size, pixels and depth.
    tf : TransferFunction
        Colour and opacity per density; unused (may be None) for ``mode="xray"``. A
        categorical one (:meth:`TransferFunction.categorical`, label maps) is sampled at the
        nearest voxel, never interpolated: with ray casting, shear-warp and the reference,
        ``"over"``/``"under"``, no shading, no pre-integration, shear-warp's one slice per
        voxel, and the full level (``"auto"`` renders the full level).
    method : {"shear_warp", "splat", "raycast", "raycast_navigate", "reference"}
        ``"shear_warp"`` (default): shear-warp factorisation (Lacroute & Levoy), the fastest
        on the CPU. ``"splat"``: sheet-buffer splatting (Westover), post-classified.
        ``"raycast"``: ray casting with the EVM as space-leaping structure.
        ``"raycast_navigate"``: the same caster finding every density through the EVM (no
        dense array; the report's baseline). ``"reference"``: the dense float64 ray caster,
        the accuracy oracle (slow; ignores ``level``).
    mode : {"over", "under", "xray", "mip"}
        ``"over"``: front-to-back emission–absorption compositing; ``"under"``: back to front
        (the same image up to rounding); ``"xray"``: attenuation through the region (grey,
        ``xray_scale``/``xray_offset``, no transfer function); ``"mip"``: the maximum density
        along each ray, classified by ``tf``.
    depth_in : (H, W) ndarray, optional
        Axial depth (Blender units) of the scene's geometry; rays stop there.
    matrix_world : (4, 4) array_like, optional
        Placement of the volume object in the scene (identity by default).
    level : {"full", "auto"} or int
        Resolution level: ``"full"`` (default) renders ``vevm`` itself; an integer ``f >= 2``
        renders ``vevm.level(f)``, ``f`` times coarser voxels; ``"auto"`` picks the coarsest
        power of two whose voxels are still no wider than a pixel where the volume is nearest
        the camera (:func:`volumeevm_addon.rendering._levels.auto_factor`). A coarser level scales a
        given ``step_mm`` by the factor (the ray casters keep their samples per voxel). The
        reference method ignores it: it is the full-resolution oracle.
    **options
        Method-specific quality settings: the options under Other Parameters, each with the
        methods that take it and their defaults (:func:`render_options` gives the same per
        method). An option the method does not take raises ``TypeError``; a value of the
        wrong type (a number where a flag is expected, a fraction where an integer is) or out
        of range raises :class:`VolumeEVMError` naming it.

    Returns
    -------
    rgba : (H, W, 4) float32
        Premultiplied colour and opacity, row 0 at the top of the image.
    depth : (H, W) float32
        Axial depth in Blender units of the first visible sample; 1e10 where none.

    Other Parameters
    ----------------
    step_mm : float or None
        Default ``None`` (raycast, raycast_navigate, reference). Sample spacing along the rays
        in mm; None: half the smallest voxel size for the ray casters, a sixteenth for the
        reference (its largest spacing: it also samples at every voxel boundary). A coarser
        ``level`` multiplies a given step by its factor.
    skip_empty : bool
        Default ``True`` (shear_warp, splat, raycast, raycast_navigate). True: work only where
        the EVM (and, for over/under, the transfer function) shows something visible. False:
        the same algorithm over every voxel of the dense grid with the region as a mask: the
        same image, slower (the dense side of the exactness contract).
    termination : float
        Default ``0.99`` (shear_warp, splat, raycast, raycast_navigate). Early ray termination
        for ``"over"``: a pixel takes no more samples once its opacity reaches this, so the
        error is at most ``1 - termination`` per channel; 1 composites everything.
    shading : None, True, dict or Shading
        Default ``None`` (shear_warp, splat, raycast, raycast_navigate, reference). Gradient
        shading for ``"over"`` and ``"under"`` (:class:`Shading`: a Blinn–Phong headlight;
        True for its defaults, a dict for its fields); ignored by ``"xray"`` and ``"mip"``.
        Gradients are the 3x3x3 Sobel over region voxels, and shading fades out where they
        are small (``Shading.fade_from``/``fade_to``); shear-warp lights voxels before
        interpolation, the others light each sample.
    xray_scale : float
        Default ``1.0`` (shear_warp, splat, raycast, raycast_navigate, reference). ``"xray"``:
        attenuation per mm per data unit above ``xray_offset``.
    xray_offset : float
        Default ``0.0`` (shear_warp, splat, raycast, raycast_navigate, reference). ``"xray"``:
        the density of zero attenuation (e.g. -1000 HU for air).
    intermediate_scale : float
        Default ``1.0`` (shear_warp). Intermediate-image pixels per voxel along each in-slice
        axis: above 1 keeps detail when the camera zooms in beyond a pixel per voxel (cost
        grows with its square), below 1 gives a coarse preview.
    slices_per_voxel : {1, 2, 3, 4, 8}
        Default ``1`` (shear_warp). Samples along each ray per voxel slice: 1 is VolPack's one
        sample per slice; more interpolate between slices (trilinear).
    classification : {"pre", "post"}
        Default ``"pre"`` (shear_warp). ``"pre"``: classify (and light) voxels, then
        interpolate colours (VolPack); ``"post"``: interpolate densities, then classify each
        sample as the reference does (sharper boundaries). Over/under only.
    lut_size : int
        Default ``4096`` (shear_warp). Rows of the classification table over the transfer
        function's control-point range.
    kernel_sigma : float
        Default ``0.4`` (splat). Standard deviation of the Gaussian splat kernel, in voxels.
    kernel_radius : float
        Default ``1.0`` (splat). Truncation radius of the kernel in voxels, >= 0.9 (every cell
        a ray crosses must reach the pixel).
    max_footprint_px : int
        Default ``32`` (splat). Largest half-width of a footprint in pixels; larger footprints
        (extreme close-ups) are cut.
    blend : float
        Default ``0.2`` (splat). Cross-fade between sheet families, in ``[0, 1)``: axes whose
        view component is within this fraction of the largest render their own sheets and
        the images are blended, so the image changes smoothly where the principal axis
        switches (up to 3x the cost there); 0 is a hard switch (pops).
    substeps : int
        Default ``1`` (splat). Sub-slabs per sheet, each classified apart: 1 is Westover's
        one sample per sheet; 3 removes the popping with the rays' sub-voxel phase at 2.2x
        the time. MIP always takes one.
    block : int
        Default ``None`` (raycast, raycast_navigate). Edge in voxels of the space-leaping
        blocks; None: 4, doubled for grids of more than 2**24 such blocks (past 1024³ voxels).
    chunk_rays : int
        Default ``1024`` (raycast, raycast_navigate), ``8192`` (reference). Ray casters: pixels
        per task of the threads (square tiles; the image does not depend on it). Reference:
        rays marched together (bounds the working memory).
    jitter : bool
        Default ``False`` (raycast, raycast_navigate). Offset each ray's samples by its pixel's
        fraction of a step (a fixed hash: the same image every run), so banding at coarse steps
        becomes noise.
    preintegrate : bool
        Default ``False`` (raycast, raycast_navigate). Over/under: classify each segment by the
        densities at both its ends through the pre-integrated table
        (:meth:`TransferFunction.preintegrated_table`), for transfer functions narrower than
        the density change per step.
    boundary : {"clamp", "shell"}
        Default ``"clamp"`` (reference). What interpolation reads at the region's surface:
        only the region's voxels (``"clamp"``, every method's policy), or also the one-voxel
        shell of outside voxels around it (``"shell"``).

    Raises
    ------
    VolumeEVMError
        For a bad method, mode, camera, option or placement (or one a categorical transfer
        function cannot be rendered with); for a render that would take
        more than :data:`MAX_SAMPLES` samples (the message says which ``step_mm`` or
        ``substeps`` would do); and when the image or the render's estimated peak memory
        (:func:`render_memory`) exceeds the memory available
        (:func:`volumeevm_addon.system.available_memory`; the message suggests a coarser level,
        a smaller image or another method).
    TypeError
        For an option the method does not take.

    Examples
    --------
    >>> from volumeevm_addon import Camera, TransferFunction, VolumeEVM, phantoms
    >>> vevm = VolumeEVM.from_volume(phantoms.box((4, 4, 4), lo=(1, 1, 1), hi=(3, 3, 3)), 0.5)
    >>> camera = Camera.look_at((0.0015, 0.0015, 1.0), (0.0015, 0.0015, 0.0), (0.0, 1.0, 0.0),
    ...                         ortho_scale=0.004, resolution_x=4, resolution_y=4)
    >>> tf = TransferFunction([(0, 1, 1, 1, 0.5), (1, 1, 1, 1, 0.5)])
    >>> rgba, depth = render(vevm, camera, tf)  # shear-warp
    >>> rgba[1, :, 3].round(4).tolist()  # opacity 0.5 per mm through the 2 mm box
    [0.0, 0.75, 0.75, 0.0]
    >>> [round(float(d), 4) for d in depth[1]]  # the box's top (z = 0.0025 BU) seen from z = 1
    [10000000000.0, 0.9975, 0.9975, 10000000000.0]
    >>> rgba2, _ = render(vevm, camera, tf, method="splat", substeps=3)
    >>> bool(abs(rgba2 - rgba).max() < 1e-6)
    True
    """
    record = _cpu_method(method)
    check_mode(mode)
    if not isinstance(camera, Camera):
        raise VolumeEVMError(f"camera: expected a Camera, got {type(camera).__name__}")
    check_volumeevm(vevm)
    _check_option_types(record, options)
    if categorical(tf, mode) and not record.categorical:
        names = tuple(name for name, other in REGISTRY.items() if other.categorical)
        raise VolumeEVMError(f"method: {method!r} interpolates densities; a categorical transfer "
                             f"function (labels) renders with one of {names}")
    level = checked_categorical_level(tf, mode, level, options)
    depth_in = checked_depth_in(depth_in, camera.shape)
    h, w = camera.shape
    check_memory(h * w * IMAGE_BYTES_PER_PIXEL, f"a {w}x{h} image", source="camera",
                 advice="lower the resolution or resolution_percentage")
    if matrix_world is not None:
        matrix_world = checked_affine("matrix_world", matrix_world)
    to_world = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation, matrix_world)
    factor = level_factor(level, vevm.shape, to_world, camera)
    if factor > 1 and not record.full_level:
        vevm = vevm.level(factor)
        to_world = grid_to_world(vevm.spacing, vevm.origin, vevm.orientation, matrix_world)
        if options.get("step_mm") is not None:
            options["step_mm"] = options["step_mm"] * factor
    check_samples(method, vevm, camera, to_world, options)
    advice = (f"the {method} renders the full grid at full resolution: use another method "
              f"or a smaller image" if record.full_level else
              "render a coarser level (level='auto' or an integer >= 2), a smaller image or "
              "another method")
    check_memory(render_memory(method, vevm, camera, tf, to_world, {"mode": mode, **options}),
                 f"rendering {'x'.join(map(str, vevm.shape))} voxels at {w}x{h} pixels "
                 f"({method})", source="render", advice=advice)
    return record.render(vevm, camera, tf, to_world, mode=mode, depth_in=depth_in, **options)


def check_samples(method, vevm, camera, grid_to_world, options):
    """Refuse a render of more than :data:`MAX_SAMPLES` samples, naming the option to change.

    The count is the pixels the volume's box covers times the samples a ray takes through the
    box's diagonal: ``diagonal_mm / step_mm`` for the ray casters and the reference (default
    steps: half, resp. a sixteenth of the smallest voxel), the sheets (the largest side)
    times ``substeps`` for splatting (the record's ``check_samples``). Shear-warp is bounded
    by its own ranges (``slices_per_voxel <= 8``, ``intermediate_scale <= 8``).

    Parameters
    ----------
    method, vevm, camera, grid_to_world, options
        As for :func:`render_memory`; of the options, ``step_mm`` or ``substeps`` are read.

    Raises
    ------
    VolumeEVMError
        Naming ``step_mm`` or ``substeps``, with the smallest step (largest substeps) allowed.
    """
    record = method_record(method)
    check_method_samples(record, vevm, camera, grid_to_world, _with_defaults(record, options))


def render_memory(method, vevm, camera, tf, grid_to_world, options):
    """Estimated peak memory (bytes) of rendering ``vevm`` with ``method`` for ``camera``.

    The sum of the image buffers, the per-pixel ray state (all rays of the image: the ray
    casters' default chunk holds a 512² image), the tables the method builds from the grid
    (once per set the render would build: tables an earlier render left in ``vevm.cache``
    cost nothing, :func:`_tables_to_build`) and per-method working sets (shear-warp's
    intermediate image, the reference's chunks, lookup tables): the method record's
    :class:`._method.MemoryModel`.

    Parameters
    ----------
    method : str
        One of :data:`METHODS`.
    vevm : VolumeEVM
        The VolumeEVM rendered (the level, when a coarser one is rendered).
    camera : Camera
    tf : TransferFunction
        The render's transfer function (shear-warp caches its classes per function).
    grid_to_world : (4, 4) ndarray
        Voxel-centre indices to world (:func:`volumeevm_addon.grid_to_world`): the view decides the
        principal axes whose tables shear-warp and splatting build.
    options : dict
        The renderer's keywords, ``mode`` included (``shading``, ``intermediate_scale`` and
        those that select the cached tables change the estimate).

    Returns
    -------
    int
        Bytes.
    """
    record = _cpu_method(method)
    sets = _tables_to_build(method, vevm, camera, tf, grid_to_world, options)
    h, w = camera.shape
    return record.memory.bytes(vevm, h * w, sets, _with_defaults(record, options))


def render_options(method):
    """The options ``method`` takes as keywords of :func:`render`, with their defaults.

    Each method's options are the keyword-only parameters of its renderer, less ``mode`` and
    ``depth_in`` (which :func:`render` takes for every method); the defaults are the
    renderer's own (each method's fastest settings). :func:`render` checks the options it is
    given against this: an unknown name raises ``TypeError``, a value whose type does not
    match the default's raises :class:`VolumeEVMError`. What each option means is under
    "Other Parameters" in :func:`render`'s docstring, which a test keeps equal to this. The
    GPU method's (drawn on the Blender side) are those of :func:`gpu_frame`.

    Parameters
    ----------
    method : str
        One of :data:`METHODS`, or another method of
        :func:`~volumeevm_addon.rendering.methods` (the GPU's).

    Returns
    -------
    dict of str to object
        Option name to default value, in the renderer's order (a new dict on every call).

    Raises
    ------
    VolumeEVMError
        When ``method`` is not the name of a method.

    Examples
    --------
    >>> from volumeevm_addon.rendering import render_options
    >>> render_options("splat")["substeps"]
    1
    >>> sorted(render_options("raycast"))[:4]
    ['block', 'chunk_rays', 'jitter', 'preintegrate']
    """
    return dict(method_record(method).options)


def _cpu_method(name):
    """The record of a method :func:`render` runs, or :class:`VolumeEVMError`."""
    if name in REGISTRY and name not in METHODS:
        raise VolumeEVMError(f"method: {name!r} is drawn by Blender (Render VolumeEVM); the "
                             f"core renders one of {METHODS}")
    if name not in METHODS:
        raise VolumeEVMError(f"method: one of {METHODS}, got {name!r}")
    return REGISTRY[name]


def _with_defaults(record, options):
    """``options`` with the method's defaults filled in."""
    return {**dict(record.options), **options}


def _tables_to_build(method, vevm, camera, tf, grid_to_world, options):
    """Sets of grid tables the render would build (the record's ``tables_to_build``: one per
    principal axis for shear-warp and splatting, one for the ray casters; 0 when all are
    cached). The reference caches nothing: always 1."""
    return method_record(method).tables_to_build(vevm, camera, tf, grid_to_world, options)


def _check_option_types(record, options):
    """Refuse an option value of the wrong type for the method's option, judged by the
    option's default (:func:`render_options`): a flag (default True/False) must be a bool, a
    count (an int default) an integer, a quantity (a float default) a finite real number;
    ``step_mm`` a number > 0. Ranges are the renderer's to check. An option the method does not
    take raises ``TypeError``, as calling its renderer would."""
    method = record.name
    defaults = dict(record.options)
    for name, value in options.items():
        if name not in defaults:
            raise TypeError(f"{name}: not an option of method {method!r}; its options are "
                            f"{', '.join(sorted(defaults))}")
        default = defaults[name]
        if isinstance(default, bool):
            ok, kind = isinstance(value, (bool, np.bool_)), "True or False"
        elif isinstance(default, int):
            ok = isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))
            kind = "an integer"
        elif isinstance(default, float):
            ok = (isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
                  and bool(np.isfinite(value)))
            kind = "a finite number"
        else:
            continue
        if not ok:
            raise VolumeEVMError(f"{name}: {kind} for method {method!r}, got {value!r}")
    if "step_mm" in options and options["step_mm"] is not None:
        positive_number("step_mm", options["step_mm"])

