"""NIfTI-1/2 volumes (``.nii``, ``.nii.gz``): the header parsed by nibabel, the data read here.

The header (348 bytes for NIfTI-1, 540 for NIfTI-2, either byte order) is parsed by nibabel's
header classes without their silent repairs, and checked before any data is read: a single-file
magic (``n+1`` / ``n+2``), 1 to 7 positive dimensions, a known datatype whose ``bitpix``
agrees, and a ``vox_offset`` past the header. The file must then hold exactly ``vox_offset``
plus the bytes the dimensions and datatype need: for ``.nii.gz`` the decompressed stream, which
is read to its end so that gzip verifies its CRC-32 and length, and is never inflated past that
size (a decompression bomb is cut off). A changed dimension or datatype, a truncated or padded
file and a corrupt compressed stream are refused, not read as different voxels.

Voxels are stored with i fastest, so the array is already ``[x, y, z]``. The affine (sform if
its code is set, else qform, else pixdim only, as nibabel's ``get_best_affine`` chooses) maps
voxel centres to RAS+ mm; LPS is the same frame with x and y reversed, so the LPS affine is the
RAS one with its first two rows negated. Column ``i`` of the 3x3 part is the voxel step along
index axis ``i``: its length is the spacing, its direction the orientation column; the
translation is the centre of voxel ``(0, 0, 0)``. Without an sform the voxel sizes come from
``pixdim[1:4]``: all three 0 means the file gives none (spacing unknown, 1 mm used), any other
value that is not a positive finite number is a corrupt header.

``scl_slope`` / ``scl_inter`` are applied when they are not the identity (with nibabel's
``apply_read_scaling``, so the result is the ``float64`` nibabel's scaled ``dataobj`` gives);
a slope of 0 or NaN means no scaling (NIfTI standard). With identity scaling the stored dtype is
kept, so an ``int16`` file stays ``int16``. Trailing axes of length 1 (``(X, Y, Z, 1)`` files)
are dropped.

Data units: the NIfTI header has no field for them (``xyzt_units`` are space and time,
``intent_*`` the statistic, ``descrip`` free text), so the volume's ``units`` are "" and the
caller says them (``read_volume(path, units="HU")``).

``lazy=True`` on an uncompressed ``.nii`` maps the voxel data read-only after the same header and
length checks (:func:`._checks.lazy_mapped`) and scales chunk by chunk, so a file larger than
memory opens; a ``.nii.gz`` stream can only be read whole, and is refused with that said.
"""

import gzip
import io
import math
import os
import zlib

import numpy as np

from .._errors import VolumeEVMError
from ._checks import (
    check_ndim,
    check_read_memory,
    checked_volume,
    import_reader_package,
    lazy_mapped,
    mm_per_unit,
    open_file,
    read_payload,
)

_RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0])

#: Header size (``sizeof_hdr``) -> (header class name in nibabel, single-file magic).
_VERSIONS = {348: ("Nifti1Header", b"n+1"), 540: ("Nifti2Header", b"n+2")}


