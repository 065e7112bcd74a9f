"""The Extreme Vertices Model of a voxel region.

A voxel region (an orthogonal pseudo-polyhedron) is stored as its extreme vertices: the lattice
points with an odd number of inside voxels among the 8 around them. Voxel ``(i, j, k)`` is the
unit cell ``[i, i+1] x [j, j+1] x [k, k+1]``, so vertices are lattice points from ``0`` to ``n``.

The vertex set is the XOR of the 8 shifted copies of the occupancy grid, and the occupancy is
the prefix XOR of the vertex grid; hence ``EVM(P xor Q) = EVM(P) xor EVM(Q)``. Every other
operation (Booleans, volume, area, faces, splits) sweeps planes of vertices and their sections,
in compiled kernels (:mod:`.._jit`): the sweeps of :mod:`._sweep`, and here the extraction from
a mask and the clip by a box.

References
----------
J. Rodríguez, D. Ayala, "VolumeEVM: a new surface/volume integrated model", UPC technical report.
A. Aguilera, D. Ayala, "Orthogonal polyhedra as geometric bounds in constructive solid
geometry", ACM Solid Modeling 1997.
"""

import itertools
from dataclasses import dataclass

import numpy as np

from .._errors import VolumeEVMError
from .._jit import kernel, parallel_map
from .._memory import check_memory
from . import _sweep
from ._components import face_components
from ._manifold import manifold_mesh
from ._mesh import boundary_mesh
from ._smooth import smooth_mesh

ORDERS = ("xyz", "xzy", "yxz", "yzx", "zxy", "zyx")
"""The six lexicographic axis orders "ABC": A slowest."""


def _axes(order):
    if order not in ORDERS:
        raise VolumeEVMError(f"order must be one of {ORDERS}, got {order!r}")
    return ["xyz".index(a) for a in order]


def check_lattice_range(lo, hi, name):
    """Refuse lattice coordinates from ``lo`` to ``hi`` (per axis, inclusive) an EVM cannot hold.

    Vertices are packed into int64 keys of :data:`._sweep.BITS` bits per coordinate (see
    :mod:`._sweep`), so every coordinate must lie in ``[-LIMIT, LIMIT)`` with ``LIMIT = 2**20``:
    a grid of up to 1048575 voxels along each axis. ``lo`` and ``hi`` may be any integers
    (Python integers, so that an offset near the int64 limits is judged without overflow).

    Raises
    ------
    VolumeEVMError
        Naming ``name`` (the parameter that put the region there) and the limit.
    """
    lo, hi = [int(a) for a in lo], [int(a) for a in hi]
    if min(lo) < -_sweep.LIMIT or max(hi) >= _sweep.LIMIT:
        raise VolumeEVMError(
            f"{name}: the region would span lattice coordinates {tuple(lo)} to {tuple(hi)}, but an "
            f"EVM holds coordinates from {-_sweep.LIMIT} to {_sweep.LIMIT - 1} only (a grid of at "
            f"most {_sweep.LIMIT - 1} voxels along each axis)"
        )


def integer_triple(value, name):
    """``value`` as 3 Python ints; refuses floats, booleans, text and other shapes."""
    array = np.asarray(value)
    if array.shape != (3,) or array.dtype.kind not in "iu":
        raise VolumeEVMError(f"{name} must be 3 integers, got {value!r}")
    return tuple(int(a) for a in array)


@kernel
def _plane_keys(before, after, plane, oy, oz, out):
    """Packed keys of the extreme vertices on one lattice plane, sorted; returns their count.

    ``before`` and ``after`` are the ``(Y, Z)`` slices (uint8, 0 or 1) on either side of the
    plane (zeros beyond the grid), ``plane`` its packed x part and ``oy``, ``oz`` the packed
    offsets. A lattice point is a vertex when an odd number of its 8 cells are inside: row by
    row, the XOR of the 4 cells at each z (two slices, rows y - 1 and y) differs from the one at
    z - 1. ``out`` has room for ``(Y + 1) * (Z + 1)`` keys.
    """
    ny, nz = after.shape
    row = np.zeros(nz, np.uint8)  # XOR of the two slices on the row before
    cells = np.empty(nz, np.uint8)  # XOR of the 4 cells at each z
    count = 0
    for y in range(ny + 1):
        changed = 0  # a row whose cells are all 0 (most, away from the surface) has no vertex
        if y < ny:
            for z in range(nz):
                across = before[y, z] ^ after[y, z]
                cells[z] = row[z] ^ across
                changed |= cells[z]
                row[z] = across
        else:
            cells[:] = row
            changed = 1
        if not changed:
            continue
        key = plane | ((y + oy) << _sweep.BITS)
        left = 0
        for z in range(nz):
            if cells[z] != left:
                out[count] = key | (z + oz)
                count += 1
                left = cells[z]
        if left:
            out[count] = key | (nz + oz)
            count += 1
    return count


