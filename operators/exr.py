"""OpenEXR files for the DVR: write R, G, B, A, Z atomically; read every channel of a file.

Writing and reading go through the ``OpenEXR`` module (PyPI ``OpenEXR`` >= 3.3) when it can be
imported, else through the OpenImageIO module that Blender bundles (exposed with
``bpy.utils.expose_bundled_modules()``, Blender 4.4+). Arrays are ``(H, W)`` float32 with row 0
at the **top** (EXR's own order; Blender images are bottom row first).

Files are written to a temporary name in the target folder and renamed into place, so a reader
never sees half a file; an existing file is replaced only when ``overwrite=True``.
"""

import os
import tempfile
from pathlib import Path

import numpy as np

from ..volumeevm_addon import VolumeEVMError

__all__ = ["write_exr", "read_exr", "atomic_target", "replace_atomically"]


def _openexr():
    try:
        import OpenEXR
    except ImportError:
        return None
    return OpenEXR


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


def atomic_target(path, *, overwrite):
    """Check that ``path`` may be written and make its folder; returns it as a ``Path``.

    Raises
    ------
    VolumeEVMError
        If ``path`` exists and ``overwrite`` is False, or names a folder.
    """
    path = Path(path)
    if path.is_dir():
        raise VolumeEVMError(f"{path}: is a folder, not a file name")
    if path.exists() and not overwrite:
        raise VolumeEVMError(f"{path}: exists; choose another name or allow overwriting")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def temporary_beside(path):
    """A new empty file in ``path``'s folder with the same suffix (for an atomic write)."""
    handle, temporary = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix,
                                         dir=path.parent)
    os.close(handle)
    return Path(temporary)


def replace_atomically(temporary, path):
    """Give ``temporary`` the usual file mode and rename it to ``path``."""
    mask = os.umask(0o022)
    os.umask(mask)
    os.chmod(temporary, 0o666 & ~mask)  # mkstemp makes 0600
    os.replace(temporary, path)


def write_exr(path, rgba, depth=None, *, overwrite=False):
    """Write an RGBA (+ Z) float image to an OpenEXR file, atomically.

    Parameters
    ----------
    path : str or Path
        Target file.
    rgba : (H, W, 4) ndarray
        Premultiplied, scene-linear colour and alpha; row 0 at the top.
    depth : (H, W) ndarray, optional
        Axial depth (Blender units) for the ``Z`` channel (1e10 where nothing is seen).
    overwrite : bool
        Replace an existing file (default False: raise instead).

    Returns
    -------
    Path
        The file written.
    """
    rgba = np.ascontiguousarray(rgba, np.float32)
    if rgba.ndim != 3 or rgba.shape[2] != 4:
        raise VolumeEVMError(f"rgba: expected (H, W, 4), got shape {rgba.shape}")
    channels = {name: np.ascontiguousarray(rgba[..., i]) for i, name in enumerate("RGBA")}
    if depth is not None:
        depth = np.ascontiguousarray(depth, np.float32)
        if depth.shape != rgba.shape[:2]:
            raise VolumeEVMError(f"depth: expected shape {rgba.shape[:2]}, got {depth.shape}")
        channels["Z"] = depth
    path = atomic_target(path, overwrite=overwrite)
    temporary = temporary_beside(path)
    try:
        exr = _openexr()
        if exr is not None:
            header = {"compression": exr.ZIP_COMPRESSION, "type": exr.scanlineimage}
            parts = {name: exr.Channel(name, data) for name, data in channels.items()}
            with exr.File(header, parts) as file:
                file.write(str(temporary))
        else:
            _write_oiio(temporary, channels)
        replace_atomically(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    return path


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
    """Every channel of an OpenEXR file (all parts), by its full name.

    Returns
    -------
    dict of str to (H, W) ndarray of np.float32
        E.g. ``{"ViewLayer.Combined.R": ..., "ViewLayer.Depth.Z": ...}``; row 0 at the top.
    """
    exr = _openexr()
    if exr is not None:
        channels = {}
        with exr.File(str(path), separate_channels=True) as file:
            for part in file.parts:
                for name, channel in part.channels.items():
                    channels[name] = np.asarray(channel.pixels, np.float32)
        return channels
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
