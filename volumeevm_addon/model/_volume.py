"""The volume record every reader returns: densities on a regular grid and where the grid sits.

Conventions (one place for all of them):

- ``array`` is indexed ``[x, y, z]``; x is the first index.
- Voxel ``(i, j, k)`` is the unit cell ``[i, i+1] x [j, j+1] x [k, k+1]`` of the lattice; its
  density sits at the cell centre (the EVM's cells; Blender/OpenVDB convention).
- ``origin`` is the physical position (mm) of the *centre* of voxel ``(0, 0, 0)``, as DICOM,
  NIfTI and NRRD give it.
- ``orientation`` is a 3x3 matrix whose column ``i`` is the unit direction of index axis ``i`` in
  the patient frame LPS (+x left, +y posterior, +z superior). LPS maps straight onto Blender's
  axes: Z up is superior and the front view (looking along +Y) faces the patient's anterior side.
- ``units`` are the data's own units ("HU" for CT); densities are never rescaled by the core.

Points go through affine maps with :func:`transform` (scaled sums, not a BLAS product: the same
bits on every CPU).
"""

from dataclasses import KW_ONLY, dataclass, field, replace

import numpy as np

from .._errors import VolumeEVMError

BLENDER_UNITS_PER_MM = 0.001
"""The one unit mapping: 1 mm of patient space is 0.001 Blender units (1 BU = 1 m, Blender's
default metric scene), so a 25 cm head is 0.25 BU across and measures right in Blender."""


@dataclass(frozen=True)
class Volume:
    """A grey-level volume with its grid geometry.

    What every reader returns, and what :meth:`VolumeEVM.from_volume` builds a region from.
    The record stores what it is given; the readers and :meth:`VolumeEVM.from_volume` check
    it. Every field after ``array`` is keyword-only.

    Parameters
    ----------
    array : (X, Y, Z) ndarray
        Densities in data units, indexed ``[x, y, z]``.
    spacing : tuple of 3 float, optional
        Voxel size in mm along x, y, z (default 1 mm).
    origin : tuple of 3 float, optional
        Physical position (mm, LPS) of the centre of voxel ``(0, 0, 0)`` (default 0).
    orientation : (3, 3) ndarray, optional
        Column ``i`` is the direction of index axis ``i`` in LPS (default the identity).
    units : str, optional
        Data units ("HU", "a.u.", ...); "" when the file does not say.
    source : str, optional
        The file or folder the volume was read from ("" for arrays made in memory).
    spacing_known : bool, optional
        False when the file carries no spacing and ``spacing`` is a guess of 1 mm.
    labels : dict, optional
        For a label map (a segmentation: integers, 0 = background), each label's name and
        colour, ``label -> LabelInfo`` (:mod:`._label_table`); None for densities.
    layers : tuple of (X, Y, Z) ndarray, optional
        For a label map whose labels overlap (a 3D Slicer segmentation in layers), the label
        maps that hold them, each label in one layer; ``array`` is then their overlay (a later
        layer over an earlier one), and :meth:`VolumeEVM.from_labels` builds each label from its
        layer. None when ``array`` holds every label.

    Examples
    --------
    >>> vol = Volume(np.zeros((4, 3, 2)), spacing=(0.5, 0.5, 2.0), units="HU")
    >>> vol.shape, vol.index_to_physical()[:3, 3].tolist()
    ((4, 3, 2), [0.0, 0.0, 0.0])
    """

    array: np.ndarray
    _: KW_ONLY
    spacing: tuple = (1.0, 1.0, 1.0)
    origin: tuple = (0.0, 0.0, 0.0)
    orientation: np.ndarray = field(default_factory=lambda: np.eye(3))
    units: str = ""
    source: str = ""
    spacing_known: bool = True
    labels: dict = None
    layers: tuple = None

    @property
    def is_label_map(self):
        """True when the volume is a label map (its ``labels`` are known)."""
        return self.labels is not None

    @property
    def shape(self):
        """Grid shape ``(X, Y, Z)``."""
        return self.array.shape

    def index_to_physical(self):
        """4x4 matrix taking voxel-centre indices ``(i, j, k, 1)`` to physical mm (LPS).

        Returns
        -------
        (4, 4) ndarray of np.float64
            :func:`index_to_physical` of this volume's geometry.
        """
        return index_to_physical(self.spacing, self.origin, self.orientation)

    def index_box(self, lo_mm, hi_mm):
        """The voxel box covering a physical box: what ``crop=`` of
        :meth:`VolumeEVM.from_volume` takes to build only that region of interest.

        The box ``lo_mm .. hi_mm`` is axis-aligned in the patient frame (LPS mm, as
        :meth:`index_to_physical` places voxels: a tool's world bounds divided by
        :data:`BLENDER_UNITS_PER_MM`). Its 8 corners go to index space through the inverse
        placement; every voxel whose cell overlaps their bounding box there (by more than
        :data:`INDEX_BOX_TOLERANCE` of a voxel, so a box edge on a cell face takes no
        neighbour by rounding) is in the result, cut to the grid. With an oblique orientation
        the result covers the box with the voxels around it.

        Parameters
        ----------
        lo_mm, hi_mm : (3,) array_like of float
            Opposite corners of the box in LPS mm, finite, ``lo_mm <= hi_mm`` per axis.

        Returns
        -------
        tuple of 3 (int, int) pairs
            ``((i0, i1), (j0, j1), (k0, k1))``, half-open, along the array's axes x, y, z.

        Raises
        ------
        VolumeEVMError
            If a corner is not 3 finite numbers, ``hi_mm < lo_mm`` along an axis, or the box
            misses the grid (naming ``crop``).

        Examples
        --------
        >>> vol = Volume(np.zeros((10, 10, 4)), spacing=(2.0, 2.0, 5.0))
        >>> vol.index_box((3.0, -50.0, 0.0), (7.0, 50.0, 0.0))  # x: the cells 3..5 and 5..7 mm
        ((2, 4), (0, 10), (0, 1))
        """
        lo = _reals(lo_mm, (3,), "lo_mm", "crop: ", "3 finite numbers (mm)")
        hi = _reals(hi_mm, (3,), "hi_mm", "crop: ", "3 finite numbers (mm)")
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or (hi < lo).any():
            raise VolumeEVMError(f"crop: the box {lo.tolist()} .. {hi.tolist()} mm must be finite "
                                 f"with lo_mm <= hi_mm along every axis")
        corners = np.array([[(lo, hi)[c >> a & 1][a] for a in range(3)] for c in range(8)])
        matrix = self.index_to_physical()
        inverse = np.linalg.inv(matrix[:3, :3])
        index = transform(corners - matrix[:3, 3], inverse.T)
        low, high = index.min(axis=0), index.max(axis=0)
        # Voxel i's cell spans i - 0.5 .. i + 0.5 in index space.
        first = np.floor(low + 0.5 + INDEX_BOX_TOLERANCE).astype(np.int64)
        last = np.ceil(high + 0.5 - INDEX_BOX_TOLERANCE).astype(np.int64)
        box = tuple((max(0, int(a)), min(n, int(b)))
                    for a, b, n in zip(first, last, self.shape))
        if any(a >= b for a, b in box):
            raise VolumeEVMError(f"crop: the box {lo.tolist()} .. {hi.tolist()} mm misses the "
                                 f"volume's grid {tuple(self.shape)}")
        return box


