"""DICOM image series (a folder, one file of the series, or a list of files) via pydicom.

A series is the set of images sharing a ``SeriesInstanceUID``; each image gives one slice,
or several:

- an enhanced multi-frame image (Enhanced CT and MR, what current Siemens XA, Philips and GE
  scanners export: ``PerFrameFunctionalGroupsSequence``) gives one slice per frame, with the
  plane position and orientation, pixel measures and rescale of its shared and per-frame
  functional groups (PS3.3 C.7.6.16);
- a Siemens mosaic (``ImageType`` with ``MOSAIC``) gives the slices tiled in it, as many as
  the CSA header's ``NumberOfImagesInMosaic``, placed as nibabel and dcm2niix place them (see
  :func:`_mosaic_headers`); one mosaic file given is read alone, being a whole volume.

The grid is built from the slices' image-plane attributes (DICOM PS3.3 C.7.6.2):

- ``ImageOrientationPatient`` = (row direction, column direction) in LPS: the row direction is
  the way the column index (x) grows, the column direction the way the row index (y) grows;
  the slice normal is their cross product. Both must be unit vectors at right angles (within
  :data:`_DIRECTION_TOLERANCE`, as the decimal strings allow); they are then normalised.
- ``ImagePositionPatient`` is the LPS centre of the first transmitted pixel of each slice.
  Slices are sorted by the projection of that position on the normal (file names and
  ``InstanceNumber`` are not reliable), the origin is the first sorted slice's position and the
  z step is the mean step between consecutive positions. Its direction is normally the normal;
  for a gantry-tilted series it is the actual (oblique) stacking direction, so the grid is
  sheared rather than misplaced. A single slice takes its z spacing from
  ``SpacingBetweenSlices``, else ``SliceThickness``, else 1 mm.
- ``PixelSpacing`` is (between rows, between columns) = (y, x) spacing.
- ``pixel_array`` is ``[row, column]`` = ``[y, x]``; it is transposed into ``[x, y, z]``.

Stored values: the bits above ``BitsStored`` are not assumed zero (PS3.5 8.1.1; Siemens
scanners leave values there): pydicom masks them for unsigned data and sign-extends from
``HighBit`` for signed data, which must be ``BitsStored - 1``. Native pixel data longer than the
image needs reads when the extra bytes are zero padding.

Modality rescale ``RescaleSlope`` / ``RescaleIntercept`` is applied per slice. The result keeps
the stored integer dtype when every slice's rescale is the identity, is ``int16`` (or ``int32``
if the values need it) when slopes and intercepts are integers and the stored pixels are at
most 16-bit, and ``float32`` otherwise. Units: ``RescaleType`` when it names them, else "HU"
for a rescaled CT, else "".

Which files are read. In a folder (sub-folders are not scanned) a regular file is taken as
DICOM when it carries the DICOM marker (``DICM`` after the 128-byte preamble) or its name ends
in ``.dcm`` or ``.dicom``; when a folder is given every such file must be readable, and an
unreadable or truncated one is an error naming it, never skipped (skipping a first or last slice
would shift the volume). Other files (a README, a ``.npy``) are skipped unread, and so are
FIFOs, devices and sockets, which are never opened. A DICOM file without ``SeriesInstanceUID``
is an error unless it is a DICOMDIR, and so is a ``SeriesInstanceUID`` that is not a valid UID
(a corrupt length field makes it swallow the elements that follow). Every file of the chosen
series must be an image slice. Named files (a list, or the one file given) must all be readable
DICOM regular files.

One file given reads the series it belongs to: the other DICOM files of its folder that cannot
be read without the DICOM file marker, have no (valid) series UID or repeat an image
(``SOPInstanceUID``) are skipped and listed in a ``UserWarning``; a broken file with the marker
or in which pydicom still finds the chosen series' UID is an error naming it; a missing slice
is still found from the positions. A chosen file without a series UID is read alone.

Refused with a message rather than guessed: several series in one folder (unless
``series_uid`` picks one), slices of different sizes, pixel formats, orientations or pixel
spacings, two slices at one position (several echoes, time points or stacks), unevenly spaced
slices (missing files), a rescale given in some slices only, a ``RescaleSlope`` of 0 or a
non-finite one, pixel data whose length does not match the frames x ``Rows`` x ``Columns`` x
``BitsAllocated`` (shorter, or longer by more than zero padding), a ``HighBit`` other than
``BitsStored - 1``, multi-frame images without per-frame functional groups, colour images, a
mosaic without its CSA header, and a series whose decoded volume would not fit in the memory
available. pydicom's warnings about the deviations it tolerates are not shown: the checks above
decide what is usable.
"""

import math
import os
import re
import stat
import warnings
from pathlib import Path

import numpy as np

from .._errors import VolumeEVMError
from .._memory import check_memory, format_bytes
from ._checks import checked_volume, data_units, import_reader_package, require_regular_file

