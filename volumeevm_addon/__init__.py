"""VolumeEVM core: the Extreme Vertices Model of voxel regions and volumes built on it.

NumPy, plus Numba for the compiled kernels (``_jit.py``; imported on a kernel's first call,
not with the package); never imports ``bpy``, so it works in plain Python as well as inside
Blender.

What a user calls is importable from here: read a volume, build its region, mesh, cut, measure
and render it::

    from volumeevm_addon import TransferFunction, VolumeEVM, read_volume, render

The Blender side and scripts that manage files, memory or GPU drawing themselves find the rest
in public sub-packages named for what they hold: ``model`` (the edit stack, mesh records, the
CAD tools' voxelization), ``rendering`` (quality options, compositing, EXR channels, the GPU
method's inputs), ``readers`` (the supported extensions) and ``system`` (atomic writes, the
memory budget, the kernel cache). Modules whose names start with ``_`` are private and may
move. The layout, by concept:

- ``model/``: the EVM and its sweeps, mesh and components; the VolumeEVM, its densities tables,
  ``.vevm`` files, resolution levels and edit stack; the volume record; label maps; the CAD
  tools' voxelization.
- ``rendering/``: camera, transfer functions, the depth rule, image files, the entry point
  ``render`` and one module per method (shear-warp, splatting, ray casting, the reference).
- ``readers/``: one module per file format behind ``read_volume``.
- ``_errors.py``, ``_memory.py``, ``_files.py``, ``_jit.py`` (the compiled-kernel layer: its
  cache folder and thread count): shared by all.
- ``phantoms`` and ``metrics``: public modules imported on demand, like ``skimage.data``: test
  volumes with closed-form images, and image errors and stability measures.
"""

import importlib
import warnings

# system loads with the package, as model, rendering and readers do
from . import system as system
from ._errors import VolumeEVMError
from ._jit import kernel_threads, set_kernel_threads
from .model._evm import EVM
from .model._histogram import density_histogram, otsu_threshold
from .model._label_set import LabelSet
from .model._volume import Volume, grid_to_world
from .model._volumeevm import VolumeEVM
from .model._voxelize import voxelize_mesh
from .readers import read_volume, volume_levels
from .rendering._camera import Camera
from .rendering._images import read_exr, write_exr, write_png
from .rendering._levels import LEVELS
from .rendering._modes import MODES
from .rendering._render import METHODS, render
from .rendering._shading import Shading
from .rendering._transfer import PRESETS, TransferFunction

__all__ = [
    "Camera",
    "EVM",
    "LEVELS",
    "LabelSet",
    "METHODS",
    "MODES",
    "PRESETS",
    "Shading",
    "TransferFunction",
    "Volume",
    "VolumeEVM",
    "VolumeEVMError",
    "density_histogram",
    "grid_to_world",
    "kernel_threads",
    "otsu_threshold",
    "read_exr",
    "read_volume",
    "render",
    "set_kernel_threads",
    "volume_levels",
    "voxelize_mesh",
    "write_exr",
    "write_png",
]

#: Names the top level exported up to version 0.1.0, now in the public sub-package that holds
#: them; the old spelling works with a DeprecationWarning for one release.
_MOVED = {
    **dict.fromkeys(["BLENDER_UNITS_PER_MM", "BoundaryMesh", "DerivedCache", "EditStack",
                     "LabelInfo", "MeshCheck", "Polygons", "ToolOperation", "box_evm",
                     "check_closed_mesh", "index_to_physical", "tool_to_grid",
                     "voxelize_mesh_evm"], "model"),
    **dict.fromkeys(["BACKGROUND_DEPTH", "GPUFrame", "GPU_UNIFORMS_GLSL", "MAX_SAMPLES",
                     "VISIBLE_ALPHA", "axial_from_window", "camera_from_viewport",
                     "composite_over", "exr_channels", "gpu_frame", "gpu_gradients",
                     "gpu_occupancy", "gpu_region", "gpu_transfer_table", "method_options",
                     "openexr_module", "output_depth", "render_options", "window_from_axial"],
                    "rendering"),
    "SUPPORTED_EXTENSIONS": "readers",
    **dict.fromkeys(["LIMIT_VARIABLE", "atomic_target", "available_memory", "check_memory",
                     "set_kernel_cache_dir", "set_kernel_compile_hook", "write_atomically"],
                    "system"),
}


def __getattr__(name):
    """The moved names (:data:`_MOVED`), with a DeprecationWarning naming the new place."""
    if name not in _MOVED:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    place = f"{__name__}.{_MOVED[name]}"
    warnings.warn(f"{__name__}.{name} moved to {place}.{name}; the old name goes in the next "
                  f"release", DeprecationWarning, stacklevel=2)
    return getattr(importlib.import_module(place), name)
