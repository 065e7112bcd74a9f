"""The regions of a label map as one object: label -> VolumeEVM, names and colours, and the
edits and measurements that treat all labels together.

A :class:`LabelSet` is what :meth:`VolumeEVM.from_labels` returns: a read-only mapping from
label to its VolumeEVM (so ``regions[127]``, ``for label, region in regions.items()``), plus
``infos`` (each label's name and colour, :mod:`._label_table`). The regions are parts of one
grid, disjoint for a label map (a segmentation in layers, :attr:`Volume.layers`, may overlap
across layers): a cut removes the tool's voxels from every label, a keep keeps every label's
voxels inside the tool, and an add gives the tool's voxels to one label and takes them from the
others. A label an edit empties leaves the set.
"""

from collections.abc import Mapping

import numpy as np

from .._errors import VolumeEVMError
from ._label_mesh import label_meshes
from ._label_table import default_label_info
from ._manifold import split_non_manifold
from ._measure import measure_labels, write_measurements_csv
from ._smooth import smooth_mesh


class LabelSet(Mapping):
    """Regions of one grid, one per label, with each label's name and colour.

    Parameters
    ----------
    regions : mapping
        ``label (int > 0) -> VolumeEVM``, regions of one grid (disjoint in a label map).
    infos : mapping, optional
        ``label -> LabelInfo``; labels it lacks get :func:`._label_table.default_label_info`.

    Attributes
    ----------
    infos : dict
        ``label -> LabelInfo`` for every label of the set.

    Raises
    ------
    VolumeEVMError
        If the regions do not all share one grid (shape and geometry).

    Examples
    --------
    >>> import numpy as np
    >>> from volumeevm_addon import VolumeEVM
    >>> from volumeevm_addon.model import box_evm
    >>> array = np.zeros((6, 6, 6), np.uint8); array[:3] = 1; array[3:] = 2
    >>> regions = VolumeEVM.from_labels(array)
    >>> {label: r.voxel_count
    ...  for label, r in regions.cut(box_evm((0, 0, 0), (4, 6, 6), (6, 6, 6))).items()}
    {2: 72}
    """

    def __init__(self, regions, infos=None):
        self._regions = {int(label): region for label, region in sorted(regions.items())}
        grids = {(r.shape, r.spacing, r.origin, r.orientation.tobytes())
                 for r in self._regions.values()}
        if len(grids) > 1:
            raise VolumeEVMError("regions: the labels of a set must share one grid (shape and "
                                 "geometry)")
        infos = infos or {}
        self.infos = {label: infos.get(label) or default_label_info(label)
                      for label in self._regions}

    def __getitem__(self, label):
        return self._regions[label]

    def __iter__(self):
        return iter(self._regions)

    def __len__(self):
        return len(self._regions)

    def __repr__(self):
        return f"LabelSet({len(self)} labels: {', '.join(str(label) for label in self)})"

    # ------------------------------------------------------------------ meshes
    def meshes(self, manifold=False, smooth=False):
        """Every label's boundary mesh in physical mm, made together so that where two labels
        touch their meshes carry the same polygons, reversed (see :mod:`._label_mesh`).

        A label's own :meth:`VolumeEVM.mesh` merges its faces by itself: the same surface, but
        a polygon of it may span a contact and the faces beside it. These are the meshes to
        show or export a label map with.

        Parameters
        ----------
        manifold : bool
            Each mesh made 2-manifold for 3D printing (:meth:`EVM.mesh`); split vertices move
            by 1e-3 voxel, so contacts no longer share them exactly.
        smooth : bool
            Each mesh relaxed into a smooth display surface (:meth:`EVM.mesh`), label by label.

        Returns
        -------
        dict
            ``label -> (vertices, polygons)`` in increasing label order, as
            :meth:`VolumeEVM.mesh` returns them: closed, outward, vertices in mm.

        Raises
        ------
        VolumeEVMError
            When the meshes would need more memory than is available.

        Examples
        --------
        >>> import numpy as np
        >>> from volumeevm_addon import VolumeEVM
        >>> array = np.zeros((4, 4, 4), np.uint8); array[:2] = 1; array[2:, 1:3, 1:3] = 2
        >>> meshes = VolumeEVM.from_labels(array).meshes()
        >>> [len(polygons) for _, polygons in meshes.values()]  # label 1's side x = 2 in 5 parts
        [10, 6]
        """
        lattice = label_meshes([region.evm for region in self._regions.values()])
        out = {}
        for (label, region), (vertices, polygons) in zip(self._regions.items(), lattice):
            if manifold:
                vertices, polygons = split_non_manifold(vertices, polygons)
            if smooth:
                vertices, polygons = smooth_mesh(vertices, polygons)
            out[label] = region.corner_positions(vertices), polygons
        return out

    # ------------------------------------------------------------------ measurements
    def measure(self):
        """Every label's exact measurements and the areas it shares with the labels it touches.

        Returns
        -------
        dict
            ``label -> dict``: :meth:`VolumeEVM.measure`'s keys, plus ``name`` and
            ``shared_area_mm2`` (``{other label: mm²}``); see :mod:`._measure`.
        """
        return {label: {"name": self.infos[label].name, **row}
                for label, row in measure_labels(self._regions).items()}

    def write_measurements(self, path, *, overwrite=False):
        """Write :meth:`measure`'s rows as CSV (one row per label); see
        :func:`._measure.write_measurements_csv`.

        Parameters
        ----------
        path : str or os.PathLike
            The ``.csv`` file, written atomically.
        overwrite : bool, optional
            Replace an existing file (default False: an existing file is an error).

        Returns
        -------
        Path
            The file written.

        Raises
        ------
        VolumeEVMError
            If the file exists and ``overwrite`` is False, or cannot be written.
        """
        rows = [{"label": label, **row} for label, row in self.measure().items()]
        return write_measurements_csv(path, rows, overwrite=overwrite)

    # ------------------------------------------------------------------ edits
    def cut(self, tool):
        """Remove the tool's voxels from every label.

        Parameters
        ----------
        tool : EVM
            The voxels to remove, in the grid's lattice.

        Returns
        -------
        LabelSet
            Labels the tool empties are left out.

        Raises
        ------
        VolumeEVMError
            When the tool removes every label.
        """
        return self._edited({label: region.evm - tool for label, region in self.items()}, "cut")

    def keep(self, tool):
        """Keep every label's voxels inside the tool.

        Parameters
        ----------
        tool : EVM
            The voxels that may stay.

        Returns
        -------
        LabelSet
            Labels outside the tool are left out.

        Raises
        ------
        VolumeEVMError
            When the tool misses every label.
        """
        return self._edited({label: region.evm & tool for label, region in self.items()},
                            "keep inside")

    def add(self, tool, label):
        """Give the tool's voxels to ``label`` (a new label too), taking them from the others.

        Parameters
        ----------
        tool : EVM
            The voxels to add, in the grid's lattice; clipped to the grid.
        label : int
            The label that gets them (> 0); its density is the label value.

        Returns
        -------
        LabelSet

        Raises
        ------
        VolumeEVMError
            If ``label`` is not an integer > 0, or the tool has no voxel inside the grid.
        """
        if (isinstance(label, (bool, np.bool_)) or not isinstance(label, (int, np.integer))
                or label <= 0):
            raise VolumeEVMError(f"add: label must be an integer > 0, got {label!r}")
        label = int(label)
        first = next(iter(self._regions.values()))
        tool = tool.clip((0, 0, 0), first.shape)
        if tool.is_empty():
            raise VolumeEVMError("add: the tool has no voxel inside the volume's grid")
        regions = {other: region.evm - tool for other, region in self.items() if other != label}
        edited = self._edited(regions, "add", keep_empty=True)._regions
        if label in self._regions:
            edited[label] = self._regions[label].add(tool, density=label)
        else:
            edited[label] = first._derived(tool, np.full(tool.volume(), label,
                                                         first.table(0).dtype))
            edited[label].threshold = edited[label].upper = float(label)
        return LabelSet(edited, self.infos)

    def _edited(self, regions, what, keep_empty=False):
        """The set of each label's region reduced to ``regions[label]`` (a subset of it)."""
        kept = {label: self._regions[label]._subset(region, what)
                for label, region in regions.items() if not region.is_empty()}
        if not kept and not keep_empty:
            raise VolumeEVMError(f"{what}: the result would be empty (no label keeps a voxel)")
        return LabelSet(kept, self.infos)
