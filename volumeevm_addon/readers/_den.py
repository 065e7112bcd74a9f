"""VolPack / Stanford ``.den`` density files (the format of VolPack's ``brainsmall.den``).

Layout (VolPack ``examples/denfile.c``, Stanford ``volrend`` ``map.c``): a 62-byte header of
29 ``short`` fields and one ``int``,

========  ==============================================================
field     meaning
========  ==============================================================
0         ``map_version``, 1 (the only version)
1-3       ``orig_min``; 4-6 ``orig_max``; 7-9 ``orig_len`` (source data)
10-18     ``extr_min``, ``extr_max``, ``extr_len`` (extracted part)
19-27     ``map_min``, ``map_max``, ``map_len`` (this map; x, y, z)
28        ``map_warps`` (resamplings since extraction)
int       ``map_length`` = product of ``map_len``
========  ==============================================================

followed by ``map_length`` unsigned bytes with x varying fastest. The byte order is the writer's
machine's: VolPack reads the version and swaps bytes when it is not 1, and so does this reader.
The format stores no voxel size, so spacing is unknown.
"""

import math
import os

import numpy as np

from .._errors import VolumeEVMError
from ._checks import check_read_memory, checked_volume, lazy_mapped, open_file, read_payload

_HEADER_BYTES = 62
_VERSION = 1
_MAP_LEN = slice(25, 28)


def read_den(path, lazy=False):
    """Read a VolPack ``.den`` file.

    Parameters
    ----------
    path : str or Path
        The ``.den`` file.
    lazy : bool
        Map the file read-only and return its array as a lazy Dask array (nothing is read
        until a chunk is computed).

    Returns
    -------
    Volume
        ``uint8`` densities as ``(X, Y, Z)`` = ``map_len``; identity orientation, zero origin,
        spacing 1 mm with ``spacing_known=False``.

    Raises
    ------
    VolumeEVMError
        If the header is short or not version 1 in either byte order, ``map_length`` disagrees
        with ``map_len``, the file length is not header plus ``map_length`` bytes, or the
        volume would not fit in memory.
    """
    with open_file(path) as f:
        size = os.fstat(f.fileno()).st_size
        header = f.read(_HEADER_BYTES)
        if len(header) < _HEADER_BYTES:
            raise VolumeEVMError(
                f"{path}: truncated VolPack .den file: {size} bytes, shorter than the "
                f"{_HEADER_BYTES}-byte header"
            )
        for order in "<>":
            fields = np.frombuffer(header, dtype=f"{order}i2", count=29)
            if fields[0] == _VERSION:
                break
        else:
            raise VolumeEVMError(
                f"{path}: corrupt header: not a VolPack .den file (version field is "
                f"{int(fields[0])} in either byte order, expected {_VERSION})"
            )
        map_length = int(np.frombuffer(header, dtype=f"{order}i4", count=1, offset=58)[0])
        map_len = tuple(int(n) for n in fields[_MAP_LEN])
        if min(map_len) <= 0 or map_length != math.prod(map_len):
            raise VolumeEVMError(
                f"{path}: corrupt header: map_len {map_len} and map_length {map_length} disagree"
            )
        if size != _HEADER_BYTES + map_length:
            raise VolumeEVMError(
                f"{path}: file has {size} bytes but its header announces "
                f"{_HEADER_BYTES} + {map_length}; the file is truncated or corrupt"
            )
        if lazy:
            return checked_volume(lazy_mapped(path, _HEADER_BYTES, map_len, np.dtype(np.uint8),
                                              fortran_order=True), path)
        check_read_memory(path, map_len, np.dtype(np.uint8), copies=2)  # bytes, then C order
        buffer = read_payload(f, map_length, path, "density data")
    flat = np.frombuffer(buffer, dtype=np.uint8)
    return checked_volume(flat.reshape(map_len[::-1]).transpose(), path)