#: Largest deviation of a slice step from the mean step, relative to the mean step.
_SPACING_RTOL = 1e-2
#: Tolerance on direction cosines when checking that slices share one orientation.
_ORIENTATION_ATOL = 1e-4
#: Largest accepted deviation of an ``ImageOrientationPatient`` vector's length from 1, and of
#: the cosine between its two vectors from 0 (decimal strings of limited precision).
_DIRECTION_TOLERANCE = 1e-3
#: Name endings that mark a file in a folder as DICOM even without the ``DICM`` marker.
_DICOM_SUFFIXES = (".dcm", ".dicom")
#: SOP class of a DICOMDIR (Media Storage Directory Storage): DICOM, but not part of a series.
_DICOMDIR_CLASS = "1.2.840.10008.1.3.10"
#: A DICOM UID: at most 64 characters, numbers separated by dots (PS3.5 9.1).
_UID = re.compile(r"(?=.{1,64}$)[0-9]+(\.[0-9]+)*")
#: Functional group macros whose attributes an enhanced multi-frame image's frame takes.
_FRAME_MACROS = ("PlanePositionSequence", "PlaneOrientationSequence", "PixelMeasuresSequence",
                 "PixelValueTransformationSequence")
#: Most slices a mosaic may claim: far beyond any scanner's (a corrupt count of millions of
#: one-pixel tiles would otherwise cost a header per tile).
_MAX_MOSAIC_SLICES = 4096
#: Attributes of an enhanced multi-frame image that every frame shares.
_FRAME_IMAGE_KEYWORDS = ("Modality", "Rows", "Columns", "NumberOfFrames", "SamplesPerPixel",
                         "BitsAllocated", "BitsStored", "HighBit", "PixelRepresentation")
#: Transfer syntaxes whose pixel data is stored as is (the bytes needed follow from the header).
_NATIVE_SYNTAXES = ("1.2.840.10008.1.2", "1.2.840.10008.1.2.1", "1.2.840.10008.1.2.2")
_DEFLATED_SYNTAX = "1.2.840.10008.1.2.1.99"


def read_dicom(source, *, series_uid=None):
    """Read one DICOM image series into a volume.

    Parameters
    ----------
    source : str, Path or sequence of str or Path
        A folder (its files are scanned, sub-folders are not; see the module notes for which
        files are read), one file (the series it belongs to is read from its folder), or an
        explicit list of the series' files.
    series_uid : str, optional
        ``SeriesInstanceUID`` of the series to read when the files hold several.

    Returns
    -------
    Volume
        ``(Columns, Rows, slices)`` array; orientation columns (row direction, column
        direction, stacking direction) in LPS; origin = ``ImagePositionPatient`` of the first
        slice along the normal; spacing (x, y, z) in mm; units "HU" for CT.

    Raises
    ------
    VolumeEVMError
        If pydicom is missing, a file that must be read cannot be (the message names it), no
        image series is found, several are found and ``series_uid`` is not given (the message
        lists them), ``series_uid`` is not among them, a slice's header is corrupt, the slices
        do not form one regular grid (see the module notes), a file's pixel data cannot be
        decoded, or the volume would not fit in memory.
    """
    files, label, named = _candidate_files(source)
    explicit = not isinstance(source, (str, os.PathLike))
    pydicom = import_reader_package("pydicom", "pydicom", label)
    name = (lambda path: str(path)) if explicit else (lambda path: path.name)
    if named and not explicit:  # one file: read the series it belongs to
        series, uid = _series_of_file(pydicom, named[0], files, name, label)
        series_uid = uid if series_uid is None else series_uid
    else:
        series = {}
        for path in files:
            if path in named or _marked_as_dicom(path):
                ds = _read_header(pydicom, path)
                series.setdefault(_series_uid(path, ds), []).append((path, ds))
        series.pop(None, None)  # DICOMDIR files
    images = {uid: items for uid, items in series.items() if any("Rows" in ds for _, ds in items)}
    if not images:
        others = [name(path) for items in series.values() for path, _ in items]
        raise VolumeEVMError(
            f"{label}: no DICOM image series found among {len(files)} file(s)"
            + (f"; these DICOM files hold no image (no Rows): {', '.join(others[:5])}"
               if others else "")
        )
    if series_uid is None and len(images) > 1:
        raise VolumeEVMError(
            f"{label}: holds {len(images)} DICOM series; choose one with series_uid=:\n"
            + _describe(images, name)
        )
    uid = series_uid if series_uid is not None else next(iter(images))
    if uid not in images:
        raise VolumeEVMError(
            f"{label}: no series with SeriesInstanceUID {uid!r}; the series found are:\n"
            + _describe(images, name)
        )
    slices = [header for path, ds in images[uid]
              for header in _image_headers(pydicom, path, ds, name(path), label)]
    _check_same(slices, label, "size", "image sizes", lambda s: f"{s['columns']}x{s['rows']}",
                " (columns x rows)")
    _check_same(slices, label, "pixel_format", "pixel formats",
                lambda s: "{} bits allocated, {} stored, {}".format(*s["pixel_format"]))
    order, geometry = _grid_geometry(slices, label)
    slices = [slices[i] for i in order]
    units = _data_units(slices[0])
    slopes, intercepts = _rescale_values(slices, label)
    identity = bool(np.all(slopes == 1) and np.all(intercepts == 0))
    raw = _read_pixels(pydicom, slices, label, identity=identity)
    array = _rescale(raw, slopes, intercepts)
    return checked_volume(array, label, units=units, **geometry)


