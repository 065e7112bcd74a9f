"""VolumeEVM: the EVM of a region of interest plus the densities of its voxels.

Only the region is stored: its extreme vertices and one densities table, the region's voxels in
slice-major order along x (table order "xyz", the C order of an ``[x, y, z]`` array). Tables for
the other principal axes are made from it when a view asks for them, and cached. The relation v
(voxel -> table index) comes from the EVM alone (:mod:`._densities`).

Files: one ``.vevm`` file is a NumPy ``.npz`` archive of plain arrays (never pickled objects),
with a format name and version, the geometry as JSON, and SHA-256 checksums of the vertices and
the table; it is written atomically (:mod:`._files`).
"""

import hashlib
import json
import os
import zipfile
from pathlib import Path

import numpy as np

from ._densities import TABLE_ORDERS, TableIndex
from ._errors import VolumeEVMError
from ._evm import EVM
from ._files import write_atomically
from ._volume import index_to_physical

FORMAT = "volumeevm"
VERSION = 1


class VolumeEVM:
    """A region of interest of a volume: its EVM and the densities of its voxels.

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
    """

    def __init__(self, evm, table, *, shape, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0),
                 orientation=None, units="", threshold=None, upper=None):
        table = np.asarray(table)
        if table.ndim != 1:
            raise ValueError(f"table must be 1-D, got shape {table.shape}")
        count = evm.volume()
        if count != len(table):
            raise ValueError(f"the region has {count} voxels but the table {len(table)} densities")
        self.evm = evm
        self.shape = tuple(int(s) for s in shape)
        self.spacing = tuple(float(s) for s in spacing)
        self.origin = tuple(float(o) for o in origin)
        self.orientation = np.eye(3) if orientation is None else np.array(orientation, float)
        self.units = units
        self.threshold = threshold
        self.upper = upper
        self._tables = {0: table}
        self._indices = {}
        self._levels = {}

    # ------------------------------------------------------------------ building
    @classmethod
    def from_array(cls, array, threshold, upper=None, *, spacing=(1.0, 1.0, 1.0),
                   origin=(0.0, 0.0, 0.0), orientation=None, units="", source="array"):
        """Build the VolumeEVM of the voxels with ``threshold <= density`` (``<= upper``).

        Raises :class:`VolumeEVMError` for NaN/Inf densities, a threshold that is not a number,
        or an empty region; ``source`` names the data in those messages.
        """
        array = np.asarray(array)
        if array.ndim != 3:
            raise VolumeEVMError(f"{source}: expected a 3-D array, got shape {array.shape}")
        if not (np.issubdtype(array.dtype, np.integer) or np.issubdtype(array.dtype, np.floating)):
            raise VolumeEVMError(f"{source}: densities must be numbers, got dtype {array.dtype}")
        if np.issubdtype(array.dtype, np.floating) and not np.isfinite(array).all():
            bad = int(np.count_nonzero(~np.isfinite(array)))
            raise VolumeEVMError(f"{source}: {bad} densities are NaN or infinite")
        for name, value in (("threshold", threshold), ("upper", upper)):
            if value is not None and not np.isfinite(value):
                raise VolumeEVMError(f"{source}: {name} must be a finite number, got {value!r}")
        mask = array >= threshold
        if upper is not None:
            mask &= array <= upper
        if not mask.any():
            band = f">= {threshold}" if upper is None else f"in [{threshold}, {upper}]"
            raise VolumeEVMError(
                f"{source}: the region is empty: no density is {band} "
                f"(data range {array.min()} .. {array.max()})"
            )
        return cls(EVM.from_mask(mask), array[mask], shape=array.shape, spacing=spacing,
                   origin=origin, orientation=orientation, units=units,
                   threshold=float(threshold), upper=None if upper is None else float(upper))

    @classmethod
    def from_volume(cls, volume, threshold, upper=None):
        """Build from a :class:`Volume` (a reader's result), keeping its geometry and units."""
        return cls.from_array(volume.array, threshold, upper, spacing=volume.spacing,
                              origin=volume.origin, orientation=volume.orientation,
                              units=volume.units, source=volume.source or "volume")

    # ------------------------------------------------------------------ densities
    @property
    def voxel_count(self):
        """Number of voxels in the region."""
        return len(self._tables[0])

    def table(self, axis=0):
        """Densities of the region's voxels in slice-major order along ``axis`` (0, 1, 2).

        Axis 0 is the stored table; the others are made on first use and cached. Making one
        scatters the stored table into a transient grid and reads it back in the other order:
        two vectorized passes, and only the cached table stays.
        """
        if axis not in (0, 1, 2):
            raise ValueError(f"axis must be 0, 1 or 2, got {axis!r}")
        if axis not in self._tables:
            axes = ["xyz".index(a) for a in TABLE_ORDERS[axis]]
            mask = self.evm.to_mask(self.shape)
            dense = np.zeros(self.shape, self._tables[0].dtype)
            dense[mask] = self._tables[0]
            self._tables[axis] = np.transpose(dense, axes)[np.transpose(mask, axes)]
        return self._tables[axis]

    def index(self, voxels, axis=0):
        """The relation v: table indices (in ``table(axis)``) of voxels ``(m, 3)``; -1 outside."""
        if axis not in self._indices:
            self._indices[axis] = TableIndex(self.evm, TABLE_ORDERS[axis])
        return self._indices[axis](voxels)

    def level(self, factor):
        """This VolumeEVM at ``factor`` times coarser voxels (:func:`._levels.coarsen`): made on
        first use and cached, so only the levels views ask for are ever built."""
        if factor not in self._levels:
            from ._levels import coarsen

            self._levels[factor] = coarsen(self, factor)
        return self._levels[factor]

    def to_dense(self, background=0):
        """The full grid: the region's densities, ``background`` everywhere else."""
        table = self._tables[0]
        dense = np.full(self.shape, background, dtype=table.dtype)
        dense[self.evm.to_mask(self.shape)] = table
        return dense

    # ------------------------------------------------------------------ editing
    def cut(self, tool):
        """Remove the tool's voxels: a new VolumeEVM of ``region - tool``, densities kept."""
        return self._subset(self.evm - _check_tool(tool), "cut")

    def keep(self, tool):
        """Keep only the voxels inside the tool: ``region & tool``, densities kept."""
        return self._subset(self.evm & _check_tool(tool), "keep inside")

    def clip(self, lo, hi):
        """Keep only the voxels inside the box ``[lo, hi)`` (lattice corners)."""
        return self._subset(self.evm.clip(lo, hi), "clip")

    def largest_component(self):
        """Keep only the largest face-connected part of the region."""
        return self._subset(self.evm.components()[0], "keep largest part")

    def add(self, tool, density=None):
        """Add the tool's voxels as material: ``region | tool``; every tool voxel gets ``density``.

        ``density`` defaults to the largest density of the region (the report gives geometric
        models the maximum grey value). The tool is clipped to the grid.
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
                raise VolumeEVMError(f"add: density {density} does not fit the data type {table.dtype}")
        region = self.evm | tool
        result = self._derived(region, np.empty(region.volume(), table.dtype))
        # Both tables list voxels in the same (C) order, so the old voxels the tool leaves alone
        # keep their relative order: fill them in one masked copy.
        from_tool = result._table_mask(tool)
        covered = self._table_mask(self.evm & tool)
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
        return self._derived(region, self._tables[0][self._table_mask(region)])

    def _table_mask(self, part):
        """Which entries of the table (order "xyz") belong to ``part``, a subset of the region.

        Each row of ``part`` (fixed x and y, a run along z) is one contiguous stretch of the
        table, so the mask comes from the rows' first indices (the relation v) and lengths,
        without visiting ``part``'s voxels one by one.
        """
        lo, hi = part.boxes()
        size = hi - lo
        rows = size[:, 0] * size[:, 1]
        box = np.repeat(np.arange(len(lo)), rows)
        local = np.arange(rows.sum()) - np.repeat(np.cumsum(rows) - rows, rows)
        firsts = lo[box] + np.stack([local // size[box, 1], local % size[box, 1], np.zeros_like(local)], axis=1)
        start = self.index(firsts)
        end = start + size[box, 2]
        edges = np.bincount(start, minlength=self.voxel_count + 1) - np.bincount(end, minlength=self.voxel_count + 1)
        return np.cumsum(edges[:-1]) > 0

    def _derived(self, region, table):
        return VolumeEVM(region, table, shape=self.shape, spacing=self.spacing, origin=self.origin,
                         orientation=self.orientation, units=self.units, threshold=self.threshold,
                         upper=self.upper)

    # ------------------------------------------------------------------ geometry
    def index_to_physical(self):
        """4x4 matrix from voxel-centre indices to physical mm (LPS); see :mod:`._volume`."""
        return index_to_physical(self.spacing, self.origin, self.orientation)

    def mesh(self):
        """The region's boundary mesh in physical mm (LPS): ``(vertices (n, 3), Polygons)``."""
        vertices, polygons = self.evm.mesh()
        # Lattice point p is the corner at voxel-centre index p - 0.5.
        matrix = self.index_to_physical()
        return (vertices - 0.5) @ matrix[:3, :3].T + matrix[:3, 3], polygons

    def size_report(self):
        """Bytes of the vertices and the tables built so far, against the dense array."""
        vertices = self.evm.vertices.nbytes
        tables = sum(t.nbytes for t in self._tables.values())
        dense = int(np.prod(self.shape)) * self._tables[0].dtype.itemsize
        return {
            "vertices_bytes": vertices,
            "tables_bytes": tables,
            "total_bytes": vertices + tables,
            "dense_bytes": dense,
            "ratio": (vertices + tables) / dense,
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
            "vertices_sha256": _sha256(self.evm.vertices),
            "table_sha256": _sha256(self._tables[0]),
        }

    def save(self, path, *, overwrite=False):
        """Write one ``.vevm`` file atomically; refuses to replace a file unless ``overwrite``."""

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
        """Read a ``.vevm`` file; a corrupt or foreign file raises :class:`VolumeEVMError`."""
        path = Path(path)
        try:
            # Open the file here so that it is closed even when NumPy fails half-way.
            with open(path, "rb") as file, np.load(file, allow_pickle=False) as archive:
                if "format" not in archive or str(archive["format"]) != FORMAT:
                    raise VolumeEVMError(f"{path}: not a VolumeEVM file")
                version = int(archive["version"])
                if version != VERSION:
                    raise VolumeEVMError(f"{path}: format version {version}, this add-on reads {VERSION}")
                meta = json.loads(str(archive["meta"]))
                vertices, table = archive["vertices"], archive["table"]
        except FileNotFoundError:
            raise VolumeEVMError(f"{path}: file not found") from None
        except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as error:
            if isinstance(error, VolumeEVMError):
                raise
            raise VolumeEVMError(f"{path}: not a readable VolumeEVM file ({error})") from None
        if _sha256(vertices) != meta.get("vertices_sha256") or _sha256(table) != meta.get("table_sha256"):
            raise VolumeEVMError(f"{path}: checksum mismatch, the file is corrupt")
        try:
            evm = EVM(vertices)
            return cls(evm, table, shape=meta["shape"], spacing=meta["spacing"],
                       origin=meta["origin"], orientation=meta["orientation"],
                       units=meta["units"], threshold=meta["threshold"], upper=meta["upper"])
        except (ValueError, KeyError) as error:
            raise VolumeEVMError(f"{path}: inconsistent VolumeEVM file ({error})") from None


def _check_tool(tool):
    if not isinstance(tool, EVM):
        raise TypeError(f"tool must be an EVM (e.g. EVM.from_mask(voxelize_mesh(...))), got {type(tool).__name__}")
    return tool


def _sha256(array):
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()
