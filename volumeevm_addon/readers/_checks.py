"""Validation shared by all readers: one place decides what a usable volume is.

Every reader decodes its format into a NumPy array plus grid geometry and hands both to
:func:`checked_volume`, which refuses what the core cannot use (wrong number of dimensions, an
empty grid, a dtype that is not a real number, NaN or Inf densities, degenerate geometry) with a
:class:`~volumeevm_addon.VolumeEVMError` naming the file, and otherwise returns the
:class:`~volumeevm_addon.Volume` in the core's conventions (native byte order,
C-contiguous ``[x, y, z]`` array).

Before that, the readers share one way to get at the bytes: :func:`require_regular_file` and
:func:`open_file` (no FIFO read forever, an unreadable file named in words),
:func:`check_read_memory` (the read's peak against the memory available, before allocating)
and :func:`read_payload` (exactly the bytes the header announces, from a file or a
decompressing stream, checksums verified); for ``lazy=True``, :func:`lazy_mapped` (the samples
as a lazy Dask array over a read-only memory map, after the same checks of the file's length).
"""

import importlib
import math
import os
import stat
import zlib
from pathlib import Path

import numpy as np

from .._errors import VolumeEVMError
from .._memory import check_memory
from ..model._volume import Volume, is_lazy

#: Bytes read per call when filling a buffer, so a decompressing stream never holds a second
#: full-size copy of the data.
_CHUNK_BYTES = 1 << 20

#: Length units found in file headers (NRRD, NIfTI, ImageJ, OME), as millimetres per unit, in
#: the spellings tools write (Fiji's NRRD writer: "microns"; ImageJ: ``\\u00B5m``).
MM_PER_UNIT = {
    **dict.fromkeys(["mm", "millimeter", "millimeters", "millimetre", "millimetres"], 1.0),
    **dict.fromkeys(["cm", "centimeter", "centimeters", "centimetre", "centimetres"], 10.0),
    **dict.fromkeys(["m", "meter", "meters", "metre", "metres"], 1000.0),
    **dict.fromkeys(["um", "\u00b5m", "\u03bcm", "\\u00b5m", "micron", "microns", "micrometer",
                     "micrometers", "micrometre", "micrometres"], 1e-3),
    **dict.fromkeys(["nm", "nanometer", "nanometers", "nanometre", "nanometres"], 1e-6),
}

#: Length "units" that say the spacing is not known (ImageJ and Fiji write "pixel" for an
#: uncalibrated image): the spacing is reported unknown, not refused.
UNKNOWN_LENGTH_UNITS = frozenset(["pixel", "pixels", ""])

#: Spellings of data units mapped to the short names the core uses.
_DATA_UNIT_ALIASES = {"hounsfield units": "HU", "hounsfield unit": "HU", "hu": "HU"}


def import_reader_package(module, pip_name, path):
    """Import a third-party package a reader needs, only when that reader runs.

    Keeping the import here (not at module level) lets ``import volumeevm_addon`` work in a
    Blender without pydicom, nibabel, pynrrd or tifffile; the user learns which one to install
    only when opening a file that needs it.

    Parameters
    ----------
    module : str
        Module to import ("pydicom", "nibabel", "nrrd", "tifffile").
    pip_name : str
        Name of the package that provides it on PyPI, for the message.
    path : str
        The file being read, for the message.

    Returns
    -------
    module
        The imported module.

    Raises
    ------
    VolumeEVMError
        If the package is not installed.
    """
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise VolumeEVMError(
            f"{path}: reading this format needs the Python package '{pip_name}', which is not "
            f"installed ({exc})"
        ) from exc


#: Bytes per chunk of a lazy memory-mapped volume (whole planes, as many as fit).
LAZY_CHUNK_BYTES = 64 << 20


class MappedChunks:
    """A memory-mapped array as Dask reads it: each chunk a copy of its part of the map.

    Handing Dask the ``np.memmap`` itself would not do: ``dask.array.from_array`` copies a
    NumPy array (a memmap is one) into memory whole.
    """

    def __init__(self, mapped):
        self.mapped = mapped
        self.shape, self.dtype, self.ndim = mapped.shape, mapped.dtype, mapped.ndim

    def __getitem__(self, slices):
        return np.array(self.mapped[slices])


