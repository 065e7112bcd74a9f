"""The model: a voxel region as an Extreme Vertices Model, and the VolumeEVM built on it.

The names users need (:class:`~volumeevm_addon.EVM`, :class:`~volumeevm_addon.VolumeEVM`,
:class:`~volumeevm_addon.LabelSet`, ...) are imported from ``volumeevm_addon``; this package
exports what the Blender side and the tool-stack scripts need beyond them: the edit stack and
its caches, the mesh records, the CAD tools' voxelization on a box, and where a grid sits in
Blender's units. One private module per concept:

- ``_evm.py``: the Extreme Vertices Model of a voxel region (:class:`~volumeevm_addon.EVM`).
- ``_sweep.py``: plane sweeps over sorted extreme vertices (compiled kernels): Booleans, boxes.
- ``_mesh.py``: the boundary of an EVM as a closed, outward polygon mesh with merged faces.
- ``_label_mesh.py``: the meshes of a label set's regions made together, so that touching
  labels carry the same polygons (reversed) at their contact.
- ``_manifold.py``: that mesh made 2-manifold (for 3D printing): non-manifold edges and
  vertices split.
- ``_smooth.py``: that mesh relaxed into a smooth display surface within half a voxel.
- ``_components.py``: face-connected components of an EVM, one EVM each.
- ``_densities.py``: voxel -> index in a densities table, computed from the EVM alone.
- ``_volumeevm.py``: the EVM of a region of interest plus the densities of its voxels.
- ``_vevm_file.py``: reading and checking a ``.vevm`` file before anything is built.
- ``_levels.py``: coarser resolution levels of a VolumeEVM (no more than a view needs).
- ``_cache.py``: what is derived from a VolumeEVM on first use (the renderers' tables, its
  levels), kept in its :class:`~volumeevm_addon.model.DerivedCache`: counted, bounded, clearable.
- ``_stack.py``: the non-destructive stack of tool operations on a VolumeEVM.
- ``_volume.py``: the volume record every reader returns, and where its grid sits.
- ``_histogram.py``: a volume's densities histogram and Otsu's threshold.
- ``_labels.py``: a label map's regions, every label in one sweep.
- ``_measure.py``: exact measurements of regions and label sets (volume, area, shared faces).
- ``_label_table.py``: label names and colours from segmentation files, and a fixed palette.
- ``_label_set.py``: a label map's regions as one mapping, edited and measured together.
- ``_voxelize.py``: a closed triangle mesh (a CAD tool) as the voxels whose centres it holds,
  with exact predicates; the mesh checks that come first.
"""

from ._cache import DerivedCache
from ._chunked import chunked_build_memory
from ._label_table import LabelInfo
from ._mesh import BoundaryMesh, Polygons
from ._stack import EditStack, ToolOperation
from ._volume import BLENDER_UNITS_PER_MM, index_to_physical
from ._voxelize import MeshCheck, box_evm, check_closed_mesh, tool_to_grid, voxelize_mesh_evm

__all__ = ["BLENDER_UNITS_PER_MM", "BoundaryMesh", "DerivedCache", "EditStack", "LabelInfo",
           "MeshCheck", "Polygons", "ToolOperation", "box_evm", "check_closed_mesh",
           "chunked_build_memory", "index_to_physical", "tool_to_grid", "voxelize_mesh_evm"]
