"""VolumeEVM core: the Extreme Vertices Model of voxel regions and volumes built on it.

NumPy only; never imports ``bpy``, so it works in plain Python as well as inside Blender.
"""

from ._camera import Camera
from ._errors import VolumeEVMError
from ._evm import EVM
from ._images import read_exr, write_exr, write_png
from ._mesh import Polygons
from ._render import render
from ._stack import EditStack, ToolOperation
from ._transfer import TransferFunction
from ._volume import BLENDER_UNITS_PER_MM, Volume
from ._volumeevm import VolumeEVM
from ._voxelize import box_evm, check_closed_mesh, voxelize_mesh, voxelize_mesh_evm
from .readers import SUPPORTED_EXTENSIONS, read_volume

__all__ = [
    "BLENDER_UNITS_PER_MM",
    "Camera",
    "EVM",
    "EditStack",
    "Polygons",
    "SUPPORTED_EXTENSIONS",
    "ToolOperation",
    "TransferFunction",
    "Volume",
    "VolumeEVM",
    "VolumeEVMError",
    "box_evm",
    "check_closed_mesh",
    "read_exr",
    "read_volume",
    "render",
    "voxelize_mesh",
    "voxelize_mesh_evm",
    "write_exr",
    "write_png",
]
