"""Headerless raw volumes (``.raw``, ``.bin``): the user gives the layout.

A raw file is ``header_bytes`` bytes to skip, then ``X * Y * Z`` samples of one dtype with x
varying fastest, then y, then z (the layout of most volume tools' raw exports). Nothing in the
file can confirm the layout, so the one check possible is made strictly: the file length must
equal ``header_bytes + X * Y * Z * itemsize`` exactly, which catches most wrong shapes, dtypes
and truncated downloads.
"""

import math
import os

import numpy as np

from .._errors import VolumeEVMError
from ._checks import check_read_memory, checked_volume, lazy_mapped, open_file, read_payload

_BYTE_ORDERS = {"little": "<", "big": ">"}


def read_raw(path, *, shape=None, dtype=None, byte_order="little", header_bytes=0, spacing=None,
             lazy=False):
    """Read a headerless raw volume with x fastest in the file.

    Parameters
    ----------
    path : str or Path
        The raw file.
    shape : sequence of 3 int
        Grid size ``(X, Y, Z)``. Required.
    dtype : str or numpy dtype
        Sample type, e.g. ``np.uint16`` or ``"int16"``. Required. Its own byte-order mark, if
        any, is replaced by ``byte_order``.
    byte_order : {"little", "big"}
        Byte order of multi-byte samples.
    header_bytes : int
        Bytes to skip at the start of the file.
    spacing : sequence of 3 float, optional
        Voxel size in mm (x, y, z); without it 1 mm is used and ``spacing_known`` is False.
    lazy : bool
        Map the file read-only and return a lazy Dask array (chunks of whole z planes,
        :func:`._checks.lazy_mapped`): nothing is read until a chunk is computed.

    Returns
    -------
    Volume
        The samples as an ``(X, Y, Z)`` array in native byte order; identity orientation and
        zero origin (the file has no patient frame).

    Raises
    ------
    VolumeEVMError
        If ``shape`` or ``dtype`` is missing or invalid, ``byte_order`` or ``header_bytes`` is
        invalid, the file length does not match the layout, or the volume would not fit in
        memory.
    """
    if shape is None or dtype is None:
        raise VolumeEVMError(
            f"{path}: a raw file has no header; give its layout with shape=(X, Y, Z) and "
            f"dtype=... (and byte_order=, header_bytes= if needed)"
        )
    try:
        sample = np.dtype(dtype)
    except (TypeError, ValueError) as exc:
        raise VolumeEVMError(f"{path}: unknown dtype {dtype!r} ({exc})") from exc
    if sample.kind not in "uif":
        raise VolumeEVMError(
            f"{path}: unsupported dtype {sample}; raw samples must be integers or real floats"
        )
    if byte_order not in _BYTE_ORDERS:
        raise VolumeEVMError(
            f"{path}: byte_order must be 'little' or 'big', got {byte_order!r}"
        )
    sample = sample.newbyteorder(_BYTE_ORDERS[byte_order])
    if (
        not isinstance(shape, (tuple, list, np.ndarray))
        or len(shape) != 3
        or not all(isinstance(n, (int, np.integer)) and n > 0 for n in shape)
    ):
        raise VolumeEVMError(f"{path}: shape must be 3 positive integers (X, Y, Z), got {shape!r}")
    if not isinstance(header_bytes, (int, np.integer)) or header_bytes < 0:
        raise VolumeEVMError(
            f"{path}: header_bytes must be a non-negative integer, got {header_bytes!r}"
        )
    shape = tuple(int(n) for n in shape)
    nbytes = math.prod(shape) * sample.itemsize  # Python ints: no overflow for any shape
    expected = int(header_bytes) + nbytes
    with open_file(path) as f:
        size = os.fstat(f.fileno()).st_size
        if size != expected:
            raise VolumeEVMError(
                f"{path}: file has {size} bytes but shape {shape} of {sample.name} after "
                f"{header_bytes} header bytes needs exactly {expected}; the file is truncated or "
                f"the layout is wrong"
            )
        if lazy:
            array = lazy_mapped(path, int(header_bytes), shape, sample, fortran_order=True)
            return checked_volume(array, path, spacing=spacing)
        check_read_memory(path, shape, sample, copies=2)  # the file's bytes, then C order
        f.seek(header_bytes)
        buffer = read_payload(f, nbytes, path, "raw data")
    flat = np.frombuffer(buffer, dtype=sample)
    return checked_volume(flat.reshape(shape[::-1]).transpose(), path, spacing=spacing)
