"""What a rendering method is: one record of its facts (:class:`Method`) and its memory model.

Each method module ends with its record(s); :mod:`._registry` lists them. :func:`render`, the
quality setting (:func:`._quality.method_options`), the memory and sample checks, the Blender
render job and the sidebar's method list read the records, so nothing outside a method's
module is keyed by its name. The pieces several records share are here: the sample bound
(:data:`MAX_SAMPLES`, :func:`step_samples`), the quality mapping of the ray casters
(:func:`step_quality`) and the options read from a renderer's signature
(:func:`keyword_options`).
"""

import inspect
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .._errors import VolumeEVMError
from ._checks import checked_step_mm

MAX_SAMPLES = 20_000_000_000
"""Most samples a render may take: covered pixels x samples per ray through the volume's box.

Ray casting every sample (``skip_empty=False``) marches 3e7 samples per second on one core
(CT head, 128² image, the compiled caster; the navigation variant and the reference are 7 to
100 times slower), so 2e10 samples are ten minutes at best and hours for the slower methods: a
step that asks for more is never what a user means (a step in the wrong unit, a typo). A 4K
frame (3840 x 2160) of a 512³ volume at the ray casters' default step (half a voxel) is about
1.5e10 samples, still allowed.
"""

IMAGE_BYTES_PER_PIXEL = 20
"""The float32 RGBA image and depth every method returns."""

_COMMON_KEYWORDS = ("mode", "depth_in")
"""Keywords of every renderer that :func:`render` takes itself (not options)."""


@dataclass(frozen=True)
class MemoryModel:
    """A method's peak memory in bytes, fitted to tracemalloc peaks and rounded up.

    The constants come from ``bench/bench_memory.py`` (CT head 256x256x108 and the same
    upsampled to 512³, MRI 128x128x84; 64² to 512² images), which prints each estimate beside
    the measured peak, cold and warm. "Grid" counts the voxels of the grid padded by one on
    every side.

    Attributes
    ----------
    pixel : int
        Per pixel, beside the image buffers (:data:`IMAGE_BYTES_PER_PIXEL`): the ray set-up
        and per-ray state (all rays of the image).
    fixed : int
        Fixed working set: lookup tables and the renderers' small tables.
    grid : int
        Per grid voxel, for each set of tables the render builds (the record's
        ``tables_to_build``): the tables and their construction temporaries.
    region : int
        Per region voxel, for each set of tables the render builds.
    axis_table : bool
        Each set of tables also reads the densities table of its principal axis
        (:meth:`VolumeEVM.table`), made scanline by scanline: ``itemsize`` per region voxel.
    shading_grid, shading_region : int
        Per grid voxel and per region voxel with ``shading``: the gradient tables and their
        temporaries.
    per_set : callable or None
        ``per_set(vevm, options) -> int``: bytes of each set of tables beyond ``grid`` and
        ``region`` (tables whose size follows something else, such as occupied blocks).
    per_view : callable or None
        ``per_view(vevm, options) -> int``: the method's own working set per view beyond
        the above (``options``: the renderer's keywords with its defaults filled in).
    """

    pixel: int
    fixed: int = 1 << 20
    grid: int = 0
    region: int = 0
    axis_table: bool = False
    shading_grid: int = 0
    shading_region: int = 0
    per_set: Callable | None = None
    per_view: Callable | None = None

    def bytes(self, vevm, pixels, sets, options):
        """Estimated peak memory of one render.

        Parameters
        ----------
        vevm : VolumeEVM
            The VolumeEVM rendered (the level, when a coarser one is rendered).
        pixels : int
            Pixels of the image.
        sets : int
            Sets of tables the render builds (the record's ``tables_to_build``).
        options : dict
            The renderer's keywords with its defaults filled in, ``mode`` included.

        Returns
        -------
        int
            Bytes.
        """
        grid = int(np.prod(np.asarray(vevm.shape, dtype=np.int64) + 2))
        needed = pixels * (IMAGE_BYTES_PER_PIXEL + self.pixel) + self.fixed
        region = int(vevm.voxel_count)
        each_set = grid * self.grid + region * self.region
        if self.axis_table:
            each_set += region * vevm.table(0).dtype.itemsize
        if self.per_set is not None:
            each_set += self.per_set(vevm, options)
        needed += sets * each_set
        if options.get("shading") not in (None, False):
            needed += grid * self.shading_grid + region * self.shading_region
        if self.per_view is not None:
            needed += self.per_view(vevm, options)
        return int(needed)