#: Overlap (in voxels) a cell needs with a physical box to be in :meth:`Volume.index_box`.
INDEX_BOX_TOLERANCE = 1e-6


def cropped(volume, crop):
    """``volume`` cut to the voxel box ``crop`` (see :meth:`VolumeEVM.from_volume`), its
    origin moved to the box's first voxel so that every kept voxel sits where it sat.

    The array is sliced, not copied: a NumPy view, or a lazy Dask array that reads only the
    chunks meeting the box. A label map's layers are cut alike.
    """
    array = volume.array if is_lazy(volume.array) else np.asanyarray(volume.array)
    if array.ndim != 3:
        raise VolumeEVMError(f"{volume.source or 'volume'}: expected a 3-D array indexed "
                             f"[x, y, z], got shape {array.shape}")
    box = checked_crop(crop, array.shape)
    slices = tuple(slice(a, b) for a, b in box)
    matrix = volume.index_to_physical()
    first = np.array([a for a, _ in box], np.float64)
    origin = transform(first, matrix[:3, :3].T, matrix[:3, 3])
    layers = None if volume.layers is None else tuple(layer[slices] for layer in volume.layers)
    return replace(volume, array=array[slices], origin=tuple(float(o) for o in origin),
                   layers=layers)


def checked_crop(crop, shape):
    """``crop`` as 3 ``(start, stop)`` pairs of Python ints with ``0 <= start < stop <= n``
    for the grid's ``shape``; refuses anything else (floats, bools, other lengths) naming
    ``crop``."""
    expected = (f"crop must be 3 (start, stop) pairs of voxel indices along x, y, z, "
                f"0 <= start < stop <= {tuple(shape)}")
    try:
        pairs = [tuple(pair) for pair in crop]
    except TypeError:
        raise VolumeEVMError(f"{expected}; got {crop!r}") from None
    if len(pairs) != 3 or any(len(pair) != 2 for pair in pairs):
        raise VolumeEVMError(f"{expected}; got {crop!r}")
    if not all(isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))
               for pair in pairs for v in pair):
        raise VolumeEVMError(f"{expected}; got {crop!r}, not integers")
    box = tuple((int(a), int(b)) for a, b in pairs)
    if any(not 0 <= a < b <= n for (a, b), n in zip(box, shape)):
        raise VolumeEVMError(f"{expected}; got {box}: empty, reversed or outside the grid")
    return box


