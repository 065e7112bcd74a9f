"""Reading and checking a ``.vevm`` file: every part is verified before anything is built.

A ``.vevm`` file is a ZIP archive in NumPy's ``.npz`` layout holding exactly five ``.npy``
members, stored or deflated:

- ``format``: the string ``"volumeevm"``; ``version``: the integer :data:`VERSION`;
- ``meta``: a JSON object (the keys of :data:`META_KEYS`): the grid ``shape``, ``spacing``,
  ``origin`` and ``orientation``, the data ``units``, the ``threshold``/``upper`` interval that
  selected the region (or ``null``), the number of ``voxels``, and SHA-256 checksums of the two
  arrays (:func:`checksum`);
- ``vertices``: the region's extreme vertices, ``(n, 3)`` integers;
- ``table``: the densities of its voxels in table order "xyz", ``(voxels,)`` integers or reals.

A file comes from outside, so :func:`read_vevm` trusts nothing in it:

1. The ZIP directory must list exactly these members, unencrypted, stored or deflated. Each
   member's ``.npy`` header is parsed alone (an object dtype, which would need unpickling, is
   refused: nothing is ever unpickled) and must declare a dtype and shape of the kind above whose
   size is exactly the member's size in the directory. The declared and compressed sizes must
   fit each other: equal for a stored member; for a deflated one, no larger than deflate's
   maximum expansion (a "zip bomb" declaring a huge array) and no smaller than the compressed
   data could hold (a stream that would inflate beyond its declared size). The arrays' total is
   checked against the free memory (:func:`~volumeevm_addon.system.check_memory`) before any is
   read. The ZIP reader never inflates beyond the declared size and verifies each member's CRC.
2. The metadata must have every key with the right type: shape 3 positive integers, spacing 3
   finite positive numbers, origin 3 finite numbers, orientation an orthonormal 3x3 matrix (the
   geometry by the same rules as for a new VolumeEVM), units a string, threshold and upper
   finite numbers or null (``upper >= threshold``), voxels an integer.
3. The arrays must match their checksums.
4. The vertices must be the extreme vertices of a region inside the grid: every coordinate in
   ``[0, shape]``, no duplicates, and an even number of vertices on every axis-parallel line.
   (Any finite point set with even lines is the EVM of exactly one bounded region, so these
   checks are complete.) The region's voxel count must equal ``voxels`` and the table's length,
   and the densities must be finite.

Every failure raises :class:`~volumeevm_addon.VolumeEVMError` naming the file and what is wrong.
"""

import ast
import collections
import hashlib
import json
import os
import re
import stat
import struct
import sys
import zipfile
import zlib
from pathlib import Path

import numpy as np
from numpy.lib import format as npy_format

from .._errors import VolumeEVMError
from .._memory import check_memory
from . import _sweep
from ._evm import EVM
from ._volume import checked_geometry

FORMAT = "volumeevm"
VERSION = 1

#: The members, each with the dtype kinds and the number of dimensions its array must have.
MEMBERS = {"format": ("U", 0), "version": ("iu", 0), "meta": ("U", 0), "vertices": ("iu", 2),
           "table": ("iuf", 1)}

#: How a message names each accepted set of dtype kinds.
_KIND_WORDS = {"U": "a string", "iu": "integers", "iuf": "integers or real numbers"}

META_KEYS = frozenset({"shape", "spacing", "origin", "orientation", "units", "threshold", "upper",
                       "voxels", "vertices_sha256", "table_sha256"})

#: Deflate turns one compressed byte into at most 1032 bytes (a 258-byte match per 2 bits).
DEFLATE_MAX_RATIO = 1032

#: And it grows data by at most 1/8 (fixed Huffman codes' worst case: 9 bits for a byte), so a
#: member holding more compressed bytes than that carries data beyond its declared size.
DEFLATE_MAX_GROWTH = 9 / 8

#: Peak working memory of checking and building the EVM, per vertex (keys, sorts, copies,
#: boxes), beyond the arrays themselves: measured with tracemalloc at about 70 bytes on the CT
#: head (76 000 and 127 000 vertices); with a margin.
BYTES_PER_VERTEX = 96

#: NumPy's own limit on a ``.npy`` header's length (``read_array`` refuses longer ones).
MAX_HEADER_BYTES = 10000