def _series_uid(path, ds):
    """A file's checked ``SeriesInstanceUID``; ``None`` for a DICOMDIR, which has none."""
    if "SeriesInstanceUID" not in ds:
        if ds.file_meta.get("MediaStorageSOPClassUID") == _DICOMDIR_CLASS:
            return None
        raise VolumeEVMError(
            f"{path}: this DICOM file has no SeriesInstanceUID (corrupt header?); it cannot "
            f"be placed in a series"
        )
    uid = str(ds.SeriesInstanceUID)
    if not _UID.fullmatch(uid):
        raise VolumeEVMError(
            f"{path}: SeriesInstanceUID {uid[:80]!r} is not a valid UID (corrupt header?)"
        )
    return uid


def _series_of_file(pydicom, chosen, files, name, label):
    """``({uid: [(path, header)]}, uid)`` of the series ``chosen`` belongs to, from its folder.

    The other files of the folder that carry a DICOM name or marker are read too; one that
    has no series or an invalid UID, or fails without the DICOM file marker (a ``.dcm`` that is
    not a DICOM file, or an old one without preamble) is skipped and named in a warning. A
    file that fails but has the marker, or in which pydicom still finds the chosen series' UID,
    may be a broken slice of that series: an error naming it.
    A file with the ``SOPInstanceUID`` of one already taken is the same image (another copy or
    encoding of it, as in pydicom's test folder) and is skipped too, the chosen file kept. A
    chosen file without a ``SeriesInstanceUID`` is read alone, and so is a Siemens mosaic: a
    whole volume, whose series holds the other time points or diffusion directions.
    """
    ds = _read_header(pydicom, chosen)
    if "SeriesInstanceUID" not in ds:
        return {"": [(chosen, ds)]}, ""
    uid = _series_uid(chosen, ds)
    if _is_mosaic(ds):
        return {uid: [(chosen, ds)]}, uid
    members, skipped = [(chosen, ds)], []
    instances = {str(ds.get("SOPInstanceUID", "")): chosen}
    for path in files:
        if path == chosen or not _marked_as_dicom(path):
            continue
        found = _bare_series_uid(pydicom, path)
        if found != uid and _UID.fullmatch(found):
            continue  # a file of another series: not read further
        try:
            other = _read_header(pydicom, path)
        except VolumeEVMError as exc:
            if _has_dicm_marker(path) or found == uid:
                raise
            skipped.append(f"{name(path)} ({str(exc).removeprefix(f'{path}: ')})")
            continue
        try:
            if _series_uid(path, other) != uid:
                continue
        except VolumeEVMError as exc:  # no series UID, or an invalid one
            skipped.append(f"{name(path)} ({str(exc).removeprefix(f'{path}: ')})")
            continue
        instance = str(other.get("SOPInstanceUID", ""))
        if instance and instance in instances:
            skipped.append(f"{name(path)} (the same image as {name(instances[instance])}: "
                           f"SOPInstanceUID {instance})")
            continue
        instances[instance] = path
        members.append((path, other))
    if skipped:
        warnings.warn(
            f"{label}: {len(skipped)} other file(s) of the folder are not readable DICOM, "
            f"belong to no series or repeat an image, and were skipped: " + "; ".join(skipped[:5])
            + ("; ..." if len(skipped) > 5 else ""),
            UserWarning, stacklevel=2,
        )
    members.sort(key=lambda item: item[0])
    return {uid: members}, uid