def read_nifti(path, lazy=False):
    """Read a 3-D NIfTI image.

    Parameters
    ----------
    path : str or Path
        The ``.nii`` or ``.nii.gz`` file.
    lazy : bool
        Map an uncompressed ``.nii`` read-only and return its array as a lazy Dask array
        (nothing is read until a chunk is computed; scaling applied per chunk).

    Returns
    -------
    Volume
        Spacing, orientation (LPS columns) and origin from the image affine; spacing converted
        to mm from the header's spatial unit ("unknown" is taken as mm).

    Raises
    ------
    VolumeEVMError
        If nibabel is missing, the file is not a readable single-file NIfTI (corrupt header,
        a length other than the header announces, a corrupt compressed stream), the image is
        not 3-D, it would not fit in memory, or ``lazy`` is asked of a ``.nii.gz``.
    """
    nib = import_reader_package("nibabel", "nibabel", path)
    compressed = str(path).lower().endswith(".gz")
    if lazy and compressed:
        raise VolumeEVMError(f"{path}: lazy=True needs uncompressed data (a gzip stream is read "
                             f"whole); decompress it to a .nii first, or read it without lazy")
    with open_file(path) as raw, (gzip.GzipFile(fileobj=raw) if compressed else raw) as stream:
        what = "gzip-compressed NIfTI data" if compressed else "NIfTI voxel data"
        header, header_bytes = _read_header(nib, stream, path, what)
        shape, dtype, offset = _layout(header, header_bytes, path)
        count = math.prod(shape)
        nbytes = count * dtype.itemsize
        size = None if compressed else os.fstat(raw.fileno()).st_size
        if size is not None and size != offset + nbytes:
            raise VolumeEVMError(
                f"{path}: not a readable NIfTI image (the file has {size} bytes but its header "
                f"announces {offset} + {nbytes} for {'x'.join(map(str, shape))} voxels of "
                f"{dtype}); the file is truncated or its header is corrupt"
            )
        slope, inter = _scaling(header, path)
        scaled = slope is not None and (slope, inter) != (1.0, 0.0)
        if lazy:
            scaling = (slope, inter) if scaled else None
            return _lazy(nib, path, header, offset, shape, dtype, scaling)
        # The buffer and its C-ordered copy; when scaled, later the C-ordered copy and two
        # float64 arrays at once (the product and the sum nibabel's scaling makes).
        check_read_memory(path, shape, dtype, copies=1,
                          extra=max(nbytes, 16 * count) if scaled else nbytes)
        buffer = read_payload(stream, offset - header_bytes + nbytes, path, what,
                              start=header_bytes)
    array = np.frombuffer(buffer, dtype, count, offset - header_bytes).reshape(shape, order="F")
    array = np.ascontiguousarray(array, dtype=dtype.newbyteorder("="))
    del buffer
    if scaled:
        array = nib.volumeutils.apply_read_scaling(array, slope, inter)
    spacing, origin, orientation = _geometry(header, path)
    return checked_volume(array, path, spacing=spacing, origin=origin, orientation=orientation)


def _lazy(nib, path, header, offset, shape, dtype, scaling):
    """The image over a read-only memory map; ``scaling`` ``(slope, inter)`` applied per chunk
    with nibabel's own function, to the dtype it gives a whole array (the eager result's)."""
    array = lazy_mapped(path, offset, shape, dtype, fortran_order=True)
    if scaling is not None:
        native = dtype.newbyteorder("=")
        scaled = nib.volumeutils.apply_read_scaling(np.zeros(1, native), *scaling).dtype
        array = array.map_blocks(lambda block: nib.volumeutils.apply_read_scaling(
            np.ascontiguousarray(block, native), *scaling), dtype=scaled)
    spacing, origin, orientation = _geometry(header, path)
    return checked_volume(array, path, spacing=spacing, origin=origin, orientation=orientation)


def _read_header(nib, stream, path, what):
    """nibabel's header object for the header at the start of ``stream``, and its size in bytes."""
    try:
        start = stream.read(4)
        size = next((n for n in _VERSIONS if start in (n.to_bytes(4, "little"),
                                                       n.to_bytes(4, "big"))), None)
        if size is None:
            raise VolumeEVMError(
                f"{path}: not a readable NIfTI image (the header size field is not 348 or 540: "
                f"not a NIfTI-1 or NIfTI-2 file)"
            )
        block = start + stream.read(size - 4)
    except (OSError, EOFError, zlib.error) as exc:
        raise VolumeEVMError(
            f"{path}: the {what} is corrupt or truncated ({type(exc).__name__}: {exc})"
        ) from exc
    if len(block) < size:
        raise VolumeEVMError(
            f"{path}: not a readable NIfTI image (the file ends inside the {size}-byte header)"
        )
    class_name, magic = _VERSIONS[size]
    try:
        # check=False: nibabel's checks would silently repair a bad vox_offset or pixdim.
        header = getattr(nib, class_name).from_fileobj(io.BytesIO(block), check=False)
    except Exception as exc:  # nibabel reports a corrupt header in several exception types
        raise VolumeEVMError(f"{path}: not a readable NIfTI image (corrupt header: {exc})") from exc
    if header["magic"].item() != magic:
        raise VolumeEVMError(
            f"{path}: not a readable NIfTI image (magic {header['magic'].item()!r}, expected "
            f"{magic!r}: a .hdr/.img pair header or a corrupt file)"
        )
    return header, size


