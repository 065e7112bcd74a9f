"""The volume record every reader returns: densities on a regular grid and where the grid sits.

Conventions (one place for all of them):

- ``array`` is indexed ``[x, y, z]``; x is the first index.
- Voxel ``(i, j, k)`` is the unit cell ``[i, i+1] x [j, j+1] x [k, k+1]`` of the lattice; its
  density sits at the cell centre (the EVM's cells; Blender/OpenVDB convention).
- ``origin`` is the physical position (mm) of the *centre* of voxel ``(0, 0, 0)``, as DICOM,
  NIfTI and NRRD give it.
- ``orientation`` is a 3x3 matrix whose column ``i`` is the unit direction of index axis ``i`` in
  the patient frame LPS (+x left, +y posterior, +z superior). LPS maps straight onto Blender's
  axes: Z up is superior and the front view (looking along +Y) faces the patient's anterior side.
- ``units`` are the data's own units ("HU" for CT); densities are never rescaled by the core.
"""

from dataclasses import dataclass, field

import numpy as np

BLENDER_UNITS_PER_MM = 0.001
"""The one unit mapping: 1 mm of patient space is 0.001 Blender units (1 BU = 1 m, Blender's
default metric scene), so a 25 cm head is 0.25 BU across and measures right in Blender."""


@dataclass(frozen=True)
class Volume:
    """A grey-level volume with its grid geometry.

    Parameters
    ----------
    array : (X, Y, Z) ndarray
        Densities in data units, indexed ``[x, y, z]``.
    spacing : tuple of 3 float
        Voxel size in mm along x, y, z.
    origin : tuple of 3 float
        Physical position (mm, LPS) of the centre of voxel ``(0, 0, 0)``.
    orientation : (3, 3) ndarray
        Column ``i`` is the direction of index axis ``i`` in LPS.
    units : str
        Data units ("HU", "a.u.", ...); "" when the file does not say.
    source : str
        The file or folder the volume was read from ("" for arrays made in memory).
    spacing_known : bool
        False when the file carries no spacing and ``spacing`` is a guess of 1 mm.
    """

    array: np.ndarray
    spacing: tuple = (1.0, 1.0, 1.0)
    origin: tuple = (0.0, 0.0, 0.0)
    orientation: np.ndarray = field(default_factory=lambda: np.eye(3))
    units: str = ""
    source: str = ""
    spacing_known: bool = True

    @property
    def shape(self):
        """Grid shape ``(X, Y, Z)``."""
        return self.array.shape

    def index_to_physical(self):
        """4x4 matrix taking voxel-centre indices ``(i, j, k, 1)`` to physical mm (LPS)."""
        return index_to_physical(self.spacing, self.origin, self.orientation)


def index_to_physical(spacing, origin, orientation=None):
    """4x4 matrix from voxel-centre index space to physical mm (LPS).

    A lattice point ``p`` (a voxel corner, as EVM vertices are) sits at index ``p - 0.5``.
    """
    m = np.eye(4)
    rot = np.eye(3) if orientation is None else np.asarray(orientation, dtype=np.float64)
    m[:3, :3] = rot * np.asarray(spacing, dtype=np.float64)[None, :]
    m[:3, 3] = origin
    return m


def grid_to_world(spacing, origin, orientation=None, matrix_world=None):
    """4x4 matrix from voxel-centre indices to Blender world units.

    ``matrix_world`` (the volume object's placement, default identity) after the one unit mapping
    :data:`BLENDER_UNITS_PER_MM` after :func:`index_to_physical`.
    """
    scale = np.diag([BLENDER_UNITS_PER_MM] * 3 + [1.0])
    placement = np.eye(4) if matrix_world is None else np.asarray(matrix_world, dtype=np.float64)
    return placement @ scale @ index_to_physical(spacing, origin, orientation)
