"""The Extreme Vertices Model of a voxel region.

A voxel region (an orthogonal pseudo-polyhedron) is stored as its extreme vertices: the lattice
points with an odd number of inside voxels among the 8 around them. Voxel ``(i, j, k)`` is the
unit cell ``[i, i+1] x [j, j+1] x [k, k+1]``, so vertices are lattice points from ``0`` to ``n``.

The vertex set is the XOR of the 8 shifted copies of the occupancy grid, and the occupancy is
the prefix XOR of the vertex grid; hence ``EVM(P xor Q) = EVM(P) xor EVM(Q)``. Every other
operation (Booleans, volume, area, faces, splits) sweeps planes of vertices and their sections;
:mod:`._sweep` evaluates those sweeps for all planes at once.

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
from .._memory import check_memory
from . import _sweep

ORDERS = ("xyz", "xzy", "yxz", "yzx", "zxy", "zyx")
"""The six lexicographic axis orders "ABC": A slowest."""


def _axes(order):
    if order not in ORDERS:
        raise ValueError(f"order must be one of {ORDERS}, got {order!r}")
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


def vertex_keys(slices, shape, offset=(0, 0, 0)):
    """Packed keys of the extreme vertices of a region given as boolean x-slices, plane by plane.

    ``slices`` yields the ``(Y, Z)`` boolean slices ``x = 0 .. X-1`` of a region in a grid of
    ``shape``; the generator yields the sorted keys (:func:`._sweep.pack`) of the vertices of
    planes ``x = 0 .. X``, each shifted by ``offset``. Only two slices' parities are held at a
    time, so a caller can make the slices on the fly (:meth:`EVM.from_mask`, and
    ``VolumeEVM.from_array`` straight from the densities).
    """
    _, ny, nz = shape
    ox, oy, oz = (int(o) + _sweep.OFFSET for o in offset)
    previous = np.zeros((ny + 1, nz + 1), np.uint8)
    for x, mask in enumerate(itertools.chain(slices, [None])):
        current = np.zeros((ny + 1, nz + 1), np.uint8)
        if mask is not None:
            # 2-D parity of slice x: XOR of the four shifted copies.
            s = mask.view(np.uint8)
            current[:-1, :-1] ^= s
            current[1:, :-1] ^= s
            current[:-1, 1:] ^= s
            current[1:, 1:] ^= s
        ys, zs = np.nonzero(previous ^ current)
        yield ((np.int64(x + ox) << 2 * _sweep.BITS) | ((ys.astype(np.int64) + oy) << _sweep.BITS)
               | (zs.astype(np.int64) + oz))
        previous = current


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

    __slots__ = ("_vertices", "_keys", "_boxes")

    def __init__(self, vertices=None):
        """Wrap extreme vertices ``(n, 3)`` (any order; duplicates are an error)."""
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
        self._vertices = compact_integers(_sweep.unpack(keys, 3)[1])

    @classmethod
    def _from_keys(cls, keys):
        evm = cls.__new__(cls)
        evm._set(keys)
        return evm

    # ------------------------------------------------------------------ conversion
    @classmethod
    def from_mask(cls, mask, offset=(0, 0, 0)):
        """The EVM of a boolean voxel mask indexed ``[x, y, z]`` (parity rule).

        ``offset`` places voxel ``mask[0, 0, 0]`` at lattice cell ``offset``. Works slab by slab
        in x (:func:`vertex_keys`) so that the padded copy never exceeds two x-slices at a time.

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
        check_lattice_range(offset, [o + n for o, n in zip(offset, mask.shape)], "mask placed at offset")
        keys = vertex_keys(mask.astype(bool, copy=False), mask.shape, offset)
        return cls._from_keys(np.concatenate(list(keys)))

    def to_mask(self, shape, offset=(0, 0, 0)):
        """The voxels of the region inside a grid of ``shape`` (prefix XOR of the vertices).

        Voxel ``mask[i, j, k]`` is lattice cell ``offset + (i, j, k)``. Vertices outside the grid
        are folded in exactly (a vertex before the grid toggles the whole orthant it starts).
        """
        shape = tuple(int(s) for s in shape)
        if len(shape) != 3:
            raise ValueError(f"shape must have 3 entries, got {shape}")
        # The prefix-XOR grid, the boolean result and two int64 copies of the vertices.
        check_memory(2 * int(np.prod([s + 1 for s in shape], dtype=np.float64)) + 48 * len(self),
                     "making the voxel mask", source=f"EVM grid {shape}",
                     advice="use a smaller grid, or clip the region to the part you need")
        v = self.vertices.astype(np.int64) - np.asarray(offset, np.int64)
        grid = np.zeros(tuple(s + 1 for s in shape), np.uint8)
        clipped = np.clip(v, 0, shape)
        # A vertex past the far end of an axis toggles nothing inside; drop it.
        inside = (v < np.asarray(shape)).all(axis=1)
        np.bitwise_xor.at(grid, tuple(clipped[inside].T), 1)
        for axis in range(3):
            np.bitwise_xor.accumulate(grid, axis=axis, out=grid)
        return grid[: shape[0], : shape[1], : shape[2]].astype(bool)

    # ------------------------------------------------------------------ access
    @property
    def vertices(self):
        """Extreme vertices ``(n, 3)``, sorted in x, y, z order (read-only view)."""
        v = self._vertices.view()
        v.flags.writeable = False
        return v

    def __len__(self):
        return len(self._vertices)

    def __eq__(self, other):
        return isinstance(other, EVM) and np.array_equal(self._keys["xyz"], other._keys["xyz"])

    def __hash__(self):
        return hash(self._keys["xyz"].tobytes())

    def __repr__(self):
        return f"EVM({len(self)} vertices, bounds={self.bounds()})"

    def is_empty(self):
        """True when the region has no voxels."""
        return len(self) == 0

    def bounds(self):
        """``(lo, hi)`` lattice corners of the bounding box, or ``None`` when empty."""
        if self.is_empty():
            return None
        v = self._vertices
        return tuple(int(a) for a in v.min(axis=0)), tuple(int(a) for a in v.max(axis=0))

    def keys(self, order="xyz"):
        """Packed int64 keys of the vertices sorted in ``order`` (cached; see :mod:`._sweep`)."""
        if order not in self._keys:
            keys = _sweep.pack(self._vertices[:, _axes(order)])
            keys.sort()
            self._keys[order] = keys
        return self._keys[order]

    def sorted(self, order="xyz"):
        """Vertices ``(n, 3)`` as x, y, z columns, sorted lexicographically in ``order``."""
        columns = _sweep.unpack(self.keys(order), 3)[1]
        out = np.empty_like(columns)
        out[:, _axes(order)] = columns
        return compact_integers(out)

    def planes(self, order="xyz"):
        """Planes of vertices: ``(coordinate, points (m, 2))`` for A ascending, points as (B, C)."""
        columns = _sweep.unpack(self.keys(order), 3)[1]
        cuts = np.flatnonzero(np.diff(columns[:, 0])) + 1
        for chunk in np.split(columns, cuts) if len(columns) else []:
            yield int(chunk[0, 0]), chunk[:, 1:]

    def sections(self, order="xyz", reverse=False):
        """Sweep the sections: one :class:`Slab` per pair of consecutive planes.

        Forwards ``S_i = S_{i-1} xor plv_i``; backwards (``reverse=True``, far end first)
        ``S_{i-1} = S_i xor plv_i``, as back-to-front rendering needs.
        """
        planes = list(self.planes(order))
        if reverse:
            planes = planes[::-1]
        section = np.zeros(0, np.int64)
        for (c, points), (c_next, _) in zip(planes, planes[1:]):
            section = _sweep.xor(section, _sweep.pack(points))
            lo, hi = (c, c_next) if not reverse else (c_next, c)
            yield Slab(lo, hi, _sweep.unpack(section, 2)[1])

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
        """Symmetric difference: a plain XOR merge of the vertex sets."""
        return EVM._from_keys(_sweep.xor(self.keys(), _check_evm(other).keys()))

    def union(self, other):
        """Union, by sweeping sections inside ``other``'s bounding box only."""
        other = _check_evm(other)
        if other.is_empty():
            return self
        inside = self.clip(*other.bounds())
        # The part of self outside other's box is quasi-disjoint from the rest: XOR merges.
        return (self ^ inside) ^ inside._sweep(other, "union")

    def intersection(self, other):
        """Intersection, by sweeping sections inside the overlap of the bounding boxes."""
        box = _overlap(self, _check_evm(other))
        if box is None:
            return EVM()
        return self.clip(*box)._sweep(other.clip(*box), "intersection")

    def difference(self, other):
        """Difference ``self - other``, by sweeping sections inside the bounding-box overlap."""
        box = _overlap(self, _check_evm(other))
        if box is None:
            return self
        inside = self.clip(*box)
        return (self ^ inside) ^ inside._sweep(other.clip(*box), "difference")

    def _sweep(self, other, operation):
        return EVM._from_keys(_sweep.boolean(self.keys(), other.keys(), 3, operation))

    # ------------------------------------------------------------------ measures
    def boxes(self, order="xyz"):
        """Ordered disjoint boxes ``(lo, hi)`` ``(n, 3)`` each, x, y, z columns, split in ``order``.

        Cached: volume, the relation v and the densities of edits all start from them.
        """
        if order not in self._boxes:
            _, lo, hi = _sweep.boxes(self.keys(order), 3)
            axes = _axes(order)
            out_lo, out_hi = np.empty_like(lo), np.empty_like(hi)
            out_lo[:, axes], out_hi[:, axes] = lo, hi
            out_lo.flags.writeable = out_hi.flags.writeable = False
            self._boxes[order] = out_lo, out_hi
        return self._boxes[order]

    def voxels(self):
        """The region's voxels ``(n, 3)`` (int64), box by box: for lookups, not in table order."""
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
        """Number of voxels in the region (content of the slabs' sections)."""
        lo, hi = self.boxes()
        return int(np.prod(hi - lo, axis=1).sum())

    def area(self):
        """Boundary area in unit voxel faces: the area of every plane's faces, for all 3 axes."""
        total = 0
        for order in ("xyz", "yzx", "zxy"):
            # Read as grouped 2-D keys, the vertices of each plane form the plane's 2-D EVM.
            _, lo, hi = _sweep.boxes(self.keys(order), 2)
            total += int(np.prod(hi - lo, axis=1).sum())
        return total

    # ------------------------------------------------------------------ geometry
    def translate(self, offset):
        """The region moved by an integer ``offset`` (3,).

        Raises :class:`VolumeEVMError` if the moved region leaves the lattice coordinates an EVM
        holds (:func:`check_lattice_range`).
        """
        offset = integer_triple(offset, "offset")
        if self.is_empty():
            return self
        lo, hi = self.bounds()
        check_lattice_range([a + o for a, o in zip(lo, offset)], [a + o for a, o in zip(hi, offset)], "offset")
        # A translation keeps the lexicographic order: the keys stay sorted.
        return EVM._from_keys(_sweep.pack(self._vertices.astype(np.int64) + np.array(offset)))

    def split(self, axis, c):
        """Split by the plane ``axis = c``: ``(part below c, part at or above c)``.

        The section just below ``c`` closes the lower part and opens the upper one. ``c`` may be
        any integer: planes beyond the lattice range split off nothing.
        """
        if axis not in (0, 1, 2):
            raise VolumeEVMError(f"axis must be 0, 1 or 2, got {axis!r}")
        if isinstance(c, (bool, np.bool_)) or not isinstance(c, (int, np.integer)):
            raise VolumeEVMError(f"split plane c must be an integer, got {c!r}")
        if c >= _sweep.LIMIT:  # every vertex lies below the plane
            return self, EVM()
        c = max(int(c), -_sweep.LIMIT)  # no vertex lies below -LIMIT: the same split
        order = ("xyz", "yzx", "zxy")[axis]
        keys = self.keys(order)
        cut = np.int64(c + _sweep.OFFSET) << (2 * _sweep.BITS)
        n = np.searchsorted(keys, cut)
        below, above = keys[:n], keys[n:]
        closing = _sweep.parity(below & ((1 << (2 * _sweep.BITS)) - 1)) | cut
        parts = []
        for part in (_sweep.xor(below, closing), _sweep.xor(closing, above)):
            columns = _sweep.unpack(part, 3)[1]
            xyz = np.empty_like(columns)
            xyz[:, _axes(order)] = columns
            parts.append(EVM._from_keys(np.sort(_sweep.pack(xyz))))
        return tuple(parts)

    def clip(self, lo, hi):
        """The part of the region inside the box ``[lo, hi)`` (lattice corners).

        Per axis, the vertices between the two planes are kept, the section entering at ``lo``
        opens the part and the section leaving at ``hi`` closes it (a split at both planes).
        ``lo`` and ``hi`` may be any integers: the box is first cut down to the bounding box.
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
        plane_bits = 2 * _sweep.BITS
        columns = _sweep.unpack(self.keys(), 3)[1]
        for axis in range(3):
            axes = ["xyz".index(a) for a in ("xyz", "yzx", "zxy")[axis]]
            keys = np.sort(_sweep.pack(columns[:, axes]))
            cuts = [np.int64(int(c) + _sweep.OFFSET) << plane_bits for c in (lo[axis], hi[axis])]
            first, stop = np.searchsorted(keys, cuts)
            rest = (1 << plane_bits) - 1
            opening = _sweep.parity(keys[:first] & rest) | cuts[0]
            closing = _sweep.parity(keys[:stop] & rest) | cuts[1]
            keys = _sweep.parity(np.concatenate([opening, keys[first:stop], closing]), runs=True)
            columns = np.empty((len(keys), 3), np.int64)
            columns[:, axes] = _sweep.unpack(keys, 3)[1]
        return EVM._from_keys(np.sort(_sweep.pack(columns)))

    def mesh(self):
        """Boundary as a closed, outward polygon mesh in lattice units; see :mod:`._mesh`."""
        from ._mesh import boundary_mesh

        return boundary_mesh(self)

    def components(self):
        """Face-connected components, one EVM each, largest first; see :mod:`._components`."""
        from ._components import face_components

        return face_components(self)


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