#: The ``descr`` of a plain dtype: byte order, type letter, size (structured dtypes never match).
_SIMPLE_DESCR = re.compile(r"[<>|][biufcSUO]\d{0,9}")

#: What the ZIP and ``.npy`` layers raise for a damaged archive.
_ARCHIVE_ERRORS = (zipfile.BadZipFile, zlib.error, struct.error, EOFError, OSError, ValueError,
                   NotImplementedError, SyntaxError, RecursionError)


def checksum(array):
    """SHA-256 (hex) of an array's values in C order, as stored in a ``.vevm``'s metadata."""
    return hashlib.sha256(np.ascontiguousarray(array).data).hexdigest()


def read_vevm(path):
    """Read and check a ``.vevm`` file (see the module docstring for what is checked).

    Parameters
    ----------
    path : str or path-like
        The file.

    Returns
    -------
    evm : EVM
        The region.
    table : (N,) ndarray
        Its densities in table order "xyz", native byte order.
    geometry : dict
        ``shape``, ``spacing``, ``origin``, ``orientation``, ``units``, ``threshold``, ``upper``:
        the keyword arguments of :class:`~._volumeevm.VolumeEVM`.

    Raises
    ------
    VolumeEVMError
        If the file is missing, not a regular file, not a VolumeEVM file, of another version,
        damaged, inconsistent, or too large for the free memory.
    """
    path = Path(os.fsdecode(path))
    _check_regular_file(path)
    try:
        with zipfile.ZipFile(path) as archive:
            headers = _member_headers(archive, path)
            vertex_count = headers["vertices"][0][0]
            needed = sum(nbytes for _, nbytes in headers.values()) + vertex_count * BYTES_PER_VERTEX
            check_memory(needed, "reading the VolumeEVM file", source=str(path),
                         advice="close other programs to free memory")
            arrays = {}
            for name in MEMBERS:
                with archive.open(f"{name}.npy") as member:
                    arrays[name] = npy_format.read_array(member, allow_pickle=False)
    except VolumeEVMError:
        raise
    except _ARCHIVE_ERRORS as error:
        raise _unreadable(path, f"{type(error).__name__}: {error}") from error
    if str(arrays["format"][()]) != FORMAT:
        raise VolumeEVMError(f"{path}: not a VolumeEVM file (format {str(arrays['format'][()])!r})")
    version = int(arrays["version"][()])
    if version != VERSION:
        raise VolumeEVMError(f"{path}: format version {version}, this add-on reads {VERSION}")
    meta = _check_meta(str(arrays["meta"][()]), path)
    vertices, table = arrays["vertices"], arrays["table"]
    changed = [name for name in ("vertices", "table")
               if checksum(arrays[name]) != meta[f"{name}_sha256"]]
    if changed:
        raise VolumeEVMError(f"{path}: checksum mismatch ({' and '.join(changed)}), the file is "
                             f"corrupt")
    evm = _check_region(vertices, meta["shape"], path)
    if not evm.volume() == meta["voxels"] == len(table):
        raise _corrupt(path, f"the region has {evm.volume()} voxels, the metadata says "
                             f"{meta['voxels']} and the table holds {len(table)} densities")
    if table.dtype.kind == "f" and not np.isfinite(table).all():
        bad = int(np.count_nonzero(~np.isfinite(table)))
        raise _corrupt(path, f"{bad} densities are NaN or infinite")
    table = table.astype(table.dtype.newbyteorder("="), copy=False)
    geometry = {key: meta[key] for key in
                ("shape", "spacing", "origin", "orientation", "units", "threshold", "upper")}
    return evm, table, geometry


def _check_regular_file(path):
    """Refuse a missing path, a folder, a FIFO or a device before opening (a FIFO would block)."""
    try:
        mode = path.stat().st_mode
    except FileNotFoundError as error:
        raise VolumeEVMError(f"{path}: file not found") from error
    except OSError as error:
        raise VolumeEVMError(f"{path}: cannot read the file ({error.strerror or error})") from error
    if not stat.S_ISREG(mode):
        kind = "a folder" if stat.S_ISDIR(mode) else "not a regular file (a pipe or a device)"
        raise VolumeEVMError(f"{path}: is {kind}, not a VolumeEVM file")


