"""VolumeEVM: the EVM of a region of interest plus the densities of its voxels.

Only the region is stored: its extreme vertices and one densities table, the region's voxels in
slice-major order along x (table order "xyz", the C order of an ``[x, y, z]`` array). Tables for
the other principal axes are made from it when a view asks for them, and cached. The relation v
(voxel -> table index) comes from the EVM alone (:mod:`._densities`). What the renderers derive
from it, and its coarser levels, are kept in its :class:`DerivedCache` (:mod:`._cache`).

Files: one ``.vevm`` file is a NumPy ``.npz`` archive of plain arrays (never pickled objects),
with a format name and version, the geometry as JSON, and SHA-256 checksums of the vertices and
the table. It is written atomically and never replaces a file unasked
(:mod:`volumeevm_addon._files`); loading checks every member and the metadata before anything is
built (:mod:`._vevm_file`).
"""

import copy
import json
import math
import numbers
import os

import numpy as np

from .._errors import VolumeEVMError
from .._files import write_atomically
from .._jit import kernel
from .._memory import available_memory, check_memory
from ._cache import DerivedCache, default_budget
from ._chunked import build_chunked, labels_chunked
from ._densities import TABLE_ORDERS, TableIndex, reordered_table, run_count
from ._evm import EVM, check_lattice_range, integer_triple, vertex_keys
from ._label_set import LabelSet
from ._labels import checked_labels, layered_regions, wanted_labels, warn_missing
from ._levels import checked_factor, coarsen
from ._measure import measure
from ._vevm_file import FORMAT, VERSION, checksum, read_vevm
from ._volume import (
    Volume,
    checked_densities,
    checked_geometry,
    cropped,
    index_to_physical,
    is_lazy,
    transform,
)

_ROW_BYTES = 96
"""Per row of a part (:meth:`VolumeEVM._table_mask`): its box number, local index, first voxel
(three int64) and their temporaries, its first table index and length."""


@kernel
def _mark_stretches(starts, lengths, mask):
    """Set ``mask[starts[r] : starts[r] + lengths[r]]`` for every row ``r``."""
    for r in range(len(starts)):
        mask[starts[r]:starts[r] + lengths[r]] = True


