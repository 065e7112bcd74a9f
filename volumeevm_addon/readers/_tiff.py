"""TIFF page stacks (``.tif``, ``.tiff``) via tifffile: one grey page per z slice.

tifffile returns the first image series as ``(Z, Y, X)`` (pages, rows, columns); reversing the
axes gives ``[x, y, z]``. Only a grey 3-D stack is accepted: colour samples, channels or more
than one non-image axis are refused rather than guessed.

Spacing comes from the microscopy metadata when there is some, converted to mm:

- ImageJ: x and y from the ``XResolution`` / ``YResolution`` tags (pixels per ``unit``), z from
  ``spacing`` (ImageJ omits it when it is 1), the unit from ``unit`` in the ImageJ description;
- OME-TIFF: ``PhysicalSizeX/Y/Z`` of the first ``Pixels`` element, with their ``...Unit``
  attributes (OME's default is micrometres). A file named ``.ome.tif`` or ``.ome.tiff`` must
  hold OME-XML.

Otherwise the spacing is unknown (TIFF resolution tags alone are usually a print DPI). TIFF has
no patient frame: orientation is the identity and the origin zero.

TIFF has no checksum, so the reader checks that the file's structure is consistent before it
trusts the pixels: every page of the file belongs to the stack and has the same size, type and
compression; every page's pixel data lies inside the file, without overlapping another page's
data or the directories and tag values; uncompressed pages hold exactly the bytes their size
needs; the ImageJ description is plain ASCII text; its ``images=`` count and the OME
``SizeX/Y/Z/C/T`` and ``Type`` match the pages found; resolutions, ImageJ ``spacing`` and OME
physical sizes are positive finite numbers; and the decoded stack fits in the memory available. Any
damage tifffile reports while reading (a broken page chain, missing OME frames it would fill with
zeros, invalid metadata it would ignore) is an error too, not a warning.
"""

import logging
import math
import xml.etree.ElementTree as ET
from contextlib import contextmanager
from pathlib import Path

from .._errors import VolumeEVMError
from .._memory import check_memory
from ._checks import (
    UNKNOWN_LENGTH_UNITS,
    check_ndim,
    checked_volume,
    import_reader_package,
    mm_per_unit,
    require_regular_file,
)

#: TIFF compression code of uncompressed data.
_UNCOMPRESSED = 1
#: Attributes of an OME ``Pixels`` element (schemas 2010-06 to 2016-06): a misspelt one is a
#: corrupt header (a damaged ``PhysicalSizeX`` would otherwise read as "no spacing given").
_OME_PIXELS_ATTRIBUTES = frozenset(
    ["ID", "DimensionOrder", "Type", "SignificantBits", "Interleaved", "BigEndian",
     "SizeX", "SizeY", "SizeZ", "SizeC", "SizeT", "TimeIncrement", "TimeIncrementUnit",
     "WaveStart", "WaveIncrement"]
    + [f"PhysicalSize{axis}{unit}" for axis in "XYZ" for unit in ("", "Unit")]
)
#: OME pixel types whose NumPy name differs (the others are spelt alike: "uint16", "int8").
_OME_TYPES = {"float": "float32", "double": "float64"}


def read_tiff(path):
    """Read a grey 3-D TIFF page stack.

    Parameters
    ----------
    path : str or Path
        The ``.tif`` / ``.tiff`` file (ImageJ, OME or plain multi-page).

    Returns
    -------
    Volume
        ``(X, Y, Z)`` array; spacing from ImageJ or OME metadata, else 1 mm with
        ``spacing_known=False``.

    Raises
    ------
    VolumeEVMError
        If tifffile is missing, the file is not a readable regular TIFF file, its structure or
        metadata is inconsistent (see the module notes), the first series is not a grey 3-D
        stack holding every page, its metadata holds an unknown length unit or a non-positive
        size, or the stack would not fit in memory.
    """
    tifffile = import_reader_package("tifffile", "tifffile", path)
    require_regular_file(Path(path))
    try:
        with _damage_reports(tifffile) as damage, tifffile.TiffFile(str(path)) as tif:
            _check_pages(tif, path)
            if not tif.series:
                raise VolumeEVMError(f"{path}: not a readable TIFF file (no image in it)")
            series = tif.series[0]
            _check_damage(damage, path)
            if "S" in series.axes or "C" in series.axes:
                raise VolumeEVMError(
                    f"{path}: the TIFF holds colour samples or channels (axes "
                    f"{series.axes!r}, shape {series.shape}); a grey z stack is needed"
                )
            check_ndim(series.shape, path)
            _check_series_covers_file(tif, series, path)
            float_mask = series.size if series.dtype.kind == "f" else 0
            check_memory(  # the stack, its transposed copy, a mask if float, pages decoding
                2 * series.nbytes + float_mask + 2 * series.keyframe.nbytes,
                f"reading a {'x'.join(map(str, series.shape[::-1]))} {series.dtype} TIFF stack",
                source=str(path),
                advice="crop the stack or free memory",
            )
            stack = series.asarray()
            spacing = _imagej_spacing(tif, series, path) or _ome_spacing(tif, series, path)
            _check_damage(damage, path)
    except VolumeEVMError:
        raise
    except Exception as exc:  # a corrupt file can make tifffile fail in any way
        raise VolumeEVMError(
            f"{path}: not a readable TIFF file ({type(exc).__name__}: {exc})"
        ) from exc
    return checked_volume(stack.transpose(), path, spacing=spacing)