def _member_headers(archive, path):
    """``{name: (shape, nbytes)}`` of the members, from the ZIP directory and the ``.npy``
    headers alone, after checking them against each other (nothing of the data is read)."""
    names = collections.Counter(info.filename for info in archive.infolist())
    if "format.npy" not in names:
        listed = ", ".join(sorted(names)[:5]) + (", ..." if len(names) > 5 else "") or "nothing"
        raise VolumeEVMError(f"{path}: not a VolumeEVM file (it holds {listed})")
    expected = collections.Counter(f"{name}.npy" for name in MEMBERS)
    if names != expected:
        missing = sorted(expected - names)
        other = sorted(names - expected)
        raise _unreadable(path, f"members {sorted(expected)} expected; missing {missing}, "
                                f"unexpected or repeated {other[:5]}")
    headers = {}
    for info in archive.infolist():
        name = info.filename[:-len(".npy")]
        if info.flag_bits & 0x1:
            raise _unreadable(path, f"member '{name}' is encrypted")
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise _unreadable(path, f"member '{name}' uses compression method "
                                    f"{info.compress_type}; only stored and deflated members are "
                                    f"read")
        _check_sizes(info, name, path)
        with archive.open(info) as member:
            shape, dtype = _npy_header(member, name, path)
            data_bytes = info.file_size - member.tell()
        nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
        if nbytes != data_bytes:
            raise _unreadable(path, f"member '{name}' declares an array of shape {shape} and dtype "
                                    f"{dtype} ({nbytes} bytes) but holds {data_bytes} bytes of "
                                    f"data")
        headers[name] = (shape, nbytes)
    return headers


def _check_sizes(info, name, path):
    """Refuse a member whose compressed and declared sizes cannot belong together."""
    size, packed = info.file_size, info.compress_size
    if info.compress_type == zipfile.ZIP_STORED and packed != size:
        problem = "a stored member's two sizes must be equal"
    elif size > packed * DEFLATE_MAX_RATIO:
        problem = "deflate cannot expand so few bytes that much"
    elif packed > size * DEFLATE_MAX_GROWTH + 1024:
        problem = "it holds more than it declares and would inflate beyond its declared size"
    else:
        return
    raise _unreadable(path, f"member '{name}' declares {size} bytes but holds {packed} "
                            f"compressed bytes; {problem}")


def _npy_header(member, name, path):
    """``(shape, dtype)`` from a member's ``.npy`` header, checked against :data:`MEMBERS`.

    The header is parsed here, strictly (``ast.literal_eval`` of the header dict, nothing else):
    NumPy's own parser falls back to Python 2 era rewriting with warnings, and wraps a huge
    string length round instead of refusing it.
    """
    version = npy_format.read_magic(member)
    if version not in ((1, 0), (2, 0)):
        raise _unreadable(path, f"member '{name}' has .npy version {version}; 1.0 and 2.0 are read")
    length_format = "<H" if version == (1, 0) else "<I"
    (length,) = struct.unpack(length_format, member.read(struct.calcsize(length_format)))
    if length > MAX_HEADER_BYTES:
        raise _unreadable(path, f"member '{name}' has a .npy header of {length} bytes, at most "
                                f"{MAX_HEADER_BYTES} are read")
    header = ast.literal_eval(member.read(length).decode("latin1"))
    if (not isinstance(header, dict) or header.keys() != {"descr", "fortran_order", "shape"}
            or type(header["fortran_order"]) is not bool or not isinstance(header["shape"], tuple)
            or not all(type(n) is int for n in header["shape"])):
        raise _unreadable(path, f"member '{name}' has a malformed .npy header {_shown(header)}")
    descr, shape = header["descr"], header["shape"]
    kinds, ndim = MEMBERS[name]
    dtype = _simple_dtype(descr)
    if dtype is None:
        raise _unreadable(path, f"member '{name}' has an unsupported dtype {_shown(descr)}, "
                                f"expected {_KIND_WORDS[kinds]}")
    if dtype.hasobject:
        raise _unreadable(path, f"member '{name}' holds Python objects (dtype {dtype}), which are "
                                f"never unpickled")
    if dtype.kind not in kinds or dtype.itemsize == 0:
        raise _unreadable(path, f"member '{name}' has dtype {dtype}, expected "
                                f"{_KIND_WORDS[kinds]}")
    if len(shape) != ndim or any(n < 0 for n in shape) or (name == "vertices" and shape[1] != 3):
        expected = {"vertices": "(n, 3)", "table": "(n,)"}.get(name, "() (a single value)")
        raise _unreadable(path, f"member '{name}' has shape {shape}, expected {expected}")
    return shape, dtype


