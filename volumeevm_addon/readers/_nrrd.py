"""NRRD volumes (``.nrrd``, and ``.nhdr`` with a detached data file): the header parsed strictly,
its fields by pynrrd, the data read here.

The header is read line by line up to the blank line that ends it and refused, before pynrrd
parses it, when a line holds bytes that are not ASCII or names a field the NRRD format does not
define (Teem, the reference implementation, refuses both): a misspelt ``space origin`` would
otherwise be kept as a custom field and the origin silently taken as 0. Key/value pairs
(``key:=value``) may carry any key. pynrrd then parses the values; ``dimension``, ``type``,
``sizes`` and ``encoding`` are required, and ``endian`` for multi-byte samples.

The data (raw, gzip, bzip2 or ASCII encoding, attached or in the one ``data file`` of a
``.nhdr``, after ``line skip`` lines and ``byte skip`` bytes) must hold exactly the samples the
sizes and type announce: a raw file of another length, a compressed stream that inflates to
another size (it is never inflated past the announced size) or fails its checksum, and an ASCII
section with another count of numbers are refused. The first NRRD axis is the fastest in the
file, so the array is indexed ``[x, y, z]``. ``lazy=True`` maps raw data read-only after the
same checks (:func:`._checks.lazy_mapped`); compressed and ASCII data can only be read whole.

Geometry: the NRRD ``space directions`` give one vector per axis (voxel step in ``space``
coordinates, its length is the spacing) and ``space origin`` is the centre of the first voxel.
Patient spaces are converted to LPS by flipping the axes the space names opposite ways
(RAS flips x and y, LAS flips y). Spaces without a patient frame (``scanner-xyz``,
``3D-right-handed``) are taken as they are. Without ``space directions`` the per-axis
``spacings`` field (Teem writes it for files without a space) is used with the per-axis
``units``, and without either the spacing is unknown. ``space units`` (or ``units``) other than
millimetres are converted to millimetres, in the spellings tools write ("microns" from Fiji);
"pixel" (Fiji's uncalibrated images) means the spacing is unknown.

Axis kinds: every axis whose ``kinds`` entry is not spatial (``domain``, ``space``, or none
given) is refused: a colour, vector or list component, time or complex parts would otherwise be
read as a grey volume whose first axis is the colour channel. The one exception is a 3D Slicer
segmentation whose overlapping segments sit in layers: ``dimension: 4``, ``kinds: list domain
domain domain``, the first axis the layer.

Data units: the NRRD ``sample units`` field ("HU" and its spellings), else "" (the format has no
other field for it; Slicer writes none).
"""

import bz2
import dataclasses
import difflib
import gzip
import math
import os
import warnings
from pathlib import Path

import numpy as np

from .._errors import VolumeEVMError
from .._memory import check_memory
from ..model._label_table import LabelInfo, default_label_info, slicer_segments
from ..model._labels import checked_labels, labels_present
from ._checks import (
    UNKNOWN_LENGTH_UNITS,
    check_ndim,
    check_read_memory,
    checked_volume,
    data_units,
    import_reader_package,
    lazy_mapped,
    mm_per_unit,
    open_file,
    read_payload,
    require_regular_file,
)
from ._labels import label_map

#: Sign per space axis that maps a NRRD space to LPS.
_TO_LPS = {
    "left-posterior-superior": (1.0, 1.0, 1.0),
    "lps": (1.0, 1.0, 1.0),
    "right-anterior-superior": (-1.0, -1.0, 1.0),
    "ras": (-1.0, -1.0, 1.0),
    "left-anterior-superior": (1.0, -1.0, 1.0),
    "las": (1.0, -1.0, 1.0),
    "scanner-xyz": (1.0, 1.0, 1.0),
    "3d-right-handed": (1.0, 1.0, 1.0),
}

