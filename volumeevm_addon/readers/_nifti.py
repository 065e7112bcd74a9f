"""NIfTI-1/2 volumes (``.nii``, ``.nii.gz``) via nibabel.

nibabel's array is indexed ``[i, j, k]`` with i fastest in the file, i.e. already ``[x, y, z]``.
Its affine (sform, else qform, as nibabel chooses) maps voxel centres to RAS+ mm; LPS is the same
frame with x and y reversed, so the LPS affine is the RAS one with its first two rows negated.
Column ``i`` of the 3x3 part is the voxel step along index axis ``i``: its length is the spacing,
its direction the orientation column. The translation is the centre of voxel ``(0, 0, 0)``.

``scl_slope`` / ``scl_inter`` are applied when they are not the identity (the result is
``float64``, as nibabel's scaled ``dataobj`` gives it); with identity scaling the stored dtype
is kept, so an ``int16`` file stays ``int16``. Trailing axes of length 1 (``(X, Y, Z, 1)``
files) are dropped.
"""

import numpy as np

from .._errors import VolumeEVMError
from ._checks import check_ndim, checked_volume, import_reader_package, mm_per_unit

_RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0])


def read_nifti(path):
    """Read a 3-D NIfTI image.

    Parameters
    ----------
    path : str or Path
        The ``.nii`` or ``.nii.gz`` file.

    Returns
    -------
    Volume
        Spacing, orientation (LPS columns) and origin from the image affine; spacing converted
        to mm from the header's spatial unit ("unknown" is taken as mm).

    Raises
    ------
    VolumeEVMError
        If nibabel is missing, the file is not a readable NIfTI (corrupt header, truncated
        data) or the image is not 3-D.
    """
    nib = import_reader_package("nibabel", "nibabel", path)
    try:
        img = nib.load(str(path))
        shape = img.shape
        while len(shape) > 3 and shape[-1] == 1:
            shape = shape[:-1]
        check_ndim(shape, path)
        # nibabel's dataobj applies the scaling itself; identity scaling keeps the stored dtype.
        array = np.asanyarray(img.dataobj).reshape(shape)
        space_unit = img.header.get_xyzt_units()[0]
    except (nib.filebasedimages.ImageFileError, ValueError, OSError, EOFError) as exc:
        raise VolumeEVMError(f"{path}: not a readable NIfTI image ({exc})") from exc
    scale = 1.0 if space_unit == "unknown" else mm_per_unit(space_unit, path, "xyzt_units")
    steps = _RAS_TO_LPS @ img.affine[:3, :3] * scale
    spacing = np.linalg.norm(steps, axis=0)
    # A zero column reaches checked_volume as a corrupt (non-positive) spacing.
    orientation = steps / np.where(spacing > 0, spacing, 1.0)
    return checked_volume(
        array,
        path,
        spacing=spacing,
        origin=_RAS_TO_LPS @ img.affine[:3, 3] * scale,
        orientation=orientation,
    )
