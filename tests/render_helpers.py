"""Helpers shared by the renderer tests: cameras looking at a volume, the reference render
(rendered once per test run for each scene, camera, transfer function and options)."""

import dataclasses
import hashlib

import numpy as np

from volumeevm_addon import Camera, TransferFunction
from volumeevm_addon.model import BLENDER_UNITS_PER_MM
from volumeevm_addon.rendering._reference import render_reference

MODES = ("over", "under", "xray", "mip")
XRAY = {"xray_scale": 2e-4, "xray_offset": -1024.0}  # CT: attenuation from -1024 HU up

# The reference images of this test run, keyed by the digest of everything they are made of.
_REFERENCES = {}


def centre(vevm, g):
    """World position of the middle of the volume's grid (``g``: grid to world)."""
    return g[:3, 3] + g[:3, :3] @ ((np.array(vevm.shape) - 1) / 2.0)


def camera(kind, g, vevm, offset, scale, res=(36, 30), up=(0.0, 0.0, 1.0), **kw):
    """An orthographic (``scale`` = ortho scale) or perspective camera at the volume's centre
    plus ``offset``, looking at the centre."""
    c = centre(vevm, g)
    return Camera.look_at(c + np.asarray(offset), c, up, kind=kind, ortho_scale=scale,
                          resolution_x=res[0], resolution_y=res[1], clip_start=1e-4, **kw)


def orbit_camera(g, shape, spacing, direction, kind, res=(48, 40), distance=1.5, zoom=0.9,
                 lens=45.0):
    """A camera looking at the grid's centre from ``direction`` (world), far enough to see it:
    ``distance`` and ``zoom`` (the orthographic scale) in units of the grid's diagonal."""
    c = g[:3, :3] @ ((np.asarray(shape) - 1) / 2.0) + g[:3, 3]
    size = np.linalg.norm(np.asarray(shape) * spacing) * BLENDER_UNITS_PER_MM
    d = np.asarray(direction, dtype=np.float64)
    return Camera.look_at(c + d / np.linalg.norm(d) * size * distance, c, kind=kind,
                          ortho_scale=size * zoom, lens_mm=lens, resolution_x=res[0],
                          resolution_y=res[1], clip_start=0.001)


def _feed(digest, value):
    """Add ``value`` (arrays, numbers, strings, records, containers) to ``digest``, typed."""
    if dataclasses.is_dataclass(value):
        digest.update(type(value).__name__.encode())
        for f in dataclasses.fields(value):
            if f.compare:
                _feed(digest, (f.name, getattr(value, f.name)))
    elif isinstance(value, dict):
        _feed(digest, sorted(value.items()))
    elif isinstance(value, (list, tuple)):
        digest.update(f"{type(value).__name__}{len(value)}(".encode())
        for item in value:
            _feed(digest, item)
        digest.update(b")")
    elif isinstance(value, np.ndarray):
        digest.update(f"{value.dtype.str}{value.shape}".encode())
        digest.update(np.ascontiguousarray(value).tobytes())
    else:
        digest.update(f"{type(value).__name__}:{value!r};".encode())


def scene_key(*parts):
    """The SHA-256 of ``parts``: equal for equal inputs, whichever objects hold them."""
    digest = hashlib.sha256()
    _feed(digest, parts)
    return digest.hexdigest()


def reference(vevm, cam, tf, g, **kw):
    """The dense reference render of a VolumeEVM (the region as the mask).

    Rendered once per test run: the image and depth are kept, read-only, under the digest of
    the densities, the region, the placement, the camera, the transfer function and the
    options, so every test that needs the same reference shares one render."""
    dense = vevm.to_dense()
    mask = vevm.evm.to_mask(vevm.shape)
    key = scene_key(dense, mask, np.asarray(g, np.float64), tuple(vevm.spacing), cam, tf, kw)
    if key not in _REFERENCES:
        images = render_reference(dense, mask, g, vevm.spacing, cam, tf, **kw)
        for image in images:
            image.flags.writeable = False
        _REFERENCES[key] = images
    return _REFERENCES[key]


def const_tf(alpha, rgb=(0.9, 0.6, 0.3)):
    """The same colour and opacity for every density."""
    return TransferFunction([(-1e6, *rgb, alpha), (1e6, *rgb, alpha)])
