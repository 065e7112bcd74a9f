"""DICOM image series (a folder, one file of the series, or a list of files) via pydicom.

A series is the set of single-frame images sharing a ``SeriesInstanceUID``. The grid is built
from the image-plane attributes (DICOM PS3.3 C.7.6.2):

- ``ImageOrientationPatient`` = (row direction, column direction) in LPS: the row direction is
  the way the column index (x) grows, the column direction the way the row index (y) grows;
  the slice normal is their cross product.
- ``ImagePositionPatient`` is the LPS centre of the first transmitted pixel of each slice.
  Slices are sorted by the projection of that position on the normal (file names and
  ``InstanceNumber`` are not reliable), the origin is the first sorted slice's position and the
  z step is the mean step between consecutive positions. Its direction is normally the normal;
  for a gantry-tilted series it is the actual (oblique) stacking direction, so the grid is
  sheared rather than misplaced. A single slice takes its z spacing from
  ``SpacingBetweenSlices``, else ``SliceThickness``, else 1 mm.
- ``PixelSpacing`` is (between rows, between columns) = (y, x) spacing.
- ``pixel_array`` is ``[row, column]`` = ``[y, x]``; it is transposed into ``[x, y, z]``.

Modality rescale ``RescaleSlope`` / ``RescaleIntercept`` is applied per slice. The result keeps
the stored integer dtype when every slice's rescale is the identity, is ``int16`` (or ``int32``
if the values need it) when slopes and intercepts are integers and the stored pixels are at
most 16-bit, and ``float32`` otherwise. CT data is in Hounsfield units ("HU").

Refused with a message rather than guessed: several series in one folder (unless
``series_uid`` picks one), slices of different sizes, orientations or pixel spacings, two slices
at one position, unevenly spaced slices (missing files), multi-frame and colour images.
"""

import os
from pathlib import Path

import numpy as np

from .._errors import VolumeEVMError
from ._checks import checked_volume, import_reader_package

#: Largest deviation of a slice step from the mean step, relative to the mean step.
_SPACING_RTOL = 1e-2
#: Tolerance on direction cosines when checking that slices share one orientation.
_ORIENTATION_ATOL = 1e-4


def read_dicom(source, *, series_uid=None):
    """Read one DICOM image series into a volume.

    Parameters
    ----------
    source : str, Path or sequence of str or Path
        A folder (its files are scanned, sub-folders are not; non-DICOM files are skipped),
        one file (the series it belongs to is read from its folder), or an explicit list of
        the series' files.
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
        If pydicom is missing, no image series is found, several are found and
        ``series_uid`` is not given (the message lists them), ``series_uid`` is not among
        them, the slices do not form one regular grid (see the module notes), or a file's
        pixel data cannot be decoded.
    """
    files, label, explicit = _candidate_files(source)
    pydicom = import_reader_package("pydicom", "pydicom", label)
    if series_uid is None and isinstance(source, (str, os.PathLike)) and Path(source).is_file():
        series_uid = _read_header(pydicom, Path(source), explicit=True).get("SeriesInstanceUID")

    series = {}
    for path in files:
        ds = _read_header(pydicom, path, explicit)
        if ds is not None and "SeriesInstanceUID" in ds and "Rows" in ds:
            series.setdefault(str(ds.SeriesInstanceUID), []).append((path, ds))
    if not series:
        raise VolumeEVMError(f"{label}: no DICOM image series found among {len(files)} file(s)")
    if series_uid is None and len(series) > 1:
        raise VolumeEVMError(
            f"{label}: holds {len(series)} DICOM series; choose one with series_uid=:\n"
            + _describe(series)
        )
    uid = series_uid if series_uid is not None else next(iter(series))
    if uid not in series:
        raise VolumeEVMError(
            f"{label}: no series with SeriesInstanceUID {uid!r}; the series found are:\n"
            + _describe(series)
        )
    slices = series[uid]
    order, geometry = _grid_geometry(slices, label)
    slices = [slices[i] for i in order]
    raw = np.stack([_pixels(path, pydicom).T for path, _ in slices], axis=2)
    array = _rescale(raw, [ds for _, ds in slices])
    units = "HU" if slices[0][1].get("Modality") == "CT" else ""
    return checked_volume(array, label, units=units, **geometry)


def _candidate_files(source):
    """Files to scan, the label used in messages and whether the files were named explicitly."""
    if isinstance(source, (str, os.PathLike)):
        source = Path(source)
        folder = source if source.is_dir() else source.parent
        files = sorted(p for p in folder.iterdir() if p.is_file())
        return files, str(source), False
    files = [Path(p) for p in source]
    if not files:
        raise VolumeEVMError("read_dicom: the list of DICOM files is empty")
    label = str(files[0]) if len(files) == 1 else f"{files[0]} (and {len(files) - 1} more files)"
    return files, label, True