class VolumeEVM:
    """A region of interest of a volume: its EVM and the densities of its voxels.

    What every renderer and tool works on. Usually built with :meth:`from_volume` or
    :meth:`from_array`, or read with :meth:`load`; the constructor wraps a region and its table
    as they are (everything after ``table`` is keyword-only). The attributes ``evm``, ``shape``,
    ``spacing``, ``origin``, ``orientation``, ``units``, ``threshold`` and ``upper`` hold the
    checked parameters; treat them as read-only (edits return new VolumeEVMs).

    Parameters
    ----------
    evm : EVM
        The region (lattice coordinates of the volume's grid).
    table : (N,) ndarray
        Densities of the region's N voxels in table order "xyz", in data units.
    shape : tuple of 3 int
        The grid the region lives in.
    spacing, origin, orientation, units
        Grid geometry and data units, as in :class:`Volume`.
    threshold, upper : float or None
        The density interval that selected the region (``None`` for regions made otherwise).

    Attributes
    ----------
    cache : DerivedCache
        What is derived from this VolumeEVM on first use and kept for the next use: the
        renderers' tables and the coarser levels (:mod:`._cache`). Counted by
        :meth:`size_report` (``cache_bytes``), bounded by ``cache.budget`` (default
        :func:`._cache.default_budget`, settable), dropped by ``cache.clear()``.

    Raises
    ------
    VolumeEVMError
        If ``evm`` is not an EVM or reaches outside the grid, the table is not a 1-D array of
        finite numbers with one density per voxel of the region, or the geometry, units or
        interval are bad (naming the parameter).

    Examples
    --------
    >>> import numpy as np
    >>> from volumeevm_addon import EVM
    >>> mask = np.zeros((4, 4, 4), bool); mask[1:3, 1:3, 1:3] = True
    >>> vevm = VolumeEVM(EVM.from_mask(mask), np.arange(8.0), shape=(4, 4, 4))
    >>> vevm.voxel_count, float(vevm.to_dense()[2, 2, 2])
    (8, 7.0)
    """

    def __init__(self, evm, table, *, shape, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0),
                 orientation=None, units="", threshold=None, upper=None):
        if not isinstance(evm, EVM):
            raise VolumeEVMError(f"evm must be an EVM, got {type(evm).__name__}")
        table = np.asarray(table)
        if table.ndim != 1 or table.dtype.kind not in "uif":
            raise VolumeEVMError(f"table must be a 1-D array of integers or real numbers, got "
                                 f"shape {table.shape} and dtype {table.dtype}")
        if table.dtype.kind == "f" and not np.isfinite(table).all():
            raise VolumeEVMError(f"table: {np.count_nonzero(~np.isfinite(table))} densities are "
                                 f"NaN or infinite")
        self.shape = _grid_shape(shape, "")
        if not evm.is_empty():
            lo, hi = evm.bounds()
            if min(lo) < 0 or any(h > s for h, s in zip(hi, self.shape)):
                raise VolumeEVMError(f"evm: the region spans lattice corners {lo} to {hi}, outside "
                                     f"the grid of shape {self.shape}")
        count = evm.volume()
        if count != len(table):
            raise VolumeEVMError(f"table: the region has {count} voxels but the table "
                                 f"{len(table)} densities")
        spacing, origin, orientation = checked_geometry(spacing, origin, orientation)
        if not isinstance(units, str):
            raise VolumeEVMError(f"units must be a string (such as 'HU'), got {units!r}")
        threshold, upper = _density_interval(threshold, upper, "", optional=True)
        self._fill(evm, table, self.shape, (spacing, origin, orientation), units, threshold, upper)

    @classmethod
    def _checked_parts(cls, evm, table, shape, geometry, units, threshold, upper):
        """A VolumeEVM of parts right by construction (checked geometry, a table of one
        density per voxel of ``evm``), without the checks of ``__init__``: counting the voxels
        sweeps the EVM, which for the many labels of a map costs more than building them."""
        vevm = cls.__new__(cls)
        vevm._fill(evm, table, shape, geometry, units, threshold, upper)
        return vevm

    def _fill(self, evm, table, shape, geometry, units, threshold, upper):
        """Set the fields from checked parts (the one place that sets them)."""
        self.shape = shape
        self.spacing, self.origin, self.orientation = geometry
        self.threshold = None if threshold is None else float(threshold)
        self.upper = None if upper is None else float(upper)
        self.evm = evm
        self.units = units
        self._tables = {0: table}
        self._indices = {}
        self.cache = DerivedCache(budget=default_budget(self.shape))

    # ------------------------------------------------------------------ building
    @classmethod
    def from_array(cls, array, threshold, upper=None, *, spacing=(1.0, 1.0, 1.0),
                   origin=(0.0, 0.0, 0.0), orientation=None, units="", source="array"):
        """Build the VolumeEVM of the voxels with ``threshold <= density`` (``<= upper``).

        Parameters
        ----------
        array : (X, Y, Z) ndarray
            Densities indexed ``[x, y, z]``: integers or real floating-point numbers, all finite.
            Booleans are refused (a mask is not densities: use :meth:`EVM.from_mask`), and so
            are masked arrays (fill the masked voxels explicitly: ``array.filled(value)``).
            At most 1048575 voxels along each axis (the EVM's coordinate range).
        threshold, upper : real number
            The density interval that selects the region; finite, ``upper >= threshold``.
        spacing, origin, orientation
            Grid geometry as in :class:`Volume`, checked by :func:`._volume.checked_geometry`.
        units : str
            The data units ("HU").
        source : str
            Names the data in messages.

        Returns
        -------
        VolumeEVM

        Raises
        ------
        VolumeEVMError
            For any input above that is not as described, naming ``source`` and the parameter;
            for an empty region; and when the build would need more memory than is available
            (:func:`volumeevm_addon.system.check_memory`).

        Notes
        -----
        The region is made straight from the densities one x-slice at a time, so no dense mask
        of the grid is ever allocated: a first pass extracts the extreme vertices (8 bytes each,
        the keys the EVM keeps) and counts the region's voxels; then the memory for the rest
        (:func:`build_memory`) is checked; a second pass copies the region's densities into the
        table. Memory is also checked during the first pass, as the counts grow.
        """
        array = checked_densities(array, source)
        shape = _grid_shape(array.shape, f"{source}: ")
        spacing, origin, orientation = checked_geometry(spacing, origin, orientation, source=source)
        threshold, upper = _density_interval(threshold, upper, f"{source}: ")
        if not isinstance(units, str):
            raise VolumeEVMError(f"{source}: units must be a string (such as 'HU'), got {units!r}")

        def inside(plane):
            selected = plane >= threshold
            if upper is not None:
                selected &= plane <= upper
            return selected

        totals = {"voxels": 0, "boxes": 0}

        def slices():
            previous = np.zeros(shape[1:], bool)
            for plane in array:
                selected = inside(plane)
                totals["voxels"] += int(np.count_nonzero(selected))
                totals["boxes"] += _new_boxes(selected, previous)
                yield selected
                previous = selected

        def needed(vertex_count):
            return build_memory(shape, array.dtype, totals["voxels"], vertex_count, totals["boxes"])

        def check(vertex_count):
            check_memory(needed(vertex_count), "building the VolumeEVM", source=source,
                         advice="crop the volume, raise the threshold or narrow the density "
                                "interval")

        budget = available_memory()
        keys, vertex_count = [], 0
        for plane_keys in vertex_keys(slices(), shape):
            keys.append(plane_keys)
            vertex_count += len(plane_keys)
            if budget is not None and needed(vertex_count) > budget:
                check(vertex_count)  # refuses now, unless memory was freed meanwhile
        if totals["voxels"] == 0:
            band = f">= {threshold}" if upper is None else f"in [{threshold}, {upper}]"
            raise VolumeEVMError(
                f"{source}: the region is empty: no density is {band} "
                f"(data range {array.min()} .. {array.max()})"
            )
        check(vertex_count)
        evm = EVM._from_keys(np.concatenate(keys))
        del keys  # the per-plane keys go before the table comes
        table = np.empty(totals["voxels"], array.dtype)
        start = 0
        for plane in array:
            values = plane[inside(plane)]
            table[start:start + len(values)] = values
            start += len(values)
        return cls(evm, table, shape=shape, spacing=spacing, origin=origin,
                   orientation=orientation, units=units, threshold=threshold, upper=upper)

    @classmethod
    def from_volume(cls, volume, threshold, upper=None, *, crop=None, progress=None):
        """Build from a :class:`Volume` (a reader's result), keeping its geometry and units.

        A lazy volume (its ``array`` a Dask array: an OME-Zarr store, ``read_volume(path,
        lazy=True)``) is built chunk by chunk (:mod:`._chunked`) on Dask's scheduler: threads
        by default, a ``dask.distributed`` cluster when a ``Client`` exists. The result is
        identical to :meth:`from_array` on the same data in memory, for any chunk shape, and
        memory follows the chunks in flight and the result, not the grid.

        Parameters
        ----------
        volume : Volume
            As :func:`volumeevm_addon.read_volume` returns it.
        threshold, upper : real number
            The density interval that selects the region, as for :meth:`from_array`.
        crop : sequence of 3 (int, int) pairs, optional
            Build only the voxels of this box, a region of interest: ``((i0, i1), (j0, j1),
            (k0, k1))`` in voxel indices along the array's axes x, y, z (``volume.array[i0:i1,
            j0:j1, k0:k1]``), half-open, ``0 <= start < stop <= shape``; from physical bounds,
            :meth:`Volume.index_box` gives it. The result's grid is the box (its ``shape`` the
            box's size, its ``origin`` the centre of voxel ``(i0, j0, k0)``), so each kept voxel
            sits where it sat: it equals the whole volume's VolumeEVM clipped to the box
            (:meth:`clip`), moved by ``-(i0, j0, k0)``. Nothing outside the box is read (a lazy
            volume's chunks that miss it are never computed) and memory is checked for the box.
        progress : callable, optional
            Called as ``progress(done, total)`` after each chunk of a lazy volume (``total``
            chunks in all), on the calling thread (on a ``dask.distributed`` cluster, when
            each batch of chunks ends); an in-memory volume is one chunk, ``(1, 1)`` once
            built. An exception it raises stops the build and comes out of this call (a
            caller cancels so).

        Returns
        -------
        VolumeEVM
            With the volume's spacing, origin, orientation and units.

        Raises
        ------
        VolumeEVMError
            If ``volume`` is not a :class:`Volume`, or ``crop`` is not a box of voxel indices
            inside the grid (empty, reversed, outside, not 3 pairs of integers: naming
            ``crop``); otherwise as :meth:`from_array`, the
            messages naming the volume's source file (for a lazy volume, a chunk with NaN or
            infinite densities names the chunk, and memory is checked before the first chunk
            and after every batch of chunks).

        Examples
        --------
        >>> from volumeevm_addon import phantoms
        >>> vol = phantoms.box((8, 8, 8), lo=(2, 2, 2), hi=(6, 6, 6), density=100.0)
        >>> vevm = VolumeEVM.from_volume(vol, 50)
        >>> vevm.voxel_count, len(vevm.evm), vevm.units
        (64, 8, 'a.u.')
        >>> part = VolumeEVM.from_volume(vol, 50, crop=((0, 4), (0, 8), (3, 8)))
        >>> part.shape, part.voxel_count, part.origin
        ((4, 8, 5), 24, (0.0, 0.0, 3.0))
        """
        if not isinstance(volume, Volume):
            raise VolumeEVMError(f"volume must be a Volume (as read_volume returns), got "
                                 f"{type(volume).__name__}")
        if crop is not None:
            volume = cropped(volume, crop)
        if is_lazy(volume.array):
            return cls._from_lazy(volume, threshold, upper, progress)
        built = cls.from_array(volume.array, threshold, upper, spacing=volume.spacing,
                               origin=volume.origin, orientation=volume.orientation,
                               units=volume.units, source=volume.source or "volume")
        if progress is not None:
            progress(1, 1)
        return built

    @classmethod
    def _from_lazy(cls, volume, threshold, upper, progress):
        """:meth:`from_volume` of a lazy volume, checked as :meth:`from_array` checks."""
        source = volume.source or "volume"
        array = volume.array
        if array.ndim != 3 or array.dtype.kind not in "uif" or 0 in array.shape:
            raise VolumeEVMError(f"{source}: expected a non-empty 3-D array of integers or real "
                                 f"numbers indexed [x, y, z], got shape {array.shape} and dtype "
                                 f"{array.dtype}")
        shape = _grid_shape(array.shape, f"{source}: ")
        spacing, origin, orientation = checked_geometry(volume.spacing, volume.origin,
                                                        volume.orientation, source=source)
        threshold, upper = _density_interval(threshold, upper, f"{source}: ")
        if not isinstance(volume.units, str):
            raise VolumeEVMError(
                f"{source}: units must be a string (such as 'HU'), got {volume.units!r}")
        keys, table, low, high = build_chunked(array, threshold, upper, source, progress)
        if len(table) == 0:
            band = f">= {threshold}" if upper is None else f"in [{threshold}, {upper}]"
            raise VolumeEVMError(f"{source}: the region is empty: no density is {band} "
                                 f"(data range {low} .. {high})")
        return cls(EVM._from_keys(keys), table, shape=shape, spacing=spacing, origin=origin,
                   orientation=orientation, units=volume.units, threshold=threshold, upper=upper)

    @classmethod
    def from_labels(cls, labels_map, labels=None, *, spacing=None, origin=None, orientation=None,
                    units="", source="array"):
        """One VolumeEVM per label of a label map (0 = background), built in one sweep.

        Each is identical to ``VolumeEVM.from_array(array, L, upper=L)`` (vertices, table,
        geometry, interval) but the whole map is swept once (:mod:`._labels`), so a map of 100
        labels costs about one build. Labels that touch share their boundary faces exactly.
        A lazy label map (a Dask array: ``read_volume(path, lazy=True)``, an OME-Zarr store) is
        swept chunk by chunk as :meth:`from_volume` builds (:mod:`._chunked`), with the same
        result for any chunk shape, memory following the chunks in flight and the result.

        Parameters
        ----------
        labels_map : Volume or (X, Y, Z) ndarray of int
            The label map: non-negative integers. A :class:`Volume` brings its geometry, units
            and source; for an array, pass them here. A Volume with ``layers`` (a segmentation
            whose segments overlap) builds each label from its layer: labels of different
            layers may then share voxels.
        labels : int or iterable of int, optional
            The labels to build (default every label present but 0).
        spacing, origin, orientation, units, source
            The grid's geometry and the data's name, as for :meth:`from_array` (for an array
            only).

        Returns
        -------
        LabelSet
            A mapping ``label -> VolumeEVM`` in increasing label order, with each label's name
            and colour (``infos``: a Volume's ``labels``, a fixed palette otherwise) and edits
            and measurements of all labels together; a wanted label with no voxels is left
            out, with a warning naming it.

        Raises
        ------
        VolumeEVMError
            For a map that is not non-negative integers (floats, booleans, negative labels; in
            a lazy map, the message names the chunk), more than :data:`._labels.MAX_LABELS`
            labels, geometry given twice or bad, or no memory for the result (for a lazy map,
            checked before the first chunk and after every batch of chunks).

        Examples
        --------
        >>> import numpy as np
        >>> array = np.zeros((4, 4, 4), np.uint8); array[:2] = 1; array[2:, :2] = 7
        >>> regions = VolumeEVM.from_labels(array, spacing=(0.5, 0.5, 1.0))
        >>> {label: region.voxel_count for label, region in regions.items()}
        {1: 32, 7: 16}
        """
        geometry = {"spacing": spacing, "origin": origin, "orientation": orientation}
        infos = None
        if isinstance(labels_map, Volume):
            given = [name for name, value in geometry.items() if value is not None]
            if given:
                raise VolumeEVMError(f"{', '.join(given)}: a Volume brings its own geometry; "
                                     f"pass the array instead to set it")
            geometry = {"spacing": labels_map.spacing, "origin": labels_map.origin,
                        "orientation": labels_map.orientation}
            units, source = labels_map.units, labels_map.source or "volume"
            infos, maps = labels_map.labels, labels_map.layers or (labels_map.array,)
            labels_map = maps[0]
        else:
            maps = (labels_map,)
        geometry = checked_geometry(
            (1.0, 1.0, 1.0) if geometry["spacing"] is None else geometry["spacing"],
            (0.0, 0.0, 0.0) if geometry["origin"] is None else geometry["origin"],
            geometry["orientation"], source=source)
        if not isinstance(units, str):
            raise VolumeEVMError(f"{source}: units must be a string, got {units!r}")
        if len(maps) == 1 and is_lazy(labels_map):
            checked_labels(labels_map, source)
            wanted = wanted_labels(labels)
            regions = labels_chunked(labels_map, wanted, source)
            warn_missing(wanted, regions, source)
        else:
            regions = layered_regions(maps, labels, source=source)
        shape = _grid_shape(np.shape(labels_map), f"{source}: ")
        check_memory(sum(count for _, count in regions.values()) * labels_map.dtype.itemsize,
                     "the label tables", source=source, advice="pick fewer labels with labels=")
        spacing, origin, orientation = geometry
        return LabelSet({label: cls._checked_parts(EVM._from_keys(keys),
                                                   np.full(count, label, labels_map.dtype), shape,
                                                   (spacing, origin, orientation.copy()), units,
                                                   label, label)
                         for label, (keys, count) in regions.items()}, infos)

    # ------------------------------------------------------------------ densities
    @property
    def voxel_count(self):
        """Number of voxels in the region."""
        return len(self._tables[0])

    def table(self, axis=0):
        """Densities of the region's voxels in slice-major order along ``axis`` (0, 1, 2).

        Axis 0 is the stored table; the others are made on first use and cached. Making one
        reads the stored table scanline by scanline into the other order
        (:func:`._densities.reordered_table`): no grid, only the new table and the region's
        runs per scanline.

        Parameters
        ----------
        axis : {0, 1, 2}, optional
            The slowest axis of the order (:data:`TABLE_ORDERS`): 0 is x, y, z (the C order of
            the ``[x, y, z]`` array), 1 is y, x, z and 2 is z, x, y.

        Returns
        -------
        (N,) ndarray
            The densities, in the data's dtype; do not modify (it is cached).

        Raises
        ------
        VolumeEVMError
            If ``axis`` is not 0, 1 or 2.
        VolumeEVMError
            When the new table would need more memory than is available.
        """
        if axis not in (0, 1, 2):
            raise VolumeEVMError(f"axis must be 0, 1 or 2, got {axis!r}")
        if axis not in self._tables:
            table = self._tables[0]
            runs = run_count(self.evm, TABLE_ORDERS[0])
            check_memory(table.nbytes + int(self.shape[0]) * int(self.shape[1]) * 8 + runs * 16,
                         f"the densities table in {TABLE_ORDERS[axis]} order",
                         source=f"VolumeEVM table({axis})",
                         advice="render at a coarser level or clip the region")
            self._tables[axis] = reordered_table(self.evm, table, self.shape, axis)
        return self._tables[axis]

    def index(self, voxels, axis=0):
        """The relation v: where voxels' densities sit in :meth:`table`, from the EVM alone.

        Parameters
        ----------
        voxels : (m, 3) array_like of int
            Voxel indices ``[x, y, z]``.
        axis : {0, 1, 2}, optional
            Which table (:meth:`table`).

        Returns
        -------
        (m,) ndarray of np.int64
            Indices into ``table(axis)``; -1 for voxels outside the region.

        Examples
        --------
        >>> from volumeevm_addon import phantoms
        >>> vevm = VolumeEVM.from_volume(phantoms.ramp((3, 2, 2)), 0.5)
        >>> vevm.index([[2, 1, 1], [0, 0, 0]]).tolist(), vevm.table()[7].item()
        ([7, -1], 1.0)
        """
        if axis not in self._indices:
            self._indices[axis] = TableIndex(self.evm, TABLE_ORDERS[axis])
        return self._indices[axis](voxels)

    def level(self, factor):
        """This VolumeEVM at ``factor`` times coarser voxels (:func:`._levels.coarsen`): made on
        first use and kept in :attr:`cache` (key ``("level", factor)``), so only the levels views
        ask for are ever built. :func:`volumeevm_addon.render` picks one with ``level``.

        Parameters
        ----------
        factor : int
            Fine voxels per coarse voxel along each axis, from 2 to the grid's largest side.

        Returns
        -------
        VolumeEVM
            Same orientation, units and threshold; ``spacing * factor``.

        Raises
        ------
        VolumeEVMError
            For a factor that is not such an integer, or when the level would need more
            memory than is available.
        """
        factor = checked_factor(factor, self.shape)
        return self.cache.get(("level", factor), lambda: self._coarse(factor))

    def _coarse(self, factor):
        """The VolumeEVM of :func:`._levels.coarsen`'s arrays (not cached): right by
        construction (one mean density per coarse voxel), so its voxels are not counted again."""
        evm, table, shape, spacing, origin = coarsen(self, factor)
        geometry = checked_geometry(spacing, origin, self.orientation)
        return VolumeEVM._checked_parts(evm, table, shape, geometry, self.units, self.threshold,
                                        self.upper)

    def to_dense(self, background=0):
        """The full grid: the region's densities, ``background`` everywhere else.

        Parameters
        ----------
        background : scalar, optional
            Value outside the region (default 0), cast to the table's dtype.

        Returns
        -------
        (X, Y, Z) ndarray
            In the table's dtype.

        Raises
        ------
        VolumeEVMError
            When the grid would need more memory than is available.
        """
        return self._scatter(background)[0]

    def dense_box(self, background, dtype=np.float32):
        """The region's bounding box as a dense array: its densities, ``background`` elsewhere.

        What a sparse grid is copied from (e.g. OpenVDB's ``copyFromArray`` with ``background``
        as the grid's background: exactly the region's voxels differ from it when no density
        equals it). Memory follows the region's box, not the whole grid.

        Parameters
        ----------
        background : scalar
            Value outside the region, cast to ``dtype``.
        dtype : dtype, optional
            Type of the array (default ``np.float32``).

        Returns
        -------
        lo : tuple of 3 int
            Voxel index of ``box[0, 0, 0]``.
        box : (X, Y, Z) ndarray
            C-contiguous; ``box[i, j, k]`` is voxel ``lo + (i, j, k)``.

        Raises
        ------
        VolumeEVMError
            For an empty region, or when the box would need more memory than is available.

        Examples
        --------
        >>> array = np.zeros((5, 5, 5)); array[1:3, 2, 2:4] = [[5, 6], [7, 8]]
        >>> lo, box = VolumeEVM.from_array(array, 1).dense_box(-1)
        >>> lo, box.shape, box[:, 0, :].tolist()
        ((1, 2, 2), (2, 1, 2), [[5.0, 6.0], [7.0, 8.0]])
        """
        bounds = self.evm.bounds()
        if bounds is None:
            raise VolumeEVMError("the region is empty: no voxels to copy")
        lo, hi = bounds
        shape = tuple(b - a for a, b in zip(lo, hi))
        check_memory(math.prod(shape) * (np.dtype(dtype).itemsize + 1), "making the region's box",
                     source=f"VolumeEVM box {shape}",
                     advice="clip the region to the part you need")
        mask = self.evm.to_mask(shape, offset=lo)
        box = np.full(shape, background, dtype=dtype)
        box[mask] = self._tables[0]
        return lo, box

    def _scatter(self, background):
        """The dense grid (``background`` outside the region) and the region's voxel mask.

        Its memory is checked first: the grid and the mask are as large as the whole volume.
        """
        table = self._tables[0]
        check_memory(math.prod(self.shape) * (table.dtype.itemsize + 2), "making the dense grid",
                     source=f"VolumeEVM grid {self.shape}",
                     advice="work on the VolumeEVM itself, or clip it to the part you need")
        mask = self.evm.to_mask(self.shape)
        dense = np.full(self.shape, background, dtype=table.dtype)
        dense[mask] = table
        return dense, mask

    # ------------------------------------------------------------------ editing
    def cut(self, tool):
        """Remove the tool's voxels: a new VolumeEVM of ``region - tool``, densities kept.

        Parameters
        ----------
        tool : EVM
            The voxels to remove, in this grid's lattice (e.g. a drill's voxelized mesh).

        Returns
        -------
        VolumeEVM
            The region less the tool; this one is left as it is.

        Raises
        ------
        TypeError
            If ``tool`` is not an EVM.
        VolumeEVMError
            When the tool covers the whole region.
        """
        return self._subset(self.evm - _check_tool(tool), "cut")

    def keep(self, tool):
        """Keep only the voxels inside the tool: ``region & tool``, densities kept.

        Parameters
        ----------
        tool : EVM
            The voxels that may stay, in this grid's lattice.

        Returns
        -------
        VolumeEVM
            The part of the region inside the tool.

        Raises
        ------
        TypeError
            If ``tool`` is not an EVM.
        VolumeEVMError
            When the tool misses the region.
        """
        return self._subset(self.evm & _check_tool(tool), "keep inside")

    def clip(self, lo, hi):
        """Keep only the voxels inside the box ``[lo, hi)`` (lattice corners).

        Parameters
        ----------
        lo, hi : (3,) array_like of int
            The box's corners, as for :meth:`EVM.clip`.

        Returns
        -------
        VolumeEVM

        Raises
        ------
        VolumeEVMError
            For corners that are not 3 integers, or when nothing would be left.
        """
        return self._subset(self.evm.clip(lo, hi), "clip")

    def largest_component(self):
        """Keep only the largest face-connected part of the region (e.g. drop loose debris).

        Returns
        -------
        VolumeEVM
        """
        return self._subset(self.evm.components()[0], "keep largest part")

    def add(self, tool, density=None):
        """Add the tool's voxels as material: ``region | tool``; every tool voxel gets ``density``.

        Parameters
        ----------
        tool : EVM
            The tool's voxels in this grid's lattice; clipped to the grid.
        density : real number, optional
            Density of every tool voxel; by default the largest density of the region (the
            report gives geometric models the maximum grey value). Must fit the table's dtype.

        Returns
        -------
        VolumeEVM

        Raises
        ------
        TypeError
            If ``tool`` is not an EVM.
        VolumeEVMError
            When the tool has no voxel inside the grid, or ``density`` is not finite or does
            not fit the table's integer dtype.
        """
        tool = _check_tool(tool).clip((0, 0, 0), self.shape)
        if tool.is_empty():
            raise VolumeEVMError("add: the tool has no voxel inside the volume's grid")
        table = self._tables[0]
        density = table.max() if density is None else density
        if not np.isfinite(density):
            raise VolumeEVMError(f"add: density {density!r} is not a finite number")
        if np.issubdtype(table.dtype, np.integer):
            info = np.iinfo(table.dtype)
            if not info.min <= density <= info.max:
                raise VolumeEVMError(f"add: density {density} does not fit the data type "
                                     f"{table.dtype}")
        region = self.evm | tool
        result = self._derived(region, np.empty(region.volume(), table.dtype))
        # Both tables list voxels in the same (C) order, so the old voxels the tool leaves alone
        # keep their relative order: fill them in one masked copy.
        from_tool = result._table_mask(tool, "add")
        covered = self._table_mask(self.evm & tool, "add")
        result._tables[0][from_tool] = density
        result._tables[0][~from_tool] = table[~covered]
        return result

    def _subset(self, region, what):
        """The VolumeEVM of ``region``, a subset of this region, with the densities it keeps.

        Tables list voxels in C order, and a subset keeps that order, so the new table is the old
        one masked.
        """
        if region.is_empty():
            raise VolumeEVMError(f"{what}: the result would be empty")
        return self._derived(region, self._tables[0][self._table_mask(region, what)])

    def _table_mask(self, part, what):
        """Which entries of the table (order "xyz") belong to ``part``, a subset of the region
        (for the edit ``what``, named when the memory it needs is refused).

        Each row of ``part`` (fixed x and y, a run along z) is one contiguous stretch of the
        table, so the mask comes from the rows' first indices (the relation v) and lengths,
        without visiting ``part``'s voxels one by one; a kernel sets each stretch, a byte per
        entry (the difference counts and their running sum it replaces took 24 bytes: a cut
        of the bone of a 2048³ head peaked at 10 GiB). The memory is checked first.
        """
        lo, hi = part.boxes()
        size = hi - lo
        rows = size[:, 0] * size[:, 1]
        row_count = int(rows.sum())
        check_memory(self.voxel_count + row_count * _ROW_BYTES + len(lo) * 80,
                     "selecting the densities the result keeps", source=what,
                     advice="cut a coarser level or a cropped build of the volume")
        box = np.repeat(np.arange(len(lo)), rows)
        local = np.arange(row_count) - np.repeat(np.cumsum(rows) - rows, rows)
        firsts = lo[box] + np.stack([local // size[box, 1], local % size[box, 1],
                                     np.zeros_like(local)], axis=1)
        del local
        mask = np.zeros(self.voxel_count, bool)
        _mark_stretches(self.index(firsts), size[box, 2], mask)
        return mask

    def _derived(self, region, table):
        """The VolumeEVM of ``region`` in this grid with ``table``, which the caller made for it
        (one density per voxel, in table order). The grid, units and interval were checked when
        this one was made and carry over; nothing is checked again (counting the region's
        voxels would cost a sweep of it)."""
        derived = copy.copy(self)
        derived.evm, derived._tables, derived._indices = region, {0: table}, {}
        derived.cache = DerivedCache(budget=default_budget(self.shape))
        return derived

    # ------------------------------------------------------------------ geometry
    def index_to_physical(self):
        """4x4 matrix from voxel-centre indices to physical mm (LPS); see :mod:`._volume`.

        Returns
        -------
        (4, 4) ndarray of np.float64
            :func:`volumeevm_addon.model.index_to_physical` of this grid's geometry.
        """
        return index_to_physical(self.spacing, self.origin, self.orientation)

    def mesh(self, manifold=False, smooth=False):
        """The region's boundary mesh in physical mm (LPS), e.g. to show it in Blender.

        Parameters
        ----------
        manifold : bool
            Every edge with two faces and every vertex one fan, for 3D printing
            (:meth:`EVM.mesh`): split copies move by 1e-3 voxel, i.e. 1e-3 times the spacing.
        smooth : bool
            A smooth display surface (:meth:`EVM.mesh`): every vertex within half a voxel of
            its exact position along each grid axis (half the spacing); faces no longer planar
            cut into triangles. Measurements (:meth:`measure`) use the exact mesh.

        Returns
        -------
        vertices : (n, 3) ndarray of np.float64
            Voxel corners in physical mm (moved ones with ``smooth``).
        polygons : Polygons
            Faces merged per plane, counter-clockwise seen from outside (:meth:`EVM.mesh`).

        Raises
        ------
        VolumeEVMError
            When the mesh would need more memory than is available.
        """
        vertices, polygons = self.evm.mesh(manifold, smooth)
        return self.corner_positions(vertices), polygons

    def measure(self):
        """Exact measurements of the region: volume (mm³, mL), boundary area (mm²), bounding box
        and centroid (LPS mm), face-connected parts; see :mod:`._measure`.

        Returns
        -------
        dict
            ``voxels``, ``volume_mm3``, ``volume_ml``, ``area_mm2``, ``bbox_mm``,
            ``centroid_mm``, ``components``.

        Examples
        --------
        >>> import numpy as np
        >>> array = np.zeros((6, 6, 6)); array[1:4, 1:3, 1:2] = 1
        >>> m = VolumeEVM.from_array(array, 1, spacing=(1.0, 2.0, 0.5)).measure()
        >>> m["volume_mm3"], m["area_mm2"], m["centroid_mm"]
        (6.0, 31.0, (2.0, 3.0, 0.5))
        """
        return measure(self)

    def corner_positions(self, vertices):
        """Lattice points (voxel corners: :meth:`mesh`'s, or a :class:`BoundaryMesh`'s vertices)
        in physical mm (LPS).

        Parameters
        ----------
        vertices : (n, 3) array_like of float
            Lattice coordinates; point ``p`` is the corner at voxel-centre index ``p - 0.5``.

        Returns
        -------
        (n, 3) ndarray of np.float64
        """
        matrix = self.index_to_physical()
        return transform(np.asarray(vertices, np.float64) - 0.5, matrix[:3, :3].T, matrix[:3, 3])

    def size_report(self):
        """Bytes of the model (vertices and the densities tables built so far) against the dense
        array, and of what :attr:`cache` holds beside it.

        Returns
        -------
        dict
            ``vertices_bytes``, ``tables_bytes`` (every axis's table built so far),
            ``total_bytes`` (their sum: the model itself), ``dense_bytes`` (the dense array of
            the table's type), ``ratio`` (``total_bytes / dense_bytes``) and ``cache_bytes``
            (``cache.nbytes``: the renderers' tables and the coarser levels, not part of the
            model; ``cache.clear()`` frees them).
        """
        vertices = self.evm.vertices.nbytes
        tables = sum(t.nbytes for t in self._tables.values())
        dense = int(np.prod(self.shape)) * self._tables[0].dtype.itemsize
        return {
            "vertices_bytes": vertices,
            "tables_bytes": tables,
            "total_bytes": vertices + tables,
            "dense_bytes": dense,
            "ratio": (vertices + tables) / dense,
            "cache_bytes": self.cache.nbytes,
        }

    def __repr__(self):
        return (f"VolumeEVM({self.voxel_count} voxels, {len(self.evm)} vertices, "
                f"grid {self.shape}, spacing {self.spacing})")

    # ------------------------------------------------------------------ files
    def _meta(self):
        return {
            "shape": list(self.shape),
            "spacing": list(self.spacing),
            "origin": list(self.origin),
            "orientation": self.orientation.tolist(),
            "units": self.units,
            "threshold": self.threshold,
            "upper": self.upper,
            "voxels": self.voxel_count,
            "vertices_sha256": checksum(self.evm.vertices),
            "table_sha256": checksum(self._tables[0]),
        }

    def save(self, path, *, overwrite=False):
        """Write one ``.vevm`` file atomically (:func:`volumeevm_addon.system.write_atomically`).

        Parameters
        ----------
        path : str or path-like
            The file to write (``.vevm`` by convention).
        overwrite : bool, optional
            Replace an existing file (default False: raise instead). Keyword-only.

        Returns
        -------
        Path
            The file written.

        Raises
        ------
        VolumeEVMError
            If the file exists (even one that appears while this writes) and ``overwrite`` is
            False, or the file system refuses the write (disk full, no permission); any old file
            is then kept as it was and no temporary file is left.
        """

        def write(temporary):
            with open(temporary, "wb") as file:
                np.savez(file, format=np.array(FORMAT), version=np.array(VERSION),
                         meta=np.array(json.dumps(self._meta())),
                         vertices=self.evm.vertices, table=self._tables[0])
                file.flush()
                os.fsync(file.fileno())

        return write_atomically(path, write, overwrite=overwrite)

    @classmethod
    def load(cls, path):
        """Read a ``.vevm`` file, checked in full before anything is built (:mod:`._vevm_file`).

        Parameters
        ----------
        path : str or path-like
            A file written by :meth:`save`.

        Returns
        -------
        VolumeEVM
            Equal to the one saved: same vertices, table (and dtype) and geometry.

        Raises
        ------
        VolumeEVMError
            If the file is missing, foreign, of another version, damaged or inconsistent, or
            would not fit the free memory; the message names the file and what is wrong.
        """
        evm, table, geometry = read_vevm(path)
        try:
            return cls(evm, table, **geometry)
        except VolumeEVMError as error:  # read_vevm checks all this first: a safety net
            raise VolumeEVMError(f"{path}: inconsistent VolumeEVM file ({error})") from error


