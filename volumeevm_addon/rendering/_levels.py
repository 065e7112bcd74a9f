"""Which resolution level a view needs: the camera's side of "model no more than a view needs".

The levels themselves (how a coarser VolumeEVM is made) are the model's
(:mod:`volumeevm_addon.model._levels`); choosing one is a decision about pixels, made here.
"""

import numpy as np

from .._errors import VolumeEVMError

__all__ = ["LEVELS", "auto_factor", "level_factor"]

LEVELS = ("full", "auto")
"""The named levels ``render`` accepts besides an integer factor."""


def auto_factor(shape, grid_to_world, camera):
    """The coarsest level whose voxels are still no wider than one image pixel.

    Rule: with ``s`` the largest voxel edge in world units (the columns of ``grid_to_world``)
    and ``p`` the smaller pixel edge in world units where the volume is nearest the camera
    (orthographic: the view plane over the resolution; perspective: that at unit distance times
    the smallest axial depth of the volume's box, at least the near clip), the factor is the
    largest power of two ``f`` with ``f * s <= p`` (1 when a voxel already covers a pixel or
    more), and never more than the grid's largest side.

    Parameters
    ----------
    shape : tuple of 3 int
        The fine grid.
    grid_to_world : (4, 4) ndarray
        Voxel-centre indices to world units (:func:`volumeevm_addon.grid_to_world`).
    camera : Camera

    Returns
    -------
    int
    """
    g = np.asarray(grid_to_world, dtype=np.float64)
    voxel = float(np.linalg.norm(g[:3, :3], axis=0).max())
    xmin, xmax, ymin, ymax = camera.viewplane
    pixel = min((xmax - xmin) / camera.width, (ymax - ymin) / camera.height)
    if not camera.is_ortho:
        n = np.asarray(shape, dtype=np.float64)
        corners = np.array([[a, b, c] for a in (-0.5, n[0] - 0.5) for b in (-0.5, n[1] - 0.5)
                            for c in (-0.5, n[2] - 0.5)])
        nearest = camera.axial_depth(corners @ g[:3, :3].T + g[:3, 3]).min()
        pixel *= max(float(nearest), camera.clip_start)
    f = 1
    while 2 * f * voxel <= pixel and 2 * f <= max(shape):
        f *= 2
    return f


def level_factor(level, shape, grid_to_world, camera):
    """The integer factor that ``level`` ("full", "auto" or an int >= 1) names for this view."""
    if isinstance(level, str):
        if level not in LEVELS:
            raise VolumeEVMError(f"level must be one of {LEVELS} or an integer >= 1, got {level!r}")
        return 1 if level == "full" else auto_factor(shape, grid_to_world, camera)
    if isinstance(level, (bool, np.bool_)) or not isinstance(level, (int, np.integer)) or level < 1:
        raise VolumeEVMError(f"level must be one of {LEVELS} or an integer >= 1, got {level!r}")
    return int(level)