def _bare_series_uid(pydicom, path):
    """The ``SeriesInstanceUID`` pydicom finds reading that element alone, or "".

    Forced, so it is found also in a file the full read refuses (an old file without preamble);
    quicker than the full read, which is kept for the files of the chosen series.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(path, force=True, stop_before_pixels=True,
                                 specific_tags=["SeriesInstanceUID"])
            return str(ds.get("SeriesInstanceUID", ""))
    except Exception:  # the file is broken in a way that hides its series: nothing to find
        return ""


def _candidate_files(source):
    """Regular files to scan, the label used in messages, and the files named by the caller.

    Named files must be readable DICOM; the other files of a folder are read only when
    :func:`_marked_as_dicom`.
    """
    if isinstance(source, (str, os.PathLike)):
        source = Path(source)
        named = [] if source.is_dir() else [source]
        for path in named:
            require_regular_file(path)
        folder = source.parent if named else source
        try:
            entries = sorted(folder.iterdir())
        except OSError as exc:
            raise VolumeEVMError(f"{folder}: cannot list the folder ({exc})") from exc
        files = [path for path in entries if _is_regular_file(path)]
        return files, str(source), named
    files = [Path(p) for p in source]
    if not files:
        raise VolumeEVMError("read_dicom: the list of DICOM files is empty")
    for path in files:
        require_regular_file(path)
    label = str(files[0]) if len(files) == 1 else f"{files[0]} (and {len(files) - 1} more files)"
    return files, label, files


def _is_regular_file(path):
    """Whether a folder entry is a regular file (FIFOs, devices and sub-folders are skipped)."""
    try:
        return stat.S_ISREG(path.stat().st_mode)
    except OSError as exc:
        raise VolumeEVMError(f"{path}: cannot read this entry of the folder ({exc})") from exc


def _marked_as_dicom(path):
    """Whether a file found in a folder must be read as DICOM: a DICOM name or the DICM marker."""
    return path.name.lower().endswith(_DICOM_SUFFIXES) or _has_dicm_marker(path)


def _has_dicm_marker(path):
    """Whether a file has the DICOM file marker: ``DICM`` after the 128-byte preamble."""
    try:
        with open(path, "rb") as file:
            return file.read(132)[128:] == b"DICM"
    except OSError as exc:
        raise VolumeEVMError(f"{path}: cannot read the file ({exc})") from exc


def _read_header(pydicom, path):
    """Header of ``path`` (no pixel data); any failure is an error naming the file."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(path, stop_before_pixels=True)
            # pydicom decodes values when they are first used: decode them all here, so that a
            # corrupt value fails now, as an error naming the file.
            ds.file_meta.walk(lambda dataset, element: None)
            ds.walk(lambda dataset, element: None)
            return ds
    except Exception as exc:  # a corrupt file can make the parser fail in any way
        raise VolumeEVMError(
            f"{path}: not a readable DICOM file ({type(exc).__name__}: {exc})"
        ) from exc


def _describe(series, name):
    """One line per series: UID, modality, description, number of files and the first files."""
    lines = []
    for uid, items in series.items():
        ds = items[0][1]
        shown = ", ".join(name(path) for path, _ in items[:3]) + (", ..." if len(items) > 3 else "")
        lines.append(
            f"  {uid}: {ds.get('Modality', '?')} '{ds.get('SeriesDescription', '')}', "
            f"{len(items)} file(s): {shown}"
        )
    return "\n".join(lines)


def _image_headers(pydicom, path, ds, name, label):
    """The slice headers of one file: one for a single-frame image, one per frame for an
    enhanced multi-frame image (its frames are slices placed by their own functional groups),
    one per tile of a Siemens mosaic."""
    if "PerFrameFunctionalGroupsSequence" in ds:
        frames = _frames(pydicom, ds, f"{label}: {name}")
        return [_slice_header(path, frame, f"{name} frame {k + 1}", label, part=(k,))
                for k, frame in enumerate(frames)]
    if _is_mosaic(ds):
        return _mosaic_headers(path, ds, name, label)
    return [_slice_header(path, ds, name, label)]


def _is_mosaic(ds):
    """Whether an image is a Siemens mosaic (``ImageType`` holds ``MOSAIC``)."""
    image_type = ds.get("ImageType") or []
    image_type = [image_type] if isinstance(image_type, str) else image_type
    return "MOSAIC" in [str(value).strip().upper() for value in image_type]