@contextmanager
def _damage_reports(tifffile):
    """Collect the problems tifffile logs (it logs damage and reads on) into a list."""

    class Collect(logging.Handler):
        def emit(self, record):
            found.append(record.getMessage())

    found = []
    handler = Collect(logging.WARNING)
    logger = tifffile.logger()
    level = logger.level
    if logger.getEffectiveLevel() > logging.WARNING:  # a quieter setting must not hide damage
        logger.setLevel(logging.WARNING)
    logger.addHandler(handler)
    try:
        yield found
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def _check_damage(damage, path):
    """Refuse the file when tifffile reported damage while parsing or decoding it."""
    if damage:
        raise VolumeEVMError(f"{path}: the TIFF file is damaged or inconsistent: {damage[0]}")


def _check_pages(tif, path):
    """Every page alike, and the pages' data, directories and tag values laid out sanely.

    Pages are read in full here (tifffile otherwise reads only the first page of an ImageJ or
    OME stack and assumes the others are alike).
    """
    tif.pages.useframes = False
    pages = list(tif.pages)
    if not pages:
        return
    file_size = tif.filehandle.size
    layout = []  # (start, end, what, shareable)
    first = pages[0]
    for index, page in enumerate(pages):
        kind = (page.shape, page.dtype, page.compression, page.predictor, page.planarconfig,
                page.photometric)
        if kind != (first.shape, first.dtype, first.compression, first.predictor,
                    first.planarconfig, first.photometric):
            raise VolumeEVMError(
                f"{path}: page {index} differs from page 0 (shape {page.shape} {page.dtype}, "
                f"compression {page.compression} against {first.shape} {first.dtype}, "
                f"compression {first.compression}); the pages do not form one stack"
            )
        tiff = tif.tiff
        directory = tiff.tagnosize + len(page.tags) * tiff.tagsize + tiff.offsetsize
        layout.append((page.offset, page.offset + directory, f"the directory of page {index}",
                       False))
        for tag in page.tags.values():
            if tag.valuebytecount > tiff.tagoffsetthreshold:
                layout.append((tag.valueoffset, tag.valueoffset + tag.valuebytecount,
                               f"tag {tag.name} of page {index}", True))
        counts = [int(count) for count in page.databytecounts]
        for offset, count in zip(page.dataoffsets, counts):
            if count:
                layout.append((int(offset), int(offset) + count,
                               f"the pixel data of page {index}", False))
        if page.compression == _UNCOMPRESSED and page.bitspersample % 8 == 0 and (
            sum(counts) != page.nbytes
        ):
            raise VolumeEVMError(
                f"{path}: page {index} is {page.shape} {page.dtype} uncompressed "
                f"({page.nbytes} bytes) but its strips hold {sum(counts)} bytes; the file "
                f"is corrupt"
            )
    layout.sort()
    for start, end, what, _ in layout:
        if end > file_size:
            raise VolumeEVMError(
                f"{path}: {what} lies beyond the end of the file (bytes {start} to {end} of "
                f"{file_size}); the file is truncated or corrupt"
            )
    for before, after in zip(layout, layout[1:]):
        shared = before[3] and after[3] and before[:2] == after[:2]
        if after[0] < before[1] and not shared:
            raise VolumeEVMError(
                f"{path}: {before[2]} and {after[2]} overlap in the file (bytes {after[0]} to "
                f"{min(before[1], after[1])}); the file is corrupt"
            )


def _check_series_covers_file(tif, series, path):
    """The stack read must hold every page of the file, and its data must lie in the file."""
    planes = math.prod(series.shape[:-2])
    if planes == len(tif.pages):
        return
    # ImageJ writes only the first page's directory of a stack larger than 4 GiB: the other
    # slices follow the first one's data contiguously.
    contiguous_end = (series.dataoffset or 0) + series.nbytes
    if (tif.is_imagej and len(tif.pages) == 1 and series.dataoffset is not None
            and contiguous_end <= tif.filehandle.size):
        return
    raise VolumeEVMError(
        f"{path}: the file holds {len(tif.pages)} pages but the first image stack has {planes} "
        f"slices of {series.shape[-1]}x{series.shape[-2]}; a file must hold one stack of "
        f"alike pages (damaged metadata, or several images?)"
    )