def is_lazy(array):
    """True when ``array`` is a lazy Dask array (a store's or a memory-mapped file's), whose
    chunks are read only when computed; found without importing Dask.

    Parameters
    ----------
    array : object
        A volume's ``array``.

    Returns
    -------
    bool
    """
    return type(array).__module__.split(".")[0] == "dask"


def index_to_physical(spacing, origin, orientation=None):
    """4x4 matrix from voxel-centre index space to physical mm (LPS).

    A lattice point ``p`` (a voxel corner, as EVM vertices are) sits at index ``p - 0.5``.

    Parameters
    ----------
    spacing : (3,) array_like
        Voxel size in mm along x, y, z.
    origin : (3,) array_like
        Physical position (mm) of the centre of voxel ``(0, 0, 0)``.
    orientation : (3, 3) array_like, optional
        Column ``i`` is the direction of index axis ``i`` (default the identity).

    Returns
    -------
    (4, 4) ndarray of np.float64
        ``[orientation · diag(spacing) | origin]``, last row ``(0, 0, 0, 1)``.

    Examples
    --------
    >>> index_to_physical((0.5, 0.5, 2.0), (10.0, 0.0, 0.0)) @ (2, 0, 1, 1)
    array([11.,  0.,  2.,  1.])
    """
    m = np.eye(4)
    rot = np.eye(3) if orientation is None else np.asarray(orientation, dtype=np.float64)
    m[:3, :3] = rot * np.asarray(spacing, dtype=np.float64)[None, :]
    m[:3, 3] = origin
    return m


def grid_to_world(spacing, origin, orientation=None, matrix_world=None):
    """4x4 matrix from voxel-centre indices to Blender world units.

    ``matrix_world`` (the volume object's placement, default identity) after the one unit mapping
    :data:`BLENDER_UNITS_PER_MM` after :func:`index_to_physical`: where a renderer or a tool
    finds a voxel in the scene.

    Parameters
    ----------
    spacing, origin, orientation
        Grid geometry, as for :func:`index_to_physical`.
    matrix_world : (4, 4) array_like, optional
        The volume object's placement in the scene (default the identity).

    Returns
    -------
    (4, 4) ndarray of np.float64

    Examples
    --------
    >>> grid_to_world((1.0, 1.0, 1.0), (0.0, 0.0, 0.0)) @ (1000, 0, 0, 1)
    array([1., 0., 0., 1.])
    """
    scale = np.diag([BLENDER_UNITS_PER_MM] * 3 + [1.0])
    placement = np.eye(4) if matrix_world is None else np.asarray(matrix_world, dtype=np.float64)
    return placement @ scale @ index_to_physical(spacing, origin, orientation)


#: Largest deviation of ``orientation.T @ orientation`` from the identity that still counts as
#: orthonormal. Headers store directions in float32 or as decimal strings of six digits or so
#: (DICOM), which leaves errors near 1e-6; a sheared or scaled frame is off by far more.
ORTHONORMAL_TOLERANCE = 1e-5


def transform(points, matrix, offset=None):
    """``points @ matrix (+ offset)`` for ``(..., k)`` points and a ``(k, m)`` matrix, as ``k``
    scaled sums in a fixed order.

    Not a BLAS matrix product: its kernels round differently from one CPU to another, and on
    tall, thin products like these (a point per pixel or voxel) its threads spin for tens of
    milliseconds on a loaded machine. float32 points stay float32.
    """
    m = np.asarray(matrix, dtype=points.dtype)
    out = points[..., 0:1] * m[0]
    for i in range(1, m.shape[0]):
        out += points[..., i:i + 1] * m[i]
    if offset is not None:
        out += offset
    return out


