"""What "visible" means for the output depth: one opacity threshold shared by every renderer.

Every renderer (the reference, ray casting and its navigation variant, splatting, shear-warp)
outputs the axial depth of the first *visible* sample along each pixel's ray (``1e10`` where
there is none). A sample is visible when its material is at least :data:`VISIBLE_ALPHA` opaque
per unit length of the transfer function (X-ray: per millimetre of attenuation). The rule is on
the opacity per unit length, not on the sample's own opacity, so that it does not depend on how
long a sample is: a ray caster's sample shortened by the region's surface, the reference's
short pieces between cell boundaries and the shear-warp's slice spacing all see the same
material as visible or not, and the depth at a surface stays exact.

Without a threshold, depth would come from numerical dust: a bilinear tap weight of 1e-15 (the
rounding of a slice's shift) on an opaque voxel gives a sample of opacity 1e-16 beside
transparent ones, which would count as a hit a whole slice in front of what is seen, or where
nothing is seen, and which side of the dust a pixel falls on changes with one ulp of the camera
matrix (with the CPU's BLAS kernel). :func:`visible` and :func:`attenuates` (with their
thresholds, :func:`visible_threshold` and :func:`attenuation_threshold`), and their compiled
twins in :mod:`._optics` for kernels that test one sample at a time, are the only places the
renderers decide a hit for the depth; the colour and opacity they composite are not
thresholded.
"""

import math

import numpy as np

from .._errors import VolumeEVMError
from ._transfer import opacity_correction

__all__ = ["VISIBLE_ALPHA", "VISIBLE_OPTICAL_DEPTH", "visible", "attenuates",
           "visible_threshold", "attenuation_threshold"]

VISIBLE_ALPHA = 2.0 ** -16
"""Opacity per unit length at and above which a sample is visible (gives the depth).

``2**-16 ≈ 1.5e-5``, chosen between two bounds three orders of magnitude or more apart:

- far above numerical dust: float32 rounding of an opacity in ``[0, 1]`` is at most ``2**-24
  ≈ 6e-8`` (256 times smaller), and the dust of float64 rounding in slice shifts and tap
  weights is ``1e-16 .. 1e-13``;
- far below anything a user sees: one step of an 8-bit image is ``1/255 ≈ 3.9e-3`` (256 times
  larger) and one step of a 16-bit image ``1/65535``; a sample under the threshold changes
  neither by itself. (A ray through thousands of such samples can add up to a faint veil that
  then has no depth: the depth is the first sample that is visible by itself.)

A power of two, so that it is exact in float32 and float64 and the comparison means the same
in both.
"""

VISIBLE_OPTICAL_DEPTH = -math.log1p(-VISIBLE_ALPHA)
"""The same threshold as optical depth per unit length, ``-ln(1 - VISIBLE_ALPHA)``: X-ray
samples carry attenuation (``μ·Δ``) rather than opacity."""


def visible(alpha, units):
    """Whether samples of opacity ``alpha`` over ``units`` unit lengths are visible.

    Parameters
    ----------
    alpha : ndarray
        Each sample's opacity over its own length (float32 or float64).
    units : ndarray or float
        The samples' lengths in unit lengths of the transfer function (mm divided by its
        ``unit_length_mm``), broadcast against ``alpha``; a length of 0 is never visible.
        1 for an opacity that is per unit length already (MIP's classified maximum).

    Returns
    -------
    ndarray of bool
        ``alpha >= 1 - (1 - VISIBLE_ALPHA) ** units`` and ``alpha > 0``: the opacity per unit
        length is at least :data:`VISIBLE_ALPHA`. The threshold is rounded to ``alpha``'s
        precision, so that the comparison does not depend on NumPy's casting rules.
    """
    alpha = np.asarray(alpha)
    return (alpha > 0) & (alpha >= visible_threshold(units, alpha.dtype))


def visible_threshold(units, dtype):
    """The opacity from which samples over ``units`` unit lengths are visible (:func:`visible`:
    ``alpha > 0`` and ``alpha >= threshold``), rounded to ``dtype`` (the record of
    :func:`._optics.optics` holds it for a whole step)."""
    return np.asarray(opacity_correction(VISIBLE_ALPHA, units)).astype(dtype)[()]


def attenuates(tau, step_mm):
    """X-ray: whether samples of optical depth ``tau`` (``μ·Δ``) over ``step_mm`` mm are
    visible, i.e. attenuate at least :data:`VISIBLE_OPTICAL_DEPTH` per mm (the opacity of
    :func:`visible` over one mm, ``1 - exp(-μ)``, at least :data:`VISIBLE_ALPHA`).

    Parameters
    ----------
    tau : ndarray
        Each sample's optical depth (float32 or float64).
    step_mm : ndarray or float
        The samples' lengths in mm (broadcast against ``tau``); 0 is never visible.

    Returns
    -------
    ndarray of bool
        ``tau >= VISIBLE_OPTICAL_DEPTH * step_mm`` and ``tau > 0``, the threshold rounded to
        ``tau``'s precision.
    """
    tau = np.asarray(tau)
    return (tau > 0) & (tau >= attenuation_threshold(step_mm, tau.dtype))


def attenuation_threshold(step_mm, dtype):
    """The optical depth from which X-ray samples over ``step_mm`` mm are visible
    (:func:`attenuates`: ``tau > 0`` and ``tau >= threshold``), rounded to ``dtype``."""
    return np.multiply(step_mm, VISIBLE_OPTICAL_DEPTH, dtype=np.float64).astype(dtype)[()]


def checked_depth_in(depth_in, shape):
    """``depth_in`` (the scene's axial depth per pixel, where rays stop) as float64, checked.

    Every renderer takes it; ``None`` (no geometry) stays ``None``.

    Raises
    ------
    VolumeEVMError
        If it is not an array of numbers, its shape is not the image's ``shape``, or it holds
        NaN (1e10 marks pixels without geometry).
    """
    if depth_in is None:
        return None
    try:
        depth_in = np.asarray(depth_in, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise VolumeEVMError(f"depth_in: expected an array of numbers, got "
                             f"{type(depth_in).__name__}") from error
    if depth_in.shape != tuple(shape):
        raise VolumeEVMError(f"depth_in: shape {depth_in.shape} differs from the image's "
                             f"{tuple(shape)}")
    if np.isnan(depth_in).any():
        raise VolumeEVMError(
            f"depth_in: {int(np.isnan(depth_in).sum())} NaN values; use 1e10 for no geometry")
    return depth_in