def _layout(header, header_bytes, path):
    """Shape (3-D, trailing unit axes dropped), dtype and data offset, checked."""
    corrupt = f"{path}: not a readable NIfTI image (corrupt header:"
    dim = [int(d) for d in header["dim"]]
    if not 1 <= dim[0] <= 7 or min(dim[1:dim[0] + 1]) < 1:
        raise VolumeEVMError(f"{corrupt} dimensions {dim[:8]} are not 1 to 7 positive sizes)")
    shape = tuple(dim[1:dim[0] + 1])
    while len(shape) > 3 and shape[-1] == 1:
        shape = shape[:-1]
    check_ndim(shape, path)
    try:
        dtype = header.get_data_dtype()
    except Exception as exc:  # nibabel: an unknown datatype code
        raise VolumeEVMError(
            f"{corrupt} datatype code {int(header['datatype'])} is not one NIfTI defines)"
        ) from exc
    if dtype.kind not in "uif":
        raise VolumeEVMError(
            f"{path}: unsupported data type {dtype}; densities must be integers or real floating "
            f"point numbers"
        )
    if int(header["bitpix"]) != 8 * dtype.itemsize:
        raise VolumeEVMError(
            f"{corrupt} bitpix {int(header['bitpix'])} disagrees with datatype {dtype}, "
            f"{8 * dtype.itemsize} bits)"
        )
    offset = float(header["vox_offset"])
    if not offset.is_integer() or offset < header_bytes + 4:
        raise VolumeEVMError(
            f"{corrupt} vox_offset {offset:g} is not a whole number of bytes past the "
            f"{header_bytes + 4}-byte header and extension flag)"
        )
    return shape, dtype, int(offset)


def _scaling(header, path):
    """``(slope, intercept)`` or ``(None, None)`` for no scaling, as nibabel reads them."""
    try:
        return header.get_slope_inter()
    except Exception as exc:  # nibabel: a valid slope with a non-finite intercept
        raise VolumeEVMError(f"{path}: not a readable NIfTI image (corrupt header: {exc})") from exc


def _geometry(header, path):
    """Spacing (``None`` when unknown), origin and orientation in LPS mm from the header."""
    pixdim = header["pixdim"].astype(np.float64)
    voxel = pixdim[1:4]
    spacing_known = True
    if int(header["sform_code"]) == 0:
        if np.all(voxel == 0):
            spacing_known = False
            pixdim[1:4] = 1.0
        elif not (np.all(np.isfinite(voxel)) and np.all(voxel > 0)):
            raise VolumeEVMError(
                f"{path}: not a readable NIfTI image (corrupt header: voxel sizes pixdim[1:4] = "
                f"{voxel.tolist()} are not positive finite numbers)"
            )
        if pixdim[0] == 0:  # NIfTI standard: a qfac of 0 means 1
            pixdim[0] = 1.0
        header = header.copy()
        header["pixdim"] = pixdim
    try:
        affine = header.get_best_affine()
    except Exception as exc:  # nibabel: a qfac other than -1, 0 or 1, a bad quaternion, ...
        raise VolumeEVMError(f"{path}: not a readable NIfTI image (corrupt header: {exc})") from exc
    try:
        space_unit = header.get_xyzt_units()[0]
    except KeyError as exc:
        raise VolumeEVMError(
            f"{path}: not a readable NIfTI image (corrupt header: xyzt_units "
            f"{int(header['xyzt_units'])} holds no known spatial unit code)"
        ) from exc
    scale = 1.0 if space_unit == "unknown" else mm_per_unit(space_unit, path, "xyzt_units")
    steps = _RAS_TO_LPS @ affine[:3, :3] * scale
    spacing = np.linalg.norm(steps, axis=0)
    # A zero column reaches checked_volume as a corrupt (non-positive) spacing.
    orientation = steps / np.where(spacing > 0, spacing, 1.0)
    return (spacing if spacing_known else None), _RAS_TO_LPS @ affine[:3, 3] * scale, orientation
