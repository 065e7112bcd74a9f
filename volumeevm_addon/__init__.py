"""VolumeEVM core: the Extreme Vertices Model of voxel regions and volumes built on it.

NumPy only; never imports ``bpy``, so it works in plain Python as well as inside Blender.

Everything a script, the Blender side or a benchmark needs is importable from here; the
modules whose names start with ``_`` are private and may move. Two public sub-modules are
imported on demand, like ``skimage.data``: :mod:`volumeevm_addon.phantoms` (test volumes with
closed-form images) and :mod:`volumeevm_addon.metrics` (image errors and stability measures).
"""

from ._camera import BACKGROUND_DEPTH, Camera
from ._depth import VISIBLE_ALPHA
from ._errors import VolumeEVMError
from ._evm import EVM
from ._files import atomic_target, write_atomically
from ._images import exr_channels, openexr_module, read_exr, write_exr, write_png
from ._levels import LEVELS
from ._memory import LIMIT_VARIABLE, available_memory, check_memory
from ._mesh import Polygons
from ._reference import MODES, Shading
from ._render import MAX_SAMPLES, METHODS, render, render_options
from ._stack import EditStack, ToolOperation
from ._transfer import PRESETS, TransferFunction
from ._volume import BLENDER_UNITS_PER_MM, Volume, grid_to_world, index_to_physical
from ._volumeevm import VolumeEVM
from ._voxelize import box_evm, check_closed_mesh, voxelize_mesh, voxelize_mesh_evm
from .readers import SUPPORTED_EXTENSIONS, read_volume

__all__ = [
    "BACKGROUND_DEPTH",
    "BLENDER_UNITS_PER_MM",
    "Camera",
    "EVM",
    "EditStack",
    "LEVELS",
    "LIMIT_VARIABLE",
    "MAX_SAMPLES",
    "METHODS",
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
    "box_evm",
    "check_closed_mesh",
    "check_memory",
    "exr_channels",
    "grid_to_world",
    "index_to_physical",
    "openexr_module",
    "read_exr",
    "read_volume",
    "render",
    "render_options",
    "voxelize_mesh",
    "voxelize_mesh_evm",
    "write_atomically",
    "write_exr",
    "write_png",
]
