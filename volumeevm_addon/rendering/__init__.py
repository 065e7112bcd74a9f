"""Direct volume rendering of a VolumeEVM: camera, transfer functions, the methods, images.

Private modules; the public names (:func:`~volumeevm_addon.render`, ``Camera``,
``TransferFunction``, ``METHODS``, ...) are imported from ``volumeevm_addon``. One module per
method; ``_render.py`` is the entry point that checks the inputs and dispatches to them:

- ``_render.py``: :func:`~volumeevm_addon.render`, whatever the method (checks, memory, levels).
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
  ``blender/gpu_dvr.py``): checks, pixel rays, depth conversions, textures, uniforms.

To add a method: write its ``render_<method>`` (and ``tables_to_build``) in a module of its own
here, with the signature of the others and built on the shared pieces above, then name it in
``_render.py``: ``METHODS``, ``_renderers()``, ``_tables_to_build()`` and the memory model
(``_GRID_BYTES`` and the tables beside it, measured with ``bench/bench_memory.py``).
"""