#: Field names the NRRD format defines (NRRD0005, with the spellings Teem accepts).
_FIELDS = frozenset([
    "dimension", "type", "sizes", "endian", "encoding", "content", "min", "max", "old min",
    "oldmin", "old max", "oldmax", "spacings", "thicknesses", "axis mins", "axismins",
    "axis maxs", "axismaxs", "centers", "centerings", "labels", "units", "kinds", "space",
    "space dimension", "space units", "space origin", "space directions", "measurement frame",
    "sample units", "data file", "datafile", "line skip", "lineskip", "byte skip", "byteskip",
    "block size", "blocksize", "number",
])

#: NRRD sample types (every spelling the format allows) as NumPy type codes.
_TYPES = {
    **dict.fromkeys(["signed char", "int8", "int8_t"], "i1"),
    **dict.fromkeys(["uchar", "unsigned char", "uint8", "uint8_t"], "u1"),
    **dict.fromkeys(["short", "short int", "signed short", "signed short int", "int16",
                     "int16_t"], "i2"),
    **dict.fromkeys(["ushort", "unsigned short", "unsigned short int", "uint16", "uint16_t"],
                    "u2"),
    **dict.fromkeys(["int", "signed int", "int32", "int32_t"], "i4"),
    **dict.fromkeys(["uint", "unsigned int", "uint32", "uint32_t"], "u4"),
    **dict.fromkeys(["longlong", "long long", "long long int", "signed long long",
                     "signed long long int", "int64", "int64_t"], "i8"),
    **dict.fromkeys(["ulonglong", "unsigned long long", "unsigned long long int", "uint64",
                     "uint64_t"], "u8"),
    "float": "f4",
    "double": "f8",
}

#: Axis kinds of a spatial axis ("???" and "none" say nothing, which pynrrd and Teem allow).
_SPATIAL_KINDS = frozenset(["domain", "space", "none", "???"])

#: Encodings and the opener of the decompressing reader each needs (``None``: plain bytes).
_ENCODINGS = {"raw": None, "gzip": gzip.open, "gz": gzip.open, "bzip2": bz2.open, "bz2": bz2.open,
              "ascii": None, "text": None, "txt": None}

#: Longest header (and longest skipped line) accepted: far beyond any real one, and a bound on
#: what a file with no blank line after its header makes the reader hold.
_MAX_HEADER_BYTES = 1 << 20

#: Python bytes per number while an ASCII data section is parsed (a str object per token).
_ASCII_BYTES_PER_VALUE = 64


def read_nrrd(path, lazy=False):
    """Read a 3-D scalar NRRD file (a 3D Slicer ``.seg.nrrd`` as a label map with its segments'
    names and colours; a segmentation in several layers with every segment a label of its own,
    ``layers`` holding each layer, see :func:`_layered_segmentation`).

    Parameters
    ----------
    path : str or Path
        The ``.nrrd`` file or ``.nhdr`` header.
    lazy : bool
        Map raw-encoded data read-only and return its array as a lazy Dask array (nothing is
        read until a chunk is computed).

    Returns
    -------
    Volume
        Orientation columns and origin in LPS from ``space directions`` / ``space origin``;
        identity orientation and zero origin when the header has no space.

    Raises
    ------
    VolumeEVMError
        If pynrrd is missing, the header is not strict NRRD (non-ASCII bytes, an unknown or
        misspelt field, a value that does not parse, a required field missing), the data does
        not hold exactly what the header announces (truncated, padded, a corrupt compressed
        stream), the space is not 3-D or not one listed above, the data is not a 3-D scalar
        grid, it would not fit in memory, or ``lazy`` is asked of data that is not raw or of a
        segmentation in layers.
    """
    nrrd = import_reader_package("nrrd", "pynrrd", path)
    path = Path(path)
    with open_file(path) as f:
        header = _parse_header(nrrd, _header_lines(f, path), path)
        segments = slicer_segments(header, path)
        layered = bool(segments) and _is_layered(header)
        sizes, dtype, encoding = _layout(header, path, layered)
        if lazy and (layered or encoding != "raw"):
            what = "a segmentation in layers" if layered else f"{encoding}-encoded data"
            raise VolumeEVMError(f"{path}: lazy=True needs raw data in one layer, this file holds "
                                 f"{what} (read whole); read it without lazy")
        data_file = _data_file(header, path)
        if data_file is None:
            data = _read_data(f, header, sizes, dtype, encoding, path, str(path), lazy)
        else:
            require_regular_file(data_file)
            with open_file(data_file) as g:
                data = _read_data(g, header, sizes, dtype, encoding, path,
                                  f"{path}: data file {data_file}", lazy)
    if layered:
        header = {**header, "space directions": np.asarray(header["space directions"])[1:]}
    spacing, origin, orientation = _geometry(header, path)
    if layered:
        return _layered_segmentation(data, segments, path, spacing=spacing, origin=origin,
                                     orientation=orientation)
    volume = checked_volume(data, path, spacing=spacing, origin=origin, orientation=orientation,
                            units=data_units(header.get("sample units", "")))
    if not segments:
        return volume
    table = {s["value"]: LabelInfo(s["name"], s["color"]) for s in segments}
    return label_map(volume, table)