def _simple_dtype(descr):
    """The dtype of a ``.npy`` ``descr`` naming one plain type exactly as NumPy writes it (such as
    ``'<i2'``, ``'|u1'``, ``'<f4'``, ``'<U9'``, ``'|O'``), or ``None``."""
    if not isinstance(descr, str) or not _SIMPLE_DESCR.fullmatch(descr):
        return None
    try:
        dtype = np.dtype(descr)
    except TypeError:
        return None
    return dtype if npy_format.dtype_to_descr(dtype) == descr else None


def _check_meta(text, path):
    """The metadata JSON with every key checked; the geometry by :func:`~._volume.checked_geometry`
    (the same rules as for a new VolumeEVM), as Python numbers and a (3, 3) orientation."""
    try:
        meta = json.loads(text, parse_constant=_refuse_constant)
    except (ValueError, RecursionError) as error:
        raise _corrupt(path, f"the metadata is not valid JSON ({error})") from error
    if not isinstance(meta, dict):
        raise _corrupt(path, f"the metadata is a JSON {type(meta).__name__}, not an object")
    if meta.keys() != META_KEYS:
        raise _corrupt(path, f"metadata keys missing {sorted(META_KEYS - meta.keys())}, "
                             f"unexpected {sorted(meta.keys() - META_KEYS)[:5]}")
    shape = meta["shape"]
    if not (isinstance(shape, list) and len(shape) == 3
            and all(type(n) is int and 0 < n < _sweep.LIMIT for n in shape)):
        raise _corrupt(path, f"shape {_shown(shape)} must be 3 integers from 1 to "
                             f"{_sweep.LIMIT - 1}")
    spacing, origin, orientation = checked_geometry(meta["spacing"], meta["origin"],
                                                    meta["orientation"], source=str(path))
    if not isinstance(meta["units"], str):
        raise _corrupt(path, f"units {_shown(meta['units'])} must be a string")
    for key in ("threshold", "upper"):
        value = meta[key]
        if value is not None and (type(value) not in (int, float)
                                  or not abs(value) <= sys.float_info.max):
            raise _corrupt(path, f"{key} {_shown(value)} must be a finite number or null")
    if (meta["threshold"] is not None and meta["upper"] is not None
            and meta["upper"] < meta["threshold"]):
        raise _corrupt(path, f"upper {meta['upper']} is below threshold {meta['threshold']}")
    voxels = meta["voxels"]
    if type(voxels) is not int or voxels < 0:
        raise _corrupt(path, f"voxels {_shown(voxels)} must be a non-negative integer")
    for key in ("vertices_sha256", "table_sha256"):
        if not isinstance(meta[key], str):
            raise _corrupt(path, f"{key} {_shown(meta[key])} must be a string")
    return {**meta, "shape": tuple(shape), "spacing": spacing, "origin": origin,
            "orientation": orientation,
            **{key: None if meta[key] is None else float(meta[key])
               for key in ("threshold", "upper")}}


def _shown(value):
    """``repr(value)`` cut to a length that fits a message."""
    text = repr(value)
    return text if len(text) <= 80 else f"{text[:77]}..."


def _refuse_constant(name):
    raise ValueError(f"{name} is not a number")


def _check_region(vertices, shape, path):
    """The EVM of ``vertices`` after checking that they bound a region inside ``shape``."""
    if len(vertices):
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        if min(int(v) for v in lo) < 0 or any(int(h) > s for h, s in zip(hi, shape)):
            raise _corrupt(path, f"vertices span {lo.tolist()} .. {hi.tolist()}, outside the grid "
                                 f"[0, 0, 0] .. {list(shape)}")
    for axis, others in (("x", [1, 2]), ("y", [0, 2]), ("z", [0, 1])):
        odd = _sweep.parity(_sweep.pack(vertices[:, others])).size
        if odd:
            raise _corrupt(path, f"an odd number of vertices on {odd} line(s) along {axis}: they "
                                 f"are not the vertices of a region")
    try:
        return EVM(vertices)
    except ValueError as error:
        raise _corrupt(path, str(error)) from error


def _unreadable(path, what):
    return VolumeEVMError(f"{path}: not a readable VolumeEVM file ({what})")


def _corrupt(path, what):
    return VolumeEVMError(f"{path}: corrupt VolumeEVM file: {what}")