@kernel
def _block_keys(mask, first, stop, ox, oy, oz):
    """Sorted keys of the vertices on the planes ``x = first .. stop - 1`` of a uint8 mask."""
    nx, ny, nz = mask.shape
    empty = np.zeros((ny, nz), np.uint8)
    buffer = np.empty((ny + 1) * (nz + 1), np.int64)
    keys = np.empty(buffer.size, np.int64)
    n = 0
    for x in range(first, stop):
        count = _plane_keys(mask[x - 1] if x > 0 else empty, mask[x] if x < nx else empty,
                            np.int64(x + ox) << (2 * _sweep.BITS), oy, oz, buffer)
        if n + count > len(keys):
            grown = np.empty(2 * (n + count), np.int64)
            grown[:n] = keys[:n]
            keys = grown
        keys[n:n + count] = buffer[:count]
        n += count
    return keys[:n].copy()


_BLOCK_VOXELS = 1 << 21
"""Voxels per block of x-slices that :meth:`EVM.from_mask` hands to one thread."""


@kernel
def _clip_line(points, start, stop, lo, hi, prefix, out, n):
    """Append to ``out[n:]`` the 1-D EVM of the breakpoints ``points[start:stop]`` (their last
    coordinate, sorted) cut to ``[lo, hi)``: ``lo`` when inside there, the breakpoints between,
    ``hi`` when inside just below it; each key ``prefix | c``. Returns the new count."""
    inside = 0
    i = start
    while i < stop and points[i] & _sweep.MASK <= lo:
        inside ^= 1
        i += 1
    if inside:
        out[n] = prefix | lo
        n += 1
    while i < stop and points[i] & _sweep.MASK < hi:
        out[n] = prefix | (points[i] & _sweep.MASK)
        n += 1
        inside ^= 1
        i += 1
    if inside:
        out[n] = prefix | hi
        n += 1
    return n


@kernel
def _clip_plane(points, start, stop, lo, hi, prefix, out, n, row, scratch):
    """Append the 2-D EVM of the points ``points[start:stop]`` (sorted by their last two
    coordinates, B then C) cut to ``[lo[1], hi[1]) x [lo[2], hi[2])``, as :func:`_clip_line`
    one dimension up: the row (1-D section) at ``lo[1]``, the lines between, the row below
    ``hi[1]``. ``out`` has room for ``5 * (stop - start) + 4`` more keys; ``row`` and
    ``scratch`` for ``stop - start``."""
    length = 0
    i = start
    while i < stop and (points[i] >> _sweep.BITS) & _sweep.MASK <= lo[1]:
        j = _sweep.same_end(points, i, stop, _sweep.BITS)
        length = _sweep.xor_into(row, length, points, i, j, _sweep.MASK, scratch)
        row[:length] = scratch[:length]
        i = j
    n = _clip_line(row, 0, length, lo[2], hi[2], prefix | (lo[1] << _sweep.BITS), out, n)
    while i < stop and (points[i] >> _sweep.BITS) & _sweep.MASK < hi[1]:
        j = _sweep.same_end(points, i, stop, _sweep.BITS)
        line = (points[i] >> _sweep.BITS) & _sweep.MASK
        n = _clip_line(points, i, j, lo[2], hi[2], prefix | (line << _sweep.BITS), out, n)
        length = _sweep.xor_into(row, length, points, i, j, _sweep.MASK, scratch)
        row[:length] = scratch[:length]
        i = j
    return _clip_line(row, 0, length, lo[2], hi[2], prefix | (hi[1] << _sweep.BITS), out, n)