def _mosaic_headers(path, ds, name, label):
    """One slice header per tile of a Siemens mosaic, placed as the CSA header says.

    The image holds ``NumberOfImagesInMosaic`` tiles (Siemens' CSA image header, read with
    nibabel's ``csareader``) in a square grid of ``ceil(sqrt(n))`` tiles a side, row by row.
    ``ImagePositionPatient`` is that of the whole mosaic's first pixel; the first tile's is
    shifted by half the difference of the mosaic and tile sizes (the correction nibabel and
    dcm2niix apply). Tiles stack along the slice normal, signed as the CSA ``SliceNormalVector``
    says, ``SpacingBetweenSlices`` (else ``SliceThickness``) apart.
    """
    where = f"{label}: {name}"
    header = _slice_header(path, ds, name, label, part=(slice(None), slice(None)))
    with warnings.catch_warnings():  # nibabel.nicom warns that its DICOM *readers* are
        warnings.simplefilter("ignore")  # experimental; only its CSA header parser is used
        csareader = import_reader_package("nibabel.nicom.csareader", "nibabel", where)
    try:
        csa = csareader.get_csa_header(ds, "image")
        count = None if csa is None else int(csareader.get_n_mosaic(csa))
        csa_normal = None if csa is None else csareader.get_slice_normal(csa)
    except Exception as exc:  # nibabel reports a corrupt CSA header in several ways
        raise VolumeEVMError(f"{where} is a mosaic with a corrupt CSA header ({exc})") from exc
    if count is None:
        raise VolumeEVMError(
            f"{where} is a mosaic (ImageType MOSAIC) without the Siemens CSA image header that "
            f"gives its number of slices"
        )
    side = math.ceil(math.sqrt(count)) if 0 < count <= _MAX_MOSAIC_SLICES else 0
    rows, columns = header["rows"], header["columns"]
    if side == 0 or rows % side or columns % side:
        raise VolumeEVMError(
            f"{where} is a mosaic of {columns}x{rows} pixels that cannot hold {count} slices "
            f"in a square grid (corrupt CSA header?)"
        )
    tile_rows, tile_columns = rows // side, columns // side
    row_dir, col_dir = header["orientation"][:3], header["orientation"][3:]
    shift = ((columns - tile_columns) / 2 * header["pixel_spacing"][1] * row_dir
             + (rows - tile_rows) / 2 * header["pixel_spacing"][0] * col_dir)
    normal = np.cross(row_dir, col_dir)
    if csa_normal is not None and np.dot(csa_normal, normal) < 0:
        normal = -normal
    step = 1.0 if header["thickness"] is None else header["thickness"]
    if not step > 0:
        raise VolumeEVMError(f"{where} is a mosaic whose slice spacing is {step} mm")
    headers = []
    for k in range(count):
        r0, c0 = (k // side) * tile_rows, (k % side) * tile_columns
        headers.append({
            **header, "name": f"{name} tile {k + 1}", "rows": tile_rows,
            "columns": tile_columns, "size": (tile_columns, tile_rows),
            "part": (slice(r0, r0 + tile_rows), slice(c0, c0 + tile_columns)),
            "position": header["position"] + shift + k * step * normal,
        })
    return headers


def _frames(pydicom, ds, where):
    """One dataset per frame of an enhanced multi-frame image (PS3.3 C.7.6.16): the image's
    pixel attributes with those of the shared functional groups, overridden by the frame's own
    (plane position and orientation, pixel measures, pixel value transformation)."""
    count = _integer(ds, "NumberOfFrames", None, where)
    per_frame = ds.PerFrameFunctionalGroupsSequence
    if len(per_frame) != count:
        raise VolumeEVMError(
            f"{where} has NumberOfFrames {count} but {len(per_frame)} per-frame functional "
            f"groups (corrupt header?)"
        )
    shared = ds.get("SharedFunctionalGroupsSequence") or [pydicom.Dataset()]
    frames = []
    for groups in per_frame:
        frame = pydicom.Dataset()
        frame.file_meta = ds.file_meta
        for keyword in _FRAME_IMAGE_KEYWORDS:
            if keyword in ds:
                frame[keyword] = ds[keyword]
        for group in (shared[0], groups):
            for macro in _FRAME_MACROS:
                items = group.get(macro)
                if items:
                    for element in items[0]:
                        frame[element.tag] = element
        frames.append(frame)
    return frames


def _slice_header(path, ds, name, label, *, part=None):
    """The attributes the reader uses, from one slice's header, checked and as plain numbers.

    ``part`` indexes the slice in its file's decoded pixel array when the file holds several:
    ``(k,)`` for frame ``k`` of an enhanced multi-frame file (whose ``ds`` is that frame's
    dataset from :func:`_frames`), a tile's rows and columns for a mosaic; ``None`` for a
    single-frame image.
    """
    where = f"{label}: {name}"
    if "Rows" not in ds:
        raise VolumeEVMError(f"{where} is not an image (no Rows) but belongs to the series")
    header = {"path": path, "name": name, "modality": str(ds.get("Modality", "")),
              "part": part}
    for key, keyword, default in (
        ("rows", "Rows", None), ("columns", "Columns", None), ("frames", "NumberOfFrames", 1),
        ("samples", "SamplesPerPixel", 1), ("bits", "BitsAllocated", None),
        ("stored", "BitsStored", None), ("signed", "PixelRepresentation", 0),
    ):
        header[key] = _integer(ds, keyword, default, where)
    high_bit = _integer(ds, "HighBit", header["stored"] - 1, where)
    if (header["frames"] != 1 and part is None) or header["frames"] < 1:
        raise VolumeEVMError(
            f"{where} has NumberOfFrames {header['frames']}; single-frame slices or an enhanced "
            f"multi-frame image (with per-frame functional groups) are needed"
        )
    if header["samples"] != 1:
        raise VolumeEVMError(f"{where} is a colour image; a grey series is needed")
    if header["rows"] < 1 or header["columns"] < 1:
        raise VolumeEVMError(f"{where} has {header['columns']}x{header['rows']} pixels")
    if header["bits"] not in (1, 8, 16, 32, 64) or not 1 <= header["stored"] <= header["bits"]:
        raise VolumeEVMError(
            f"{where} has BitsAllocated {header['bits']} and BitsStored {header['stored']}; "
            f"the pixel format is corrupt or unsupported"
        )
    if high_bit != header["stored"] - 1:
        raise VolumeEVMError(
            f"{where} has HighBit {high_bit} with BitsStored {header['stored']}; an image's high "
            f"bit is BitsStored - 1 (PS3.5 8.1.1): the pixel format is corrupt"
        )
    header["size"] = (header["columns"], header["rows"])
    header["pixel_format"] = (header["bits"], header["stored"],
                              "signed" if header["signed"] else "unsigned")
    header["syntax"] = str(ds.file_meta.get("TransferSyntaxUID", ""))
    # The whole file's decoded pixel array (every frame) and its bytes.
    header["file_shape"] = ((header["frames"],) if header["frames"] > 1 else ()) + (
        header["rows"], header["columns"])
    header["pixel_bytes"] = (math.prod(header["file_shape"]) * header["bits"] + 7) // 8
    if header["syntax"] in _NATIVE_SYNTAXES:
        try:
            file_bytes = path.stat().st_size
        except OSError as exc:
            raise VolumeEVMError(f"{path}: cannot read the file ({exc})") from exc
        if header["pixel_bytes"] > file_bytes:
            raise VolumeEVMError(
                f"{path}: cannot decode the pixel data (The number of bytes of pixel data that "
                f"{header['columns']}x{header['rows']} pixels of {header['bits']} bits need, "
                f"{header['pixel_bytes']}, is more than the whole file holds, {file_bytes}); "
                f"the file is truncated or its header is corrupt"
            )
    header["orientation"] = _numbers(ds, "ImageOrientationPatient", 6, where)
    header["pixel_spacing"] = _numbers(ds, "PixelSpacing", 2, where)
    header["position"] = _numbers(ds, "ImagePositionPatient", 3, where)
    header["rescale_type"] = str(ds.get("RescaleType", "") or "").strip()
    header["slope"] = _numbers(ds, "RescaleSlope", 1, where, required=False)
    header["intercept"] = _numbers(ds, "RescaleIntercept", 1, where, required=False)
    header["thickness"] = _thickness(ds)
    if np.any(header["pixel_spacing"] <= 0):
        raise VolumeEVMError(f"{where} has PixelSpacing {header['pixel_spacing'].tolist()}; "
                             f"spacings must be positive")
    if header["slope"] is not None and header["slope"][0] == 0:
        raise VolumeEVMError(f"{where} has RescaleSlope 0, which would make every pixel equal")
    return header


def _integer(ds, keyword, default, where):
    """A non-negative integer attribute; ``default`` when absent (``None``: it is required)."""
    if keyword not in ds:
        if default is None:
            raise VolumeEVMError(f"{where} has no {keyword}; the pixel data cannot be read")
        return default
    value = ds[keyword].value
    try:
        number = int(value)
    except (TypeError, ValueError) as exc:
        raise VolumeEVMError(f"{where} has {keyword} {value!r}, not an integer") from exc
    if number < 0:
        raise VolumeEVMError(f"{where} has {keyword} {number}, a negative count")
    return number


def _numbers(ds, keyword, count, where, *, required=True):
    """The ``count`` finite numbers of a numeric attribute as a float array.

    ``None`` when the attribute is absent and not ``required``; an attribute present but empty,
    unparsable, non-finite or with another number of values is an error.
    """
    if keyword not in ds:
        if required:
            raise VolumeEVMError(f"{where} has no {keyword}; cannot place the slice in a volume")
        return None
    value = ds[keyword].value
    items = [value] if isinstance(value, (str, bytes, int, float)) else list(value or [])
    try:
        numbers = np.array([float(item) for item in items], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise VolumeEVMError(f"{where} has {keyword} {value!r}, which is not numbers") from exc
    if numbers.shape != (count,) or not np.all(np.isfinite(numbers)):
        raise VolumeEVMError(
            f"{where} has {keyword} {value!r}; {count} finite number(s) are needed"
        )
    return numbers


def _thickness(ds):
    """``SpacingBetweenSlices``, else ``SliceThickness`` (mm) for a lone slice; ``None`` if neither
    has a value (both may legally be empty), NaN if the value is not a number."""
    for keyword in ("SpacingBetweenSlices", "SliceThickness"):
        value = ds.get(keyword)
        if value not in (None, ""):
            try:
                return float(value)
            except (TypeError, ValueError):
                return float("nan")
    return None


def _data_units(header):
    """Units of the rescaled values: ``RescaleType`` when it names them ("US" is unspecified),
    else "HU" for a CT image with a rescale (PS3.3 C.8.2.1: CT rescales to Hounsfield units),
    else "" (an MR's values have no unit)."""
    if header["rescale_type"] and header["rescale_type"].upper() != "US":
        return data_units(header["rescale_type"])
    rescaled = header["slope"] is not None or header["intercept"] is not None
    return "HU" if header["modality"] == "CT" and rescaled else ""


def _check_same(slices, label, key, what, show, hint=""):
    """Refuse a series whose slices differ in ``slices[i][key]``, naming an odd file."""
    values = [s[key] for s in slices]
    if any(value != values[0] for value in values):
        odd = min(slices, key=lambda s: values.count(s[key]))
        usual = next(s for s in slices if s[key] != odd[key])
        raise VolumeEVMError(
            f"{label}: the series mixes {what} {', '.join(sorted({show(s) for s in slices}))}; "
            f"{odd['name']} has {show(odd)} but {usual['name']} has {show(usual)}{hint}"
        )


def _grid_geometry(slices, label):
    """Slice order and the spacing, origin and orientation of a series; refuses irregular grids."""
    first = slices[0]
    iop = np.array([s["orientation"] for s in slices])
    differs = np.abs(iop - iop[0]).max(axis=1) > _ORIENTATION_ATOL
    if differs.any():
        odd = slices[int(np.argmax(differs))]["name"]
        raise VolumeEVMError(
            f"{label}: the series mixes slice orientations (ImageOrientationPatient of {odd} "
            f"differs from {first['name']}); it is not one volume"
        )
    row_dir, col_dir = iop[0, :3], iop[0, 3:]
    lengths = np.array([np.linalg.norm(row_dir), np.linalg.norm(col_dir)])
    if np.abs(lengths - 1).max() > _DIRECTION_TOLERANCE or abs(row_dir @ col_dir) > (
        _DIRECTION_TOLERANCE
    ):
        raise VolumeEVMError(
            f"{label}: {first['name']} has ImageOrientationPatient {iop[0].tolist()}: the row "
            f"and column directions must be unit vectors at right angles (lengths "
            f"{lengths.round(6).tolist()}, cosine {row_dir @ col_dir:.6g})"
        )
    row_dir, col_dir = row_dir / lengths[0], col_dir / lengths[1]
    pixel_spacing = np.array([s["pixel_spacing"] for s in slices])
    differs = np.abs(pixel_spacing - pixel_spacing[0]).max(axis=1) > 1e-6
    if differs.any():
        odd = slices[int(np.argmax(differs))]["name"]
        raise VolumeEVMError(
            f"{label}: the series mixes pixel spacings ({odd} differs from {first['name']})"
        )
    positions = np.array([s["position"] for s in slices])
    normal = np.cross(row_dir, col_dir)
    order = np.argsort(positions @ normal, kind="stable")
    positions = positions[order]
    names = [slices[i]["name"] for i in order]
    if len(slices) > 1:
        steps = np.diff(positions, axis=0)
        step = (positions[-1] - positions[0]) / (len(slices) - 1)
        gaps = steps @ normal
        if gaps.min() <= 1e-6:
            k = int(np.argmin(gaps))
            raise VolumeEVMError(
                f"{label}: two or more slices share one position along the normal ({names[k]} "
                f"and {names[k + 1]}; several acquisitions, echoes or time points in one "
                f"series?)"
            )
        errors = np.linalg.norm(steps - step, axis=1)
        if errors.max() > _SPACING_RTOL * np.linalg.norm(step):
            k = int(np.argmax(errors))
            raise VolumeEVMError(
                f"{label}: slices are not evenly spaced: gaps along the normal range from "
                f"{gaps.min():.4g} to {gaps.max():.4g} mm (missing slices? the step from "
                f"{names[k]} to {names[k + 1]} is {gaps[k]:.4g} mm)"
            )
        z_spacing = np.linalg.norm(step)
        z_dir = step / z_spacing
    else:
        z_spacing = 1.0 if first["thickness"] is None else first["thickness"]
        if not z_spacing > 0:
            raise VolumeEVMError(
                f"{label}: {first['name']} has a slice spacing of {z_spacing} mm "
                f"(SpacingBetweenSlices or SliceThickness); it must be positive"
            )
        z_dir = normal
    return order, {
        "spacing": (pixel_spacing[0, 1], pixel_spacing[0, 0], z_spacing),
        "origin": positions[0],
        "orientation": np.column_stack([row_dir, col_dir, z_dir]),
    }


def _rescale_values(slices, label):
    """Per-slice slopes and intercepts; refuses a rescale that only some slices give."""
    for key, keyword, identity in (("slope", "RescaleSlope", 1.0),
                                   ("intercept", "RescaleIntercept", 0.0)):
        given = [s[key] is not None for s in slices]
        if any(given) and not all(given):
            without, having = slices[given.index(False)], slices[given.index(True)]
            raise VolumeEVMError(
                f"{label}: {without['name']} has no {keyword} but {having['name']} has one; "
                f"the slices' values cannot be compared (corrupt header?)"
            )
        for s in slices:
            s[key] = identity if s[key] is None else float(s[key][0])
    return (np.array([s["slope"] for s in slices]),
            np.array([s["intercept"] for s in slices]))


def _read_pixels(pydicom, slices, label, *, identity):
    """The stored pixels ``(X, Y, Z)`` of the sorted slices, memory checked before allocating.

    The peak is the stored array, the rescaled copy (at most 4 bytes a voxel) unless the
    rescale is the identity, a 1-byte mask for the finiteness check of float data, and a few
    slices being decoded (a multi-frame file is decoded whole, once).
    """
    first = slices[0]
    columns, rows, count = first["columns"], first["rows"], len(slices)
    stored_bytes = max(first["bits"] // 8, 1)
    per_voxel = stored_bytes + (0 if identity else 4 + 1)
    check_memory(
        columns * rows * count * per_voxel
        + (2 if first["part"] is not None else 4) * first["pixel_bytes"],
        f"reading {count} slices of {columns}x{rows} pixels",
        source=label,
        advice="read fewer slices (pass a list of files) or free memory",
    )
    raw, decoded = None, {}
    for k, header in enumerate(slices):
        if header["part"] is None:
            pixels = _pixels(pydicom, header)
        else:
            if header["path"] not in decoded:  # the one multi-frame or mosaic file being read
                decoded = {header["path"]: _pixels(pydicom, header)}
            pixels = decoded[header["path"]][header["part"]]
        if raw is None:
            raw = np.empty((columns, rows, count), dtype=pixels.dtype)
        elif pixels.dtype != raw.dtype:
            raise VolumeEVMError(
                f"{header['path']}: the pixels decode as {pixels.dtype} but those of "
                f"{first['name']} as {raw.dtype}"
            )
        raw[:, :, k] = pixels.T
    return raw


def _pixels(pydicom, header):
    """The pixel array of a slice's file, ``[row, column]`` (``[frame, row, column]`` for a
    multi-frame file), its size checked."""
    path = header["path"]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(path)
            if "PixelData" not in ds:
                raise VolumeEVMError(f"{path}: the file has no pixel data")
            if header["syntax"] in _NATIVE_SYNTAXES + (_DEFLATED_SYNTAX,):
                _check_length(ds.PixelData, header)
            pixels = ds.pixel_array
    except VolumeEVMError:
        raise
    except Exception as exc:  # pydicom and its decoders fail in many ways on corrupt data
        raise VolumeEVMError(
            f"{path}: cannot decode the pixel data ({type(exc).__name__}: {exc})"
        ) from exc
    shape = header["file_shape"]
    if pixels.shape != shape or pixels.dtype.kind not in "uif":
        raise VolumeEVMError(
            f"{path}: the pixel data decodes to shape {pixels.shape} ({pixels.dtype}), not "
            f"{' x '.join(map(str, shape))} (frames, rows, columns) of grey values"
        )
    return pixels


def _check_length(data, header):
    """Refuse native pixel data shorter than the header needs, or longer with data past the end.

    Trailing zero bytes are padding (some writers round the value up) and are not read; bytes
    past the image that are not zero mean the header does not describe the data (a wrong
    ``Rows``, ``Columns`` or ``BitsAllocated``). Zero padding cannot be told apart from a header
    whose size was shrunk onto zero pixels.
    """
    needed = header["pixel_bytes"]
    *frames, rows, columns = header["file_shape"]
    shape = (f"{frames[0]} frames of " if frames else "") + (
        f"{columns}x{rows} pixels of {header['bits']} bits")
    if len(data) < needed:
        raise VolumeEVMError(
            f"{header['path']}: cannot decode the pixel data (it holds {format_bytes(len(data))}"
            f" but {shape} need {needed} bytes; the data is missing or the header is corrupt)"
        )
    if np.frombuffer(data, np.uint8, offset=needed).any():
        raise VolumeEVMError(
            f"{header['path']}: cannot decode the pixel data (it holds {len(data)} bytes where "
            f"{shape} need {needed}, and the {len(data) - needed} bytes after them are not "
            f"zero padding; corrupt header?)"
        )


def _rescale(raw, slopes, intercepts):
    """Apply each slice's modality rescale to ``raw`` (``(X, Y, Z)``, slices in sorted order).

    The integer result type is chosen from the exact range (per-slice extremes), then filled
    slice by slice so that no full-size temporary is needed.
    """
    if np.all(slopes == 1) and np.all(intercepts == 0):
        return raw
    integral = np.all(slopes == np.round(slopes)) and np.all(intercepts == np.round(intercepts))
    if (
        integral
        and raw.dtype.kind in "ui"
        and raw.dtype.itemsize <= 2
        and np.abs(slopes).max() <= 2**14
        and np.abs(intercepts).max() <= 2**30
    ):
        # |raw| < 2**16, so |value| < 2**30 + 2**30: exact in int32.
        ends = np.stack([raw.min(axis=(0, 1)), raw.max(axis=(0, 1))]).astype(np.int64)
        ends = ends * slopes.astype(np.int64) + intercepts.astype(np.int64)
        info = np.iinfo(np.int16)
        fits = info.min <= ends.min() and ends.max() <= info.max
        values = np.empty(raw.shape, np.int16 if fits else np.int32)
        for k in range(raw.shape[2]):
            values[:, :, k] = raw[:, :, k].astype(np.int32) * int(slopes[k]) + int(intercepts[k])
        return values
    values = np.empty(raw.shape, np.float32)
    for k in range(raw.shape[2]):
        values[:, :, k] = raw[:, :, k].astype(np.float32) * np.float32(slopes[k]) + np.float32(
            intercepts[k]
        )
    return values
