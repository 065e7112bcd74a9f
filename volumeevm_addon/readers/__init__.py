"""Volume readers: every supported file format into one :class:`~volumeevm_addon.Volume`.

:func:`read_volume` picks the reader from the path (a folder or a list of files is a DICOM
series, a file goes by its extension) and passes the keyword options on. Each reader lives in its
own private module and imports its third-party library (pydicom, nibabel, pynrrd, tifffile) only
when it runs, so importing this package needs NumPy alone.

Whatever the format, the result follows the conventions of ``model/_volume.py``: array
``[x, y, z]`` (C-contiguous, native byte order), spacing in mm, origin = centre of voxel
``(0, 0, 0)`` and orientation columns in LPS. Bad input raises
:class:`~volumeevm_addon.VolumeEVMError` with the file and the problem in the message, chained
to the library's own error if any:

- the path is looked at before any reader runs: a ``bytes`` path, a missing file, a broken
  link, a path too long or not accessible, a FIFO, socket or device (which would be read
  forever) and a folder named like a volume file are refused;
- every reader checks its header before reading data: the data must be exactly as long as the
  header announces (uncompressed files by their length, compressed streams by inflating no
  further and by their checksums), and the peak memory of the read must fit
  (:func:`~volumeevm_addon.system.check_memory`), so a corrupt or hostile header costs neither a
  huge allocation nor silently different voxels.
"""

import dataclasses
import errno
import os
import stat
from pathlib import Path

from .._errors import VolumeEVMError
from ._den import read_den
from ._dicom import read_dicom
from ._labels import as_label_map
from ._nifti import read_nifti
from ._npy import read_npy
from ._nrrd import read_nrrd
from ._raw import read_raw
from ._tiff import read_tiff
from ._zarr import read_zarr, volume_levels

_READERS = {
    ".npy": read_npy,
    ".raw": read_raw,
    ".bin": read_raw,
    ".nrrd": read_nrrd,
    ".nhdr": read_nrrd,
    ".nii": read_nifti,
    ".nii.gz": read_nifti,
    ".dcm": read_dicom,
    ".tif": read_tiff,
    ".tiff": read_tiff,
    ".den": read_den,
}

#: File name endings :func:`read_volume` accepts (lower case; matched case-insensitively).
#: DICOM series are also read from a folder or a list of files, whatever their names, and
#: OME-Zarr stores from a folder named ``*.zarr`` (``*.ome.zarr``).
SUPPORTED_EXTENSIONS = tuple(_READERS)

__all__ = ["SUPPORTED_EXTENSIONS", "read_volume", "volume_levels"]


def read_volume(path, *, units=None, labels=None, **options):
    """Read a volume file, DICOM folder or list of DICOM files.

    Parameters
    ----------
    path : str, Path or sequence of str or Path
        A file with one of :data:`SUPPORTED_EXTENSIONS`, a folder holding a DICOM series, or
        the files of one DICOM series.
    units : str, optional
        The data's units ("HU", ...), overriding what the file says; for a file that states
        none (most NRRD and every NIfTI file, where the format has no field for it). ``None``
        keeps the file's own: DICOM ``RescaleType``, else "HU" for a rescaled CT; NRRD
        ``sample units``; the ``.npy`` sidecar's ``units``; "" when the file says nothing.
    labels : bool, str or os.PathLike, optional
        Whether the volume is a label map (a segmentation: integers, 0 = background), and its
        labels' names and colours. ``None`` keeps what the file says (a 3D Slicer
        ``.seg.nrrd`` is a label map with its segments' names and colours, an OME-Zarr label
        image one with its ``image-label`` colours); ``True`` reads a label map, named and
        coloured by the file where it is one, by a fixed palette otherwise; a path reads one
        named by that label table (ITK-SNAP label description ``.txt``, or JSON ``{label:
        {name, color}}``); ``False`` reads densities. The result's ``labels`` holds them
        (``is_label_map``).
    **options
        Format options, keyword only:

        - raw (``.raw``, ``.bin``): ``shape=(X, Y, Z)`` and ``dtype`` (required),
          ``byte_order="little"`` or ``"big"``, ``header_bytes=0``, ``spacing=(sx, sy, sz)``
          in mm;
        - ``.npy``, raw, ``.den``, uncompressed NIfTI (``.nii``), raw-encoded NRRD and
          TIFF: ``lazy=True`` returns a lazy Dask array (memory-mapped where the samples lie
          uncompressed in the file, read page by page from a compressed TIFF), so a file
          larger than memory opens and :meth:`VolumeEVM.from_volume` builds it chunk by chunk;
          compressed NIfTI and NRRD are refused with ``lazy=True`` (a stream is read whole);
        - DICOM (folder, list, ``.dcm``): ``series_uid=`` to pick one series of several;
        - OME-Zarr (a ``.zarr`` / ``.ome.zarr`` folder, NGFF 0.4 or 0.5): ``level=0`` (the
          pyramid level, :func:`volume_levels` lists them), ``channel=0`` and ``time=0``; the
          result's ``array`` is a lazy Dask array with the store's chunks (nothing is read
          until it is computed: :meth:`VolumeEVM.from_volume` builds chunk by chunk).

        Other formats take none.

    Returns
    -------
    Volume
        Densities ``(X, Y, Z)`` in data units (``units``), with spacing (mm), origin (centre
        of voxel ``(0, 0, 0)``, mm, LPS) and orientation (columns in LPS); ``source`` is
        ``str(path)``.

    Raises
    ------
    VolumeEVMError
        If the path is not a ``str`` or ``Path`` (a ``bytes`` path), does not exist (or is a
        broken link), cannot be accessed, is neither a regular file nor a folder (a FIFO or
        device would be read forever), is a folder named like a volume file, has an unsupported
        extension, ``units`` is not a ``str``, ``labels`` is not as above, its label table is
        malformed, a label map's data are not integers >= 0, or the reader finds the file
        unusable or too large for the memory available (the message names the file and the
        problem).
    TypeError
        If an option is not one the format takes.

    Examples
    --------
    >>> vol = read_volume("head.nrrd")  # doctest: +SKIP
    >>> vol.array.shape, vol.spacing  # doctest: +SKIP
    ((256, 256, 108), (0.957, 0.957, 1.5))
    >>> read_volume("chest.nrrd", units="HU").units  # doctest: +SKIP
    'HU'
    """
    if units is not None and not isinstance(units, str):
        raise VolumeEVMError(
            f"units: {units!r} is a {type(units).__name__}; the data's units are a str such as "
            f"'HU', or None to keep what the file says"
        )
    if not (labels is None or isinstance(labels, (bool, str, os.PathLike))):
        raise VolumeEVMError(f"labels: {labels!r} is not True, False, None or a label table's path")
    volume = as_label_map(_read(path, options, labels), labels)
    return volume if units is None else dataclasses.replace(volume, units=units.strip())


