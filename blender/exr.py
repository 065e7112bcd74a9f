"""OpenEXR files for the DVR inside Blender: the core's writer and reader
(:func:`volumeevm_addon.write_exr`, through the ``OpenEXR`` module), or, when that module is not
installed (Blender does not bundle it), the OpenImageIO module Blender bundles (exposed with
``bpy.utils.expose_bundled_modules()``, Blender 4.4+). Same arrays, same atomic writes.
"""

import numpy as np

from .. import volumeevm_addon as core
from ..volumeevm_addon import VolumeEVMError
from ..volumeevm_addon.rendering import exr_channels, openexr_module
from ..volumeevm_addon.system import write_atomically

__all__ = ["write_exr", "read_exr"]


def _oiio():
    import bpy

    if hasattr(bpy.utils, "expose_bundled_modules"):
        bpy.utils.expose_bundled_modules()
    try:
        import OpenImageIO
    except ImportError:
        raise VolumeEVMError("cannot read or write EXR files: neither the OpenEXR module nor "
                             "Blender's OpenImageIO is available") from None
    return OpenImageIO


def write_exr(path, rgba, depth=None, *, overwrite=False):
    """:func:`volumeevm_addon.write_exr`, through OpenImageIO without OpenEXR."""
    if openexr_module() is not None:
        return core.write_exr(path, rgba, depth, overwrite=overwrite)
    channels = exr_channels(rgba, depth)
    return write_atomically(path, lambda temporary: _write_oiio(temporary, channels),
                            overwrite=overwrite)


def _write_oiio(path, channels):
    oiio = _oiio()
    names = list(channels)
    h, w = channels[names[0]].shape
    spec = oiio.ImageSpec(w, h, len(names), "float")
    spec.channelnames = tuple(names)
    spec.alpha_channel = names.index("A")
    if "Z" in names:
        spec.z_channel = names.index("Z")
    spec.attribute("compression", "zip")
    out = oiio.ImageOutput.create(str(path))
    if out is None or not out.open(str(path), spec):
        raise OSError(f"{path}: cannot write EXR ({oiio.geterror()})")
    try:
        out.write_image(np.stack([channels[n] for n in names], axis=-1))
    finally:
        out.close()


def read_exr(path):
    """:func:`volumeevm_addon.read_exr`, through OpenImageIO without OpenEXR."""
    if openexr_module() is not None:
        return core.read_exr(path)
    oiio = _oiio()
    channels = {}
    source = oiio.ImageInput.open(str(path))
    if source is None:
        raise OSError(f"{path}: cannot read EXR ({oiio.geterror()})")
    try:
        subimage = 0
        while source.seek_subimage(subimage, 0):
            spec = source.spec()
            pixels = source.read_image(subimage, 0, 0, spec.nchannels, "float")
            pixels = np.asarray(pixels, np.float32).reshape(spec.height, spec.width, -1)
            for i, name in enumerate(spec.channelnames):
                channels[name] = np.ascontiguousarray(pixels[..., i])
            subimage += 1
    finally:
        source.close()
    return channels
