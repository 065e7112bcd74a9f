"""The compositing modes every renderer offers, a view's compositing settings, and the finishing
of X-ray and MIP rays into colours.

- ``"over"``: emission–absorption compositing front to back (early ray termination possible);
- ``"under"``: the same back to front (the same image up to rounding);
- ``"xray"``: attenuation ``T = exp(-Σ μ·Δ)`` with ``μ = xray_scale · max(density -
  xray_offset, 0)`` per mm, output grey premultiplied ``(1 - T, 1 - T, 1 - T, 1 - T)``;
- ``"mip"``: the maximum density along the ray, classified by the transfer function with its
  opacity as given (no length correction).

Over and under composite as they go; X-ray sums optical depths and MIP keeps maxima, which
:func:`finish_mode` turns into RGBA at the end, the same way for every method.
"""

from dataclasses import dataclass

import numpy as np

from . import _depth

__all__ = ["MODES", "MODE_CODES", "Compositing", "finish_mode"]

MODES = ("over", "under", "xray", "mip")
MODE_CODES = {mode: code for code, mode in enumerate(MODES)}
"""The modes as the compiled kernels know them: over 0, under 1, xray 2, mip 3."""


@dataclass(frozen=True, slots=True)
class Compositing:
    """How a view's samples combine along each ray (checked values, :mod:`._checks`).

    Attributes
    ----------
    mode : str
        One of :data:`MODES`.
    termination : float
        ``"over"``: a ray takes nothing more once its opacity reaches this (1: never).
    xray_scale, xray_offset : float
        ``"xray"``: attenuation per mm per data unit, and the density of zero attenuation.
    """

    mode: str
    termination: float = 1.0
    xray_scale: float = 1.0
    xray_offset: float = 0.0


def finish_mode(acc, vmax, mode, tf):
    """Turn the per-ray accumulators of ``"xray"`` and ``"mip"`` into premultiplied RGBA, in
    place.

    ``acc`` (m, 4): X-ray holds the optical depth in column 0; ``vmax`` (m,): MIP's maximum
    density per ray (``-inf`` for none), classified by ``tf`` without length correction.
    Returns, for MIP, the rays whose maximum is visible (the others keep no depth); else None.
    """
    if mode == "xray":
        acc[:] = 1 - np.exp(-acc[:, :1])
    elif mode == "mip":
        seen = np.isfinite(vmax)
        acc[:] = 0
        if seen.any():
            straight = tf.evaluate(vmax[seen])
            acc[seen, 3] = straight[:, 3]
            acc[seen, :3] = straight[:, :3] * straight[:, 3:4]
        return seen & _depth.visible(acc[:, 3], 1.0)
    return None