def lazy_mapped(path, offset, shape, dtype, *, fortran_order):
    """The ``(X, Y, Z)`` samples of a file as a lazy Dask array over a read-only memory map.

    Chunks are :data:`LAZY_CHUNK_BYTES` of whole planes across the axis that varies slowest
    in the file (x for C order, z for Fortran order), so each chunk is one contiguous read.

    Parameters
    ----------
    path : Path
        The file, already checked to hold exactly ``offset`` + the data's bytes.
    offset : int
        Bytes before the data.
    shape : tuple of 3 int
        The grid, positive sizes.
    dtype : numpy dtype
        The samples as stored (any byte order).
    fortran_order : bool
        True when x varies fastest in the file.

    Returns
    -------
    dask array
        Named by the file's path and modification time, so Dask never mixes two versions.
    """
    da = import_reader_package("dask.array", "dask", path)
    order = "F" if fortran_order else "C"
    mapped = np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape, order=order)
    slow = 2 if fortran_order else 0
    plane = math.prod(shape) // shape[slow] * dtype.itemsize
    chunks = [-1, -1, -1]
    chunks[slow] = max(1, min(shape[slow], LAZY_CHUNK_BYTES // plane))
    name = f"mapped-{Path(path).resolve()}-{os.stat(path).st_mtime_ns}"
    return da.from_array(MappedChunks(mapped), chunks=tuple(chunks), name=name, asarray=False,
                         fancy=False, meta=np.empty((0, 0, 0), dtype))


def mm_per_unit(unit, path, what):
    """Millimetres per one ``unit`` of a header's length unit.

    Parameters
    ----------
    unit : str
        Unit spelling from the header ("mm", "um", "micron", "cm", ...), case-insensitive.
    path : str
        The file being read, for the message.
    what : str
        Which header field holds the unit, for the message.

    Returns
    -------
    float
        Millimetres per unit.

    Raises
    ------
    VolumeEVMError
        If the unit is not a known length unit.
    """
    key = str(unit).strip().lower()
    if key not in MM_PER_UNIT:
        raise VolumeEVMError(
            f"{path}: unknown length unit {unit!r} in {what}; known units: "
            f"{', '.join(sorted(MM_PER_UNIT))}"
        )
    return MM_PER_UNIT[key]


def data_units(text):
    """The data units a header states, as the core names them ("Hounsfield units" -> "HU").

    Parameters
    ----------
    text : str
        The header's value, surrounding white space and quotes ignored.

    Returns
    -------
    str
        The units, "" when ``text`` is empty.
    """
    text = str(text).strip().strip('"').strip()
    return _DATA_UNIT_ALIASES.get(text.lower(), text)


def require_regular_file(path):
    """Refuse a path that is not a regular file: a FIFO or device would be read forever.

    Raises
    ------
    VolumeEVMError
        If ``path`` cannot be examined (missing, a broken link, permission denied) or is a
        folder, FIFO, socket or device.
    """
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise VolumeEVMError(f"{path}: cannot read the file ({reason})") from exc
    if not stat.S_ISREG(mode):
        raise VolumeEVMError(f"{path}: not a regular file (a folder, FIFO, socket or device)")


def open_file(path):
    """Open ``path`` for binary reading, or refuse with a message that names it.

    Returns
    -------
    file object
        Open in ``"rb"`` mode; the caller closes it (``with open_file(path) as f:``).

    Raises
    ------
    VolumeEVMError
        If the file cannot be opened (missing, permission denied, a folder, path too long).
    """
    try:
        return open(path, "rb")  # noqa: SIM115 - the caller's with block closes it
    except (OSError, ValueError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise VolumeEVMError(f"{path}: cannot open the file for reading ({reason})") from exc


def read_payload(stream, nbytes, path, what, *, start=0):
    """Read exactly ``nbytes`` from ``stream`` into a new buffer; refuse any other length.

    ``stream`` is an open file or a decompressing reader (``gzip.GzipFile``, ``bz2.BZ2File``)
    positioned where the data starts. The buffer is allocated once and filled in chunks, so a
    compressed stream never inflates past the size the header declared (a decompression bomb is
    cut off after ``nbytes + 1`` bytes), and the stream is read to its end, which makes the
    decompressors verify their checksums (gzip: CRC-32 and length, bzip2: CRC).

    Parameters
    ----------
    stream : binary file object
        Supports ``readinto`` and ``read``.
    nbytes : int
        Bytes the header announces.
    path : str
        The file read, for the message.
    what : str
        What the bytes are ("voxel data", "gzip-compressed voxel data"), for the message.
    start : int, optional
        Bytes of the same stream already read (a header), so that messages give totals.

    Returns
    -------
    bytearray
        Exactly ``nbytes`` bytes.

    Raises
    ------
    VolumeEVMError
        If the stream ends early, holds more than ``nbytes`` bytes, or is corrupt (a failed
        checksum, a broken compressed stream, an I/O error).
    """
    buffer = bytearray(nbytes)
    view = memoryview(buffer)
    filled = 0
    try:
        while filled < nbytes:
            got = stream.readinto(view[filled:filled + _CHUNK_BYTES])
            if not got:
                break
            filled += got
        extra = stream.read(1) if filled == nbytes else b""
    except (OSError, EOFError, zlib.error) as exc:
        raise VolumeEVMError(
            f"{path}: the {what} is corrupt or truncated ({type(exc).__name__}: {exc})"
        ) from exc
    if filled < nbytes:
        raise VolumeEVMError(
            f"{path}: the {what} ends after {start + filled} bytes but the header announces "
            f"{start + nbytes}; "
            f"the file is truncated or its header is corrupt"
        )
    if extra:
        raise VolumeEVMError(
            f"{path}: the {what} holds more than the {start + nbytes} bytes the header "
            f"announces; the file or its header is corrupt"
        )
    return buffer


def check_read_memory(path, shape, dtype, *, copies, extra=0):
    """Refuse to read a volume whose peak memory would not fit, before anything is allocated.

    The peak of a reader is ``copies`` full copies of the data as the file stores it (the buffer
    read from the file, the C-ordered array :func:`checked_array` makes from it, ...), a 1-byte
    finiteness mask per voxel for floating point data, ``extra`` bytes of the reader's own
    (scaled copies) and one read chunk of headroom (chunks, headers, decompressor state). Measured
    with ``tracemalloc`` on the CT head (256x256x108 int16) this is at most 1 MiB above the peak
    of the .npy, raw, NIfTI (plain, gzip, scaled), NRRD and .den readers.

    Parameters
    ----------
    path : str
        The file read, named first in the message.
    shape : sequence of int
        Grid shape from the header (Python ints: the product cannot overflow).
    dtype : numpy dtype
        Sample type from the header.
    copies : int
        Full-size copies of the data the reader holds at once.
    extra : int, optional
        Further bytes at the peak.

    Raises
    ------
    VolumeEVMError
        When the estimate exceeds the memory available (see :mod:`volumeevm_addon._memory`).
    """
    count = math.prod(int(n) for n in shape)
    nbytes = count * dtype.itemsize
    mask = count if dtype.kind == "f" else 0
    check_memory(
        copies * nbytes + mask + extra + _CHUNK_BYTES,
        f"reading a {'x'.join(str(int(n)) for n in shape)} {dtype.name} volume",
        source=str(path),
        advice="crop or downsample the volume in another tool, or free memory",
    )


def check_ndim(shape, path):
    """Refuse data whose ``shape`` is not 3-D, before a reader spends time decoding it.

    Raises
    ------
    VolumeEVMError
        If ``len(shape) != 3``.
    """
    if len(shape) != 3:
        raise VolumeEVMError(
            f"{path}: the data has {len(shape)} dimension(s) (shape {tuple(shape)}); "
            f"a volume needs exactly 3"
        )


def checked_array(array, path):
    """Check that ``array`` is a usable density grid and return it in the core's layout.

    A lazy Dask array (:func:`~volumeevm_addon.model._volume.is_lazy`) is checked by its
    dtype and shape only and stays lazy (native byte order as a lazy conversion): its
    densities are checked for NaN and Inf when a build computes its chunks.

    Parameters
    ----------
    array : ndarray or dask array
        Decoded densities, already indexed ``[x, y, z]``.
    path : str
        The file the array came from, for the message.

    Returns
    -------
    (X, Y, Z) ndarray or dask array
        The same values, C-contiguous and in native byte order (a copy only if needed).

    Raises
    ------
    VolumeEVMError
        If the array is not 3-D, is empty, has a dtype other than integer or real floating
        point, or (float data) holds NaN or Inf.
    """
    lazy = is_lazy(array)
    if not lazy:
        array = np.asarray(array)
    if array.dtype.kind not in "uif":
        raise VolumeEVMError(
            f"{path}: unsupported data type {array.dtype}; densities must be integers or real "
            f"floating point numbers"
        )
    check_ndim(array.shape, path)
    if array.size == 0:
        raise VolumeEVMError(f"{path}: the volume is empty (shape {array.shape})")
    if lazy:
        native = array.dtype.newbyteorder("=")
        return array if array.dtype == native else array.astype(native)
    if array.dtype.kind == "f":
        finite = np.isfinite(array)
        if not finite.all():
            bad = np.argwhere(~finite)
            first = tuple(int(i) for i in bad[0])
            raise VolumeEVMError(
                f"{path}: {len(bad)} densities are NaN or Inf (first at voxel {first}, value "
                f"{array[first]}); densities must be finite"
            )
    return np.ascontiguousarray(array, dtype=array.dtype.newbyteorder("="))


def checked_volume(
    array, path, *, spacing=None, origin=(0.0, 0.0, 0.0), orientation=None, units=""
):
    """Validate decoded data and geometry and build the :class:`Volume`.

    Parameters
    ----------
    array : ndarray or dask array
        Decoded densities indexed ``[x, y, z]`` (lazy ones as :func:`checked_array` says).
    path : str
        The file or folder read, stored as ``Volume.source`` and named in messages.
    spacing : sequence of 3 float, optional
        Voxel size in mm along x, y, z. ``None`` means the file gives none: 1 mm is used and
        ``spacing_known`` is False.
    origin : sequence of 3 float
        Physical position (mm, LPS) of the centre of voxel ``(0, 0, 0)``.
    orientation : (3, 3) array_like, optional
        Column ``i`` is the direction of index axis ``i`` in LPS; columns are normalised here.
        ``None`` means the identity (index axes along L, P, S).
    units : str
        Data units ("HU", ...), "" when unknown.

    Returns
    -------
    Volume

    Raises
    ------
    VolumeEVMError
        If the array fails :func:`checked_array`, or the geometry is not finite, a spacing is
        not positive, or the orientation is singular: signs of a corrupt header.
    """
    path = str(path)
    array = checked_array(array, path)
    spacing_known = spacing is not None
    spacing = np.ones(3) if spacing is None else np.asarray(spacing, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    rot = np.eye(3) if orientation is None else np.asarray(orientation, dtype=np.float64)
    if spacing.shape != (3,) or not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise VolumeEVMError(
            f"{path}: corrupt header: voxel spacing {spacing.tolist()} is not three positive "
            f"finite numbers"
        )
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise VolumeEVMError(
            f"{path}: corrupt header: origin {origin.tolist()} is not three finite numbers"
        )
    norms = np.linalg.norm(rot, axis=0) if rot.shape == (3, 3) else np.zeros(1)
    if not np.all(np.isfinite(rot)) or np.any(norms == 0):
        raise VolumeEVMError(
            f"{path}: corrupt header: axis directions {rot.tolist()} are not three non-zero "
            f"finite 3-vectors"
        )
    rot = rot / norms
    if abs(np.linalg.det(rot)) < 1e-6:
        raise VolumeEVMError(
            f"{path}: corrupt header: axis directions {rot.tolist()} are linearly dependent"
        )
    return Volume(
        array=array,
        spacing=tuple(float(s) for s in spacing),
        origin=tuple(float(o) for o in origin),
        orientation=rot,
        units=units,
        source=path,
        spacing_known=spacing_known,
    )
