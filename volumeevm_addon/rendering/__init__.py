"""Direct volume rendering of a VolumeEVM: camera, transfer functions, the methods, images.

The names users need (:func:`~volumeevm_addon.render`, ``Camera``, ``TransferFunction``,
``METHODS``, ...) are imported from ``volumeevm_addon``; this package exports what the Blender
side needs beyond them: the quality setting as options, compositing over a scene render and its
depth, EXR channels, the NumPy half of the GPU method, and the methods' records
(:func:`methods`). One private module per method; ``_render.py`` is the entry point that checks
the inputs and dispatches to them through their records:

- ``_render.py``: :func:`~volumeevm_addon.render`, whatever the method (checks, memory, levels).
- ``_method.py``: the :class:`Method` record, its :class:`MemoryModel` and the pieces records
  share (the sample bound, the ray casters' quality mapping); ``_registry.py``: the records,
  one line each (:func:`~volumeevm_addon.rendering.methods`).
- ``_shear_warp/``: shear-warp (Lacroute & Levoy), parallel and perspective, a package by
  stage: ``_view.py`` (the view's factorization), ``_layouts.py`` (the run layouts and class
  caches), ``_composite.py`` (compositing), ``_warp.py`` (the warp), each with its compiled
  loops; ``__init__.py`` checks the options and runs the stages.
- ``_splat.py``: sheet-buffer splatting (Westover), post-classified.
- ``_raycast.py``: ray casting with the EVM as space-leaping structure, and its navigation mode
  (their compiled per-ray loops in ``_ray_march.py``).
- ``_reference.py``: the dense float64 reference ray caster, the accuracy oracle of every method.
- ``_camera.py``: a plain camera record that reproduces Blender's projection exactly.
- ``_transfer.py``: transfer functions, piecewise-linear colour and opacity in the data's units.
- ``_depth.py``: what "visible" means for the output depth, one threshold for every method.
- ``_optics.py``: the optical model the CPU methods share: one ``Optics`` record per render and
  the compiled helpers of classification, opacity correction and visibility their kernels use.
- The pieces every method shares, each written once: ``_checks.py`` (input checks),
  ``_rays.py`` (the camera's pixel rays in index space, clipped to the volume's box, the clip
  range and ``depth_in``), ``_gradients.py`` (per-voxel gradients over the region's voxels),
  ``_shading.py`` (``Shading`` and the Blinn–Phong headlight), ``_modes.py`` (``MODES``, a
  view's compositing settings and the finishing of X-ray and MIP).
- ``_images.py``: image files of the results: OpenEXR (R, G, B, A, Z) and PNG previews.
- ``_compositing.py``: a volume render laid over a scene render (alpha over, output depth).
- ``_quality.py``: one quality setting as each method's options (``method_options``).
- ``_levels.py``: which resolution level a view needs (``LEVELS``, the auto rule); the levels
  themselves are the model's.
- ``_gpu_inputs.py``: the NumPy half of the GPU method (which draws on the Blender side,
  ``blender/gpu_draw.py``): checks, pixel rays, depth conversions, textures, uniforms; its
  shaders are GLSL files in ``shaders/`` (text the Blender side compiles).

To add a method: write a module of its own here with its renderer, with the signature every
record's ``render`` has (``render(vevm, camera, tf, grid_to_world, *, mode, depth_in,
**options)``, options keyword-only with their defaults) and built on the shared pieces above,
and end it with its ``Method`` record: name and the sidebar's label and description, the
renderer and its options (``keyword_options(renderer)``), its memory model (a
``MemoryModel``, measured with ``bench/bench_memory.py``), ``tables_to_build`` (what it
would add to ``vevm.cache``), its sample bound, its quality mapping and whether it renders
label maps. Then add the record to ``_RECORDS`` in ``_registry.py``, last (Blender stores the
sidebar's setting by position). :func:`~volumeevm_addon.render`, the quality setting, the
memory and sample checks, the Blender render job and the sidebar read it from there; what it
must satisfy is tested for every record by ``tests/test_method_contract.py``.
"""

from ._camera import BACKGROUND_DEPTH
from ._compositing import composite_over, output_depth
from ._depth import VISIBLE_ALPHA
from ._gpu_inputs import (
                          GPU_UNIFORMS_GLSL,
                          GPUFrame,
                          axial_from_window,
                          camera_from_viewport,
                          gpu_frame,
                          gpu_gradients,
                          gpu_occupancy,
                          gpu_region,
                          gpu_shader_source,
                          gpu_transfer_table,
                          window_from_axial,
)
from ._images import exr_channels, openexr_module
from ._method import MAX_SAMPLES, MemoryModel, Method
from ._quality import method_options
from ._registry import methods
from ._render import render_options

__all__ = ["BACKGROUND_DEPTH", "GPUFrame", "GPU_UNIFORMS_GLSL", "MAX_SAMPLES", "MemoryModel",
           "Method", "VISIBLE_ALPHA", "axial_from_window", "camera_from_viewport",
           "composite_over", "exr_channels", "gpu_frame", "gpu_gradients", "gpu_occupancy",
           "gpu_region", "gpu_shader_source", "gpu_transfer_table", "method_options", "methods",
           "openexr_module", "output_depth", "render_options", "window_from_axial"]