@kernel
def _clip_keys(keys, lo, hi):
    """The sorted keys of the region of sorted x, y, z ``keys`` cut to the box ``[lo, hi)``
    (offset coordinates inside the bounding box), as :func:`_clip_plane` one dimension up: the
    section at ``lo[0]``, the planes between, the section below ``hi[0]``, each cut in 2-D."""
    plane_bits = 2 * _sweep.BITS
    plane_mask = (np.int64(1) << plane_bits) - 1
    size = len(keys) + 1  # bounds every section and row
    section, scratch = np.empty(size, np.int64), np.empty(size, np.int64)
    row, row_scratch = np.empty(size, np.int64), np.empty(size, np.int64)
    out = np.empty(size + 16, np.int64)
    m = 0
    n = 0
    i = 0
    while i < len(keys) and keys[i] >> plane_bits <= lo[0]:
        j = _sweep.same_end(keys, i, len(keys), plane_bits)
        m = _sweep.xor_into(section, m, keys, i, j, plane_mask, scratch)
        section[:m] = scratch[:m]
        i = j
    out = _sweep.with_room(out, n, 5 * m + 4)
    n = _clip_plane(section, 0, m, lo, hi, lo[0] << plane_bits, out, n, row, row_scratch)
    while i < len(keys) and keys[i] >> plane_bits < hi[0]:
        j = _sweep.same_end(keys, i, len(keys), plane_bits)
        out = _sweep.with_room(out, n, 5 * (j - i) + 4)
        n = _clip_plane(keys, i, j, lo, hi, (keys[i] >> plane_bits) << plane_bits, out, n, row,
                        row_scratch)
        m = _sweep.xor_into(section, m, keys, i, j, plane_mask, scratch)
        section[:m] = scratch[:m]
        i = j
    out = _sweep.with_room(out, n, 5 * m + 4)
    n = _clip_plane(section, 0, m, lo, hi, hi[0] << plane_bits, out, n, row, row_scratch)
    return out[:n].copy()


@kernel
def _prefix_xor(vertices, shape):
    """The cells of the grid ``shape`` inside the region of ``vertices`` (grid coordinates),
    as uint8 0 or 1: each vertex toggles its cell, folded into the grid (a vertex before it
    toggles the whole orthant it starts; one past its far end toggles nothing inside), then
    the prefix XOR along z, y and x."""
    nx, ny, nz = shape
    grid = np.zeros((nx, ny, nz), np.uint8)
    for x, y, z in vertices:
        if x < nx and y < ny and z < nz:
            grid[max(x, 0), max(y, 0), max(z, 0)] ^= 1
    for x in range(nx):
        for y in range(ny):
            inside = np.uint8(0)
            for z in range(nz):
                inside ^= grid[x, y, z]
                grid[x, y, z] = inside
            if y > 0:
                grid[x, y] ^= grid[x, y - 1]
        if x > 0:
            grid[x] ^= grid[x - 1]
    return grid


def vertex_keys(slices, shape, offset=(0, 0, 0)):
    """Packed keys of the extreme vertices of a region given as boolean x-slices, plane by plane.

    ``slices`` yields the ``(Y, Z)`` boolean slices ``x = 0 .. X-1`` of a region in a grid of
    ``shape``; the generator yields the sorted keys (:func:`._sweep.pack`) of the vertices of
    planes ``x = 0 .. X``, each shifted by ``offset``. Only two slices are held at a time, so a
    caller can make the slices on the fly (``VolumeEVM.from_array``, straight from the densities).
    """
    _, ny, nz = shape
    ox, oy, oz = (int(o) + _sweep.OFFSET for o in offset)
    buffer = np.empty((ny + 1) * (nz + 1), np.int64)
    previous = np.zeros((ny, nz), np.uint8)
    for x, mask in enumerate(itertools.chain(slices, [None])):
        current = (np.zeros((ny, nz), np.uint8) if mask is None
                   else np.ascontiguousarray(mask).view(np.uint8))
        count = _plane_keys(previous, current, np.int64(x + ox) << (2 * _sweep.BITS), oy, oz,
                            buffer)
        yield buffer[:count].copy()
        previous = current


def mask_slabs(evm, shape, thickness):
    """The voxels of ``evm`` inside a grid of ``shape`` as boolean x-slabs of ``thickness``
    slices, first to last (the last one thinner when ``thickness`` does not divide the grid):
    :meth:`EVM.to_mask` one slab at a time, so no grid-sized array is made.

    Slice ``x`` is slice ``x - 1`` XOR the 2-D prefix XOR of the vertices on plane ``x``, so a
    slab is the prefix XOR of its own planes' vertices, XOR the slice carried from the slab
    before. A slab's vertices are one stretch of the EVM's sorted keys (found by binary search)
    and only they are unpacked. Vertices before the grid are folded in with the first slab;
    those on or past its far end toggle nothing inside and are left out.
    """
    nx, ny, nz = (int(s) for s in shape)
    keys = evm.keys()
    ends = np.minimum(np.arange(thickness, nx + thickness, thickness, dtype=np.int64), nx)
    planes = (ends + _sweep.OFFSET) << (2 * _sweep.BITS)  # the first key of each next slab
    carry = np.zeros((ny, nz), np.uint8)
    first = 0
    for x0, last in zip(range(0, nx, thickness), np.searchsorted(keys, planes)):
        vertices = _sweep.unpack(keys[first:last], 3)
        vertices[:, 0] -= x0
        slab = _prefix_xor(vertices, np.array([min(thickness, nx - x0), ny, nz], np.int64))
        slab ^= carry
        carry = slab[-1].copy()
        first = last
        yield slab.view(bool)