def _is_layered(header):
    """Whether a Slicer segmentation's data has a first axis of layers (``dimension: 4``,
    ``kinds: list domain domain domain``)."""
    kinds = [str(kind).lower() for kind in header.get("kinds", [])]
    return header.get("dimension") == 4 and len(kinds) == 4 and kinds[0] == "list"


def _layered_segmentation(data, segments, path, **geometry):
    """A Slicer segmentation in layers as a label map with one label per segment.

    ``data`` is ``(layers, X, Y, Z)``. Layer 0 keeps its label values; each later layer's values
    are moved past the highest value of the layers before it (in the header or the data), so
    every segment gets a label of its own: ``Volume.layers`` holds each layer so renumbered (the
    segments exactly, overlaps and all) and ``array`` their overlay, a later layer over an
    earlier one, for views that take one label per voxel. A segment with no voxels in its layer,
    and a value in a layer that no segment describes, are reported in a warning.
    """
    count = data.shape[0]
    beyond = sorted({s["name"] for s in segments if s["layer"] >= count})
    if beyond:
        raise VolumeEVMError(f"{path}: segments {beyond} are in layers the data does not have "
                             f"(it has {count})")
    layers = [checked_labels(data[k], f"{path}: layer {k}") for k in range(count)]
    present = [set(labels_present(layer).tolist()) for layer in layers]
    offsets, top = [], 0
    for k, layer in enumerate(layers):
        offsets.append(top)
        top += max([s["value"] for s in segments if s["layer"] == k] + [int(layer.max())])
    dtype = np.dtype(np.uint8 if top < 1 << 8 else np.uint16 if top < 1 << 16 else np.uint32)
    check_memory((count + 2) * layers[0].size * dtype.itemsize, "reading the segmentation's layers",
                 source=str(path))
    empty = [f"{s['name']!r} (layer {s['layer']}, label value {s['value']})"
             for s in segments if s["value"] not in present[s["layer"]]]
    if empty:
        warnings.warn(f"{path}: segments {', '.join(empty)} have no voxels in the data",
                      UserWarning, stacklevel=3)
    labels = {}
    for k in range(count):
        described = {s["value"]: s for s in segments if s["layer"] == k}
        unnamed = sorted(present[k] - set(described))
        if unnamed:
            warnings.warn(f"{path}: layer {k} holds label values {unnamed} that no segment "
                          f"describes; they get labels {[v + offsets[k] for v in unnamed]} with "
                          f"the default names and colours", UserWarning, stacklevel=3)
        for value in sorted(present[k]):
            s = described.get(value)
            labels[value + offsets[k]] = (LabelInfo(s["name"], s["color"]) if s
                                          else default_label_info(value + offsets[k]))
    shifted = []
    for k, layer in enumerate(layers):
        moved = layer.astype(dtype)
        moved[moved > 0] += dtype.type(offsets[k])
        shifted.append(moved)
    overlay = shifted[0].copy()
    for layer in shifted[1:]:
        np.copyto(overlay, layer, where=layer > 0)
    volume = checked_volume(overlay, path, **geometry)
    return dataclasses.replace(volume, labels=dict(sorted(labels.items())), layers=tuple(shifted))


