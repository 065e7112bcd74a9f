"""The core's GPU inputs as GPU textures, made lazily and kept while they are used.

The core computes what the GPU method draws from (``gpu_region``, ``gpu_gradients``,
``gpu_occupancy``, ``gpu_transfer_table``); this module uploads those arrays through Blender's
``gpu`` module and keeps the textures: per VolumeEVM (the region, the gradients once a shaded
frame needs them, and the empty-space blocks of its last few transfer functions and modes), per
transfer-function version (its table, the last few) and the display table drawn last (a 3-D
texture, :mod:`.display_lut`). They are freed with the VolumeEVM, by :func:`free`, and on file
load. A VolumeEVM's region texture is uploaded whole: Blender's Python ``GPUTexture`` (4.5 and
5.x) cannot write into part of an existing texture, so a new tool-stack result is a new upload,
not a re-upload of its changed box. A volume larger than the GPU's 3D textures is drawn from
the first coarser level that fits (:func:`fitted_frame`), and a VolumeEVM the GPU refused once
is refused again at once. Kept apart from the drawing (:mod:`.gpu_draw`): what is uploaded and
how long it lives is one concern, how it is drawn another.
"""

import weakref

import gpu
import numpy as np

from ..volumeevm_addon import VolumeEVMError
from ..volumeevm_addon.rendering import (
    gpu_frame,
    gpu_gradients,
    gpu_occupancy,
    gpu_region,
    gpu_transfer_table,
)


class _Refused(VolumeEVMError):
    """The GPU refused a texture: its size or memory."""


_volumes = weakref.WeakKeyDictionary()  # VolumeEVM -> _VolumeTextures
_refused = weakref.WeakKeyDictionary()  # VolumeEVM -> why the GPU refused its region texture
_tables = {}  # transfer-function version -> 1-D texture
_display = []  # the display table drawn last and its 3-D texture
_KEPT = 8
"""Transfer-function tables kept, and empty-space textures per VolumeEVM (the latest used)."""


def float_buffer(array):
    """A flat float32 ``gpu.types.Buffer`` sharing ``array``'s memory (a float32 C-contiguous
    copy where it is not one), to upload it or to read pixels into it: a NumPy array handed to
    ``Buffer`` is reinterpreted, not converted, and multi-dimensional Buffers come out
    transposed on Blender 4.5."""
    flat = np.ascontiguousarray(array, dtype=np.float32).ravel()
    return gpu.types.Buffer("FLOAT", flat.size, flat)


def texture(size, texture_format, what, array=None):
    """A texture of ``size`` (x first), filled from ``array`` (x fastest) if given; a size or
    memory the GPU refuses raises :class:`VolumeEVMError` naming ``what``."""
    data = {} if array is None else {"data": float_buffer(array)}  # 4.5 refuses data=None
    try:
        return gpu.types.GPUTexture(size, format=texture_format, **data)
    except RuntimeError as error:
        raise _Refused(f"{what}: the GPU cannot hold a "
                       f"{'x'.join(str(n) for n in np.ravel(size))} "
                       f"{texture_format} texture ({error}); render a coarser level "
                       f"or a smaller image") from error


def texture_3d(array, texture_format):
    """A 3D texture of a ``(Z, Y, X[, C])`` float32 array (x fastest)."""
    return texture(array.shape[2::-1], texture_format, "vevm", array)


class _VolumeTextures:
    """One VolumeEVM's textures: the region, its gradients (None until a shaded frame needs
    them), and its empty-space blocks per (transfer function, mode, X-ray parameters)."""

    def __init__(self, vevm):
        self.region = texture_3d(gpu_region(vevm), "RG32F")
        self.gradients = None
        self.occupancy = {}


def _tf_key(tf):
    """A transfer function's version: its control points, unit length and whether it is
    categorical (None for X-ray)."""
    return None if tf is None else (tf.points.tobytes(), tf.unit_length_mm,
                                    getattr(tf, "is_categorical", False))


def table_texture(tf):
    """The 1-D transfer-function texture of ``tf``'s version (a few versions kept)."""
    key = _tf_key(tf)
    made = _tables.pop(key, None)
    if made is None:
        table = gpu_transfer_table(tf)[0]
        made = texture(len(table), "RGBA32F", "tf", table)
    _keep(_tables, key, made)
    return made


def display_texture(table):
    """The 3-D texture of a display table (:mod:`.display_lut`), remade when the table is
    another array."""
    if not _display or _display[0] is not table:
        rgba = np.concatenate([table, np.ones(table.shape[:3] + (1,), np.float32)], axis=-1)
        _display[:] = [table, texture_3d(rgba, "RGBA32F")]
    return _display[1]


def _keep(textures, key, kept):
    """Put ``kept`` under ``key`` as the most recently used, dropping the oldest beyond
    :data:`_KEPT`."""
    textures.pop(key, None)
    textures[key] = kept
    while len(textures) > _KEPT:
        textures.pop(next(iter(textures)))


def _volume_textures(vevm, shaded):
    """The textures of ``vevm`` (with its gradients when ``shaded``), made on first use; a
    VolumeEVM the GPU refused once is refused again at once (a viewport does not rebuild its
    region array at each draw)."""
    refused = _refused.get(vevm, {})  # shaded -> why (False: the region itself)
    why = refused.get(False) or refused.get(shaded)
    if why:
        raise _Refused(why)
    try:
        volume = _volumes.get(vevm)
        if volume is None:
            volume = _volumes[vevm] = _VolumeTextures(vevm)
        if shaded and volume.gradients is None:
            volume.gradients = texture_3d(gpu_gradients(vevm), "RGBA32F")
    except _Refused as error:
        _refused.setdefault(vevm, {})[shaded] = str(error)
        raise
    return volume


def fitted_frame(vevm, camera, tf, **options):
    """The core's ``gpu_frame(vevm, camera, tf, **options)``, at the next coarser levels (each
    twice as coarse) while the GPU cannot hold the level's region texture (uploaded here, kept
    for :func:`frame_textures`): a volume larger than the GPU's textures is drawn from a level
    that fits (``GPUFrame.level`` says which).

    Raises
    ------
    VolumeEVMError
        As ``gpu_frame``; when not even the coarsest level fits, the GPU's refusal.
    """
    frame = gpu_frame(vevm, camera, tf, **options)
    while not frame.vevm.evm.is_empty():
        try:
            _volume_textures(frame.vevm, frame.shaded)
            break
        except _Refused:
            if 2 * frame.level > max(vevm.shape):
                raise
            frame = gpu_frame(vevm, camera, tf, **{**options, "level": 2 * frame.level})
    return frame


def frame_textures(frame, tf, xray):
    """The region, occupancy and gradient textures of the frame's VolumeEVM, made on first
    use (the region texture stands for the gradients when the frame is not shaded: the shader
    then does not read them)."""
    volume = _volume_textures(frame.vevm, frame.shaded)
    key = (_tf_key(tf), frame.mode, xray)
    occupancy = volume.occupancy.get(key)
    if occupancy is None:
        blocks = gpu_occupancy(frame.vevm, tf, mode=frame.mode, xray_scale=xray[0],
                               xray_offset=xray[1])
        occupancy = texture_3d(blocks, "R32F")
    _keep(volume.occupancy, key, occupancy)
    return volume.region, occupancy, volume.gradients if frame.shaded else volume.region


def free():
    """Drop every texture (add-on unregistered, file loaded)."""
    _volumes.clear()
    _refused.clear()
    _tables.clear()
    _display.clear()
