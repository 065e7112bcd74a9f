"""TIFF page stacks (``.tif``, ``.tiff``) via tifffile: one grey page per z slice.

tifffile returns the first image series as ``(Z, Y, X)`` (pages, rows, columns); reversing the
axes gives ``[x, y, z]``. Only a grey 3-D stack is accepted: colour samples, channels or more
than one non-image axis are refused rather than guessed.

Spacing comes from the microscopy metadata when there is some, converted to mm:

- ImageJ: x and y from the ``XResolution`` / ``YResolution`` tags (pixels per ``unit``), z from
  ``spacing``, the unit from ``unit`` in the ImageJ description;
- OME-TIFF: ``PhysicalSizeX/Y/Z`` of the first ``Pixels`` element, with their ``...Unit``
  attributes (OME's default is micrometres).

Otherwise the spacing is unknown (TIFF resolution tags alone are usually a print DPI). TIFF has
no patient frame: orientation is the identity and the origin zero.
"""

import xml.etree.ElementTree as ET

from .._errors import VolumeEVMError
from ._checks import check_ndim, checked_volume, import_reader_package, mm_per_unit


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
        If tifffile is missing, the file is not a readable TIFF, the first series is not a grey
        3-D stack, or its metadata holds an unknown length unit.
    """
    tifffile = import_reader_package("tifffile", "tifffile", path)
    try:
        with tifffile.TiffFile(str(path)) as tif:
            if not tif.series:
                raise VolumeEVMError(f"{path}: not a readable TIFF file (no image in it)")
            series = tif.series[0]
            if "S" in series.axes or "C" in series.axes:
                raise VolumeEVMError(
                    f"{path}: the TIFF holds colour samples or channels (axes "
                    f"{series.axes!r}, shape {series.shape}); a grey z stack is needed"
                )
            check_ndim(series.shape, path)
            stack = series.asarray()
            spacing = _imagej_spacing(tif, path) or _ome_spacing(tif, path)
    except VolumeEVMError:
        raise
    except (tifffile.TiffFileError, ET.ParseError, ValueError, OSError, EOFError) as exc:
        raise VolumeEVMError(f"{path}: not a readable TIFF file ({exc})") from exc
    return checked_volume(stack.transpose(), path, spacing=spacing)


def _imagej_spacing(tif, path):
    """Spacing in mm from ImageJ metadata, or ``None`` if it gives no physical unit."""
    meta = tif.imagej_metadata
    if not meta or str(meta.get("unit", "pixel")).lower() in ("pixel", "pixels", ""):
        return None
    scale = mm_per_unit(meta["unit"], path, "the ImageJ 'unit'")
    x_per_unit, y_per_unit = tif.pages[0].resolution
    if x_per_unit <= 0 or y_per_unit <= 0:
        raise VolumeEVMError(
            f"{path}: corrupt header: resolution {(x_per_unit, y_per_unit)} pixels per unit"
        )
    z = float(meta.get("spacing", 1.0))
    return (scale / x_per_unit, scale / y_per_unit, scale * z)


def _ome_spacing(tif, path):
    """Spacing in mm from OME-XML ``PhysicalSize*``, or ``None`` if not all three are given."""
    if not tif.is_ome:
        return None
    root = ET.fromstring(tif.ome_metadata)
    pixels = next((el for el in root.iter() if el.tag.endswith("}Pixels")), None)
    if pixels is None:
        return None
    sizes = []
    for axis in "XYZ":
        size = pixels.get(f"PhysicalSize{axis}")
        if size is None:
            return None
        unit = pixels.get(f"PhysicalSize{axis}Unit", "µm")
        sizes.append(float(size) * mm_per_unit(unit, path, f"OME PhysicalSize{axis}Unit"))
    return tuple(sizes)