def _header_lines(f, path):
    """The header's lines (magic line first) as text, up to the blank line or the end of file."""
    if not f.readline(16).startswith(b"NRRD"):
        raise VolumeEVMError(
            f"{path}: corrupt NRRD file (not a NRRD file: it does not start with 'NRRD000x')"
        )
    f.seek(0)
    lines = []
    total = 0
    while True:
        line = f.readline(_MAX_HEADER_BYTES + 1 - total)
        total += len(line)
        if total > _MAX_HEADER_BYTES:
            raise VolumeEVMError(
                f"{path}: corrupt NRRD file (no blank line ends the header within "
                f"{_MAX_HEADER_BYTES} bytes)"
            )
        if not line.isascii():
            raise VolumeEVMError(
                f"{path}: corrupt NRRD file (header line {len(lines) + 1} holds bytes that are "
                f"not ASCII: {line!r})"
            )
        text = line.decode("ascii")
        if not text.strip():  # a blank line (or the end of a detached header) ends it
            return lines
        lines.append(text)


def _parse_header(nrrd, lines, path):
    """pynrrd's header dict, after refusing fields the format does not define."""
    for number, line in enumerate(lines[1:], start=2):
        if line.startswith("#"):
            continue
        name, colon, rest = line.partition(":")
        if not colon:
            raise VolumeEVMError(
                f"{path}: corrupt NRRD file (header line {number} {line.strip()!r} is not "
                f"'field: value')"
            )
        if rest.startswith("="):  # key:=value pairs may use any key
            continue
        if name.strip() not in _FIELDS:
            close = difflib.get_close_matches(name.strip(), _FIELDS, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise VolumeEVMError(
                f"{path}: corrupt NRRD file (header line {number} has the unknown field "
                f"{name.strip()!r}{hint})"
            )
    try:
        return nrrd.read_header(lines)
    except Exception as exc:  # pynrrd reports a bad value in several exception types
        raise VolumeEVMError(
            f"{path}: corrupt NRRD file ({type(exc).__name__}: {exc})"
        ) from exc


def _layout(header, path, layered=False):
    """Sizes (3 Python ints, 4 with a segmentation's layers first), sample dtype and encoding,
    checked."""
    for field in ("dimension", "type", "sizes", "encoding"):
        if field not in header:
            raise VolumeEVMError(f"{path}: corrupt NRRD file (required field '{field}' missing)")
    sizes = tuple(int(n) for n in np.atleast_1d(header["sizes"]))
    if header["dimension"] != len(sizes) or min(sizes) < 1:
        raise VolumeEVMError(
            f"{path}: corrupt NRRD file (sizes {list(sizes)} are not {header['dimension']} "
            f"positive numbers as 'dimension' says)"
        )
    _check_kinds(header, path, layered)
    check_ndim(sizes[1:] if layered else sizes, path)
    if header["type"] not in _TYPES:
        raise VolumeEVMError(
            f"{path}: corrupt NRRD file (type {header['type']!r} is not a NRRD scalar type "
            f"VolumeEVM reads; known: {', '.join(sorted(set(_TYPES)))})"
        )
    encoding = header["encoding"].lower()
    if encoding not in _ENCODINGS:
        raise VolumeEVMError(
            f"{path}: corrupt NRRD file (encoding {header['encoding']!r} is not one VolumeEVM "
            f"reads: {', '.join(_ENCODINGS)})"
        )
    dtype = np.dtype(_TYPES[header["type"]])
    if dtype.itemsize > 1 and encoding not in ("ascii", "text", "txt"):
        endian = {"little": "<", "big": ">"}.get(header.get("endian"))
        if endian is None:
            raise VolumeEVMError(
                f"{path}: corrupt NRRD file ('endian' is {header.get('endian')!r}; "
                f"'little' or 'big' is required for {header['type']} samples)"
            )
        dtype = dtype.newbyteorder(endian)
    return sizes, dtype, encoding


def _check_kinds(header, path, layered=False):
    """Refuse axes that are not spatial (``kinds``: colour, vector, list, time, complex...),
    but a segmentation's first axis of layers."""
    kinds = header.get("kinds")
    if kinds is None:
        return
    kinds = [str(kind) for kind in kinds]
    if len(kinds) != header["dimension"]:
        raise VolumeEVMError(
            f"{path}: corrupt NRRD file ('kinds' gives {len(kinds)} kinds for "
            f"{header['dimension']} axes)"
        )
    odd = [(axis, kind) for axis, kind in enumerate(kinds)
           if kind.lower() not in _SPATIAL_KINDS and not (layered and axis == 0)]
    if odd:
        axis, kind = odd[0]
        raise VolumeEVMError(
            f"{path}: axis {axis} of the NRRD data is of kind {kind!r} (kinds: {' '.join(kinds)}),"
            f" not a spatial axis; a volume needs 3 spatial axes (domain or space): colour, "
            f"vector, list, time and complex axes are not read as grey levels"
        )


def _data_file(header, path):
    """The detached data file named by the header, or ``None`` when the data is attached."""
    name = header.get("data file", header.get("datafile"))
    if name is None:
        return None
    if name == "LIST" or len(name.split()) != 1:
        raise VolumeEVMError(
            f"{path}: the data is split over several files ('data file: {name}'); only one "
            f"data file is supported"
        )
    return path.parent / name


def _skips(header, encoding, path):
    """``(line skip, byte skip)`` from the header, checked."""
    line_skip = header.get("line skip", header.get("lineskip", 0))
    byte_skip = header.get("byte skip", header.get("byteskip", 0))
    if line_skip < 0 or byte_skip < -1 or (byte_skip == -1 and encoding != "raw"):
        raise VolumeEVMError(
            f"{path}: corrupt NRRD file (line skip {line_skip} / byte skip {byte_skip}: skips "
            f"are >= 0, and byte skip -1 is for raw data only)"
        )
    return line_skip, byte_skip


def _read_data(f, header, sizes, dtype, encoding, path, where, lazy=False):
    """The samples as an ``(X, Y, Z)`` array, from ``f`` positioned after the header (if any);
    ``lazy``: raw samples as a lazy Dask array over a read-only map of ``f``'s file.

    ``path`` is the file the user opened (the header), ``where`` how messages name the data: the
    header file, and for a detached header also the data file ``f`` reads.
    """
    line_skip, byte_skip = _skips(header, encoding, where)
    for _ in range(line_skip):
        line = f.readline(_MAX_HEADER_BYTES)
        if len(line) == _MAX_HEADER_BYTES and not line.endswith(b"\n"):
            raise VolumeEVMError(f"{where}: 'line skip' passes a line longer than 1 MiB")
    count = math.prod(sizes)
    nbytes = count * dtype.itemsize
    size = os.fstat(f.fileno()).st_size
    if encoding in ("ascii", "text", "txt"):
        check_read_memory(path, sizes, dtype, copies=2,
                          extra=size + _ASCII_BYTES_PER_VALUE * count)
        f.seek(max(byte_skip, 0), os.SEEK_CUR)
        return _parse_ascii(f.read(), count, dtype, where).reshape(sizes[::-1]).T
    if encoding == "raw":
        start = size - nbytes if byte_skip == -1 else f.tell() + byte_skip
        if start < f.tell() or size - start != nbytes:
            held = size - f.tell() - max(byte_skip, 0)
            raise VolumeEVMError(
                f"{where}: corrupt NRRD file (the data holds {held} bytes "
                f"but sizes {list(sizes)} of {dtype.name} need exactly {nbytes}); the file is "
                f"truncated or its header is corrupt"
            )
        if lazy:
            return lazy_mapped(Path(f.name), start, sizes, dtype, fortran_order=True)
        check_read_memory(path, sizes, dtype, copies=2)  # the file's bytes, then C order
        f.seek(start)
        buffer = read_payload(f, nbytes, where, "NRRD raw data")
        skip = 0
    else:
        check_read_memory(path, sizes, dtype, copies=2, extra=byte_skip)
        buffer = read_payload(_ENCODINGS[encoding](f), byte_skip + nbytes, where,
                              f"{encoding}-compressed NRRD data")
        skip = byte_skip
    return np.frombuffer(buffer, dtype, count, skip).reshape(sizes[::-1]).T


def _parse_ascii(content, count, dtype, path):
    """``count`` numbers from an ASCII data section, as a flat array of ``dtype``."""
    if not content.isascii():
        raise VolumeEVMError(f"{path}: corrupt NRRD file (the ASCII data holds other bytes)")
    values = content.decode("ascii").replace(",", " ").split()
    if len(values) != count:
        raise VolumeEVMError(
            f"{path}: corrupt NRRD file (the ASCII data holds {len(values)} numbers but the "
            f"sizes announce {count})"
        )
    try:
        return np.array(values, dtype=dtype)
    except (ValueError, OverflowError) as exc:
        raise VolumeEVMError(f"{path}: corrupt NRRD file (ASCII data: {exc})") from exc


def _geometry(header, path):
    """Spacing (``None`` when unknown), origin and orientation in LPS mm from the header."""
    space = header.get("space")
    sign = np.ones(3)
    if space is not None:
        key = str(space).lower()
        if key not in _TO_LPS:
            raise VolumeEVMError(
                f"{path}: unsupported NRRD space {space!r}; supported: {', '.join(_TO_LPS)}"
            )
        sign = np.asarray(_TO_LPS[key])
    elif header.get("space dimension", 3) != 3:
        raise VolumeEVMError(
            f"{path}: 'space dimension' is {header['space dimension']}; a volume needs 3"
        )
    # Per-axis 'units' give the unit of 'spacings'; 'space directions' are in 'space units'.
    spatial = "space directions" in header or "space units" in header
    field = "space units" if spatial else "units"
    units = header.get(field)
    scale = np.ones(3)
    known = True
    if units is not None:
        if len(units) != 3:
            raise VolumeEVMError(f"{path}: corrupt header: '{field}' {units} is not 3 units")
        known = not any(str(u).strip().lower() in UNKNOWN_LENGTH_UNITS for u in units)
        if known:
            scale = np.array([mm_per_unit(u, path, f"'{field}'") for u in units], dtype=float)

    directions = header.get("space directions")
    if directions is not None:
        directions = np.asarray(directions, dtype=np.float64)
        if directions.shape != (3, 3):
            raise VolumeEVMError(
                f"{path}: 'space directions' has shape {directions.shape}; a 3-D volume in a "
                f"3-D space needs 3 vectors of 3 components"
            )
        steps = directions * scale * sign  # rows: voxel step of each axis in LPS mm
        spacing = np.linalg.norm(steps, axis=1)
        # A zero or non-finite step reaches checked_volume as a corrupt spacing.
        orientation = steps.T / np.where(spacing > 0, spacing, 1.0)
    else:
        spacings = header.get("spacings")
        spacing = None
        if spacings is not None:
            spacings = np.asarray(spacings, dtype=np.float64)
            if spacings.shape != (3,):
                raise VolumeEVMError(
                    f"{path}: corrupt header: 'spacings' {spacings} is not 3 numbers"
                )
            if np.all(np.isfinite(spacings)):  # NaN marks an axis without spacing
                spacing = spacings * scale
        orientation = None
    origin = np.asarray(header.get("space origin", np.zeros(3)), dtype=np.float64)
    if origin.shape != (3,):
        raise VolumeEVMError(f"{path}: corrupt header: 'space origin' {origin} is not 3-D")
    return (spacing if known else None), origin * scale * sign, orientation