@dataclass(frozen=True)
class Method:
    """One rendering method: everything the rest of the package needs to know about it.

    Attributes
    ----------
    name : str
        The ``method`` argument of :func:`~volumeevm_addon.render` (and the sidebar's enum
        identifier: the sidebar lists methods in the registry's order, and Blender stores a
        setting by its position, so new methods go last).
    label, description : str
        The sidebar's name and tooltip for it.
    render : callable or None
        ``render(vevm, camera, tf, grid_to_world, *, mode, depth_in, **options)`` returning
        ``(rgba, depth)``; None for a method drawn outside the core (the GPU's, on the
        Blender side).
    options : tuple of (str, object)
        The options it takes with their defaults (:func:`keyword_options`), in order.
    memory : MemoryModel or None
        Its peak memory; None when the method checks each array it makes itself.
    tables_to_build : callable
        ``tables_to_build(vevm, camera, tf, grid_to_world, options) -> int``: the sets of grid
        tables the render would build (0 when all are in ``vevm.cache``); only looks.
    check_samples : callable or None
        ``check_samples(vevm, pixels, options)``: raises :class:`VolumeEVMError` naming the
        option to change when a render of ``pixels`` covered pixels would take more than
        :data:`MAX_SAMPLES` samples; None when its own option ranges bound its work.
    quality : callable
        ``quality(quality, smallest_mm) -> dict``: the sampling options that the one
        quality setting (1 = its default sampling) means for this method.
    gpu : bool
        It runs on the graphics card.
    fallback : str or None
        The CPU method that renders instead where no GPU context can be made (GPU methods).
    categorical : bool
        It can sample the nearest voxel for a categorical transfer function (label maps).
    full_level : bool
        It always renders the full resolution level (``level`` is ignored: the reference).
    """

    name: str
    label: str
    description: str
    render: Callable | None
    options: tuple
    memory: MemoryModel | None
    tables_to_build: Callable
    check_samples: Callable | None
    quality: Callable
    gpu: bool = False
    fallback: str | None = None
    categorical: bool = False
    full_level: bool = False


def keyword_options(function, *, besides=()):
    """The keyword-only parameters of ``function`` with their defaults, as a method's options:
    ``mode`` and ``depth_in`` (which :func:`render` takes for every method) and ``besides``
    left out."""
    skip = _COMMON_KEYWORDS + tuple(besides)
    return tuple((p.name, p.default) for p in inspect.signature(function).parameters.values()
                 if p.kind == p.KEYWORD_ONLY and p.name not in skip)


def one_set(vevm, camera, tf, grid_to_world, options):
    """``tables_to_build`` of a method that caches nothing: one set per render."""
    return 1


def step_quality(steps_per_voxel):
    """The quality mapping of a ray caster whose default step is the smallest voxel size over
    ``steps_per_voxel``: ``step_mm`` divided by the quality."""
    def quality(quality, smallest_mm):
        return {"step_mm": smallest_mm / steps_per_voxel / quality}
    return quality


def step_samples(steps_per_voxel):
    """The sample check of a ray caster (default step: the smallest voxel size over
    ``steps_per_voxel``): covered pixels times the samples along the box's diagonal."""
    def check(vevm, pixels, options):
        spacing = np.asarray(vevm.spacing, dtype=np.float64)
        step = checked_step_mm(options.get("step_mm"), spacing, steps_per_voxel)
        diagonal = float(np.linalg.norm(np.asarray(vevm.shape) * spacing))
        samples = pixels * diagonal / step
        if samples > MAX_SAMPLES:
            smallest = pixels * diagonal / MAX_SAMPLES
            raise VolumeEVMError(
                f"step_mm: a step of {step:.3g} mm would take about {samples:.2g} samples "
                f"({pixels} pixels x {diagonal / step:.3g} samples per ray through the volume's "
                f"box), more than the {MAX_SAMPLES:.0e} a render may take (hours); use "
                f"step_mm >= {smallest:.3g} or a smaller image")
    return check


def check_method_samples(method, vevm, camera, grid_to_world, options):
    """Refuse a render by ``method`` (a :class:`Method`) of more than :data:`MAX_SAMPLES`
    samples, counted over the pixels the volume's box covers (its ``check_samples``)."""
    if method.check_samples is not None:
        method.check_samples(vevm, covered_pixels(vevm.shape, grid_to_world, camera), options)


def covered_pixels(shape, grid_to_world, camera):
    """Pixels in the bounding rectangle of the volume box's projection (all pixels when a
    corner is at or behind a perspective camera)."""
    n = np.asarray(shape, dtype=np.float64)
    corners = np.array([[a, b, c] for a in (-0.5, n[0] - 0.5) for b in (-0.5, n[1] - 0.5)
                        for c in (-0.5, n[2] - 0.5)])
    g = np.asarray(grid_to_world, dtype=np.float64)
    uv, _ = camera.project(corners @ g[:3, :3].T + g[:3, 3])
    h, w = camera.shape
    if not np.isfinite(uv).all():
        return h * w
    u0, v0 = np.clip(np.floor(uv.min(axis=0)), 0, (w, h))
    u1, v1 = np.clip(np.ceil(uv.max(axis=0)), 0, (w, h))
    return int((u1 - u0) * (v1 - v0))

