"""Image files of DVR results: OpenEXR (R, G, B, A, Z) and PNG previews, written atomically.

Arrays are ``(H, W)`` or ``(H, W, 4)`` with row 0 at the **top** (the renderers' order; Blender
images are bottom row first). Files are written atomically (:mod:`volumeevm_addon._files`); an
existing file is replaced only when ``overwrite=True``.

EXR goes through the ``OpenEXR`` module (PyPI ``OpenEXR`` >= 3.3), imported when first needed.
PNG needs nothing beyond NumPy and the standard library.
"""

import struct
import zlib

import numpy as np

from .._errors import VolumeEVMError
from .._files import write_atomically

__all__ = ["write_exr", "read_exr", "write_png", "exr_channels", "openexr_module"]


def openexr_module():
    """The ``OpenEXR`` module, or None when it is not installed.

    EXR support is optional: callers ask first, to offer EXR only where it works.

    Returns
    -------
    module or None
    """
    try:
        import OpenEXR
    except ImportError:
        return None
    return OpenEXR


def checked_image(name, array, shape=None, dtype=np.float32):
    """``array`` as a contiguous image of ``dtype``, checked: numbers, ``(H, W, 4)`` (or exactly
    ``shape``), and at least one pixel (a 0x0 or 0xN image has nothing to write).

    Raises
    ------
    VolumeEVMError
        Naming ``name`` when the array is not numeric, has the wrong shape or no pixels.
    """
    try:
        image = np.ascontiguousarray(array, dtype)
    except (TypeError, ValueError) as error:
        raise VolumeEVMError(f"{name}: expected an array of numbers, got {type(array).__name__}") \
            from error
    if shape is None and (image.ndim != 3 or image.shape[2] != 4):
        raise VolumeEVMError(f"{name}: expected (H, W, 4), got shape {image.shape}")
    if shape is not None and image.shape != tuple(shape):
        raise VolumeEVMError(f"{name}: expected shape {tuple(shape)}, got {image.shape}")
    if image.size == 0:
        raise VolumeEVMError(f"{name}: the image is empty (shape {image.shape}); it needs at "
                             f"least one pixel")
    return image


def exr_channels(rgba, depth=None):
    """The named float32 channels of an RGBA (+ Z) image, as an EXR file (or Blender's
    compositor) takes them.

    Parameters
    ----------
    rgba : (H, W, 4) array_like
        Premultiplied colour and alpha, row 0 at the top.
    depth : (H, W) array_like, optional
        Axial depth for the ``Z`` channel.

    Returns
    -------
    dict of str to (H, W) ndarray of np.float32
        ``"R"``, ``"G"``, ``"B"``, ``"A"`` and, with ``depth``, ``"Z"``; each contiguous.

    Raises
    ------
    VolumeEVMError
        Naming ``rgba`` or ``depth`` when it is not numeric, has the wrong shape or no pixels.

    Examples
    --------
    >>> sorted(exr_channels(np.zeros((2, 3, 4)), np.ones((2, 3))))
    ['A', 'B', 'G', 'R', 'Z']
    """
    rgba = checked_image("rgba", rgba)
    channels = {name: np.ascontiguousarray(rgba[..., i]) for i, name in enumerate("RGBA")}
    if depth is not None:
        channels["Z"] = checked_image("depth", depth, rgba.shape[:2])
    return channels


def write_exr(path, rgba, depth=None, *, overwrite=False):
    """Write an RGBA (+ Z) float image to an OpenEXR file (ZIP compressed), atomically.

    Parameters
    ----------
    path : str or Path
        The file to write.
    rgba : (H, W, 4) array_like
        Premultiplied, scene-linear colour and alpha; row 0 at the top.
    depth : (H, W) array_like, optional
        Axial depth (Blender units) for the ``Z`` channel (1e10 where nothing is seen).
    overwrite : bool, optional
        Replace an existing file (default False: raise instead).

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    VolumeEVMError
        When the OpenEXR module is missing, the image is bad (:func:`exr_channels`), the file
        exists and ``overwrite`` is False, or the write fails (:func:`write_atomically`).
    """
    exr = openexr_module()
    if exr is None:
        raise VolumeEVMError(f"{path}: writing EXR needs the OpenEXR module (pip install OpenEXR)")
    channels = exr_channels(rgba, depth)

    def write(temporary):
        header = {"compression": exr.ZIP_COMPRESSION, "type": exr.scanlineimage}
        parts = {name: exr.Channel(name, data) for name, data in channels.items()}
        with exr.File(header, parts) as file:
            file.write(str(temporary))

    return write_atomically(path, write, overwrite=overwrite)


def read_exr(path):
    """Every channel of an OpenEXR file (all parts), by its full name.

    Parameters
    ----------
    path : str or Path
        An OpenEXR file (ours or Blender's multilayer EXR).

    Returns
    -------
    dict of str to (H, W) ndarray of np.float32
        E.g. ``{"R": ..., "Z": ...}`` or ``{"ViewLayer.Depth.Z": ...}``; row 0 at the top.

    Raises
    ------
    VolumeEVMError
        When the OpenEXR module is missing.
    """
    exr = openexr_module()
    if exr is None:
        raise VolumeEVMError(f"{path}: reading EXR needs the OpenEXR module (pip install OpenEXR)")
    channels = {}
    with exr.File(str(path), separate_channels=True) as file:
        for part in file.parts:
            for name, channel in part.channels.items():
                channels[name] = np.asarray(channel.pixels, np.float32)
    return channels


def write_png(path, rgba, *, overwrite=False):
    """Write a premultiplied, linear RGBA image as an 8-bit sRGB PNG preview, atomically.

    Colour is un-premultiplied and encoded with the sRGB transfer function; alpha stays linear
    (PNG stores straight alpha).

    Parameters
    ----------
    path : str or Path
        The ``.png`` file to write.
    rgba : (H, W, 4) array_like
        Premultiplied, scene-linear colour and alpha; row 0 at the top. Values are clipped
        to ``[0, 1]``.
    overwrite : bool, optional
        Whether an existing file may be replaced (default False).

    Returns
    -------
    Path
        ``path``, now holding the preview.

    Raises
    ------
    VolumeEVMError
        Naming ``rgba`` for an image without pixels, of another shape than ``(H, W, 4)`` or
        with NaN values (which have no 8-bit value); as :func:`write_atomically` when the file
        exists and ``overwrite`` is False or the write fails.
    """
    rgba = checked_image("rgba", rgba, dtype=np.float64)
    if np.isnan(rgba).any():
        raise VolumeEVMError(f"rgba: {int(np.isnan(rgba).sum())} NaN values; a PNG has no value "
                             f"for them")
    alpha = np.clip(rgba[..., 3:], 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        colour = np.where(alpha > 0, rgba[..., :3] / alpha, 0.0)
    colour = np.clip(colour, 0.0, 1.0)
    srgb = np.where(colour <= 0.0031308, 12.92 * colour, 1.055 * colour ** (1 / 2.4) - 0.055)
    pixels = np.round(np.concatenate([srgb, alpha], axis=2) * 255).astype(np.uint8)
    h, w = pixels.shape[:2]
    rows = np.concatenate([np.zeros((h, 1), np.uint8), pixels.reshape(h, w * 4)], axis=1)

    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    png = (b"\x89PNG\r\n\x1a\n"
           + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 6, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(rows.tobytes(), 6))
           + chunk(b"IEND", b""))
    return write_atomically(path, lambda temporary: temporary.write_bytes(png), overwrite=overwrite)
