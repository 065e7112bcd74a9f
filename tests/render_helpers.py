"""Helpers shared by the renderer tests: cameras looking at a volume, the reference render."""

import numpy as np

from volumeevm_addon import Camera, TransferFunction
from volumeevm_addon.rendering._reference import render_reference

MODES = ("over", "under", "xray", "mip")
XRAY = {"xray_scale": 2e-4, "xray_offset": -1024.0}  # CT: attenuation from -1024 HU up


def centre(vevm, g):
    """World position of the middle of the volume's grid (``g``: grid to world)."""
    return g[:3, 3] + g[:3, :3] @ ((np.array(vevm.shape) - 1) / 2.0)


def camera(kind, g, vevm, offset, scale, res=(36, 30), up=(0.0, 0.0, 1.0), **kw):
    """An orthographic (``scale`` = ortho scale) or perspective camera at the volume's centre
    plus ``offset``, looking at the centre."""
    c = centre(vevm, g)
    return Camera.look_at(c + np.asarray(offset), c, up, kind=kind, ortho_scale=scale,
                          resolution_x=res[0], resolution_y=res[1], clip_start=1e-4, **kw)


def reference(vevm, cam, tf, g, **kw):
    """The dense reference render of a VolumeEVM (the region as the mask)."""
    return render_reference(vevm.to_dense(), vevm.evm.to_mask(vevm.shape), g, vevm.spacing, cam,
                            tf, **kw)


def const_tf(alpha, rgb=(0.9, 0.6, 0.3)):
    """The same colour and opacity for every density."""
    return TransferFunction([(-1e6, *rgb, alpha), (1e6, *rgb, alpha)])
