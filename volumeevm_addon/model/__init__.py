"""The model: a voxel region as an Extreme Vertices Model, and the VolumeEVM built on it.

One module per concept (private; the public names are imported from ``volumeevm_addon``):

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
  levels), kept in its :class:`~volumeevm_addon.DerivedCache`: counted, bounded, clearable.
- ``_stack.py``: the non-destructive stack of tool operations on a VolumeEVM.
- ``_volume.py``: the volume record every reader returns, and where its grid sits.
- ``_histogram.py``: a volume's densities histogram and Otsu's threshold.
- ``_labels.py``: a label map's regions, every label in one sweep.
- ``_measure.py``: exact measurements of regions and label sets (volume, area, shared faces).
- ``_label_table.py``: label names and colours from segmentation files, and a fixed palette.
- ``_label_set.py``: a label map's regions as one mapping, edited and measured together.
"""
