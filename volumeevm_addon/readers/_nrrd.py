"""NRRD volumes (``.nrrd``, and ``.nhdr`` with a detached data file) via pynrrd.

pynrrd returns the data in Fortran index order, so the first NRRD axis (the fastest in the file)
is the first array index: the array is already ``[x, y, z]``.

Geometry: the NRRD ``space directions`` give one vector per axis (voxel step in ``space``
coordinates, its length is the spacing) and ``space origin`` is the centre of the first voxel.
Patient spaces are converted to LPS by flipping the axes the space names opposite ways
(RAS flips x and y, LAS flips y). Spaces without a patient frame (``scanner-xyz``,
``3D-right-handed``) are taken as they are. Without ``space directions`` the per-axis
``spacings`` field is used, and without either the spacing is unknown. ``space units`` other
than millimetres are converted to millimetres.
"""

import numpy as np

from .._errors import VolumeEVMError
from ._checks import check_ndim, checked_volume, import_reader_package, mm_per_unit

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


def read_nrrd(path):
    """Read a 3-D scalar NRRD file.

    Parameters
    ----------
    path : str or Path
        The ``.nrrd`` file or ``.nhdr`` header.

    Returns
    -------
    Volume
        Orientation columns and origin in LPS from ``space directions`` / ``space origin``;
        identity orientation and zero origin when the header has no space.

    Raises
    ------
    VolumeEVMError
        If pynrrd is missing, the header or data cannot be parsed (corrupt, truncated), the
        space is not 3-D or not one listed above, or the data is not a 3-D scalar grid.
    """
    nrrd = import_reader_package("nrrd", "pynrrd", path)
    try:
        data, header = nrrd.read(str(path))
    except (nrrd.NRRDError, KeyError, ValueError, OSError, EOFError) as exc:
        raise VolumeEVMError(f"{path}: corrupt NRRD file ({exc})") from exc
    check_ndim(data.shape, path)

    space = header.get("space")
    sign = np.ones(3)
    if space is not None:
        key = str(space).lower()
        if key not in _TO_LPS:
            raise VolumeEVMError(
                f"{path}: unsupported NRRD space {space!r}; supported: {', '.join(_TO_LPS)}"
            )
        sign = np.asarray(_TO_LPS[key])
    units = header.get("space units")
    scale = np.ones(3)
    if units is not None:
        scale = np.array([mm_per_unit(u, path, "'space units'") for u in units], dtype=float)
        if scale.shape != (3,):
            raise VolumeEVMError(f"{path}: corrupt header: 'space units' {units} is not 3 units")

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
        if spacings is not None and np.all(np.isfinite(spacings)):
            spacing = np.asarray(spacings, dtype=np.float64) * scale
        orientation = None
    origin = np.asarray(header.get("space origin", np.zeros(3)), dtype=np.float64)
    if origin.shape != (3,):
        raise VolumeEVMError(f"{path}: corrupt header: 'space origin' {origin} is not 3-D")
    return checked_volume(
        data, path, spacing=spacing, origin=origin * scale * sign, orientation=orientation
    )