def _positive(value, path, what):
    """``value`` as a positive finite float, else an error naming the header field."""
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise VolumeEVMError(f"{path}: {what} is {value!r}, not a number") from exc
    if not (math.isfinite(number) and number > 0):
        raise VolumeEVMError(f"{path}: {what} is {value!r}; it must be a positive size")
    return number


def _imagej_spacing(tif, series, path):
    """Spacing in mm from ImageJ metadata, or ``None`` if it gives no physical unit."""
    meta = tif.imagej_metadata
    if not meta:
        return None
    text = tif.pages[0].imagej_description or ""
    odd = next((c for c in text if not (c == "\n" or " " <= c <= "~")), None)
    if odd is not None:  # ImageJ writes plain ASCII lines (it escapes the micro sign)
        raise VolumeEVMError(
            f"{path}: the ImageJ description holds a non-ASCII or control character "
            f"({odd!r}), which ImageJ never writes; the metadata is corrupt"
        )
    if "images" in meta and str(meta["images"]) != str(series.shape[0]):
        raise VolumeEVMError(
            f"{path}: the ImageJ description says images={meta['images']} but the file holds "
            f"{series.shape[0]} slices; the file is truncated or its metadata corrupt"
        )
    if str(meta.get("unit", "pixel")).lower() in UNKNOWN_LENGTH_UNITS:
        return None
    scale = mm_per_unit(meta["unit"], path, "the ImageJ 'unit'")
    per_unit = []
    for name in ("XResolution", "YResolution"):
        tag = tif.pages[0].tags.get(name)
        if tag is None:
            raise VolumeEVMError(
                f"{path}: the ImageJ unit is {meta['unit']!r} but the file has no {name}; the "
                f"pixel size is unknown"
            )
        numerator, denominator = tag.value
        if numerator <= 0 or denominator <= 0:
            raise VolumeEVMError(
                f"{path}: {name} is {numerator}/{denominator} pixels per "
                f"{meta['unit']}; both numbers must be positive"
            )
        per_unit.append(numerator / denominator)
    z = _positive(meta.get("spacing", 1.0), path, "the ImageJ 'spacing'")
    return (scale / per_unit[0], scale / per_unit[1], scale * z)


def _ome_spacing(tif, series, path):
    """Spacing in mm from OME-XML ``PhysicalSize*``, or ``None`` if not all three are given.

    Also checks that the first ``Pixels`` element's attributes are OME's and that its sizes and
    type describe the stack read.
    """
    if not tif.is_ome:
        if Path(path).name.lower().endswith((".ome.tif", ".ome.tiff")):
            raise VolumeEVMError(
                f"{path}: the name says OME-TIFF but the file holds no OME-XML metadata (its "
                f"description is missing or damaged); the spacing cannot be read"
            )
        return None
    root = ET.fromstring(tif.ome_metadata)
    pixels = next((el for el in root.iter() if el.tag.endswith("}Pixels")), None)
    if pixels is None:
        return None
    unknown = sorted(name for name in pixels.keys()
                     if name not in _OME_PIXELS_ATTRIBUTES and not name.startswith("{"))
    if unknown:
        raise VolumeEVMError(
            f"{path}: the OME Pixels element has attributes the OME schema does not define "
            f"({', '.join(map(repr, unknown))}); the metadata is corrupt"
        )
    expected = {"SizeX": series.shape[2], "SizeY": series.shape[1], "SizeZ": series.shape[0],
                "SizeC": 1, "SizeT": 1}
    for name, size in expected.items():
        value = pixels.get(name, "1")
        if value.strip() != str(size):
            raise VolumeEVMError(
                f"{path}: the OME metadata says {name}={value!r} but the file holds a "
                f"{'x'.join(map(str, series.shape[::-1]))} grey stack; metadata and pages "
                f"disagree"
            )
    pixel_type = pixels.get("Type", "")
    if _OME_TYPES.get(pixel_type, pixel_type) != series.dtype.name:
        raise VolumeEVMError(
            f"{path}: the OME metadata says Type={pixel_type!r} but the pages hold "
            f"{series.dtype.name}; metadata and pages disagree"
        )
    sizes = []
    for axis in "XYZ":
        size = pixels.get(f"PhysicalSize{axis}")
        if size is None:
            return None
        unit = pixels.get(f"PhysicalSize{axis}Unit", "µm")
        value = _positive(size, path, f"the OME PhysicalSize{axis}")
        sizes.append(value * mm_per_unit(unit, path, f"OME PhysicalSize{axis}Unit"))
    return tuple(sizes)
