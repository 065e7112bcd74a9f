"""NumPy ``.npy`` volumes, with an optional JSON sidecar for spacing and units.

The array is taken as already indexed ``[x, y, z]`` (the convention of the project's real data
in ``../shared/data``). The header is parsed with NumPy's own ``numpy.lib.format`` functions
and checked before any data is read: the file length must be the header plus exactly the bytes
its shape and dtype need (a changed shape or dtype, a truncated or padded file is refused), and
the array must fit in memory. A ``.npy`` holding Python objects is refused: its data would
execute code when unpickled, and VolumeEVM never unpickles.

The sidecar is ``NAME.json`` beside ``NAME.npy`` (the schema of ``../shared/data/*.json``). The
keys used are ``spacing_mm`` (x, y, z in mm), ``spacing_known``, ``units``, and, as consistency
checks against the array, ``shape``, ``dtype`` and ``axis_order`` (must be "xyz"). Other keys
are ignored.
"""

import json
import math
import os
import tokenize
from pathlib import Path

import numpy as np

from .._errors import VolumeEVMError
from ._checks import (
    check_ndim,
    check_read_memory,
    checked_volume,
    data_units,
    lazy_mapped,
    open_file,
    read_payload,
)

#: ``numpy.lib.format`` header readers by format version (3.0 only adds UTF-8 field names,
#: which a volume's plain dtype never needs).
_HEADER_READERS = {
    (1, 0): np.lib.format.read_array_header_1_0,
    (2, 0): np.lib.format.read_array_header_2_0,
}

def read_npy(path, lazy=False):
    """Read a ``.npy`` volume indexed ``[x, y, z]`` and its optional JSON sidecar.

    Parameters
    ----------
    path : str or Path
        The ``.npy`` file.
    lazy : bool
        Map the file into memory read-only and return its array as a lazy Dask array
        (:func:`._checks.lazy_mapped`): nothing is read until a chunk is computed, so a file
        larger than memory opens (for :meth:`VolumeEVM.from_volume`, which builds chunk by
        chunk). Checked as the eager read: header and file length.

    Returns
    -------
    Volume
        Identity orientation and zero origin (a ``.npy`` has no patient frame); spacing from
        the sidecar, else 1 mm with ``spacing_known=False``.

    Raises
    ------
    VolumeEVMError
        If the file is not a readable ``.npy`` (corrupt header, a length other than the header
        announces, pickled objects), the array would not fit in memory or is not a valid
        volume, or the sidecar is unreadable or disagrees with the array.
    """
    path = Path(path)
    with open_file(path) as f:
        shape, fortran_order, dtype = _read_header(f, path)
        start = f.tell()
        if dtype.hasobject:
            raise VolumeEVMError(
                f"{path}: not a readable .npy array (Object arrays cannot be loaded: it holds "
                f"pickled Python objects, which VolumeEVM never unpickles)"
            )
        if any(n < 0 for n in shape):
            raise VolumeEVMError(
                f"{path}: not a readable .npy array (corrupt header: shape {shape} has a "
                f"negative size)"
            )
        size = os.fstat(f.fileno()).st_size
        count = math.prod(shape)
        if size != start + count * dtype.itemsize:
            raise VolumeEVMError(
                f"{path}: not a readable .npy array (the file has {size} bytes but its header "
                f"announces {start} + {count * dtype.itemsize} for shape {shape} of {dtype}); "
                f"the file is truncated or corrupt"
            )
        if lazy:
            return _lazy(path, start, shape, fortran_order, dtype)
        reordered = fortran_order or not dtype.isnative
        check_read_memory(path, shape, dtype, copies=2 if reordered else 1)
        buffer = read_payload(f, count * dtype.itemsize, path, "array data")
    array = np.frombuffer(buffer, dtype=dtype).reshape(shape, order="F" if fortran_order else "C")
    spacing, units = _read_sidecar(path.with_suffix(".json"), array)
    return checked_volume(array, path, spacing=spacing, units=units)


def _lazy(path, start, shape, fortran_order, dtype):
    """The ``.npy`` file's volume over a read-only memory map (:func:`lazy_mapped`)."""
    check_ndim(shape, path)
    if math.prod(shape) == 0:
        raise VolumeEVMError(f"{path}: the volume is empty (shape {shape})")
    array = lazy_mapped(path, start, shape, dtype, fortran_order=fortran_order)
    spacing, units = _read_sidecar(path.with_suffix(".json"), array)
    return checked_volume(array, path, spacing=spacing, units=units)


def _read_header(f, path):
    """``(shape, fortran_order, dtype)`` from the ``.npy`` header at the start of ``f``."""
    if f.read(4) == b"PK\x03\x04":
        raise VolumeEVMError(f"{path}: holds an archive of several arrays (.npz), not one volume")
    f.seek(0)
    try:
        version = np.lib.format.read_magic(f)
        if version not in _HEADER_READERS:
            raise VolumeEVMError(
                f"{path}: not a readable .npy array (format version {version[0]}.{version[1]} "
                f"is not supported; 1.0 and 2.0 are)"
            )
        # A corrupt header makes NumPy's parser fail in several ways (its tokenizer included).
        return _HEADER_READERS[version](f)
    except (ValueError, TypeError, SyntaxError, EOFError, OSError, tokenize.TokenError) as exc:
        raise VolumeEVMError(
            f"{path}: not a readable .npy array (corrupt header: {exc})"
        ) from exc


def _read_sidecar(sidecar, array):
    """Spacing (mm, or ``None``) and units from ``sidecar`` if it exists, checked on ``array``."""
    if not sidecar.is_file():
        return None, ""
    try:
        meta = json.loads(sidecar.read_text(encoding="utf-8"))
    except (ValueError, OSError) as exc:
        raise VolumeEVMError(f"{sidecar}: corrupt JSON sidecar ({exc})") from exc
    if not isinstance(meta, dict):
        raise VolumeEVMError(f"{sidecar}: corrupt JSON sidecar (not a JSON object)")
    if meta.get("axis_order", "xyz") != "xyz":
        raise VolumeEVMError(
            f"{sidecar}: axis_order is {meta['axis_order']!r}; only 'xyz' arrays are supported"
        )
    if "shape" in meta and (not isinstance(meta["shape"], list)
                            or tuple(meta["shape"]) != array.shape):
        raise VolumeEVMError(
            f"{sidecar}: shape {meta['shape']} does not match the array's shape {array.shape}"
        )
    if "dtype" in meta and str(meta["dtype"]) != str(array.dtype):
        raise VolumeEVMError(
            f"{sidecar}: dtype {meta['dtype']} does not match the array's dtype {array.dtype}"
        )
    units = data_units(meta.get("units", ""))
    if "spacing_mm" not in meta or not meta.get("spacing_known", True):
        return None, units
    spacing = meta["spacing_mm"]
    if (
        not isinstance(spacing, list)
        or len(spacing) != 3
        or not all(isinstance(s, (int, float)) for s in spacing)
    ):
        raise VolumeEVMError(f"{sidecar}: spacing_mm {spacing!r} is not a list of 3 numbers")
    return spacing, units
