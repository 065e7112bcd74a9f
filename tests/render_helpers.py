"""Helpers shared by the renderer tests: cameras looking at a volume, the reference render."""

import numpy as np

from volumeevm_addon.rendering._camera import Camera
from volumeevm_addon.rendering._reference import render_reference
from volumeevm_addon.rendering._transfer import TransferFunction

MODES = ("over", "under", "xray", "mip")
XRAY = {"xray_scale": 2e-4, "xray_offset": -1024.0}  # CT: attenuation from -1024 HU up


def look_at(eye, target, up=(0.0, 0.0, 1.0)):
    """Camera-to-world matrix of a camera at ``eye`` looking at ``target`` (Blender's frame:
    looks down -Z, +Y up as close to ``up`` as possible)."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    f = target - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    if np.linalg.norm(r) < 1e-9:  # looking along `up`
        r = np.cross(f, (0.0, 1.0, 0.0))
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = r, u, -f, eye
    return m


def centre(vevm, g):
    """World position of the middle of the volume's grid (``g``: grid to world)."""
    return g[:3, 3] + g[:3, :3] @ ((np.array(vevm.shape) - 1) / 2.0)


def camera(kind, g, vevm, offset, scale, res=(36, 30), up=(0.0, 0.0, 1.0), **kw):
    """An orthographic (``scale`` = ortho scale) or perspective camera at the volume's centre
    plus ``offset``, looking at the centre."""
    c = centre(vevm, g)
    m = look_at(c + np.asarray(offset), c, up)
    if kind == "ORTHO":
        return Camera.orthographic(m, scale, resolution_x=res[0], resolution_y=res[1],
                                   clip_start=1e-4, **kw)
    return Camera.perspective(m, 50.0, resolution_x=res[0], resolution_y=res[1],
                              clip_start=1e-4, **kw)


def reference(vevm, cam, tf, g, **kw):
    """The dense reference render of a VolumeEVM (the region as the mask)."""
    return render_reference(vevm.to_dense(), vevm.evm.to_mask(vevm.shape), g, vevm.spacing, cam,
                            tf, **kw)


def const_tf(alpha, rgb=(0.9, 0.6, 0.3)):
    """The same colour and opacity for every density."""
    return TransferFunction([(-1e6, *rgb, alpha), (1e6, *rgb, alpha)])
