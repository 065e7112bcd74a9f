"""Laying a volume render over a scene render: colour by alpha over, depth by what is seen.

Both images are premultiplied RGBA, row 0 at the top, as :func:`~volumeevm_addon.render`
returns them and as the Blender side reads the scene's render back. Alpha over is the right
operator for a translucent volume in front of opaque geometry when the volume's rays already
stopped at the scene's depth (``depth_in``): a Z-combine would be wrong (``volumeevm.md``,
section 4).
"""

import numpy as np

from .._errors import VolumeEVMError
from ._camera import BACKGROUND_DEPTH

__all__ = ["composite_over", "output_depth"]


def composite_over(dvr_rgba, scene_rgba):
    """Premultiplied alpha over: ``dvr + (1 - dvr.a) * scene`` for all four channels.

    Parameters
    ----------
    dvr_rgba : (H, W, 4) array_like
        The volume render, premultiplied RGBA.
    scene_rgba : (H, W, 4) array_like
        The scene render behind it, premultiplied RGBA, the same shape.

    Returns
    -------
    (H, W, 4) ndarray of np.float32
        The composite, premultiplied.

    Raises
    ------
    VolumeEVMError
        When the two are not RGBA images of the same shape.

    Examples
    --------
    >>> import numpy as np
    >>> from volumeevm_addon.rendering import composite_over
    >>> half_red = np.array([[[0.5, 0.0, 0.0, 0.5]]])
    >>> blue = np.array([[[0.0, 0.0, 1.0, 1.0]]])
    >>> composite_over(half_red, blue)
    array([[[0.5, 0. , 0.5, 1. ]]], dtype=float32)
    """
    dvr = np.asarray(dvr_rgba, np.float32)
    scene = np.asarray(scene_rgba, np.float32)
    if dvr.shape != scene.shape or dvr.ndim != 3 or dvr.shape[2] != 4:
        raise VolumeEVMError(f"dvr_rgba {dvr.shape} and scene_rgba {scene.shape}: expected the "
                             f"same (H, W, 4) shape")
    return dvr + (1.0 - dvr[..., 3:4]) * scene


def output_depth(dvr_depth, scene_depth):
    """Depth of the composite: the volume's where it saw something, else the scene's.

    Parameters
    ----------
    dvr_depth : (H, W) array_like
        Axial depth of the volume's first visible sample (Blender units),
        :data:`~volumeevm_addon.rendering.BACKGROUND_DEPTH` where it saw nothing.
    scene_depth : (H, W) array_like
        The scene's axial depth, the same shape.

    Returns
    -------
    (H, W) ndarray of np.float32

    Raises
    ------
    VolumeEVMError
        When the two are not images of the same (H, W) shape.

    Examples
    --------
    >>> from volumeevm_addon.rendering import BACKGROUND_DEPTH, output_depth
    >>> output_depth([[2.0, BACKGROUND_DEPTH]], [[5.0, 7.0]])
    array([[2., 7.]], dtype=float32)
    """
    dvr_depth = np.asarray(dvr_depth, np.float32)
    scene_depth = np.asarray(scene_depth, np.float32)
    if dvr_depth.shape != scene_depth.shape or dvr_depth.ndim != 2:
        raise VolumeEVMError(f"dvr_depth {dvr_depth.shape} and scene_depth {scene_depth.shape}: "
                             f"expected the same (H, W) shape")
    return np.where(dvr_depth < BACKGROUND_DEPTH, dvr_depth, scene_depth).astype(np.float32)
