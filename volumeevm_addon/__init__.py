"""VolumeEVM core: the Extreme Vertices Model of voxel regions and volumes built on it.

NumPy, plus Numba for the compiled kernels (``_jit.py``; imported on a kernel's first call,
not with the package); never imports ``bpy``, so it works in plain Python as well as inside
Blender.

Everything a script, the Blender side or a benchmark needs is importable from here; the
modules whose names start with ``_`` are private and may move. The layout, by concept:

- ``model/``: the EVM and its sweeps, mesh and components; the VolumeEVM, its densities tables,
  ``.vevm`` files, resolution levels and edit stack; the volume record.
- ``rendering/``: camera, transfer functions, the depth rule, image files, the entry point
  ``render`` and one module per method (shear-warp, splatting, ray casting, the reference).
- ``readers/``: one module per file format behind ``read_volume``.
- ``_voxelize.py`` (the CAD tools), ``_errors.py``, ``_memory.py``, ``_files.py``, ``_jit.py`` (the
  compiled-kernel layer: its cache folder and thread count): shared by all.
- ``phantoms`` and ``metrics``: public modules imported on demand, like ``skimage.data``: test
  volumes with closed-form images, and image errors and stability measures.
"""

from ._errors import VolumeEVMError
from ._files import atomic_target, write_atomically
from ._jit import kernel_threads, set_kernel_cache_dir, set_kernel_compile_hook, set_kernel_threads
from ._memory import LIMIT_VARIABLE, available_memory, check_memory
from ._voxelize import (MeshCheck, box_evm, check_closed_mesh, tool_to_grid, voxelize_mesh,
                        voxelize_mesh_evm)
from .model._cache import DerivedCache
from .model._evm import EVM
from .model._histogram import density_histogram, otsu_threshold
from .model._label_set import LabelSet
from .model._label_table import LabelInfo
from .model._mesh import BoundaryMesh, Polygons
from .model._stack import EditStack, ToolOperation
from .model._volume import BLENDER_UNITS_PER_MM, Volume, grid_to_world, index_to_physical
from .model._volumeevm import VolumeEVM
from .readers import SUPPORTED_EXTENSIONS, read_volume, volume_levels
from .rendering._camera import BACKGROUND_DEPTH, Camera
from .rendering._compositing import composite_over, output_depth
from .rendering._depth import VISIBLE_ALPHA
from .rendering._gpu_inputs import (GPU_UNIFORMS_GLSL, GPUFrame, axial_from_window,
                                    camera_from_viewport, gpu_frame, gpu_gradients, gpu_occupancy,
                                    gpu_region,
                                    gpu_transfer_table, window_from_axial)
from .rendering._images import exr_channels, openexr_module, read_exr, write_exr, write_png
from .rendering._levels import LEVELS
from .rendering._modes import MODES
from .rendering._quality import method_options
from .rendering._registry import methods
from .rendering._method import MAX_SAMPLES, MemoryModel, Method
from .rendering._render import METHODS, render, render_options
from .rendering._shading import Shading
from .rendering._transfer import PRESETS, TransferFunction

__all__ = [
    "BACKGROUND_DEPTH",
    "BLENDER_UNITS_PER_MM",
    "BoundaryMesh",
    "Camera",
    "DerivedCache",
    "EVM",
    "EditStack",
    "GPUFrame",
    "GPU_UNIFORMS_GLSL",
    "LEVELS",
    "LIMIT_VARIABLE",
    "LabelInfo",
    "LabelSet",
    "MAX_SAMPLES",
    "METHODS",
    "MemoryModel",
    "Method",
    "MeshCheck",
    "MODES",
    "PRESETS",
    "Polygons",
    "SUPPORTED_EXTENSIONS",
    "Shading",
    "ToolOperation",
    "TransferFunction",
    "VISIBLE_ALPHA",
    "Volume",
    "VolumeEVM",
    "VolumeEVMError",
    "atomic_target",
    "available_memory",
    "axial_from_window",
    "box_evm",
    "camera_from_viewport",
    "check_closed_mesh",
    "check_memory",
    "composite_over",
    "density_histogram",
    "exr_channels",
    "gpu_frame",
    "gpu_gradients",
    "gpu_occupancy",
    "gpu_region",
    "gpu_transfer_table",
    "grid_to_world",
    "index_to_physical",
    "kernel_threads",
    "method_options",
    "methods",
    "openexr_module",
    "otsu_threshold",
    "output_depth",
    "read_exr",
    "read_volume",
    "render",
    "render_options",
    "set_kernel_cache_dir",
    "set_kernel_compile_hook",
    "set_kernel_threads",
    "tool_to_grid",
    "voxelize_mesh",
    "volume_levels",
    "voxelize_mesh_evm",
    "window_from_axial",
    "write_atomically",
    "write_exr",
    "write_png",
]