def _read_header(pydicom, path, explicit):
    """Header of ``path`` (no pixel data), or ``None`` for a non-DICOM file found in a folder."""
    try:
        return pydicom.dcmread(path, stop_before_pixels=True)
    except (pydicom.errors.InvalidDicomError, OSError, ValueError, EOFError) as exc:
        if explicit:
            raise VolumeEVMError(f"{path}: not a readable DICOM file ({exc})") from exc
        return None


def _describe(series):
    """One line per series: UID, modality, description, number of files."""
    return "\n".join(
        f"  {uid}: {items[0][1].get('Modality', '?')} "
        f"'{items[0][1].get('SeriesDescription', '')}', {len(items)} file(s)"
        for uid, items in series.items()
    )


def _floats(slices, keyword, label):
    """``(n, m)`` array of a numeric multi-valued attribute over all slices."""
    values = []
    for path, ds in slices:
        if keyword not in ds:
            raise VolumeEVMError(
                f"{label}: {path.name} has no {keyword}; cannot place the slice in a volume"
            )
        values.append([float(v) for v in np.atleast_1d(ds[keyword].value)])
    if len({len(v) for v in values}) > 1:
        raise VolumeEVMError(f"{label}: corrupt header: {keyword} has different lengths in files")
    return np.asarray(values, dtype=np.float64)


def _grid_geometry(slices, label):
    """Slice order and the spacing, origin and orientation of a series; refuses irregular grids."""
    for path, ds in slices:
        if int(ds.get("NumberOfFrames", 1) or 1) > 1:
            raise VolumeEVMError(f"{label}: {path.name} is a multi-frame image (not supported)")
        if int(ds.get("SamplesPerPixel", 1)) != 1:
            raise VolumeEVMError(f"{label}: {path.name} is a colour image; a grey series is needed")
    sizes = sorted({f"{ds.Columns}x{ds.Rows}" for _, ds in slices})
    if len(sizes) > 1:
        raise VolumeEVMError(
            f"{label}: the series mixes image sizes {', '.join(sizes)} (columns x rows)"
        )
    iop = _floats(slices, "ImageOrientationPatient", label)
    if iop.shape[1] != 6 or np.abs(iop - iop[0]).max() > _ORIENTATION_ATOL:
        raise VolumeEVMError(
            f"{label}: the series mixes slice orientations (ImageOrientationPatient differs); "
            f"it is not one volume"
        )
    pixel_spacing = _floats(slices, "PixelSpacing", label)
    if pixel_spacing.shape[1] != 2 or np.abs(pixel_spacing - pixel_spacing[0]).max() > 1e-6:
        raise VolumeEVMError(f"{label}: the series mixes pixel spacings")
    positions = _floats(slices, "ImagePositionPatient", label)
    row_dir, col_dir = iop[0, :3], iop[0, 3:]
    normal = np.cross(row_dir, col_dir)
    order = np.argsort(positions @ normal, kind="stable")
    positions = positions[order]
    if len(slices) > 1:
        steps = np.diff(positions, axis=0)
        step = (positions[-1] - positions[0]) / (len(slices) - 1)
        gaps = steps @ normal
        if gaps.min() <= 1e-6:
            raise VolumeEVMError(
                f"{label}: two or more slices share one position along the normal (several "
                f"acquisitions, echoes or time points in one series?)"
            )
        deviation = np.linalg.norm(steps - step, axis=1).max()
        if deviation > _SPACING_RTOL * np.linalg.norm(step):
            raise VolumeEVMError(
                f"{label}: slices are not evenly spaced: gaps along the normal range from "
                f"{gaps.min():.4g} to {gaps.max():.4g} mm (missing slices?)"
            )
        z_spacing = np.linalg.norm(step)
        z_dir = step / z_spacing
    else:
        first = slices[0][1]
        z_spacing = float(first.get("SpacingBetweenSlices") or first.get("SliceThickness") or 1.0)
        z_dir = normal
    return order, {
        "spacing": (pixel_spacing[0, 1], pixel_spacing[0, 0], z_spacing),
        "origin": positions[0],
        "orientation": np.column_stack([row_dir, col_dir, z_dir]),
    }


def _pixels(path, pydicom):
    """The ``[row, column]`` pixel array of one single-frame slice."""
    try:
        return pydicom.dcmread(path).pixel_array
    except (RuntimeError, NotImplementedError, ValueError, AttributeError, OSError) as exc:
        raise VolumeEVMError(f"{path}: cannot decode the pixel data ({exc})") from exc


def _rescale(raw, headers):
    """Apply each slice's modality rescale to ``raw`` (``(X, Y, Z)``, slices in sorted order)."""
    slopes = np.array([float(ds.get("RescaleSlope", 1) or 1) for ds in headers])
    intercepts = np.array([float(ds.get("RescaleIntercept", 0) or 0) for ds in headers])
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
        values = raw.astype(np.int32)
        values *= slopes.astype(np.int32)
        values += intercepts.astype(np.int32)
        info = np.iinfo(np.int16)
        if info.min <= values.min() and values.max() <= info.max:
            return values.astype(np.int16)
        return values
    values = raw.astype(np.float32)
    values *= slopes.astype(np.float32)
    values += intercepts.astype(np.float32)
    return values
