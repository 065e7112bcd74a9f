"""Volume readers: every supported file format into one :class:`~volumeevm_addon._volume.Volume`.

:func:`read_volume` picks the reader from the path (a folder or a list of files is a DICOM
series, a file goes by its extension) and passes the keyword options on. Each reader lives in its
own private module and imports its third-party library (pydicom, nibabel, pynrrd, tifffile) only
when it runs, so importing this package needs NumPy alone.

Whatever the format, the result follows the conventions of ``_volume.py``: array ``[x, y, z]``
(C-contiguous, native byte order), spacing in mm, origin = centre of voxel ``(0, 0, 0)`` and
orientation columns in LPS. Bad input raises :class:`~volumeevm_addon._errors.VolumeEVMError`
with the file and the problem in the message.
"""

import os
from pathlib import Path

from .._errors import VolumeEVMError
from ._den import read_den
from ._dicom import read_dicom
from ._nifti import read_nifti
from ._npy import read_npy
from ._nrrd import read_nrrd
from ._raw import read_raw
from ._tiff import read_tiff

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
#: DICOM series are also read from a folder or a list of files, whatever their names.
SUPPORTED_EXTENSIONS = tuple(_READERS)

__all__ = ["SUPPORTED_EXTENSIONS", "read_volume"]


def read_volume(path, **options):
    """Read a volume file, DICOM folder or list of DICOM files.

    Parameters
    ----------
    path : str, Path or sequence of str or Path
        A file with one of :data:`SUPPORTED_EXTENSIONS`, a folder holding a DICOM series, or
        the files of one DICOM series.
    **options
        Format options, keyword only:

        - raw (``.raw``, ``.bin``): ``shape=(X, Y, Z)`` and ``dtype`` (required),
          ``byte_order="little"`` or ``"big"``, ``header_bytes=0``, ``spacing=(sx, sy, sz)``
          in mm;
        - DICOM (folder, list, ``.dcm``): ``series_uid=`` to pick one series of several.

        Other formats take none.

    Returns
    -------
    Volume
        Densities ``(X, Y, Z)`` in data units, with spacing (mm), origin (centre of voxel
        ``(0, 0, 0)``, mm, LPS) and orientation (columns in LPS); ``source`` is ``str(path)``.

    Raises
    ------
    VolumeEVMError
        If the path does not exist, its extension is not supported, or the reader finds the
        file unusable (the message names the file and the problem).
    TypeError
        If an option is not one the format takes.

    Examples
    --------
    >>> vol = read_volume("head.nrrd")  # doctest: +SKIP
    >>> vol.array.shape, vol.spacing  # doctest: +SKIP
    ((256, 256, 108), (0.957, 0.957, 1.5))
    """
    if not isinstance(path, (str, os.PathLike)):
        return read_dicom(list(path), **options)
    path = Path(path)
    if not path.exists():
        raise VolumeEVMError(f"{path}: no such file or folder")
    if path.is_dir():
        return read_dicom(path, **options)
    name = path.name.lower()
    for ending, reader in _READERS.items():
        if name.endswith(ending):
            return reader(path, **options)
    raise VolumeEVMError(
        f"{path}: unsupported file type; supported are {', '.join(SUPPORTED_EXTENSIONS)}, "
        f"or a folder of DICOM files"
    )