def _read(path, options, labels=None):
    """The volume at ``path`` as its reader gives it (see :func:`read_volume`); ``labels=False``
    spares an OME-Zarr label image the pass that finds its labels."""
    if isinstance(path, (bytes, bytearray)):
        raise VolumeEVMError(
            f"{path!r}: a path given as bytes is not supported; pass a str or pathlib.Path "
            f"(os.fsdecode(path) converts it)"
        )
    if not isinstance(path, (str, os.PathLike)):
        return read_dicom(list(path), **options)
    try:
        path = Path(path)
    except TypeError as exc:  # an os.PathLike whose __fspath__ gives bytes
        raise VolumeEVMError(f"{path!r}: not a usable path ({exc})") from exc
    name = path.name.lower()
    ending = next((e for e in _READERS if name.endswith(e)), None)
    mode = _file_mode(path)
    if name.endswith(".zarr"):
        if not stat.S_ISDIR(mode):
            raise VolumeEVMError(f"{path}: not a folder; an OME-Zarr store is a folder")
        return read_zarr(path, label_image=labels is not False, **options)
    if stat.S_ISDIR(mode):
        if ending is not None and _READERS[ending] is not read_dicom:
            raise VolumeEVMError(
                f"{path}: is a folder, not a {ending} file (a folder is read as a DICOM series "
                f"only when its name has no volume file extension)"
            )
        return read_dicom(path, **options)
    if not stat.S_ISREG(mode):
        raise VolumeEVMError(
            f"{path}: not a regular file or folder (a FIFO, socket or device), which would be "
            f"read forever or not at all; copy the data to a file first"
        )
    if ending is None:
        raise VolumeEVMError(
            f"{path}: unsupported file type; supported are {', '.join(SUPPORTED_EXTENSIONS)}, "
            f"or a folder of DICOM files"
        )
    return _READERS[ending](path, **options)


def _file_mode(path):
    """``st_mode`` of ``path`` (following symbolic links), or the reason it has none, in words."""
    try:
        return path.stat().st_mode
    except FileNotFoundError as exc:
        if path.is_symlink():
            raise VolumeEVMError(
                f"{path}: broken symbolic link (its target {os.readlink(path)} does not exist)"
            ) from exc
        raise VolumeEVMError(f"{path}: no such file or folder") from exc
    except OSError as exc:
        if exc.errno == errno.ENAMETOOLONG:
            reason = "the path or one of its names is too long for the operating system"
        elif isinstance(exc, PermissionError):
            reason = "permission denied (a folder on the way cannot be searched)"
        else:
            reason = exc.strerror or str(exc)
        raise VolumeEVMError(f"{path}: cannot access this path ({reason})") from exc
    except ValueError as exc:  # e.g. an embedded null character
        raise VolumeEVMError(f"{path!r}: not a usable path ({exc})") from exc
