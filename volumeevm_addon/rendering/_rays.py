"""A camera's pixel rays in a volume's index space, clipped to what a renderer may sample.

The ray casters, splatting and the reference start from the same rays: one per pixel from
:meth:`Camera.rays`, taken into index space (voxel centres at integer indices), and clipped to
the volume's box (index space ``-0.5 .. n - 0.5`` per axis), to the camera's clip range (axial
depths ``clip_start .. clip_end``) and to ``depth_in``. Along each ray the axial depth is affine
in the ray parameter, so a renderer turns the parameter of its depth event into the output
depth with ``a0 + kz·t``.
"""

from dataclasses import dataclass, fields

import numpy as np

from ..model._volume import transform

__all__ = ["Rays", "camera_rays", "box_entry_exit"]


@dataclass(frozen=True, slots=True, eq=False)
class Rays:
    """Rays ``o + t·d`` (index space), flat arrays with one row per ray (float64).

    Attributes
    ----------
    o, d : (n, 3) ndarray
        Origin and direction in index space; ``t`` is the camera's own ray parameter.
    dirs : (n, 3) ndarray
        Direction in world space (unit), for shading.
    t0, t1 : (n,) ndarray
        The clipped part of each ray, ``t0 <= t <= t1``; empty where ``t1 <= t0``.
    a0, kz : (n,) ndarray
        Axial depth (Blender units) along each ray: ``a0 + kz·t``.
    """

    o: np.ndarray
    d: np.ndarray
    dirs: np.ndarray
    t0: np.ndarray
    t1: np.ndarray
    a0: np.ndarray
    kz: np.ndarray

    def take(self, ids):
        """The rays ``ids`` (an index array, a mask or a slice)."""
        return Rays(*(getattr(self, f.name)[ids] for f in fields(self)))

    def mm_per_t(self, spacing):
        """Millimetres per unit of the ray parameter, for voxel ``spacing`` (mm): ``(n,)``."""
        return np.linalg.norm(self.d * spacing, axis=1)


def camera_rays(camera, grid_to_world, shape, depth_in):
    """The pixel rays of ``camera`` in the index space of a grid of ``shape``, clipped.

    Parameters
    ----------
    camera : Camera
    grid_to_world : (4, 4) ndarray
        Voxel-centre index space to world (checked: finite, affine, invertible).
    shape : (3,) sequence of int
        The grid's voxels per axis: its box is ``-0.5 .. n - 0.5``.
    depth_in : (H, W) ndarray or None
        Axial depth where each ray stops (checked), or None.

    Returns
    -------
    Rays
        One ray per pixel, row by row.
    """
    h, w = camera.shape
    origins, directions = camera.rays()
    origins = origins.reshape(-1, 3)
    directions = directions.reshape(-1, 3)
    a0 = camera.axial_depth(origins)
    kz = camera.axial_depth(origins + directions) - a0
    far = np.full(h * w, camera.clip_end)
    if depth_in is not None:
        far = np.minimum(far, depth_in.ravel())
    t_near = (camera.clip_start - a0) / kz
    t_far = (far - a0) / kz
    inv = np.linalg.inv(grid_to_world)
    o = transform(origins, inv[:3, :3].T, inv[:3, 3])
    d = transform(directions, inv[:3, :3].T)
    tmin, tmax = box_entry_exit(o, d, -0.5, np.asarray(shape, dtype=np.float64) - 0.5)
    return Rays(o, d, directions, np.maximum(tmin, t_near), np.minimum(tmax, t_far), a0, kz)


def box_entry_exit(o, d, lo, hi):
    """Entry and exit parameters ``(tmin, tmax)``, ``(n,)`` each, of lines ``o + t·d``
    (``(n, 3)``) through the box ``[lo, hi]`` (slab clipping; a line parallel to a slab is
    inside it everywhere or nowhere). The line misses the box where ``tmax < tmin``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (lo - o) / d
        tb = (hi - o) / d
    parallel = d == 0
    inside = (o >= lo) & (o <= hi)
    tmin = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb))
    tmax = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb))
    return tmin.max(axis=1), tmax.min(axis=1)