def compact_integers(values):
    """``values`` as the smallest signed integer type that holds them (int8 .. int64)."""
    values = np.asarray(values)
    if values.size == 0:
        return values.astype(np.int8)
    lo, hi = int(values.min()), int(values.max())
    for dtype in (np.int8, np.int16, np.int32, np.int64):
        info = np.iinfo(dtype)
        if info.min <= lo and hi <= info.max:
            return values.astype(dtype)
    raise OverflowError(f"coordinates {lo}..{hi} do not fit in int64")


@dataclass(frozen=True)
class Slab:
    """One slab of a sweep: the 2-D section valid for ``lo <= A < hi``.

    ``section`` is the section's 2-D EVM as ``(m, 2)`` points (B, C), sorted.
    """

    lo: int
    hi: int
    section: np.ndarray


class EVM:
    """Extreme Vertices Model of a region of voxels.

    Immutable. ``vertices`` is ``(n, 3)``, sorted lexicographically in x, y, z order, in the
    smallest signed integer type that holds them. Convert to ``np.int64`` before arithmetic.
    Usually built with :meth:`from_mask` (or :func:`volumeevm_addon.model.voxelize_mesh_evm`,
    :func:`volumeevm_addon.model.box_evm`); the operators ``|``, ``&``, ``-`` and ``^`` are
    :meth:`union`, :meth:`intersection`, :meth:`difference` and :meth:`xor`.

    Parameters
    ----------
    vertices : (n, 3) array_like of int, optional
        Extreme vertices (lattice points), in any order; duplicates are an error. None (the
        default) is the empty region.

    Raises
    ------
    VolumeEVMError
        If ``vertices`` is not ``(n, 3)`` integers, holds duplicates or lies beyond the
        lattice coordinates an EVM holds (:func:`check_lattice_range`).

    Examples
    --------
    >>> import numpy as np
    >>> from volumeevm_addon import EVM
    >>> mask = np.zeros((4, 4, 4), bool); mask[1:3, 1:3, 1:4] = True
    >>> evm = EVM.from_mask(mask)
    >>> len(evm), evm.volume(), evm.area()
    (8, 12, 32)
    >>> bool((evm.to_mask(mask.shape) == mask).all())
    True
    """

    __slots__ = ("_vertices", "_keys", "_boxes", "_bounds")

    def __init__(self, vertices=None):
        v = np.zeros((0, 3), np.int64) if vertices is None else np.asarray(vertices)
        if v.ndim != 2 or v.shape[1] != 3:
            raise VolumeEVMError(f"vertices must have shape (n, 3), got {v.shape}")
        if v.dtype.kind not in "iu":
            raise VolumeEVMError(f"vertices must be integer lattice points, got dtype {v.dtype}")
        if v.size:
            check_lattice_range(v.min(axis=0), v.max(axis=0), "vertices")
        keys = np.sort(_sweep.pack(v))
        if keys.size > 1 and (keys[1:] == keys[:-1]).any():
            raise VolumeEVMError("vertices contain duplicates")
        self._set(keys)

    def _set(self, keys):
        self._keys = {"xyz": keys}
        self._boxes = {}
        self._vertices = self._bounds = None  # made on first use

    @classmethod
    def _from_keys(cls, keys):
        evm = cls.__new__(cls)
        evm._set(keys)
        return evm

    # ------------------------------------------------------------------ conversion
    @classmethod
    def from_mask(cls, mask, offset=(0, 0, 0)):
        """The EVM of a boolean voxel mask indexed ``[x, y, z]`` (parity rule).

        Blocks of x-slices are read in parallel (:func:`parallel_map`), each by a compiled
        kernel that finds its planes' vertices in one pass without a padded copy.

        Parameters
        ----------
        mask : (X, Y, Z) array_like of bool
            The region's voxels (any dtype: non-zero is inside).
        offset : (3,) array_like of int, optional
            Lattice cell of voxel ``mask[0, 0, 0]`` (default the origin).

        Returns
        -------
        EVM

        Raises
        ------
        VolumeEVMError
            If the mask is not 3-D, or the grid placed at ``offset`` reaches past the lattice
            coordinates an EVM holds (:func:`check_lattice_range`).
        """
        mask = np.asarray(mask)
        if mask.ndim != 3:
            raise VolumeEVMError(f"mask must be 3-D, got shape {mask.shape}")
        offset = integer_triple(offset, "offset")
        check_lattice_range(offset, [o + n for o, n in zip(offset, mask.shape)],
                            "mask placed at offset")
        cells = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)
        ox, oy, oz = (o + _sweep.OFFSET for o in offset)
        step = max(1, _BLOCK_VOXELS // max(1, mask.shape[1] * mask.shape[2]))
        planes = range(0, mask.shape[0] + 1, step)
        blocks = parallel_map(_block_keys, [(cells, x, min(x + step, mask.shape[0] + 1), ox, oy, oz)
                                            for x in planes])
        return cls._from_keys(np.concatenate(blocks))

    def to_mask(self, shape, offset=(0, 0, 0)):
        """The voxels of the region inside a grid of ``shape`` (prefix XOR of the vertices).

        Vertices outside the grid are folded in exactly (a vertex before the grid toggles the
        whole orthant it starts).

        Parameters
        ----------
        shape : tuple of 3 int
            The grid.
        offset : (3,) array_like of int, optional
            Lattice cell of voxel ``mask[0, 0, 0]`` (default the origin).

        Returns
        -------
        (X, Y, Z) ndarray of bool
            ``mask[i, j, k]`` is lattice cell ``offset + (i, j, k)``.

        Raises
        ------
        VolumeEVMError
            If ``shape`` does not have 3 entries.
        VolumeEVMError
            When the grid would need more memory than is available.
        """
        shape = tuple(int(s) for s in shape)
        if len(shape) != 3:
            raise VolumeEVMError(f"shape must have 3 entries, got {shape}")
        # The prefix-XOR grid (the boolean result) and two int64 copies of the vertices.
        check_memory(int(np.prod(shape, dtype=np.float64)) + 48 * len(self),
                     "making the voxel mask", source=f"EVM grid {shape}",
                     advice="use a smaller grid, or clip the region to the part you need")
        v = self.vertices.astype(np.int64) - np.asarray(offset, np.int64)
        return _prefix_xor(v, np.asarray(shape, np.int64)).view(bool)

    # ------------------------------------------------------------------ access
    @property
    def vertices(self):
        """Extreme vertices ``(n, 3)``, sorted in x, y, z order (read-only view)."""
        if self._vertices is None:
            self._vertices = compact_integers(_sweep.unpack(self._keys["xyz"], 3))
        v = self._vertices.view()
        v.flags.writeable = False
        return v

    def __len__(self):
        return len(self._keys["xyz"])

    def __eq__(self, other):
        return isinstance(other, EVM) and np.array_equal(self._keys["xyz"], other._keys["xyz"])

    def __hash__(self):
        return hash(self._keys["xyz"].tobytes())

    def __repr__(self):
        return f"EVM({len(self)} vertices, bounds={self.bounds()})"

    def is_empty(self):
        """True when the region has no voxels.

        Returns
        -------
        bool
        """
        return len(self) == 0

    def bounds(self):
        """Lattice corners of the region's bounding box.

        Returns
        -------
        tuple of 2 tuples of 3 int, or None
            ``(lo, hi)``: the region's voxels lie in ``lo <= cell < hi``; None when empty.
        """
        if self.is_empty():
            return None
        if self._bounds is None:
            lo, hi = _sweep.key_bounds(self._keys["xyz"])
            self._bounds = (tuple(int(a) - _sweep.OFFSET for a in lo),
                            tuple(int(a) - _sweep.OFFSET for a in hi))
        return self._bounds

    def keys(self, order="xyz"):
        """Packed int64 keys of the vertices sorted in ``order``, what every sweep reads.

        Parameters
        ----------
        order : str, optional
            One of :data:`ORDERS`, slowest axis first (default ``"xyz"``).

        Returns
        -------
        (n,) ndarray of np.int64
            Sorted; cached, do not modify (the packing is :mod:`._sweep`'s).

        Raises
        ------
        VolumeEVMError
            For an order not in :data:`ORDERS`.
        """
        if order not in self._keys:
            axes = _axes(order)
            keys = _sweep.pack(self.vertices[:, axes])
            # The vertices are in x, y, z order: a stable sort by the leading axes of ``order``
            # up to where the rest follow x, y, z (one pass for "zxy", two for "yzx") sorts all.
            leading = next(p for p in range(3) if axes[p:] == sorted(axes[p:]))
            self._keys[order] = _sweep.radix_sort(keys, 3 - leading, leading)[0]
        return self._keys[order]

    def sorted(self, order="xyz"):
        """The vertices sorted lexicographically in another axis order.

        Parameters
        ----------
        order : str, optional
            The sort order: one of :data:`ORDERS`, slowest axis first (default ``"xyz"``).

        Returns
        -------
        (n, 3) ndarray of int
            Still x, y, z columns, in the smallest integer type that holds them.

        Raises
        ------
        VolumeEVMError
            For an order not in :data:`ORDERS`.
        """
        columns = _sweep.unpack(self.keys(order), 3)
        out = np.empty_like(columns)
        out[:, _axes(order)] = columns
        return compact_integers(out)

    def planes(self, order="xyz"):
        """The planes of vertices along the slowest axis ``A`` of ``order``, ascending.

        Parameters
        ----------
        order : str, optional
            One of :data:`ORDERS`: ``"ABC"``, A slowest (default ``"xyz"``).

        Yields
        ------
        coordinate : int
            The plane ``A = coordinate``.
        points : (m, 2) ndarray of int
            Its vertices as ``(B, C)``, sorted.

        Raises
        ------
        VolumeEVMError
            For an order not in :data:`ORDERS`.
        """
        columns = _sweep.unpack(self.keys(order), 3)
        cuts = np.flatnonzero(np.diff(columns[:, 0])) + 1
        for chunk in np.split(columns, cuts) if len(columns) else []:
            yield int(chunk[0, 0]), chunk[:, 1:]

    def sections(self, order="xyz", reverse=False):
        """Sweep the sections: one :class:`Slab` per pair of consecutive planes.

        Forwards ``S_i = S_{i-1} xor plv_i``; backwards (``reverse=True``, far end first)
        ``S_{i-1} = S_i xor plv_i``, as back-to-front rendering needs.

        Parameters
        ----------
        order : str, optional
            One of :data:`ORDERS`: ``"ABC"``, A slowest (default ``"xyz"``).
        reverse : bool, optional
            Sweep from the far end (default False).

        Yields
        ------
        Slab
            The section valid for ``lo <= A < hi``, one per pair of consecutive planes.

        Raises
        ------
        VolumeEVMError
            For an order not in :data:`ORDERS`.
        """
        planes = list(self.planes(order))
        if reverse:
            planes = planes[::-1]
        section = np.zeros(0, np.int64)
        for (c, points), (c_next, _) in zip(planes, planes[1:]):
            section = _sweep.xor(section, _sweep.pack(points))
            lo, hi = (c, c_next) if not reverse else (c_next, c)
            yield Slab(lo, hi, _sweep.unpack(section, 2))

    # ------------------------------------------------------------------ Booleans
    def __or__(self, other):
        return self.union(other)

    def __and__(self, other):
        return self.intersection(other)

    def __sub__(self, other):
        return self.difference(other)

    def __xor__(self, other):
        return self.xor(other)

    def xor(self, other):
        """Symmetric difference (``self ^ other``): a plain XOR merge of the vertex sets.

        Parameters
        ----------
        other : EVM
            A region of the same lattice.

        Returns
        -------
        EVM
            The voxels in exactly one of the two regions.

        Raises
        ------
        TypeError
            If ``other`` is not an EVM.
        """
        return EVM._from_keys(_sweep.xor(self.keys(), _check_evm(other).keys()))

    def union(self, other):
        """Union (``self | other``), by sweeping sections inside ``other``'s bounding box only.

        Parameters
        ----------
        other : EVM
            The region to add.

        Returns
        -------
        EVM
            The voxels in either region.

        Raises
        ------
        TypeError
            If ``other`` is not an EVM.
        """
        other = _check_evm(other)
        if other.is_empty():
            return self
        inside = self.clip(*other.bounds())
        # The part of self outside other's box is quasi-disjoint from the rest: XOR merges.
        return (self ^ inside) ^ inside._sweep(other, "union")

    def intersection(self, other):
        """Intersection (``self & other``), by sweeping sections inside the overlap of the
        bounding boxes.

        Parameters
        ----------
        other : EVM
            The region to intersect with.

        Returns
        -------
        EVM
            The voxels in both regions.

        Raises
        ------
        TypeError
            If ``other`` is not an EVM.
        """
        box = _overlap(self, _check_evm(other))
        if box is None:
            return EVM()
        return self.clip(*box)._sweep(other.clip(*box), "intersection")

    def difference(self, other):
        """Difference ``self - other``, by sweeping sections inside the bounding-box overlap.

        Parameters
        ----------
        other : EVM
            The region to remove.

        Returns
        -------
        EVM
            The voxels of this region outside ``other``.

        Raises
        ------
        TypeError
            If ``other`` is not an EVM.

        Examples
        --------
        >>> a = EVM.from_mask(np.ones((4, 4, 4), bool))
        >>> b = EVM.from_mask(np.ones((2, 2, 2), bool), offset=(2, 2, 2))
        >>> (a - b).volume(), (a | b).volume(), (a & b).volume()
        (56, 64, 8)
        """
        box = _overlap(self, _check_evm(other))
        if box is None:
            return self
        inside = self.clip(*box)
        return (self ^ inside) ^ inside._sweep(other.clip(*box), "difference")

    def _sweep(self, other, operation):
        return EVM._from_keys(_sweep.boolean(self.keys(), other.keys(),
                                             _sweep.TRUTH_TABLES[operation]))

    # ------------------------------------------------------------------ measures
    def boxes(self, order="xyz"):
        """The region as ordered disjoint boxes, split in ``order``.

        Cached: volume, the relation v and the densities of edits all start from them.

        Parameters
        ----------
        order : str, optional
            One of :data:`ORDERS` (default ``"xyz"``).

        Returns
        -------
        lo, hi : (n, 3) ndarray of np.int64
            Box ``b`` holds the cells ``lo[b] <= cell < hi[b]`` (x, y, z columns); read-only.

        Raises
        ------
        VolumeEVMError
            For an order not in :data:`ORDERS`.
        """
        if order not in self._boxes:
            lo, hi = _sweep.boxes(self.keys(order))
            axes = _axes(order)
            out_lo, out_hi = np.empty_like(lo), np.empty_like(hi)
            out_lo[:, axes], out_hi[:, axes] = lo, hi
            out_lo.flags.writeable = out_hi.flags.writeable = False
            self._boxes[order] = out_lo, out_hi
        return self._boxes[order]

    def voxels(self):
        """The region's voxels, box by box (for lookups, not in table order).

        Returns
        -------
        (n, 3) ndarray of np.int64
            Lattice cells, one row per voxel.
        """
        lo, hi = self.boxes()
        size = hi - lo
        count = np.prod(size, axis=1)
        box = np.repeat(np.arange(len(lo)), count)
        local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
        out = np.empty((len(local), 3), np.int64)
        out[:, 2] = local % size[box, 2]
        local //= size[box, 2]
        out[:, 1] = local % size[box, 1]
        out[:, 0] = local // size[box, 1]
        return out + lo[box]

    def volume(self):
        """Number of voxels in the region (content of the slabs' sections).

        Returns
        -------
        int
        """
        lo, hi = self.boxes()
        return int(np.prod(hi - lo, axis=1).sum())

    def area(self):
        """Boundary area in unit voxel faces: the area of every plane's faces, for all 3 axes.

        Returns
        -------
        int
        """
        # The vertices of each plane form the 2-D EVM of its faces.
        return sum(int(_sweep.plane_area(self.keys(order))) for order in ("xyz", "yzx", "zxy"))

    # ------------------------------------------------------------------ geometry
    def translate(self, offset):
        """The region moved by an integer offset.

        Parameters
        ----------
        offset : (3,) array_like of int
            Lattice cells to move by, per axis.

        Returns
        -------
        EVM

        Raises
        ------
        VolumeEVMError
            If ``offset`` is not 3 integers, or the moved region leaves the lattice
            coordinates an EVM holds (:func:`check_lattice_range`).
        """
        offset = integer_triple(offset, "offset")
        if self.is_empty():
            return self
        lo, hi = self.bounds()
        check_lattice_range([a + o for a, o in zip(lo, offset)],
                            [a + o for a, o in zip(hi, offset)], "offset")
        # A translation keeps the lexicographic order: the keys stay sorted.
        return EVM._from_keys(_sweep.pack(self.vertices.astype(np.int64) + np.array(offset)))

    def split(self, axis, c):
        """Split by the plane ``axis = c``: ``(part below c, part at or above c)``.

        Two clips (:meth:`clip`): the section just below ``c`` closes the lower part and opens
        the upper one.

        Parameters
        ----------
        axis : {0, 1, 2}
            The plane's normal axis.
        c : int
            The plane's coordinate; any integer (planes beyond the lattice range split off
            nothing).

        Returns
        -------
        below, above : EVM
            The cells with ``cell[axis] < c`` and those with ``cell[axis] >= c``.

        Raises
        ------
        VolumeEVMError
            If ``axis`` is not 0, 1 or 2, or ``c`` is not an integer.
        """
        if axis not in (0, 1, 2):
            raise VolumeEVMError(f"axis must be 0, 1 or 2, got {axis!r}")
        if isinstance(c, (bool, np.bool_)) or not isinstance(c, (int, np.integer)):
            raise VolumeEVMError(f"split plane c must be an integer, got {c!r}")
        if self.is_empty():
            return self, self
        lo, hi = self.bounds()
        c = min(max(int(c), lo[axis]), hi[axis])  # a plane beyond the region splits the same
        return (self.clip(lo, hi[:axis] + (c,) + hi[axis + 1:]),
                self.clip(lo[:axis] + (c,) + lo[axis + 1:], hi))

    def clip(self, lo, hi):
        """The part of the region inside the box ``[lo, hi)`` (lattice corners).

        One sweep of the planes (a compiled kernel): the section entering at ``lo`` opens the
        part, the planes between are kept and the section leaving at ``hi`` closes it, each cut
        the same way in 2-D by its lines, and each line in 1-D.

        Parameters
        ----------
        lo, hi : (3,) array_like of int
            The box's corners; any integers (the box is first cut down to the bounding box).

        Returns
        -------
        EVM
            Empty when the box misses the region.

        Raises
        ------
        VolumeEVMError
            If ``lo`` or ``hi`` is not 3 integers.
        """
        lo, hi = integer_triple(lo, "clip lo"), integer_triple(hi, "clip hi")
        if self.is_empty():
            return self
        low, high = self.bounds()
        lo = [max(a, b) for a, b in zip(lo, low)]
        hi = [min(a, b) for a, b in zip(hi, high)]
        if any(a >= b for a, b in zip(lo, hi)):
            return EVM()
        # Now every plane lies inside the bounding box, hence inside the range keys can hold.
        box = np.array([lo, hi], np.int64) + _sweep.OFFSET
        return EVM._from_keys(_clip_keys(self.keys(), box[0], box[1]))

    def mesh(self, manifold=False, smooth=False):
        """Boundary as a closed, outward polygon mesh in lattice units; see :mod:`._mesh`.

        Parameters
        ----------
        manifold : bool
            Split the edges and vertices where voxels touch only along an edge or at a point,
            so that every edge has two faces and every vertex one fan (for 3D printing); the
            copies move off the lattice by ``1e-3`` voxel. See :mod:`._manifold`.
        smooth : bool
            A smooth display surface: the same mesh (the manifold one with ``manifold``) with
            its vertices relaxed, each within half a voxel along each axis of its exact
            position, and its faces that are no longer planar cut into triangles. For display
            only: measurements use the exact mesh. See :mod:`._smooth`.

        Returns
        -------
        vertices : (n, 3) ndarray of np.float64
            Lattice points (voxel corners), and with ``manifold`` the split copies; with
            ``smooth`` those moved, then the centres added to faces cut into fans.
        polygons : Polygons
            Faces merged per plane, counter-clockwise seen from outside.

        Raises
        ------
        VolumeEVMError
            When the mesh would need more memory than is available.
        """
        vertices, polygons = manifold_mesh(self) if manifold else boundary_mesh(self)
        if smooth:
            return smooth_mesh(vertices, polygons)
        return vertices, polygons

    def components(self):
        """Face-connected components, one EVM each, largest first; see :mod:`._components`.

        Returns
        -------
        list of EVM
            Empty for an empty region.
        """
        return [EVM._from_keys(keys) for keys in face_components(self)]


def _check_evm(other):
    if not isinstance(other, EVM):
        raise TypeError(f"expected an EVM, got {type(other).__name__}")
    return other


def _overlap(a, b):
    """Overlap ``(lo, hi)`` of two bounding boxes, or None when they share no volume."""
    if a.is_empty() or b.is_empty():
        return None
    (alo, ahi), (blo, bhi) = a.bounds(), b.bounds()
    lo = np.maximum(alo, blo)
    hi = np.minimum(ahi, bhi)
    if (lo >= hi).any():
        return None
    return tuple(int(x) for x in lo), tuple(int(x) for x in hi)