def build_memory(shape, dtype, voxel_count, vertex_count, box_count):
    """Estimated peak bytes of :meth:`VolumeEVM.from_array` for a region of these sizes.

    Counted: the table (``voxel_count`` densities of ``dtype``, and a byte each for the
    finiteness check of a floating-point table); the extreme vertices (their keys while they
    are extracted, then the EVM's keys and compact coordinates); the EVM's boxes
    (:meth:`EVM.boxes`, which the volume count and the relation v use) and their sweep
    temporaries; a few x-slices of the grid. The per-vertex and per-box costs are measured
    peaks with a margin: tracemalloc (which traces NumPy's allocations and the compiled
    kernels') over the CT head at three density intervals and upsampled twice, two MRIs, a
    label map, noise and a checkerboard gives ``peak - table = 13 bytes * vertices + 97 bytes
    * boxes`` (least squares), and the estimate is 1.09 to 1.22 times the measured peak on each
    of them.
    """
    _, ny, nz = shape
    slices = 8 * (ny + 1) * (nz + 1)
    dtype = np.dtype(dtype)
    table = voxel_count * (dtype.itemsize + (dtype.kind == "f"))
    return int(table + 16 * vertex_count + 112 * box_count + slices)


def _new_boxes(selected, previous):
    """How many boxes of :meth:`EVM.boxes` start at x-slice ``selected`` (after ``previous``).

    A slab of the box decomposition starts where a slice differs from the one before; inside
    it, a sub-slab starts at each row that differs from the row before, and holds one box per
    run of the row along z. Counting them slice by slice gives the box count before the EVM
    exists.
    """
    if np.array_equal(selected, previous):
        return 0
    rows = np.ones(len(selected), bool)
    rows[1:] = (selected[1:] != selected[:-1]).any(axis=1)
    starts = selected[rows]
    return int(np.count_nonzero(starts[:, 0]) + np.count_nonzero(starts[:, 1:] & ~starts[:, :-1]))