def checked_geometry(spacing, origin, orientation, *, source=""):
    """Check grid geometry and return it in the core's types; the one place that decides it.

    Parameters
    ----------
    spacing : sequence of 3 real numbers
        Voxel size in mm along x, y, z: finite and positive.
    origin : sequence of 3 real numbers
        Physical position (mm, LPS) of the centre of voxel ``(0, 0, 0)``: finite.
    orientation : (3, 3) array_like or None
        Column ``i`` is the direction of index axis ``i``: an orthonormal matrix (rotation or
        reflection) within :data:`ORTHONORMAL_TOLERANCE`. ``None`` means the identity.
    source : str, optional
        The file or data the geometry belongs to, named first in messages.

    Returns
    -------
    spacing, origin : tuple of 3 float
    orientation : (3, 3) ndarray of float64

    Raises
    ------
    VolumeEVMError
        Naming the parameter and what is wrong with it.
    """
    prefix = f"{source}: " if source else ""
    spacing = _reals(spacing, (3,), "spacing", prefix,
                     "three finite positive numbers (mm per voxel)")
    if not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise VolumeEVMError(f"{prefix}spacing must be three finite positive numbers (mm per "
                             f"voxel), got {spacing.tolist()}")
    origin = _reals(origin, (3,), "origin", prefix, "three finite numbers (mm)")
    if not np.all(np.isfinite(origin)):
        raise VolumeEVMError(f"{prefix}origin must be three finite numbers (mm), got "
                             f"{origin.tolist()}")
    if orientation is None:
        rotation = np.eye(3)
    else:
        rotation = _reals(orientation, (3, 3), "orientation", prefix,
                          "a 3x3 matrix of real numbers")
        deviation = (np.abs(rotation.T @ rotation - np.eye(3)).max()
                     if np.isfinite(rotation).all() else np.inf)
        if not deviation <= ORTHONORMAL_TOLERANCE:
            raise VolumeEVMError(
                f"{prefix}orientation must be orthonormal (unit, mutually perpendicular axis "
                f"directions as columns), got {rotation.tolist()}: off by {deviation:.3g}"
            )
    return tuple(float(s) for s in spacing), tuple(float(o) for o in origin), rotation


def _reals(value, shape, name, prefix, expected):
    """``value`` as a float64 array of ``shape``; refuses bools, complex numbers and text."""
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError) as error:
        raise VolumeEVMError(f"{prefix}{name} must be {expected}, got {value!r}") from error
    if raw.shape != shape or raw.dtype.kind not in "iuf":
        raise VolumeEVMError(f"{prefix}{name} must be {expected}, got {value!r}")
    return raw.astype(np.float64)


def checked_densities(array, source):
    """The densities as an ndarray, refused unless they are a usable density grid.

    Accepted: a 3-D, non-empty array (or array-like) of integers or real floating-point
    numbers, all finite. Refused: booleans (a mask is not densities: use ``EVM.from_mask``),
    complex numbers, objects, and masked arrays, whose masked voxels have no defined density
    (fill them explicitly with ``array.filled(value)``). The finiteness test runs one x-slice at
    a time so that it allocates no copy of the grid.

    Parameters
    ----------
    array : array_like
    source : str
        The file or data the array came from, named first in messages.

    Returns
    -------
    (X, Y, Z) ndarray
        ``array`` itself when it is an ndarray (no copy).

    Raises
    ------
    VolumeEVMError
    """
    if isinstance(array, np.ma.MaskedArray):
        raise VolumeEVMError(
            f"{source}: a masked array has no density at its masked voxels; fill them "
            f"explicitly (array.filled(value)) or pass array.data"
        )
    try:
        array = np.asarray(array)
    except (TypeError, ValueError) as error:
        raise VolumeEVMError(f"{source}: not an array of densities ({error})") from error
    if array.ndim != 3:
        raise VolumeEVMError(f"{source}: expected a 3-D array indexed [x, y, z], got shape "
                             f"{array.shape}")
    if array.size == 0:
        raise VolumeEVMError(f"{source}: the volume is empty (shape {array.shape})")
    if array.dtype.kind not in "uif":
        hint = "; for a mask use EVM.from_mask" if array.dtype.kind == "b" else ""
        raise VolumeEVMError(
            f"{source}: densities must be integers or real floating-point numbers, got dtype "
            f"{array.dtype}{hint}"
        )
    if array.dtype.kind == "f":
        bad = [int(np.count_nonzero(~np.isfinite(plane))) for plane in array]
        if any(bad):
            x = next(i for i, count in enumerate(bad) if count)
            y, z = (int(i) for i in np.argwhere(~np.isfinite(array[x]))[0])
            raise VolumeEVMError(
                f"{source}: {sum(bad)} densities are NaN or infinite (first at voxel {(x, y, z)}, "
                f"value {array[x, y, z]}); densities must be finite"
            )
    return array