def _grid_shape(shape, prefix):
    """The grid shape as 3 Python ints, positive and within the EVM's coordinate range."""
    shape = integer_triple(shape, f"{prefix}shape")
    if min(shape) < 1:
        raise VolumeEVMError(f"{prefix}shape must be 3 positive integers, got {shape}")
    check_lattice_range((0, 0, 0), shape, f"{prefix}grid of shape {shape}")
    return shape


def _density_interval(threshold, upper, prefix, optional=False):
    """``threshold`` and ``upper`` checked: finite real numbers (not bools), ``upper >= threshold``.

    Python and NumPy integers are kept as they are, so that comparing them with integer
    densities stays exact; other numbers become float. ``None`` is allowed for ``upper`` (no
    upper bound), and for ``threshold`` too when ``optional`` (a region made otherwise).
    """
    values = []
    for name, value in (("threshold", threshold), ("upper", upper)):
        if value is None and (optional or name == "upper"):
            values.append(None)
            continue
        real = isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))
        try:
            number = float(value) if real else math.nan
        except OverflowError:  # an int beyond float64
            number = math.nan
        if not math.isfinite(number):
            raise VolumeEVMError(f"{prefix}{name} must be a finite number (a real number, not a "
                                 f"bool), got {value!r}")
        values.append(value if isinstance(value, (int, np.integer)) else number)
    threshold, upper = values
    if threshold is not None and upper is not None and upper < threshold:
        raise VolumeEVMError(f"{prefix}upper ({upper}) must be >= threshold ({threshold})")
    return threshold, upper


def _check_tool(tool):
    if not isinstance(tool, EVM):
        raise TypeError(f"tool must be an EVM (e.g. EVM.from_mask(voxelize_mesh(...))), got "
                        f"{type(tool).__name__}")
    return tool

